//! `formation bench-net --floor`: the floor under an agent's CPU. Plain
//! zenoh processes with the agents' exact message pattern — each publishes
//! one estimate-sized message per step on its estimate key and subscribes
//! to its neighbours' and (if it hears it) the leader's, with the same
//! session settings, priorities and congestion control — beside the real
//! agents of the same scenario, both measured the same way: each process's
//! on-CPU time (every thread, /proc/PID/task/*/schedstat) over a steady
//! window in the middle of the run (start-up and linger excluded), per
//! process and step. Also the idle cost: an agent waiting for a start that
//! does not come.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use formation_net::node::NodeArgs;
use formation_protocol::wire::{self, EstimateMsg, Header, FORMAT_VERSION};
use zenoh::Wait;

use crate::hearing::median;
use formation_exit::Error;

/// `formation node floor`: one plain-zenoh stand-in for an agent (or, with
/// `--id 0`, the leader), publishing every period for `--seconds`.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct FloorArgs {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub node: NodeArgs,
    /// The follower whose pattern this is (0: the leader's).
    #[cfg_attr(feature = "clap", arg(long))]
    pub id: u32,
    /// How long to publish (s).
    #[cfg_attr(feature = "clap", arg(long))]
    pub seconds: f64,
    /// Lock-step: publish step k only once every source's step k − 1 is in
    /// (the leader: while the slowest follower that hears it is within
    /// the leader's window), as fast as that allows, for `--seconds / Δt`
    /// steps; print the steady rate (the middle half of the steps).
    #[cfg_attr(feature = "clap", arg(long))]
    pub lockstep: bool,
}

/// Writes the benchmarks' ring of `n` agents (n/5 chords) into a new
/// folder `tmp`; its scenario file.
pub fn ring_file(tmp: &std::path::Path, n: u32) -> Result<std::path::PathBuf, Error> {
    std::fs::create_dir_all(tmp).map_err(|e| Error::Run(format!("{}: {e}", tmp.display())))?;
    let spec = formation_scenario::generate::Spec {
        chords: n / 5,
        ..formation_scenario::generate::Spec::new(n, formation_scenario::generate::GraphKind::Ring)
    };
    let text = formation_scenario::generate::toml(&spec).map_err(|e| Error::Input(e.to_string()))?;
    let file = tmp.join(format!("ring{n}.toml"));
    std::fs::write(&file, text).map_err(|e| Error::Run(format!("{}: {e}", file.display())))?;
    Ok(file)
}

/// Runs one floor process.
pub async fn node(a: &FloorArgs) -> Result<(), formation_exit::Error> {
    let identity = if a.id == 0 { "leader".to_string() } else { formation_protocol::names::agent_name(a.id) };
    let (scenario, keys) = a.node.load(&identity)?;
    let session = a.node.open(&identity, &scenario).await?;
    let mut sources: Vec<u32> = Vec::new();
    if a.id != 0 {
        let i = scenario.index_of(a.id).ok_or_else(|| formation_exit::Error::Input(format!("no follower {}", a.id)))?;
        sources.extend(scenario.graph.neighbours(i).iter().map(|&j| scenario.graph.id(j)));
        if scenario.graph.hears_leader(i) {
            sources.push(wire::LEADER_ID);
        }
    }
    if a.lockstep {
        return lockstep_node(a, &session, &keys, &scenario, sources).await;
    }
    let received = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let mut subs = Vec::new();
    for s in sources {
        let r = received.clone();
        let sub = session
            .declare_subscriber(keys.estimate(s))
            .callback(move |sample| {
                // What an agent does at least: take the bytes and decode them.
                let _ = wire::decode(&sample.payload().to_bytes());
                r.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            })
            .await
            .map_err(|e| formation_exit::Error::Run(e.to_string()))?;
        subs.push(sub);
    }
    let publisher = session
        .declare_publisher(keys.estimate(a.id))
        .congestion_control(formation_net::node::estimate_congestion(&scenario))
        .priority(formation_net::node::priority::ESTIMATE)
        .express(formation_net::node::estimate_express(&scenario))
        .await
        .map_err(|e| formation_exit::Error::Run(e.to_string()))?;
    let period = Duration::from_secs_f64(scenario.dt_s);
    let steps = (a.seconds / scenario.dt_s) as u64;
    // As an agent's real-time loop: a task on zenoh's own thread woken by
    // a timerfd, so the put is written to the sockets in the same wake-up.
    formation_net::timer::on_zenoh_thread(async move {
        let timer = formation_net::timer::Timer::new().map_err(|e| format!("a timer: {e}"))?;
        // Every floor process steps on one grid, the wall clock's whole
        // seconds (the period divides a second), as agents step on the
        // leader's timebase: neighbours' messages then arrive while a
        // process is awake for its own step, as they do for an agent.
        let wall = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
        let began = Instant::now() + (Duration::from_secs(wall.as_secs() + 1) - wall);
        for k in 0..steps {
            timer
                .sleep_until(began + period * k as u32, &formation_net::clock::Clock::real())
                .await
                .map_err(|e| format!("the timer: {e}"))?;
            let msg = EstimateMsg {
                header: Header { version: FORMAT_VERSION, sender: 0, step: k, time_s: k as f64 * 1e-3, sent_ns: 0 },
                state: Default::default(),
                fresh: true,
                term: 1,
            };
            let _ = publisher.put(wire::encode(&msg)).wait();
        }
        Ok::<(), String>(())
    })
    .await
    .and_then(|r| r)
    .map_err(formation_exit::Error::Run)?;
    drop(subs);
    let _ = session.close().await;
    Ok(())
}

/// What a lock-step floor process has heard: each source's newest step.
struct Heard {
    newest: std::sync::Mutex<Vec<Option<u64>>>,
    moved: std::sync::Condvar,
}

/// `--lockstep`: see [`FloorArgs::lockstep`]. A follower publishes step k,
/// then waits for every source's step k (repeating its newest message as
/// often as an agent does while it waits, which also carries the start: a
/// process that comes late hears it). The leader waits for the followers that
/// hear it, at most the leader's window ahead of the slowest. Prints
/// `steps/s R` on stdout.
async fn lockstep_node(
    a: &FloorArgs,
    session: &zenoh::Session,
    keys: &formation_protocol::names::Keys,
    scenario: &formation_scenario::Scenario,
    sources: Vec<u32>,
) -> Result<(), formation_exit::Error> {
    let leader = a.id == 0;
    // The leader waits for the followers that hear it; a follower for its sources.
    let waits: Vec<u32> = if leader {
        (0..scenario.followers.len())
            .filter(|&i| scenario.graph.hears_leader(i))
            .map(|i| scenario.graph.id(i))
            .collect()
    } else {
        sources
    };
    let heard = std::sync::Arc::new(Heard {
        newest: std::sync::Mutex::new(vec![None; waits.len()]),
        moved: std::sync::Condvar::new(),
    });
    let mut subs = Vec::new();
    for (slot, &s) in waits.iter().enumerate() {
        let h = heard.clone();
        let sub = session
            .declare_subscriber(keys.estimate(s))
            .callback(move |sample| {
                if let Ok(m) = wire::decode(&sample.payload().to_bytes()) {
                    let mut n = h.newest.lock().unwrap_or_else(|p| p.into_inner());
                    if n[slot].is_none_or(|k| m.header.step > k) {
                        n[slot] = Some(m.header.step);
                        h.moved.notify_one();
                    }
                }
            })
            .await
            .map_err(|e| formation_exit::Error::Run(e.to_string()))?;
        subs.push(sub);
    }
    let publisher = session
        .declare_publisher(keys.estimate(a.id))
        .congestion_control(formation_net::node::estimate_congestion(scenario))
        .priority(formation_net::node::priority::ESTIMATE)
        .express(formation_net::node::estimate_express(scenario))
        .await
        .map_err(|e| formation_exit::Error::Run(e.to_string()))?;
    let steps = (a.seconds / scenario.dt_s).round() as u64;
    let dt = scenario.dt_s;
    let rate = tokio::task::spawn_blocking(move || floor_loop(leader, steps, dt, &heard, &publisher))
        .await
        .map_err(|e| formation_exit::Error::Run(e.to_string()))?
        .map_err(|e| formation_exit::Error::Run(format!("{}: {e}", a.id)))?;
    println!("steps/s {rate:.1}");
    // A while before the session closes, so that the last steps reach the neighbours.
    tokio::time::sleep(Duration::from_millis(300)).await;
    drop(subs);
    let _ = session.close().await;
    Ok(())
}

/// The floor's lock-step loop: each step waits for what the agent or the
/// leader would wait for (the leader by the window rule,
/// `gate::leader_needs`), repeating its last message while it waits, then
/// publishes; the steps per second over the run's middle half.
fn floor_loop(
    leader: bool,
    steps: u64,
    dt: f64,
    heard: &Heard,
    publisher: &zenoh::pubsub::Publisher<'_>,
) -> Result<f64, String> {
    let msg = |k: u64| {
        wire::encode(&EstimateMsg {
            header: Header { version: FORMAT_VERSION, sender: 0, step: k, time_s: k as f64 * dt, sent_ns: 0 },
            state: Default::default(),
            fresh: true,
            term: 1,
        })
    };
    let (from, to) = (steps / 4, 3 * steps / 4);
    // As often as the agents and the leader repeat theirs (protocol::gate).
    let every = if leader {
        formation_protocol::gate::LEADER_REPEAT_EVERY
    } else {
        formation_protocol::gate::FOLLOWER_REPEAT_EVERY
    };
    let mut marks = (Instant::now(), Instant::now());
    for k in 0..=steps {
        // What step k waits for: the sources' k − 1 (a follower); the
        // slowest hearing follower within the window, and at the start
        // every one of them (the leader).
        let need = match (leader, k) {
            (false, 0) => None,
            (false, k) => Some(k - 1),
            (true, 0) => None,
            (true, 1) => Some(0),
            (true, k) => formation_protocol::gate::leader_needs(k),
        };
        let bytes = msg(k.saturating_sub(1));
        let mut n = heard.newest.lock().unwrap_or_else(|p| p.into_inner());
        let began = Instant::now();
        while let Some(need) = need {
            if n.iter().all(|h| h.is_some_and(|s| s >= need)) {
                break;
            }
            let (g, t) = heard.moved.wait_timeout(n, every).unwrap_or_else(|p| p.into_inner());
            n = g;
            if t.timed_out() {
                if began.elapsed() > Duration::from_secs(30) {
                    return Err(format!("no step {need} from every source for 30 s"));
                }
                if k > 0 {
                    // Not under the lock the callbacks take.
                    drop(n);
                    let _ = publisher.put(bytes.clone()).wait();
                    n = heard.newest.lock().unwrap_or_else(|p| p.into_inner());
                }
            }
        }
        drop(n);
        if k == from {
            marks.0 = Instant::now();
        }
        if k == to {
            marks.1 = Instant::now();
        }
        let _ = publisher.put(msg(k)).wait();
    }
    Ok((to - from) as f64 / (marks.1 - marks.0).as_secs_f64().max(1e-9))
}

/// Starts the floor's processes (a router first for `Clients`, then the
/// leader's stand-in and one per follower of `ids`), `extra` added to each
/// floor process's arguments; their stdout piped where `piped` (a lock-step
/// floor prints its rate), else discarded.
#[allow(clippy::too_many_arguments)]
fn floor_processes(
    exe: &std::path::Path,
    scenario: &std::path::Path,
    ids: &[u32],
    links: Links,
    port: u16,
    sets: &[String],
    run: &str,
    extra: &[String],
    piped: bool,
    eps: &formation_launch::plan::Endpoints,
) -> Result<Vec<std::process::Child>, Error> {
    let mut children = Vec::new();
    let quiet = |c: &mut Command| {
        c.env(formation_net::node::LAUNCHED_ENV, "1").stdin(Stdio::null()).stdout(Stdio::null()).stderr(Stdio::null());
    };
    let router = eps.dial(port);
    if links == Links::Clients {
        let mut c = Command::new(exe);
        c.args(["node", "router", "--mode", "router"]);
        for l in eps.listen(port) {
            c.arg("--listen").arg(l);
        }
        c.arg("--scenario").arg(scenario);
        for set in sets {
            c.args(["--set", set]);
        }
        formation_net::session::router_runtime(&mut c, formation_scenario::Timing::Realtime);
        quiet(&mut c);
        children.push(c.spawn().map_err(|e| Error::Run(format!("starting the floor's router: {e}")))?);
    }
    let all: Vec<u32> = std::iter::once(0).chain(ids.iter().copied()).collect();
    for (n, &id) in all.iter().enumerate() {
        let mut c = Command::new(exe);
        c.args(["bench-floor", "--scenario"]).arg(scenario).args(["--run", run, "--id", &id.to_string()]);
        c.args(extra);
        match links {
            Links::Peers => {
                c.arg("--no-gossip");
                for l in eps.listen(port + 1 + n as u16) {
                    c.arg("--listen").arg(l);
                }
                for m in 0..n {
                    c.arg("--connect").arg(eps.dial(port + 1 + m as u16));
                }
            }
            Links::Clients => {
                c.args(["--mode", "client", "--connect", &router]);
            }
        }
        for set in sets {
            c.args(["--set", set]);
        }
        quiet(&mut c);
        if piped {
            c.stdout(Stdio::piped());
        }
        match c.spawn() {
            Ok(child) => children.push(child),
            Err(e) => {
                for mut c in children {
                    let _ = c.kill();
                    let _ = c.wait();
                }
                return Err(Error::Run(format!("starting a floor process: {e}")));
            }
        }
    }
    Ok(children)
}

/// Lock-step's floor: the floor processes of `ids` (as [`FloorArgs::lockstep`])
/// stepping `seconds / Δt` steps as fast as their messages allow; the
/// median over the processes of each one's steady rate (steps/s, the
/// middle half of its steps).
pub fn lockstep_rate(
    scenario: &std::path::Path,
    sets: &[String],
    seconds: f64,
    clients: bool,
    kind: formation_launch::options::Links,
    port: u16,
) -> Result<f64, Error> {
    let exe = std::env::current_exe().map_err(|e| Error::Run(format!("locating this executable: {e}")))?;
    let s = formation_scenario::Scenario::load(scenario, sets).map_err(|e| Error::Input(e.to_string()))?;
    let links = if clients { Links::Clients } else { Links::Peers };
    let run = format!("floorls{}", std::process::id());
    let extra = ["--lockstep".to_string(), "--seconds".into(), seconds.to_string()];
    let eps = formation_launch::plan::Endpoints::new(kind)?;
    let mut children = floor_processes(&exe, scenario, s.graph.ids(), links, port, sets, &run, &extra, true, &eps)?;
    let router = if clients { Some(children.remove(0)) } else { None };
    let mut rates = Vec::new();
    let mut failed = 0;
    for c in children {
        match c.wait_with_output() {
            Ok(o) if o.status.success() => {
                let text = String::from_utf8_lossy(&o.stdout);
                rates.extend(text.lines().filter_map(|l| l.strip_prefix("steps/s ")?.trim().parse::<f64>().ok()));
            }
            _ => failed += 1,
        }
    }
    if let Some(mut r) = router {
        let _ = r.kill();
        let _ = r.wait();
    }
    if failed > 0 || rates.is_empty() {
        return Err(Error::Run(format!("the lock-step floor: {failed} of its processes failed")));
    }
    Ok(median(rates))
}

/// On-CPU ns of every thread of `pid` so far.
fn cpu_ns(pid: u32) -> u64 {
    let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else { return 0 };
    tasks
        .flatten()
        .filter_map(|t| std::fs::read_to_string(t.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next().and_then(|x| x.parse::<u64>().ok()))
        .sum()
}

/// Processes whose command line holds every one of `words`; not the
/// floor's stand-in for the leader (`--id 0`): the agents' figures are the
/// followers', so the floor's are too.
fn pids_with(words: &[&str]) -> Vec<u32> {
    let mut found = Vec::new();
    for e in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else { continue };
        let Ok(cmd) = std::fs::read(format!("/proc/{pid}/cmdline")) else { continue };
        let args: Vec<String> = cmd.split(|&b| b == 0).map(|a| String::from_utf8_lossy(a).into_owned()).collect();
        let leader = args.windows(2).any(|w| w[0] == "--id" && w[1] == "0");
        if words.iter().all(|w| args.iter().any(|a| a == w)) && !leader {
            found.push(pid);
        }
    }
    found
}

/// CPU µs per step of each process named by `words`, over `window` from
/// `after` on, at `rate` steps per second.
fn sample(words: &[&str], after: Duration, window: Duration, rate: f64) -> Vec<f64> {
    std::thread::sleep(after);
    let pids = pids_with(words);
    let before: Vec<u64> = pids.iter().map(|&p| cpu_ns(p)).collect();
    std::thread::sleep(window);
    let steps = window.as_secs_f64() * rate;
    pids.iter().zip(before).map(|(&p, b)| cpu_ns(p).saturating_sub(b) as f64 / 1e3 / steps).collect()
}

/// How the processes of one measurement meet.
#[derive(Clone, Copy, PartialEq, Debug)]
enum Links {
    /// Peers, each linked to the leader and the lower ids (as `launch`).
    Peers,
    /// Clients of one router (as `launch --mode client`).
    Clients,
}

/// One case: the floor and the agents of `scenario` at `hz`, the median CPU
/// µs per process and step of each, and how many processes each had.
fn case(
    exe: &std::path::Path,
    scenario: &std::path::Path,
    ids: &[u32],
    hz: f64,
    links: Links,
    kind: formation_launch::options::Links,
    port: u16,
) -> Result<((f64, usize), (f64, usize)), Error> {
    // Many processes take longer to start: a later, still steady window.
    let (seconds, after, window) = if ids.len() > 10 {
        (16.0, Duration::from_secs(8), Duration::from_secs(5))
    } else {
        (12.0, Duration::from_secs(4), Duration::from_secs(5))
    };
    let sets = [format!("dt={}", 1.0 / hz), "timing=\"realtime\"".into(), format!("duration={seconds}")];
    let run = format!("floor{}{}", hz as u32, ids.len());
    let extra = ["--seconds".to_string(), seconds.to_string()];
    let eps = formation_launch::plan::Endpoints::new(kind)?;
    let mut children = floor_processes(exe, scenario, ids, links, port, &sets, &run, &extra, false, &eps)?;
    let floor = sample(&["bench-floor", &run], after, window, hz);
    // The router's last: it outlives the floor processes.
    let router_child = if links == Links::Clients { Some(children.remove(0)) } else { None };
    for mut c in children {
        let _ = c.wait();
    }
    if let Some(mut r) = router_child {
        let _ = r.kill();
        let _ = r.wait();
    }
    // The agents of a real launch, sampled the same way.
    let out = std::env::temp_dir().join(format!("formation-bench-floor-{}-{run}", std::process::id()));
    let lrun = format!("agents{}{}", hz as u32, ids.len());
    let mut l = Command::new(exe);
    l.args(["launch"]).arg(scenario).args(["-q", "--out"]).arg(&out).args([
        "--run",
        &lrun,
        "--base-port",
        &(port + 200).to_string(),
        "--links",
        kind.arg(),
    ]);
    if links == Links::Clients {
        l.args(["--mode", "client"]);
    }
    for set in &sets {
        l.args(["--set", set]);
    }
    let mut launch = l
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| Error::Run(format!("starting the launch: {e}")))?;
    let agents = sample(&["agent", &lrun], after, window, hz);
    let _ = launch.wait();
    let _ = std::fs::remove_dir_all(&out);
    let (nf, na) = (floor.len(), agents.len());
    Ok(((median(floor), nf), (median(agents), na)))
}

fn row(what: String, ((f, nf), (g, na)): ((f64, usize), (f64, usize))) {
    println!("  {:<54}{:>12.1}{:>12.1}{:>8.2}", format!("{what} (median of {nf} / {na})"), f, g, g / f);
}

/// The floor, the agents and the idle cost: the scenario's agents (peers)
/// at 100 Hz and 1 kHz; generated rings of `rings` agents (n/5 chords,
/// clients of one router) at 100 Hz.
pub fn run(
    scenario: &std::path::Path,
    port: u16,
    rings: &[u32],
    kind: formation_launch::options::Links,
) -> Result<(), Error> {
    let exe = std::env::current_exe().map_err(|e| Error::Run(format!("locating this executable: {e}")))?;
    let s = formation_scenario::Scenario::load(scenario, &[]).map_err(|e| Error::Input(e.to_string()))?;
    let ids: Vec<u32> = s.graph.ids().to_vec();
    println!(
        "CPU per process and step in steady state (a 5 s window from 4 s into a 12 s run; 8 s into 16 s for rings), \
         {} links, this machine",
        kind.label()
    );
    println!("  {:<54}{:>12}{:>12}{:>8}", "", "floor µs", "agent µs", "ratio");
    for hz in [100.0, 1000.0] {
        eprintln!("bench-net (floor): {} agents, peers, {hz} Hz …", ids.len());
        row(format!("{} agents, peers, {hz} Hz", ids.len()), case(&exe, scenario, &ids, hz, Links::Peers, kind, port)?);
    }
    for (i, &n) in rings.iter().enumerate() {
        let tmp = std::env::temp_dir().join(format!("formation-bench-floor-{}-ring{n}", std::process::id()));
        let file = ring_file(&tmp, n)?;
        let ring_ids: Vec<u32> = formation_scenario::Scenario::load(&file, &[])
            .map_err(|e| Error::Input(e.to_string()))?
            .graph
            .ids()
            .to_vec();
        eprintln!("bench-net (floor): a ring of {n} agents, clients of one router, 100 Hz …");
        let measured = case(&exe, &file, &ring_ids, 100.0, Links::Clients, kind, port + 400 + 400 * i as u16);
        let _ = std::fs::remove_dir_all(&tmp);
        row(format!("ring of {n}, clients, 100 Hz"), measured?);
    }
    // Idle: an agent that waits for a start that never comes.
    let mut c = Command::new(&exe);
    let idle_run = format!("idle{}", std::process::id());
    c.args(["node", "agent", "--scenario"]).arg(scenario).args(["--run", &idle_run, "--id", &ids[0].to_string()]);
    c.args(["--listen", &format!("tcp/127.0.0.1:{}", port + 40), "--open-timeout", "60"]);
    c.env(formation_net::node::LAUNCHED_ENV, "1").stdin(Stdio::null()).stdout(Stdio::null()).stderr(Stdio::null());
    let mut idle = c.spawn().map_err(|e| Error::Run(format!("starting the idle agent: {e}")))?;
    // From 12 s: past the barrier's first 2 s of fast ticks and the clock
    // questions' first 10 s (steady idle). Five windows of 2 s, their
    // median: one burst of the VM's (single 5 s windows read 0.501 % and
    // 0.319 % once each, 25 and 16 ms) does not make the figure.
    let window = Duration::from_secs(2);
    let mut shares: Vec<f64> = (0..5)
        .map(|w| {
            let after = if w == 0 { Duration::from_secs(12) } else { Duration::ZERO };
            let per = sample(&["agent", &idle_run], after, window, 1.0);
            per.first().copied().unwrap_or(f64::NAN) / 1e6 * 100.0
        })
        .collect();
    let _ = idle.kill();
    let _ = idle.wait();
    shares.sort_by(f64::total_cmp);
    let most = shares.last().copied().unwrap_or(f64::NAN);
    println!(
        "  an agent waiting with nothing to do: {:.3} % of a core (median of five 2 s windows; the most {most:.3} %)",
        median(shares)
    );
    Ok(())
}
