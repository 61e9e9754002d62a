//! The formation in containers (issue 23): an image FROM scratch of the
//! `formation` binary and its shared libraries (`deploy/scratch-image.sh`),
//! seven containers on a podman network of their own (router, monitor,
//! leader, four agents, every node a client of the router):
//!
//! - lock-step: the run folder equals `formation sim`'s byte for byte;
//! - real time: the run completes, every step recorded;
//! - real time, agent 3's container killed and started again: it rejoins
//!   (docs/model.md §14's restarted agent) and the others carry on.
//!
//! Podman runs with a configuration of this test's own (runc, cgroupfs,
//! vfs storage in a temporary folder), which is what works on a CI machine
//! without systemd; every container, the network and the storage are
//! removed on every path. Where podman is missing or this is not root the
//! test says so and passes, unless FORMATION_CONTAINERS_REQUIRED=1 (CI).

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Whether containers can run here; panics if they must and cannot.
fn available() -> bool {
    let podman = Command::new("podman").arg("--version").output().is_ok_and(|o| o.status.success());
    let root = std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("Uid:")).map(|l| l.split_whitespace().nth(2) == Some("0")))
        .unwrap_or(false);
    let why = match (podman, root) {
        (true, true) => return true,
        (false, _) => "podman is missing (apt-get install podman runc)",
        (_, false) => "not root",
    };
    assert!(
        std::env::var("FORMATION_CONTAINERS_REQUIRED").as_deref() != Ok("1"),
        "FORMATION_CONTAINERS_REQUIRED=1 but containers cannot run here: {why}"
    );
    eprintln!("skipped: containers cannot run here ({why})");
    false
}

/// Podman with this test's configuration and storage; removes every
/// container, the network and the storage when dropped.
struct Pod {
    dir: tempfile::TempDir,
    network: String,
    subnet: String,
    image: String,
    names: Vec<String>,
}

impl Pod {
    fn new() -> Self {
        let dir = tempfile::tempdir().expect("tempdir");
        let d = dir.path();
        std::fs::write(
            d.join("containers.conf"),
            "[containers]\ndefault_ulimits = []\n[engine]\nruntime = \"runc\"\ncgroup_manager = \"cgroupfs\"\nevents_logger = \"file\"\n",
        )
        .expect("containers.conf");
        std::fs::write(
            d.join("storage.conf"),
            format!(
                "[storage]\ndriver = \"vfs\"\nrunroot = \"{}\"\ngraphroot = \"{}\"\n",
                d.join("run").display(),
                d.join("graph").display()
            ),
        )
        .expect("storage.conf");
        // A /24 of 10.89.0.0/16 of this process's own.
        let octet = 20 + std::process::id() % 200;
        let network = format!("formation-test-{}", std::process::id());
        let mut pod = Pod { dir, network, subnet: format!("10.89.{octet}"), image: String::new(), names: Vec::new() };
        pod.image = format!("localhost/formation-test:{}", std::process::id());
        pod.ok(&[
            "network",
            "create",
            "--disable-dns",
            "--subnet",
            &format!("{}.0/24", pod.subnet),
            &pod.network.clone(),
        ]);
        pod
    }

    fn command(&self) -> Command {
        let mut c = Command::new("podman");
        c.env("CONTAINERS_CONF", self.dir.path().join("containers.conf"))
            .env("CONTAINERS_STORAGE_CONF", self.dir.path().join("storage.conf"))
            .stdin(Stdio::null());
        c
    }

    fn run(&self, args: &[&str]) -> Output {
        self.command().args(args).output().expect("podman")
    }

    /// Runs podman; panics with its output unless it succeeded.
    fn ok(&self, args: &[&str]) -> String {
        let o = self.run(args);
        assert!(
            o.status.success(),
            "podman {args:?}: {}{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        );
        String::from_utf8_lossy(&o.stdout).into_owned()
    }

    /// The image, made by deploy/scratch-image.sh from this build's binary.
    fn build_image(&self) {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/scratch-image.sh");
        let o = Command::new("sh")
            .arg(&script)
            .arg(&self.image)
            .arg(env!("CARGO_BIN_EXE_formation"))
            .env("CONTAINERS_CONF", self.dir.path().join("containers.conf"))
            .env("CONTAINERS_STORAGE_CONF", self.dir.path().join("storage.conf"))
            .stdin(Stdio::null())
            .output()
            .expect("sh");
        assert!(o.status.success(), "deploy/scratch-image.sh: {}", String::from_utf8_lossy(&o.stderr));
    }

    fn ip(&self, host: u8) -> String {
        format!("{}.{host}", self.subnet)
    }

    /// `formation node NODE ARGS…` in a detached container `name` at `.host`.
    fn start(&mut self, name: &str, host: u8, mounts: &[(&Path, &str)], env: &[(&str, &str)], node: &[String]) {
        let full = format!("{}-{name}", self.network);
        let mut args: Vec<String> = ["run", "-d", "--name", &full, "--network", &self.network, "--ip", &self.ip(host)]
            .map(String::from)
            .to_vec();
        for (from, to) in mounts {
            args.extend(["-v".into(), format!("{}:{to}", from.display())]);
        }
        for (k, v) in env {
            args.extend(["-e".into(), format!("{k}={v}")]);
        }
        args.push(self.image.clone());
        args.extend(node.iter().cloned());
        let a: Vec<&str> = args.iter().map(String::as_str).collect();
        self.ok(&a);
        self.names.push(full);
    }

    /// Waits (bounded) for container `name` to exit; its exit code.
    fn wait(&self, name: &str, limit: Duration) -> i64 {
        let full = format!("{}-{name}", self.network);
        let t = Instant::now();
        loop {
            let state = self.ok(&["inspect", "-f", "{{.State.Running}} {{.State.ExitCode}}", &full]);
            let mut w = state.split_whitespace();
            if w.next() == Some("false") {
                return w.next().and_then(|c| c.parse().ok()).unwrap_or(-1);
            }
            assert!(t.elapsed() < limit, "container {name} still running after {limit:?}");
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    fn logs(&self, name: &str) -> String {
        let o = self.run(&["logs", &format!("{}-{name}", self.network)]);
        format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
    }

    /// Removes every container of a run.
    fn clear(&mut self) {
        for n in std::mem::take(&mut self.names) {
            let _ = self.run(&["rm", "-f", "-t", "0", &n]);
        }
    }

    /// Router, monitor, leader and four agents: a run of the paper scenario
    /// with `sets`, recorded into `out` (a folder of the host); returns the
    /// monitor's exit code. `during` runs while the formation runs.
    fn formation(&mut self, run: &str, sets: &[&str], out: &Path, during: impl FnOnce(&mut Self)) -> i64 {
        let scenarios = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios");
        std::fs::create_dir_all(out).expect("out");
        let router = format!("tcp/{}:7447", self.ip(2));
        let node = |kind: &str| {
            let mut a: Vec<String> =
                ["node", kind, "--scenario", "/scenarios/paper.toml", "--run", run].map(String::from).to_vec();
            for s in sets {
                a.extend(["--set".into(), s.to_string()]);
            }
            a.extend(["--mode", "client", "--connect", &router].map(String::from));
            a
        };
        let scen: [(&Path, &str); 1] = [(&scenarios, "/scenarios:ro")];
        let runtime: Vec<(&str, &str)> = if sets.contains(&"timing=realtime") {
            vec![("ZENOH_RUNTIME", formation_net::session::RUNTIME)]
        } else {
            Vec::new()
        };
        self.start("router", 2, &[], &runtime, &["node", "router", "--listen", "tcp/0.0.0.0:7447"].map(String::from));
        let mut monitor = node("monitor");
        monitor.extend(["--out".into(), "/out/run".into(), "--quiet".into()]);
        self.start("monitor", 3, &[scen[0], (out, "/out")], &[], &monitor);
        self.start("leader", 4, &scen, &[], &node("leader"));
        for id in 1..=4u8 {
            let mut a = node("agent");
            a.extend(["--id".into(), id.to_string()]);
            self.start(&format!("agent-{id}"), 10 + id, &scen, &[], &a);
        }
        during(self);
        let code = self.wait("monitor", Duration::from_secs(120));
        if code != 0 {
            for n in ["monitor", "leader", "agent-1", "agent-2", "agent-3", "agent-4", "router"] {
                eprintln!("--- {n}:\n{}", self.logs(n));
            }
        }
        self.clear();
        code
    }
}

impl Drop for Pod {
    fn drop(&mut self) {
        self.clear();
        let _ = self.run(&["network", "rm", "-f", &self.network]);
        let _ = self.run(&["rmi", "-f", &self.image]);
        // The vfs layers and podman's run state live in the temporary
        // folder, removed with it. (Not `podman system reset`: it would
        // also remove every network of the machine.)
    }
}

fn json(dir: &Path, name: &str) -> serde_json::Value {
    common::json(dir, name)
}

#[test]
fn seven_containers_run_the_formation() {
    if !available() {
        return;
    }
    let mut pod = Pod::new();
    pod.build_image();
    let tmp = tempfile::tempdir().expect("tempdir");

    // Lock-step: byte for byte the simulator's.
    let out: PathBuf = tmp.path().join("lockstep");
    let sets = ["duration=5"];
    let code = pod.formation("ct-lockstep", &sets, &out, |_| {});
    assert_eq!(code, 0, "lock-step in containers: the monitor exited {code}");
    common::assert_equals_the_simulator(&out.join("run"), &tmp.path().join("sim"), &sets, "lock-step in containers");

    // Real time: completes, every step recorded.
    let out = tmp.path().join("realtime");
    let code = pod.formation("ct-realtime", &["timing=realtime", "duration=10"], &out, |_| {});
    assert_eq!(code, 0, "real time in containers: the monitor exited {code}");
    let n = json(&out.join("run"), "network.json");
    assert_eq!(n["complete"], true, "real time in containers: ending {}, lost {}", n["ending"], n["lost_steps"]);

    // Real time, agent 3's container killed at about 5 s and started again 2 s later.
    let out = tmp.path().join("restart");
    let code = pod.formation("ct-restart", &["timing=realtime", "duration=15"], &out, |pod| {
        std::thread::sleep(Duration::from_secs(6));
        let agent = format!("{}-agent-3", pod.network);
        pod.ok(&["kill", &agent]);
        std::thread::sleep(Duration::from_secs(2));
        pod.ok(&["start", &agent]);
    });
    let run = out.join("run");
    common::exit_matches_health(code as i32, &run, &[3], "a restart in containers");
    let n = json(&run, "network.json");
    let gaps = n["nodes"]["3"]["gaps"].as_array().expect("gaps").clone();
    assert_eq!(gaps.len(), 1, "follower 3's gaps: {gaps:?}");
    assert_eq!(gaps[0]["why"], "restarted", "{gaps:?}");
    let timeline = n["nodes"]["3"]["timeline"].as_array().expect("timeline").clone();
    assert!(
        timeline.iter().any(|e| e["event"].as_str().is_some_and(|w| w.contains("restarted"))),
        "no restart in follower 3's timeline: {timeline:?}"
    );
    // It rejoins: its formation error comes back below 0.2 m after the gap.
    let to_s = gaps[0]["to"].as_f64().unwrap_or(f64::NAN) * 1e-3;
    let text = std::fs::read_to_string(run.join("follower_3.csv")).expect("csv");
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().expect("header").split(',').collect();
    let fe = head.iter().position(|h| *h == "formation_error").expect("column");
    let settled = lines
        .map(|l| l.split(',').collect::<Vec<_>>())
        .map(|f| (f[0].parse::<f64>().unwrap_or(f64::NAN), f[fe].parse::<f64>().unwrap_or(f64::NAN)))
        .find(|(t, e)| *t >= to_s && *e < 0.2)
        .map(|(t, _)| t - to_s);
    assert!(
        settled.is_some_and(|s| s <= 5.0),
        "follower 3 back below 0.2 m {settled:?} s after its gap ended at {to_s} s"
    );
    for id in ["1", "2", "4"] {
        assert_eq!(
            n["nodes"][id]["gaps"].as_array().map(Vec::len),
            Some(0),
            "follower {id} lost steps: {}",
            n["nodes"][id]
        );
    }
    eprintln!("containers: restart gap {gaps:?}; follower 3 below 0.2 m {settled:?} s after it");
}
