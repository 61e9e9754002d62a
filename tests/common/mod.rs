//! Shared by the networked end-to-end tests: `formation` started in its own
//! process group (every child it starts inherits the group), waited on with
//! a bound, and killed with its whole group on every path.

#![allow(dead_code)] // each test binary uses its own part of this module

use std::collections::BTreeSet;
use std::net::TcpListener;
use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

pub const SCENARIO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/scenarios/paper.toml");
/// How long a test waits for a run it started before it calls the run
/// hung: a guard, not a verdict on speed (a 30 s run at time scale 2 takes
/// 15 s here; a host many times slower still ends within this).
pub const LIMIT: Duration = Duration::from_secs(300);

/// How long a test waits for a process it started to listen, appear or
/// go: a guard against a hang, not a verdict on speed (a process that
/// takes 20 s to start on a starved host is slow, not wrong).
pub const GUARD: Duration = Duration::from_secs(120);

/// Loopback ports a paper-scenario `formation launch --base-port P` uses:
/// P, P + 1, …, P + 5 in peer mode (monitor, leader, four agents); in
/// client mode only P (the router).
pub const LAUNCH_PORTS: usize = 6;

/// Every port `Ports::free` has handed out in this process: never twice.
static HANDED_OUT: Mutex<BTreeSet<u16>> = Mutex::new(BTreeSet::new());

/// The claims on them (open, locked files), held until the binary exits.
static CLAIMS: Mutex<Vec<std::fs::File>> = Mutex::new(Vec::new());

/// `count` consecutive TCP ports on 127.0.0.1 that are free, for one test:
/// `launch --base-port` takes consecutive ports, and a test that starts a
/// router or a listening session needs to know its port.
///
/// How they are chosen, and why concurrent tests do not collide:
/// - Below the kernel's ephemeral range (`net.ipv4.ip_local_port_range`),
///   from 10,000 up: outgoing connections take their local ports from that
///   range, so there only a listener can take a port. (Blocks used to come
///   from the OS's own pick, inside the range: at 100 peers, one peer's
///   outgoing link took a port of a block between its release and a
///   node's bind, "Address already in use".)
/// - The search starts where this process's id says, so that test binaries
///   run at once (two worktrees, two `cargo test`s) do not try the same
///   block first, and each port of a block is bound: a port that a socket
///   holds fails to bind and the next block is tried (one in TIME_WAIT
///   binds here as it does for the node, both asking for SO_REUSEADDR).
/// - Every listener stays open, so nothing else on the machine can take the
///   ports, until `release` — to be called just before starting the
///   process that binds them (it cannot bind them while we hold them).
/// - A port is handed out at most once per process (`HANDED_OUT`): another
///   test of this binary is never given it, however its timing goes.
/// - Each port is claimed as a launch claims its own free ports
///   (`formation_launch::ports::claim`), for as long as this test binary
///   runs: a launch choosing its own ports at the same time (one without
///   `--base-port`) skips them, even between `release` and the bind.
///
/// Tests whose processes run in network namespaces (`formation lab`, the
/// containers) need none of this: each node listens on its own address in
/// its own namespace (the lab uses port 7447 on every host), so a fixed
/// port there cannot meet another test's.
pub struct Ports {
    first: u16,
    held: Vec<TcpListener>,
}

impl Ports {
    pub fn free(count: usize) -> Self {
        assert!((1..=1000).contains(&count), "{count} ports");
        // Each claim is an open file for the binary's life: a few hundred
        // in all, more than a soft limit of 1,024 leaves beside the
        // in-process sessions' sockets; raised to the hard limit once.
        static RAISED: std::sync::Once = std::sync::Once::new();
        RAISED.call_once(|| {
            let mut l = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
            // SAFETY: pointers to a local of the right type.
            unsafe {
                if libc::getrlimit(libc::RLIMIT_NOFILE, &mut l) == 0 && l.rlim_cur < l.rlim_max {
                    l.rlim_cur = l.rlim_cur.max(l.rlim_max.min(1 << 16));
                    libc::setrlimit(libc::RLIMIT_NOFILE, &l);
                }
            }
        });
        let count = count as u16;
        let ephemeral_low = formation_launch::ports::ephemeral_low();
        let (low, high) = (formation_launch::ports::LOWEST, ephemeral_low.saturating_sub(count));
        assert!(low < high, "no room below the ephemeral ports ({ephemeral_low})");
        let mut handed_out = HANDED_OUT.lock().unwrap_or_else(|e| e.into_inner());
        // Start where this process's id says, so that test binaries run at
        // once do not all try the same block first.
        let span = high - low;
        let start = low + (std::process::id() % u32::from(span)) as u16;
        let mut base = start;
        // The whole range if need be: every call of a test binary starts at
        // the same place, so the blocks handed out before lie ahead of it
        // (200 tries ran out once a binary had handed out 200 ports there).
        let mut bound = 0;
        for _ in 0..span / count + 1 {
            if let Some(ports) = Self::take_block(base, count, &mut handed_out) {
                return ports;
            }
            bound += u32::from(!handed_out.contains(&base));
            base = low + ((base - low + count) % span);
        }
        panic!(
            "no {count} consecutive free loopback ports in {low}..{ephemeral_low} ({} handed out in this binary, {bound} \
             blocks tried were in use by others)",
            handed_out.len()
        );
    }

    /// Holds `count` ports from `base` if none was handed out before and
    /// every one binds.
    fn take_block(base: u16, count: u16, handed_out: &mut BTreeSet<u16>) -> Option<Self> {
        let block = base..=base + (count - 1);
        if block.clone().any(|p| handed_out.contains(&p)) {
            return None;
        }
        let claims: Vec<_> = block.clone().map_while(formation_launch::ports::claim).collect();
        if claims.len() != usize::from(count) {
            return None;
        }
        let held: Vec<TcpListener> = block.clone().map_while(|p| TcpListener::bind(("127.0.0.1", p)).ok()).collect();
        if held.len() != usize::from(count) {
            return None;
        }
        handed_out.extend(block);
        CLAIMS.lock().unwrap_or_else(|e| e.into_inner()).extend(claims.into_iter().flatten());
        Some(Ports { first: base, held })
    }

    /// The first port.
    pub fn base(&self) -> u16 {
        self.first
    }

    /// Lets go of the ports (they stay this test's): call just before
    /// starting what binds them. Returns the first port.
    pub fn release(mut self) -> u16 {
        self.held.clear();
        self.first
    }
}

/// The share of the machine's two cores a test of the `realtime` binary
/// asks for: its processes' CPU time over its wall time, measured one test
/// at a time (docs/performance.md, "The real-time tests share the cores
/// by their load"), rounded up to a class. The shares decide how many tests
/// run at once, not any verdict: a real-time run beside others is compared
/// with the model only if its own record says it kept the period
/// ([`judge_if_timely`]), and a lock-step run's verdict does not depend on
/// time at all.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Load {
    /// Up to 0.3 cores: the ROS 2 robots, a six-node launch at 100–200 Hz
    /// (measured 0.10–0.30).
    Light,
    /// Up to 0.6 cores: one lab of the paper scenario in real time at
    /// 1 kHz, a real-time run under attack (measured 0.45–0.60; the
    /// certified node's attack 0.74).
    Lab,
    /// A lock-step run, whose verdict (equal to the simulator byte for
    /// byte) does not depend on time: it takes what the cores give
    /// (1.2–1.6 alone) at the normal priority, and is counted as a lab, so
    /// that at most one real-time lab runs beside it.
    Lockstep,
    /// The cores to itself: 50 and 100 agents, floods, the Python
    /// package's one check on threads run at once.
    Whole,
}

impl Load {
    fn cores(self) -> f64 {
        match self {
            Load::Light => 0.3,
            Load::Lab | Load::Lockstep => 0.6,
            Load::Whole => BUDGET,
        }
    }
}

/// The cores the `realtime` binary's tests may hold at once, of two: two
/// labs side by side, or a lab and two light runs; a `Whole` test alone.
/// The rest is the host's, the test harness's and the slack a 1 kHz loop
/// needs. docs/performance.md says how it was measured.
pub const BUDGET: f64 = 1.2;

/// The cores the running tests of this binary hold, and the queue.
struct Held {
    cores: f64,
    /// The next ticket to hand out, and the one that starts next.
    next: u64,
    serving: u64,
}

static HELD: Mutex<Held> = Mutex::new(Held { cores: 0.0, next: 0, serving: 0 });
static FREED: std::sync::Condvar = std::sync::Condvar::new();

/// `load`'s share of the cores, held until dropped. Tests start in the
/// order they ask (libtest's, by name), each once the tests running beside
/// it leave room within [`BUDGET`] (always when none runs): a `Whole` test
/// waiting for the cores to itself is not overtaken by a stream of labs.
pub fn cores(load: Load) -> Cores {
    let mut held = HELD.lock().unwrap_or_else(|e| e.into_inner());
    let want = load.cores();
    let ticket = held.next;
    held.next += 1;
    while held.serving != ticket || (held.cores > 0.0 && held.cores + want > BUDGET + 1e-9) {
        held = FREED.wait(held).unwrap_or_else(|e| e.into_inner());
    }
    held.serving += 1;
    held.cores += want;
    FREED.notify_all();
    Cores(load)
}

/// A share of the cores (see [`cores`]); given back on drop, also when
/// its test panicked.
pub struct Cores(Load);

impl Drop for Cores {
    fn drop(&mut self) {
        let mut held = HELD.lock().unwrap_or_else(|e| e.into_inner());
        held.cores = (held.cores - self.0.cores()).max(0.0);
        FREED.notify_all();
    }
}

/// libtest's default number of test threads for this binary, set before
/// `main` (from a `.init_array` entry, [`test_binary`]) unless
/// `RUST_TEST_THREADS` is set; `--test-threads` still wins over both.
pub fn default_test_threads(n: &str) {
    if std::env::var_os("RUST_TEST_THREADS").is_none() {
        std::env::set_var("RUST_TEST_THREADS", n);
    }
}

/// Before `main`: [`summary_at_exit`] registered to print the binary's
/// last line.
pub fn at_exit_summary() {
    // SAFETY: atexit takes a function without arguments that lives as long
    // as the process; registering it has no other precondition.
    unsafe { libc::atexit(summary_at_exit) };
}

/// `common::test_binary!("N");` in a test binary's main.rs: its tests run N
/// at a time unless told otherwise ([`default_test_threads`]), and it ends
/// with one line counting its tests judged, not judged and skipped
/// ([`summary_at_exit`]); `common::test_binary!();` only the line.
#[allow(unused_macros)]
macro_rules! test_binary {
    ($($n:literal)?) => {
        #[used]
        #[link_section = ".init_array"]
        static TEST_BINARY: extern "C" fn() = {
            extern "C" fn set() {
                $(common::default_test_threads($n);)?
                common::at_exit_summary();
            }
            set
        };
    };
}
#[allow(unused_imports)]
pub(crate) use test_binary;

/// A child process leading its own process group; the group is killed on drop.
pub struct Group(pub Child);

impl Group {
    /// `formation ARGS…` in a new process group.
    pub fn spawn(args: &[&str]) -> Self {
        let child = Command::new(env!("CARGO_BIN_EXE_formation"))
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .process_group(0)
            .spawn()
            .expect("spawn formation");
        Group(child)
    }

    /// [`Group::spawn`], its stderr into the file `log`.
    pub fn spawn_logged(args: &[&str], log: &Path) -> Self {
        let file = std::fs::File::create(log).expect("create the stderr log");
        let child = Command::new(env!("CARGO_BIN_EXE_formation"))
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(file)
            .process_group(0)
            .spawn()
            .expect("spawn formation");
        Group(child)
    }

    /// `formation launch SCENARIO -q --out OUT [--set S]… EXTRA…`.
    pub fn launch(out: &Path, sets: &[&str], extra: &[&str]) -> Self {
        let out = out.display().to_string();
        let mut args = vec!["launch", SCENARIO, "-q", "--out", &out];
        for s in sets {
            args.extend(["--set", s]);
        }
        args.extend_from_slice(extra);
        Self::spawn(&args)
    }

    pub fn wait(&mut self, limit: Duration) -> ExitStatus {
        let t = Instant::now();
        loop {
            if let Some(s) = self.0.try_wait().expect("try_wait") {
                return s;
            }
            assert!(t.elapsed() < limit, "formation did not finish within {limit:?}");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Asks the leader of the group to end (SIGTERM), as a test does once
    /// the run a helper served is over, and waits for it (bounded).
    pub fn terminate(&mut self, limit: Duration) -> ExitStatus {
        // SAFETY: kill has no preconditions; the pid is our child's, not yet reaped.
        unsafe {
            libc::kill(self.0.id() as libc::pid_t, libc::SIGTERM);
        }
        self.wait(limit)
    }

    /// Processes (other than zombies) still in the group.
    pub fn members(&self) -> Vec<u32> {
        let pgid = self.0.id().to_string();
        let mut found = Vec::new();
        for e in std::fs::read_dir("/proc").expect("/proc").flatten() {
            let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else { continue };
            let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else { continue };
            // Fields after the ")" closing the command name: state ppid pgrp …
            let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else { continue };
            let f: Vec<&str> = rest.split_whitespace().collect();
            if f.len() > 2 && f[2] == pgid && f[0] != "Z" {
                found.push(pid);
            }
        }
        found
    }

    /// The pid of `formation node agent … --id <id>` among the group's processes.
    pub fn agent_pid(&self, id: u32) -> Option<u32> {
        self.members().into_iter().find(|pid| {
            let cmd = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
            let args: Vec<&[u8]> = cmd.split(|&b| b == 0).collect();
            args.contains(&b"agent".as_slice())
                && args.windows(2).any(|w| w[0] == b"--id" && w[1] == id.to_string().as_bytes())
        })
    }

    /// Waits (bounded) until no process is left in the group.
    pub fn assert_group_empty(&self) {
        let t = Instant::now();
        while !self.members().is_empty() && t.elapsed() < Duration::from_secs(5) {
            std::thread::sleep(Duration::from_millis(50));
        }
        assert_eq!(self.members(), Vec::<u32>::new(), "processes left behind");
    }
}

impl Drop for Group {
    fn drop(&mut self) {
        let _ = Command::new("kill").args(["-KILL", "--", &format!("-{}", self.0.id())]).stderr(Stdio::null()).status();
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A run folder's `summary.json` or `network.json`, parsed.
pub fn json(dir: &Path, name: &str) -> serde_json::Value {
    let path = dir.join(name);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// What zenoh logged during a run: the files of its `zenoh-log/` folder,
/// each under its name; empty when it logged nothing (no folder).
pub fn zenoh_log(dir: &Path) -> String {
    let folder = dir.join("zenoh-log");
    let Ok(entries) = std::fs::read_dir(&folder) else { return String::new() };
    let mut files: Vec<_> = entries.filter_map(|e| e.ok().map(|e| e.path())).collect();
    files.sort();
    let mut said = String::new();
    for f in files {
        let text = std::fs::read_to_string(&f).unwrap_or_else(|e| format!("(unreadable: {e})"));
        said.push_str(&format!("{}:\n{text}", f.display()));
    }
    if said.is_empty() {
        said = format!("{} (empty)", folder.display());
    }
    said
}

/// Runs a command to the end; panics with its output unless it succeeded.
pub fn run_ok(cmd: &mut Command) -> std::process::Output {
    let out = cmd.output().expect("formation runs");
    assert!(
        out.status.success(),
        "{cmd:?} failed ({}):\n{}{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Asserts that the paper scenario's run folder `out` (with `sets`) is
/// byte for byte what `formation sim` writes into `sim`; `what` names the run.
pub fn assert_equals_the_simulator(out: &Path, sim: &Path, sets: &[&str], what: &str) {
    let mut c = Command::new(env!("CARGO_BIN_EXE_formation"));
    c.args(["sim", SCENARIO, "-q", "--out"]).arg(sim);
    for s in sets {
        c.args(["--set", s]);
    }
    run_ok(&mut c);
    for f in ["summary.json", "leader.csv", "follower_1.csv", "follower_2.csv", "follower_3.csv", "follower_4.csv"] {
        let got = std::fs::read(out.join(f)).expect("run file");
        let want = std::fs::read(sim.join(f)).expect("sim file");
        assert!(got == want, "{f} of {what} differs from formation sim's");
    }
}

/// The summary and CSVs of a four-follower run folder `run` are byte for
/// byte those `formation sim` wrote into `sim`; `what` names the run.
pub fn same_files(run: &Path, sim: &Path, what: &str) {
    for f in ["summary.json", "leader.csv", "follower_1.csv", "follower_2.csv", "follower_3.csv", "follower_4.csv"] {
        let got = std::fs::read(run.join(f)).expect("run file");
        let want = std::fs::read(sim.join(f)).expect("sim file");
        let first = got.iter().zip(&want).position(|(a, b)| a != b);
        assert!(got == want, "{f} of {what} differs from formation sim's (first differing byte {first:?})");
    }
}

/// `formation certs SCENARIO --out DIR`: an authority and every node's
/// identity for `--tls DIR`.
pub fn certs(dir: &Path) {
    run_ok(Command::new(env!("CARGO_BIN_EXE_formation")).args(["certs", SCENARIO, "--out"]).arg(dir));
}

/// `formation certs SCENARIO --out DIR EXTRA…`; its output, whatever it is.
pub fn certs_with(dir: &Path, extra: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["certs", SCENARIO, "--out"])
        .arg(dir)
        .args(extra)
        .output()
        .expect("formation certs")
}

/// Per follower, the metrics a real-time run must share with the simulator.
pub const COMPARED: [&str; 4] = ["formation_rms_last10", "formation_final", "estimator_error_final", "torque_tv"];

/// The same without torque variation: for a formation far from converged,
/// whose torques chatter, a follower's torque variation measures how
/// sensitive the chatter is to one message's timing, not the network.
pub const COMPARED_CONVERGING: [&str; 3] = ["formation_rms_last10", "formation_final", "estimator_error_final"];

/// Where a real-time run's summary differs from the simulator's by more
/// than `rel` (relative), with every figure (a source counted silent is
/// the run's timing, [`silences`], not a figure).
pub fn unlike_the_simulator(
    got: &serde_json::Value,
    sim: &serde_json::Value,
    network: &serde_json::Value,
    rel: f64,
    compared: &[&str],
) -> Vec<String> {
    let mut bad = Vec::new();
    for (id, r) in sim["followers"].as_object().expect("followers") {
        for &m in compared {
            let (g, s) = (got["followers"][id][m].as_f64().unwrap_or(f64::NAN), r[m].as_f64().unwrap_or(f64::NAN));
            if (g - s).abs() > rel * s.abs() || g.is_nan() || s.is_nan() {
                bad.push(format!("follower {id} {m}: {g:.5} in real time, {s:.5} in formation sim"));
            }
        }
    }
    let nodes = network["nodes"].as_object().expect("nodes");
    let older: u64 = nodes.values().map(|v| v["older"].as_u64().unwrap_or(0)).sum();
    let p99 = nodes.values().map(|v| v["loop"]["lateness_p99_us"].as_f64().unwrap_or(0.0)).fold(0.0, f64::max);
    if !bad.is_empty() {
        bad.push(format!(
            "(source-steps that used a message older than the delay allows: {older}; worst loop lateness p99 {p99:.0} µs)"
        ));
    }
    bad
}

/// The sources a fault-free run's followers counted silent after the
/// first second ("node 2 at t = 10.26 s: follower 1 silent"): the model
/// has no silence, so a run that shows one departed from its timing (a
/// stall of the host: slow, not wrong).
pub fn silences(network: &serde_json::Value) -> Vec<String> {
    let mut said = Vec::new();
    for (node, v) in network["nodes"].as_object().into_iter().flatten() {
        for e in v["timeline"].as_array().into_iter().flatten() {
            let (t, what) = (e["t"].as_f64().unwrap_or(0.0), e["event"].as_str().unwrap_or(""));
            if t > 1.0 && what.ends_with("silent") {
                said.push(format!("node {node} at t = {t} s: {what}"));
            }
        }
    }
    said
}

/// [`judge_if_timely`] for one fault-free run: not judged either when a
/// follower counted a source silent after the first second ([`silences`]:
/// a clean clone's quiet run on this VM, 2026-12-03, had one stall at
/// 10.26 s, 0.05 % of its source-steps late, and its figures within 5 %
/// of the model's).
pub fn judge_fault_free_if_timely(tag: &str, wrong: &[String], network: &serde_json::Value) {
    let period = Period::of(network);
    let silent = silences(network);
    let why_not = period.why_not_judged().or_else(|| {
        (!silent.is_empty())
            .then(|| format!("a source fell silent, which the model has none of: {}", silent.join("; ")))
    });
    judge_unless(tag, wrong, why_not, &format!("the run's timing: {period}"));
}

/// The verdict of a real-time run's comparison with the nominal,
/// timing-free model (`formation sim`): judged only when the runs' own
/// records (`network.json` of each, parsed) say they kept the period
/// ([`formation_recorder::period::Period::kept`]: at most 1.25 % of the
/// source-steps late; with robots driven over ROS 2, loops late by at most
/// a quarter period at p99), whatever the machine. Then `wrong` fails
/// the test, with the runs' timing in the message; otherwise it is printed,
/// with why the figures were not judged, and counted in the binary's last
/// line ([`summary_at_exit`]). What holds whatever the timing (every step
/// recorded, the replay byte for byte, the health naming the departure) is
/// the test's to assert apart, always.
pub fn judge_if_timely(tag: &str, wrong: &[String], runs: &[&serde_json::Value], context: &str) {
    let each: Vec<Period> = runs.iter().map(|n| Period::of(n)).collect();
    let period = Period::together(&each);
    let timing = match each.len() {
        1 => period.to_string(),
        _ => format!("{period} over {} runs", each.len()),
    };
    judge_unless(tag, wrong, period.why_not_judged(), &format!("{context}; the runs' timing: {timing}"));
}

/// The verdict of a comparison with the model: `wrong` fails the test
/// unless `why_not` says why the run cannot be judged (its own record
/// shows it did not keep the period); then it is printed and counted as
/// not judged.
pub fn judge_unless(tag: &str, wrong: &[String], why_not: Option<String>, context: &str) {
    match why_not {
        None => {
            tally(Verdict::Judged);
            assert!(wrong.is_empty(), "{tag}: {}; {context}", wrong.join("; "));
            eprintln!("{tag}: judged against the model, within its tolerances; {context}");
        }
        Some(why) => {
            tally(Verdict::NotJudged(format!("{tag}: {why}")));
            let off = if wrong.is_empty() {
                "within the model's tolerances all the same".to_string()
            } else {
                format!("{} off: {}", wrong.len(), wrong.join("; "))
            };
            eprintln!("{tag}: not judged against the model ({why}): {off}; {context}");
        }
    }
}

pub use formation_recorder::period::Period;

/// A test's verdict as the binary's last line counts it.
enum Verdict {
    /// Compared with the model, the runs having kept the period.
    Judged,
    /// Not compared: why.
    NotJudged(String),
    /// Not run here: why.
    Skipped(String),
}

/// Per test (libtest runs each on a thread named after it): its
/// comparisons' and skips' verdicts.
static VERDICTS: Mutex<Vec<(String, Verdict)>> = Mutex::new(Vec::new());

fn tally(v: Verdict) {
    let test = std::thread::current().name().unwrap_or("main").to_string();
    VERDICTS.lock().unwrap_or_else(|e| e.into_inner()).push((test, v));
}

/// A test that cannot run here says why (one line) and is counted as
/// skipped; the caller returns.
pub fn skipped(why: &str) {
    eprintln!("skipped: {why}");
    tally(Verdict::Skipped(why.to_string()));
}

/// The binary's last line, printed as the process exits (registered
/// before `main` by [`test_binary`]): of the tests that compared a run with
/// the model, how many were judged and how many not (each with why), and
/// the tests skipped (why). A test is "not judged" if any of its
/// comparisons was.
pub extern "C" fn summary_at_exit() {
    let verdicts = VERDICTS.lock().unwrap_or_else(|e| e.into_inner());
    let mut tests: Vec<&str> = verdicts.iter().map(|(t, _)| t.as_str()).collect();
    tests.sort_unstable();
    tests.dedup();
    let (mut judged, mut not, mut skipped) = (0, Vec::new(), Vec::new());
    for t in &tests {
        let of = || verdicts.iter().filter(move |(n, _)| n == t).map(|(_, v)| v);
        if let Some(why) = of().find_map(|v| if let Verdict::Skipped(w) = v { Some(w) } else { None }) {
            skipped.push(format!("{t} ({why})"));
        } else if let Some(why) = of().find_map(|v| if let Verdict::NotJudged(w) = v { Some(w) } else { None }) {
            not.push(format!("{t} ({why})"));
        } else {
            judged += 1;
        }
    }
    let list = |v: &[String]| if v.is_empty() { String::new() } else { format!(": {}", v.join("; ")) };
    eprintln!(
        "{}: of the tests that compare runs with the model, {judged} judged, {} not judged{}; {} skipped{}; every \
         other test's verdict does not depend on timing",
        env!("CARGO_CRATE_NAME"),
        not.len(),
        list(&not),
        skipped.len(),
        list(&skipped)
    );
}

/// `formation replay` re-computes the run in `out` from its hearing record
/// into its CSVs and summary.json, byte for byte (issue 25).
pub fn replays_byte_for_byte(tag: &str, out: &Path) {
    let o = Command::new(env!("CARGO_BIN_EXE_formation")).arg("replay").arg(out).output().expect("formation replay");
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success() && text.contains("byte-identical"),
        "{tag}: the replay differs from the run ({}):\n{text}{}",
        o.status,
        String::from_utf8_lossy(&o.stderr)
    );
    eprintln!("{tag}: {}", text.lines().next().unwrap_or_default());
}

/// A run the model does not know everything of (a process killed, a
/// partition, a slow cable): it may end degraded. Its exit status must be
/// what its network.json's health says (3 for degraded, else 0), and a
/// degraded verdict must name only followers in `may_degrade` ("follower 3").
/// Returns the verdict.
pub fn exit_matches_health(code: i32, dir: &Path, may_degrade: &[u32], what: &str) -> String {
    let n = json(dir, "network.json");
    let h = &n["health"];
    let verdict = h["verdict"].as_str().unwrap_or_else(|| panic!("{what}: no health in network.json")).to_string();
    let want = if verdict == "degraded" { 3 } else { 0 };
    assert_eq!(code, want, "{what}: exit status {code} for a {verdict} run: {h}");
    for reason in h["degraded"].as_array().into_iter().flatten().filter_map(|r| r.as_str()) {
        let named = may_degrade.iter().any(|id| reason.contains(&format!("follower {id}")));
        assert!(named, "{what}: degraded for a reason the test's fault does not explain: {reason}");
    }
    verdict
}

/// Follower `id`'s telemetry batch with nothing in it (no samples, no
/// events, an empty hearing record): the base the attack and fuzz tests
/// craft their messages from.
pub fn empty_follower_batch(id: u32) -> formation_protocol::telemetry::Telemetry {
    formation_protocol::telemetry::Telemetry::Follower {
        id,
        first_k: 0,
        samples: vec![],
        counters: Default::default(),
        done: false,
        loop_stats: None,
        delivery: Default::default(),
        events: vec![],
        clock: None,
        links: vec![],
        heard: Default::default(),
        rescued: vec![],
        resumed: None,
        diverged: None,
        left: None,
    }
}

/// The Python that has the ROS 2 checks' modules (eclipse-zenoh, rosbags,
/// mcap-ros2-support): `FORMATION_PYTHON`, else `python3`. None, with a
/// line saying why, when it lacks them; with `FORMATION_ROS2_REQUIRED=1`
/// (CI) that is a failure instead.
pub fn ros2_python() -> Option<std::path::PathBuf> {
    let python = std::env::var_os("FORMATION_PYTHON").map_or_else(|| "python3".into(), std::path::PathBuf::from);
    let probe = Command::new(&python).args(["-c", "import zenoh, rosbags, mcap_ros2"]).output();
    let why = match probe {
        Ok(o) if o.status.success() => return Some(python),
        Ok(o) => String::from_utf8_lossy(&o.stderr).lines().last().unwrap_or("").to_string(),
        Err(e) => format!("cannot run {}: {e}", python.display()),
    };
    let line = format!(
        "{}: {why} (the ROS 2 checks need eclipse-zenoh==1.10.2, rosbags and mcap-ros2-support; .ci/run installs them)",
        python.display()
    );
    assert!(std::env::var("FORMATION_ROS2_REQUIRED").as_deref() != Ok("1"), "{line}");
    skipped(&line);
    None
}

/// A ROS 2 check script of tests/ros2/.
pub fn ros2_script(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/ros2").join(name)
}

/// The paper scenario with velocity-commanded robots.
pub const VELOCITY_SCENARIO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/scenarios/paper-velocity.toml");

/// Waits (bounded) until something listens on 127.0.0.1:`port`.
/// Until a launch logging to `log` says its run started (`started:`), for
/// at most a minute (a hang guard, not a verdict on speed).
pub fn wait_started(log: &Path) {
    let said = || std::fs::read_to_string(log).unwrap_or_default();
    let t = Instant::now();
    while !said().contains("started:") {
        assert!(t.elapsed() < Duration::from_secs(60), "the run did not start: {}", said());
        std::thread::sleep(Duration::from_millis(20));
    }
}

pub fn wait_listening(port: u16, limit: Duration) {
    let t = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(t.elapsed() < limit, "nothing listens on port {port} after {limit:?}");
        std::thread::sleep(Duration::from_millis(50));
    }
}
