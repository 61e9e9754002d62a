//! Running a launch's (or a lab's) processes: [`Children`] holds them,
//! [`spawn`] starts one tied to this process's life, [`supervise`] is the
//! one loop that watches them until the monitor has written the run,
//! a node fails or a signal comes, and [`interrupt`] stops them all.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use formation_record::Summary;

use crate::zenoh_log;
use formation_exit::Error;

/// The standby leader's name among the children (`launch --standby`,
/// `lab --kill-leader`).
pub(crate) const STANDBY: &str = "standby";

/// The child processes of a launch; every one still running is killed on drop.
pub struct Children {
    list: Vec<(String, Child)>,
    /// An agent that dies (a signal: SIGKILL, a crash) is the monitor's to
    /// take for gone (real time, with `network.gone_after`) or to name
    /// killed (lock-step, formation_protocol::died); the run goes on
    /// without it. What launch then says of it.
    agents_may_die: Option<&'static str>,
}

impl Children {
    pub(crate) fn new() -> Self {
        Self { list: Vec::new(), agents_may_die: None }
    }

    /// See the field: `then`, what launch says after "agent 2 died (…)".
    pub(crate) fn let_agents_die(&mut self, then: Option<&'static str>) {
        self.agents_may_die = then;
    }

    pub(crate) fn push(&mut self, name: String, child: Child) {
        self.list.push((name, child));
    }

    /// Asks every running child to stop (SIGTERM).
    fn terminate(&mut self, only: impl Fn(&str) -> bool) {
        for (name, child) in &mut self.list {
            if only(name) && matches!(child.try_wait(), Ok(None)) {
                let _ = Command::new("kill").args(["-TERM", &child.id().to_string()]).stderr(Stdio::null()).status();
            }
        }
    }

    /// Waits up to `limit` for the named child to exit.
    fn wait_for(&mut self, name: &str, limit: Duration) -> Option<ExitStatus> {
        let t = Instant::now();
        while t.elapsed() < limit {
            for (n, c) in &mut self.list {
                if n == name {
                    match c.try_wait() {
                        Ok(Some(s)) => return Some(s),
                        Ok(None) => {}
                        Err(_) => return None,
                    }
                }
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }

    /// Waits up to `limit` for every child but the router, then kills the rest.
    pub(crate) fn reap(&mut self, limit: Duration) {
        let t = Instant::now();
        // The router never ends by itself: wait for the nodes only.
        let running = |list: &mut Vec<(String, Child)>| {
            list.iter_mut().any(|(name, c)| name != "router" && matches!(c.try_wait(), Ok(None)))
        };
        while t.elapsed() < limit && running(&mut self.list) {
            std::thread::sleep(Duration::from_millis(20));
        }
        self.kill_all();
    }

    /// Lets the monitor write what it has (SIGTERM, up to 10 s) and the
    /// agents stop their robots (SIGTERM: an agent driving a robot through
    /// ROS 2 sends it zero velocity first), then kills every child.
    pub(crate) fn wind_down(&mut self) {
        self.terminate(|n| n == "monitor" || n.starts_with("agent"));
        let _ = self.wait_for("monitor", Duration::from_secs(10));
        let agents: Vec<String> = self.list.iter().map(|(n, _)| n.clone()).filter(|n| n.starts_with("agent")).collect();
        let t = Instant::now();
        for name in agents {
            let _ = self.wait_for(&name, Duration::from_secs(2).saturating_sub(t.elapsed()));
        }
        self.kill_all();
    }

    pub(crate) fn kill_all(&mut self) {
        for (_, child) in &mut self.list {
            if matches!(child.try_wait(), Ok(None)) {
                let _ = child.kill();
            }
            let _ = child.wait();
        }
    }

    /// The first child that has exited, with its status (removed from the set
    /// if it succeeded, so a finished node is not polled again).
    pub(crate) fn poll(&mut self) -> Option<(String, ExitStatus)> {
        for (name, child) in &mut self.list {
            if let Ok(Some(status)) = child.try_wait() {
                return Some((name.clone(), status));
            }
        }
        None
    }

    /// Kills the named child (SIGKILL: a crash, not a shutdown), reaps it and forgets it.
    pub(crate) fn kill(&mut self, name: &str) {
        for (n, child) in &mut self.list {
            if n == name {
                let _ = child.kill();
                let _ = child.wait();
            }
        }
        self.remove(name);
    }

    pub(crate) fn remove(&mut self, name: &str) {
        self.list.retain(|(n, _)| n != name);
    }

    /// Whether the named child is still running.
    pub(crate) fn running(&mut self, name: &str) -> bool {
        self.list.iter_mut().any(|(n, c)| n == name && matches!(c.try_wait(), Ok(None)))
    }

    /// Process ids of the children still running.
    pub fn pids(&mut self) -> Vec<u32> {
        self.list.iter_mut().filter_map(|(_, c)| matches!(c.try_wait(), Ok(None)).then(|| c.id())).collect()
    }
}

impl Drop for Children {
    fn drop(&mut self) {
        self.kill_all();
    }
}

/// A node of a launch dies with it: should the launch itself be killed
/// (SIGKILL, the OOM killer), the kernel sends each child SIGTERM, and it
/// writes what it has and exits (they ran to the end of the run). Every
/// child is started from the launch's main thread, whose end is the
/// process's: the signal is tied to the thread that started the child.
pub(crate) fn dies_with_launch(c: &mut Command) {
    use std::os::unix::process::CommandExt;
    let parent = std::process::id();
    // SAFETY: between fork and exec only async-signal-safe calls (prctl,
    // getppid, _exit) run, on no shared state.
    unsafe {
        c.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The launch died before the line above: go now (not by a
            // signal: the launch's own handlers are still installed here).
            if libc::getppid() as u32 != parent {
                libc::_exit(1);
            }
            Ok(())
        });
    }
}

pub(crate) fn spawn(children: &mut Children, name: &str, mut c: Command) -> Result<(), Error> {
    dies_with_launch(&mut c);
    zenoh_log::route(&mut c, name);
    let child = c.spawn().map_err(|e| Error::Run(format!("starting {name}: {e}")))?;
    children.push(name.to_string(), child);
    Ok(())
}

/// Starts `c` (a `formation node router …` command) as the child "router"
/// and waits up to 30 s for its "router listening" line.
pub(crate) fn start_router_with(children: &mut Children, c: Command) -> Result<(), Error> {
    start_router_named(children, "router", c)
}

/// [`start_router_with`] for a router known to `children` as `name`.
pub(crate) fn start_router_named(children: &mut Children, name: &str, mut c: Command) -> Result<(), Error> {
    dies_with_launch(&mut c);
    zenoh_log::route(&mut c, name);
    c.stdin(Stdio::null()).stdout(Stdio::piped());
    let mut child = c.spawn().map_err(|e| Error::Run(format!("starting {name}: {e}")))?;
    let stdout = child.stdout.take();
    children.push(name.into(), child);
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut lines = stdout.map(|s| BufReader::new(s).lines());
        let first = lines.as_mut().and_then(|l| l.next()).and_then(Result::ok);
        let _ = tx.send(first);
        // Keep draining so the router never blocks on a full pipe.
        if let Some(l) = lines {
            for _ in l {}
        }
    });
    match rx.recv_timeout(Duration::from_secs(30)) {
        Ok(Some(line)) if line.starts_with("router listening") => Ok(()),
        Ok(other) => Err(Error::Run(format!("{name} did not start: {}", other.unwrap_or_default()))),
        Err(_) => Err(Error::Run(format!("{name} did not start within 30 s"))),
    }
}

/// The one supervision loop of `launch` and `lab`: every `every`, `each`
/// (the lab's fault events; an error ends the run with it), then whether the
/// run is over ([`settle`]); `shutdown` (a signal) stops every child
/// ([`interrupt`]).
pub(crate) async fn supervise(
    children: &mut Children,
    out: &Path,
    every: Duration,
    shutdown: impl std::future::Future<Output = formation_exit::shutdown::Signal>,
    mut each: impl FnMut(&mut Children) -> Result<(), Error>,
) -> Result<Summary, Error> {
    tokio::pin!(shutdown);
    let mut tick = tokio::time::interval(every);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            s = &mut shutdown => return Err(interrupt(children, out, s.number())),
        }
        each(children)?;
        if let Some(ended) = settle(children, out) {
            return ended;
        }
    }
}

/// Looks at the children that have exited: once the monitor has, the run is
/// over (its summary, or its failure); a node that failed stops the run
/// (the monitor first writes what it has). None while the run goes on.
pub(crate) fn settle(children: &mut Children, out: &Path) -> Option<Result<Summary, Error>> {
    while let Some((name, status)) = children.poll() {
        if name == "monitor" {
            let degraded = status.code() == Some(i32::from(formation_exit::DEGRADED));
            if !status.success() && !degraded {
                children.kill_all();
                return Some(Err(Error::Run(format!("the monitor failed ({status})"))));
            }
            // The run is recorded; the nodes are done or about to be, and
            // a real-time stand-in robot is told to stop.
            children.remove("monitor");
            children.terminate(|n| n.starts_with("robot "));
            children.reap(Duration::from_secs(5));
            let path = out.join("summary.json");
            let read = std::fs::read_to_string(&path).map_err(|e| e.to_string());
            let summary = read.and_then(|text| serde_json::from_str(&text).map_err(|e| e.to_string()));
            return Some(summary.map_err(|e| Error::Run(format!("reading {}: {e}", path.display()))));
        }
        // An agent stopped by SIGTERM or Ctrl-C (`kill`, `formation leave`)
        // left the run and told the monitor: the run goes on without it; a
        // leader that died beside a standby is the standby's to replace
        // (the monitor names the handover, or the run's failure).
        let replaced = name == "leader" && children.running(STANDBY);
        let then = children.agents_may_die.filter(|_| name.starts_with("agent") && died_of_a_signal(&status));
        let died = then.is_some();
        if let Some(then) = then {
            eprintln!("{name} died ({status}): {then}; the run goes on");
        }
        let left = name.starts_with("agent") && matches!(status.code(), Some(130 | 143));
        if status.success() || left || replaced || died {
            children.remove(&name);
            continue;
        }
        // A node failed: let the monitor write what it has, stop the rest.
        children.wind_down();
        return Some(Err(Error::Run(format!(
            "{name} failed ({status}); stopped every process; the run folder {} holds what the monitor received",
            out.display()
        ))));
    }
    None
}

/// Whether a child ended on a signal (killed, crashed), not with an exit code.
fn died_of_a_signal(status: &std::process::ExitStatus) -> bool {
    use std::os::unix::process::ExitStatusExt;
    status.signal().is_some()
}

/// Ctrl-C / SIGTERM (`signal`): stop the nodes, let the monitor flush, kill
/// the rest; the launch exits 128 + `signal`, as the monitor does.
pub(crate) fn interrupt(children: &mut Children, out: &Path, signal: i32) -> Error {
    children.terminate(|n| n != "monitor" && n != "router");
    children.wind_down();
    Error::Interrupted(
        format!("interrupted: stopped every process; {} holds what the monitor received", out.display()),
        signal as u8,
    )
}
