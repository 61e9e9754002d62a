//! The formation in containers (issue 23): an image FROM scratch of the
//! `formation` binary and its shared libraries (`deploy/scratch-image.sh`),
//! seven containers on a podman network of their own (router, monitor,
//! leader, four agents, every node a client of the router):
//!
//! - lock-step: the run folder equals `formation sim`'s byte for byte;
//! - real time: the run completes, every step recorded;
//! - real time, agent 3's container killed and started again: it rejoins
//!   (docs/model.md §14's restarted agent) and the others carry on;
//! - `deploy/compose.yaml` itself, under Debian's podman-compose: the 30 s
//!   paper run over mutual TLS, `up --exit-code-from monitor` returning the
//!   monitor's status when the run ends, the run folder complete.
//!
//! Podman runs with a configuration of this test's own (runc, cgroupfs,
//! vfs storage in a temporary folder), which is what works on a CI machine
//! without systemd; every container, the network and the storage are
//! removed on every path. Where podman (or podman-compose, for the compose
//! test) is missing or this is not root the test says so and passes, unless
//! FORMATION_CONTAINERS_REQUIRED=1 (CI). The tests take turns: two real-time
//! formations of seven containers on one small machine would each make the
//! other late.

mod common;

// One line at the end: the tests skipped, and why.
common::test_binary!();

use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// Held by each test for its whole run (one formation at a time).
fn one_at_a_time() -> MutexGuard<'static, ()> {
    static TURN: Mutex<()> = Mutex::new(());
    TURN.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

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
    common::skipped(&format!("containers cannot run here ({why})"));
    false
}

/// Podman's configuration for these tests in `dir`: runc, cgroupfs, and
/// vfs storage inside `dir` (removed with it).
fn write_podman_conf(dir: &Path) {
    std::fs::write(
        dir.join("containers.conf"),
        "[containers]\ndefault_ulimits = []\n[engine]\nruntime = \"runc\"\ncgroup_manager = \"cgroupfs\"\nevents_logger = \"file\"\n",
    )
    .expect("containers.conf");
    std::fs::write(
        dir.join("storage.conf"),
        format!(
            "[storage]\ndriver = \"vfs\"\nrunroot = \"{}\"\ngraphroot = \"{}\"\n",
            dir.join("run").display(),
            dir.join("graph").display()
        ),
    )
    .expect("storage.conf");
}

/// `program` (podman, or a tool that runs it) with the configuration of `dir`.
fn with_podman_conf(program: &str, dir: &Path) -> Command {
    let mut c = Command::new(program);
    c.env("CONTAINERS_CONF", dir.join("containers.conf"))
        .env("CONTAINERS_STORAGE_CONF", dir.join("storage.conf"))
        .stdin(Stdio::null());
    c
}

/// The image `tag`, made by deploy/scratch-image.sh from this build's binary
/// in the storage of `dir`.
fn scratch_image(dir: &Path, tag: &str) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/scratch-image.sh");
    let o =
        with_podman_conf("sh", dir).arg(&script).arg(tag).arg(env!("CARGO_BIN_EXE_formation")).output().expect("sh");
    assert!(o.status.success(), "deploy/scratch-image.sh: {}", String::from_utf8_lossy(&o.stderr));
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
        write_podman_conf(dir.path());
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
        with_podman_conf("podman", self.dir.path())
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
        scratch_image(self.dir.path(), &self.image);
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
    let _turn = one_at_a_time();
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

/// Whether podman-compose is here; panics if containers must run and it is not.
fn compose_available() -> bool {
    let version = Command::new("podman-compose").arg("--version").stdin(Stdio::null()).output().ok();
    if let Some(o) = version.filter(|o| o.status.success()) {
        let text = String::from_utf8_lossy(&o.stdout);
        eprintln!("{}", text.lines().find(|l| l.contains("compose")).unwrap_or("podman-compose"));
        return true;
    }
    let why = "podman-compose is missing (apt-get install podman-compose)";
    assert!(
        std::env::var("FORMATION_CONTAINERS_REQUIRED").as_deref() != Ok("1"),
        "FORMATION_CONTAINERS_REQUIRED=1 but the compose file cannot run here: {why}"
    );
    common::skipped(&format!("the compose file cannot run here ({why})"));
    false
}

/// The image the compose file names (`image: formation`), in this test's storage.
const COMPOSE_IMAGE: &str = "formation";

/// `deploy/compose.yaml` as a user runs it: the file copied unchanged into
/// a checkout of its own in a temporary folder (`deploy/` with `tls/` and
/// `out/` beside the file, `scenarios/` one up), podman with this test's
/// configuration, and a project name of this run's own. When dropped,
/// `up`'s process group is killed and every container, volume and network
/// of the project and the image are removed (podman-compose 1.0.3's `down`
/// leaves the network behind), the storage with the folder.
struct Compose {
    dir: tempfile::TempDir,
    project: String,
    up: Option<Child>,
}

impl Compose {
    fn new() -> Self {
        let dir = tempfile::tempdir().expect("tempdir");
        write_podman_conf(dir.path());
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.subsec_nanos());
        let project = format!("formation-compose-{}-{nanos}", std::process::id());
        let compose = Compose { dir, project, up: None };
        let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
        std::fs::create_dir_all(compose.deploy()).expect("deploy/");
        std::fs::create_dir_all(compose.root().join("scenarios")).expect("scenarios/");
        std::fs::copy(repo.join("deploy/compose.yaml"), compose.deploy().join("compose.yaml")).expect("compose.yaml");
        std::fs::copy(common::SCENARIO, compose.root().join("scenarios/paper.toml")).expect("paper.toml");
        compose
    }

    fn root(&self) -> PathBuf {
        self.dir.path().join("checkout")
    }

    fn deploy(&self) -> PathBuf {
        self.root().join("deploy")
    }

    fn podman(&self, args: &[&str]) -> Output {
        with_podman_conf("podman", self.dir.path()).args(args).output().expect("podman")
    }

    /// How long after the first of the project's containers to end the
    /// monitor's ended (what `--exit-code-from` under podman-compose 1.0.3
    /// allows a second for), in seconds.
    fn monitor_lag_s(&self) -> Option<f64> {
        let label = format!("label=io.podman.compose.project={}", self.project);
        let names = self.podman(&["ps", "-a", "-q", "--filter", &label]);
        let names: Vec<String> = String::from_utf8_lossy(&names.stdout).split_whitespace().map(String::from).collect();
        let mut args = vec!["inspect", "-f", "{{.Name}} {{.State.Running}} {{.State.FinishedAt.UnixNano}}"];
        args.extend(names.iter().map(String::as_str));
        let out = String::from_utf8_lossy(&self.podman(&args).stdout).into_owned();
        let ended: Vec<(String, i64)> = out
            .lines()
            .filter_map(|l| match l.split_whitespace().collect::<Vec<_>>()[..] {
                [name, "false", at] => Some((name.to_string(), at.parse().ok()?)),
                _ => None,
            })
            .collect();
        let monitor = ended.iter().find(|(n, _)| n.ends_with("_monitor_1"))?.1;
        let first = ended.iter().map(|(_, at)| *at).min()?;
        Some((monitor - first) as f64 * 1e-9)
    }

    /// The certificates, made as the compose file's header says.
    fn certs(&self) {
        let mut c = Command::new(env!("CARGO_BIN_EXE_formation"));
        c.args(["certs", common::SCENARIO, "--out"]).arg(self.deploy().join("tls"));
        for node in ["router", "monitor", "leader", "agent-1", "agent-2", "agent-3", "agent-4"] {
            c.args(["--san", node]);
        }
        common::run_ok(&mut c);
    }

    /// `podman-compose -p PROJECT -f deploy/compose.yaml up --exit-code-from
    /// monitor`, in a process group of its own, waited for at most `limit`:
    /// its exit code and its output.
    fn up(&mut self, limit: Duration) -> (Option<i32>, String) {
        let log_path = self.dir.path().join("up.log");
        let log = std::fs::File::create(&log_path).expect("up.log");
        let child = with_podman_conf("podman-compose", self.dir.path())
            .args(["-p", &self.project, "-f"])
            .arg(self.deploy().join("compose.yaml"))
            .args(["up", "--exit-code-from", "monitor"])
            .current_dir(self.root())
            .stdout(log.try_clone().expect("log"))
            .stderr(log)
            .process_group(0)
            .spawn()
            .expect("podman-compose");
        let up = self.up.insert(child);
        let t = Instant::now();
        let status = loop {
            if let Some(s) = up.try_wait().expect("try_wait") {
                break Some(s);
            }
            if t.elapsed() > limit {
                break None;
            }
            std::thread::sleep(Duration::from_millis(200));
        };
        let text = std::fs::read_to_string(&log_path).unwrap_or_default();
        let Some(status) = status else {
            panic!("podman-compose up still running after {limit:?}; its output ends:\n{}", tail(&text, 40));
        };
        self.up = None;
        (status.code(), text)
    }
}

impl Drop for Compose {
    fn drop(&mut self) {
        if let Some(mut up) = self.up.take() {
            let _ = Command::new("kill").args(["-KILL", "--", &format!("-{}", up.id())]).stderr(Stdio::null()).status();
            let _ = up.kill();
            let _ = up.wait();
        }
        let label = format!("label=io.podman.compose.project={}", self.project);
        let _ = self.podman(&["rm", "-f", "-t", "0", "--filter", &label]);
        let _ = self.podman(&["volume", "prune", "-f", "--filter", &label]);
        let _ = self.podman(&["network", "rm", "-f", &format!("{}_formation", self.project)]);
        let _ = self.podman(&["rmi", "-f", COMPOSE_IMAGE]);
    }
}

/// The last `n` lines of `text`.
fn tail(text: &str, n: usize) -> String {
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}

#[test]
fn the_compose_file_runs_the_paper_over_mutual_tls() {
    if !available() || !compose_available() {
        return;
    }
    let _turn = one_at_a_time();
    let mut compose = Compose::new();
    scratch_image(compose.dir.path(), COMPOSE_IMAGE);
    compose.certs();

    // `up` returns when the monitor has written the run folder, with the
    // monitor's exit status (0: complete and healthy).
    let t = Instant::now();
    let (code, log) = compose.up(Duration::from_secs(150));
    let wall = t.elapsed();
    let run = compose.deploy().join("out/paper");
    assert_eq!(
        code,
        Some(0),
        "podman-compose up --exit-code-from monitor exited {code:?} after {wall:.1?} (the monitor's status, or 255 \
         when the monitor had not ended a second after the first container did); its output ends:\n{}",
        tail(&log, 40)
    );
    assert!(log.contains("router listening on tls/"), "the router did not listen on TLS:\n{}", tail(&log, 40));
    common::exit_matches_health(0, &run, &[], "the compose file's run");
    let n = json(&run, "network.json");
    let s = json(&run, "summary.json");
    assert_eq!(n["complete"], true, "the compose file's run: ending {}, lost {}", n["ending"], n["lost_steps"]);
    assert_eq!(n["timing"], "realtime");
    assert_eq!(s["duration"].as_f64(), Some(30.0), "the paper's 30 s run");
    assert_eq!(n["steps"], s["steps"]);
    for f in ["leader.csv", "follower_1.csv", "follower_2.csv", "follower_3.csv", "follower_4.csv"] {
        assert!(run.join(f).is_file(), "the run folder has no {f}");
    }
    let lag = compose.monitor_lag_s().map_or("?".into(), |s| format!("{s:.2} s"));
    eprintln!(
        "compose: up returned 0 after {wall:.1?}; {} steps recorded; the monitor ended {lag} after the first container",
        n["recorded_steps"]
    );
}
