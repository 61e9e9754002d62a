//! `formation bench-net`: speed of the networked formation on this machine.
//!
//! 1. Lock-step steps per second over zenoh (`formation launch` of the
//!    paper scenario, peer mode) next to the in-process simulator's. Two
//!    runs of different length are timed and the difference is used, so
//!    process start-up and the start barrier do not count.
//! 2. Real-time control-loop period error (p50, p99, max) at 1 kHz with the
//!    scenario's agents (from the nodes' own loop statistics).
//! 3. One-hop latency of an estimate message (half the round trip through
//!    the agents' encode → put → subscriber callback → decode and checks →
//!    inbox path) next to a plain zenoh ping-pong of the same size, measured
//!    interleaved between the same two peer sessions over loopback TCP.
//! 4. The time to open a client session to a listening peer (the handshake).
//! 5. Scale (`--agents 50,100`): generated rings (n/5 chords, as `formation
//!    bench`) as clients of one router — the topology that scales (N links,
//!    where a peer mesh needs N(N−1)/2): lock-step steps/s (two runs, the
//!    difference), start-up (monitor start to every node ready, from
//!    network.json) and, at 100 Hz in real time, the CPU seconds every
//!    process of the run used per agent and per simulated second (the
//!    router, leader and monitor included: their share is the cost of
//!    scale too), with the silent source-steps.
//!
//! With `--tls DIR` every figure is measured twice, over plain TCP and over
//! mutual TLS with access control, and printed side by side.

use std::path::PathBuf;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use formation_protocol::wire;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

use crate::hearing::{network_json, worst_period};
use crate::netns::estimate;
use formation_exit::Error;
use formation_launch::options::{LaunchArgs, LaunchMode, Links, RunOptions};
use formation_net::session::{self, ZenohArgs};
use formation_protocol::inbox::{self, Inbox, Source};
use formation_protocol::loop_timing as timing;
use formation_protocol::names;
use formation_scenario::args::ScenarioArgs;
use formation_sim::{NoRecord, Simulation};

#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct BenchNetArgs {
    /// The scenario (the paper's 4 followers by default).
    #[cfg_attr(feature = "clap", arg(long, default_value = "scenarios/paper.toml"))]
    pub scenario: PathBuf,
    /// Lock-step: run-time seconds of the long run (the short one is 2 s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 20.0))]
    pub lockstep_duration: f64,
    /// Real time: run-time seconds at 1 kHz.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 5.0))]
    pub realtime_duration: f64,
    /// Latency: round trips per kind.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 5000))]
    pub round_trips: usize,
    /// First loopback port to use (about 20 consecutive ports).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 17900))]
    pub base_port: u16,
    /// Also measure with mutual TLS, with the certificates in DIR (made by
    /// `formation certs SCENARIO --out DIR`), side by side with plain TCP.
    #[cfg_attr(feature = "clap", arg(long, value_name = "DIR"))]
    pub tls: Option<PathBuf>,
    /// Scale: also run generated rings of these many agents (n/5 chords) as
    /// clients of one router: lock-step steps/s, start-up, CPU per agent in
    /// real time at 100 Hz. Empty (`--agents ''`) skips it.
    #[cfg_attr(feature = "clap", arg(long, value_parser = agent_list, default_value = "50,100", value_name = "N,N…"))]
    pub agents: AgentList,
    /// Also measure one-hop latency (estimate, plain zenoh, the clock offset
    /// exchange) between two network namespaces on a bridge, as between two
    /// hosts of a LAN (needs root, `ip`).
    #[cfg_attr(feature = "clap", arg(long))]
    pub namespaces: bool,
    /// (Internal, for --namespaces: the echo side, listening here.)
    #[cfg_attr(feature = "clap", arg(long, hide = true, value_name = "ENDPOINT"))]
    pub echo: Option<String>,
    /// (Internal, for --namespaces: the pinging side, connecting here.)
    #[cfg_attr(feature = "clap", arg(long, hide = true, value_name = "ENDPOINT"))]
    pub ping: Option<String>,
    /// Scale: run seconds of the real-time run at 100 Hz.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 5.0))]
    pub scale_realtime_duration: f64,
    /// Only measure what the hearing record costs (`formation replay`'s
    /// input): the real-time run at 1 kHz with and without it, three times
    /// each, period error side by side, its size against the CSVs'.
    #[cfg_attr(feature = "clap", arg(long))]
    pub hearing: bool,
    /// Only what ROS 2 costs: the real-time loop's period error at 1 kHz
    /// with the scenario's [ros2] topics on and off, side by side.
    #[cfg_attr(feature = "clap", arg(long, conflicts_with = "hearing"))]
    pub ros2: bool,
    /// Only the floor under an agent's CPU: plain zenoh processes with the
    /// agents' exact message pattern beside the real agents, CPU per process
    /// and step in steady state at 100 Hz and 1 kHz, their ratio, and an
    /// idle agent's CPU.
    #[cfg_attr(feature = "clap", arg(long, conflicts_with_all = ["hearing", "ros2"]))]
    pub floor: bool,
    /// Every lock-step and scale figure is measured twice: one process per
    /// agent (as on separate machines), and `launch --group N` (N followers
    /// per agent process on one session). 0: every follower in one process.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0, value_name = "N"))]
    pub group: usize,
    /// What the nodes' links run over, as `launch --links` (the floor's
    /// plain-zenoh processes use the same) [default: unix; tcp with --tls].
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub links: Option<Links>,
}

impl BenchNetArgs {
    /// The links of the runs without TLS (and of the floor).
    fn plain_links(&self) -> Links {
        self.links.unwrap_or_default()
    }
}

/// Followers per agent process of the grouped runs for `n` followers.
fn group_size(a: &BenchNetArgs, n: usize) -> usize {
    if a.group > 0 {
        a.group.min(n)
    } else {
        n
    }
}

fn launch_args(a: &BenchNetArgs, sets: &[String], port: u16, out: PathBuf, run: &str) -> LaunchArgs {
    LaunchArgs {
        opts: RunOptions {
            scenario: ScenarioArgs { scenario: a.scenario.clone(), overrides: sets.to_vec(), leader: None },
            out: Some(out),
            run: Some(run.to_string()),
            time_scale: None,
            quiet: true,
            tls: None,
            mcap: false,
            rosbag2: false,
            web: Default::default(),
            rt_priority: None,
            ros2: false,
            robots: None,
            leave: Vec::new(),
            quorum: None,
            quorum_wait: None,
            even_if_cut_off: false,
            absent: Vec::new(),
        },
        mode: LaunchMode::Peer,
        base_port: Some(port),
        group: 1,
        router: None,
        links: Some(a.plain_links()),
        zenoh_config: None,
        standby: false,
        take_over_after: 0.5,
    }
}

fn timed_launch(l: &LaunchArgs) -> Result<f64, Error> {
    let t = Instant::now();
    formation_launch::launch::run(l)?;
    Ok(t.elapsed().as_secs_f64())
}

/// What one transport measured.
struct Figures {
    /// Lock-step steps/s over zenoh, and the wall times of the short and long runs.
    net_rate: f64,
    t_short: f64,
    t_long: f64,
    /// The same with `group` followers per agent process (NaN with TLS, which needs one process each).
    grouped_rate: f64,
    group: usize,
    /// Plain zenoh processes with the agents' lock-step pattern
    /// (`floor::lockstep_rate`), steps/s; NaN with TLS.
    floor_rate: f64,
    /// Real time at 1 kHz: the worst node's |period − 1 ms| p50, p99, max (µs).
    period: (f64, f64, f64),
    /// Silent neighbour-steps summed over the agents.
    silent: u64,
    /// One-hop latency (half round trip, µs): estimate path (p50, p99), plain (p50, p99).
    estimate: (f64, f64),
    plain: (f64, f64),
    /// Median time to open a client session to a listening peer, ms.
    open_ms: f64,
    /// The offset exchange (formation_net::clock_sync): round trip p50/p99 (µs), and
    /// CPU per exchange, both sides (µs).
    time_rtt: (f64, f64),
    time_cpu_us: f64,
}

/// `--agents`: ring sizes, possibly none.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AgentList(pub Vec<u32>);

#[cfg(feature = "clap")]
fn agent_list(s: &str) -> Result<AgentList, String> {
    s.split(',')
        .map(str::trim)
        .filter(|x| !x.is_empty())
        .map(|x| match x.parse::<u32>() {
            Ok(n) if n >= 2 => Ok(n),
            _ => Err(format!("{x:?} is not a number of agents (2 or more)")),
        })
        .collect::<Result<Vec<u32>, String>>()
        .map(AgentList)
}

/// Run-time seconds of the short lock-step run (the rate is the long one's
/// steps beyond it over the extra wall time).
const SHORT_LOCKSTEP_S: f64 = 2.0;

pub fn run(a: &BenchNetArgs) -> Result<(), Error> {
    check_args(a)?;
    if a.echo.is_some() || a.ping.is_some() {
        return crate::netns::run_side(a.echo.as_deref(), a.ping.as_deref(), a.round_trips);
    }
    let scenario = formation_scenario::Scenario::load(&a.scenario, &[]).map_err(|e| Error::Input(e.to_string()))?;
    if a.floor {
        return crate::floor::run(&a.scenario, a.base_port, &a.agents.0, a.plain_links());
    }
    if a.ros2 {
        return crate::ros2::run(a.realtime_duration, a.base_port, &|sets, port, out, run| {
            launch_args(a, sets, port, out, run)
        });
    }
    if a.hearing {
        return crate::hearing::run(a.realtime_duration, a.base_port, &|sets, port, out, run| {
            launch_args(a, sets, port, out, run)
        });
    }
    if let Some(dir) = &a.tls {
        formation_net::identity::check_all(dir, &scenario).map_err(|e| Error::Input(e.0))?;
    }
    let n = scenario.followers.len();
    let sim_s = formation_scenario::Scenario::load(&a.scenario, &lockstep_sets(a.lockstep_duration))
        .map_err(|e| Error::Input(e.to_string()))?;
    let t = Instant::now();
    Simulation::new(&sim_s).run(&mut NoRecord, |_| {}).map_err(|e| Error::Run(e.to_string()))?;
    let sim_rate = sim_s.steps() as f64 / t.elapsed().as_secs_f64();

    for &n in &a.agents.0 {
        formation_exit::at_least_one("--agents", u64::from(n))?;
    }
    let mut tcp = measure(a, &scenario, None, a.base_port)?;
    let mut tls = a.tls.as_deref().map(|d| measure(a, &scenario, Some(d), a.base_port + 50)).transpose()?;
    match (&mut tls, a.tls.as_deref()) {
        (Some(t), Some(d)) => latencies(a, &mut [(&mut tcp, None), (t, Some(d))])?,
        _ => latencies(a, &mut [(&mut tcp, None)])?,
    }
    print_figures(a, n, &tcp, tls.as_ref());
    println!("in-process simulator, same scenario: {sim_rate:.0} steps/s");
    if a.namespaces {
        eprintln!("bench-net: latency between two network namespaces …");
        let ((e50, e99), (p50, p99), (t50, t99)) = crate::netns::measure(a.round_trips)?;
        println!("between two network namespaces on a bridge (plain TCP, peers)");
        println!("  {:<50}{:>18}", "one-hop estimate latency p50/p99 µs", format!("{e50:.1} / {e99:.1}"));
        println!("  {:<50}{:>18}", "one-hop plain zenoh latency p50/p99 µs", format!("{p50:.1} / {p99:.1}"));
        println!("  {:<50}{:>18}", "clock offset exchange round trip p50/p99 µs", format!("{t50:.1} / {t99:.1}"));
    }
    if !a.agents.0.is_empty() {
        print_scale(a)?;
    }
    if let Some(t) = &tls {
        println!(
            "tls / tcp: latency p50 {:.2}, p99 {:.2}; lock-step rate {:.2}; session open {:.1}x",
            t.estimate.0 / tcp.estimate.0,
            t.estimate.1 / tcp.estimate.1,
            t.net_rate / tcp.net_rate,
            t.open_ms / tcp.open_ms
        );
    }
    Ok(())
}

/// The lengths and counts `bench-net` cannot run with, in one line each.
fn check_args(a: &BenchNetArgs) -> Result<(), Error> {
    formation_exit::at_least_one("--round-trips", a.round_trips as u64)?;
    // The lock-step rate is the difference between the short run and this one.
    if !(a.lockstep_duration.is_finite() && a.lockstep_duration > SHORT_LOCKSTEP_S) {
        return Err(Error::Input(format!(
            "--lockstep-duration {}: the long lock-step run must be longer than the short one ({SHORT_LOCKSTEP_S} \
             s); the rate is their difference (e.g. 20)",
            a.lockstep_duration
        )));
    }
    for (flag, d) in
        [("--realtime-duration", a.realtime_duration), ("--scale-realtime-duration", a.scale_realtime_duration)]
    {
        if !(d.is_finite() && d > 0.0) {
            return Err(Error::Input(format!("{flag} {d}: give a positive number of seconds")));
        }
    }
    Ok(())
}

/// The table of the paper scenario's figures: plain links, and TLS beside them when measured.
fn print_figures(a: &BenchNetArgs, n: usize, tcp: &Figures, tls: Option<&Figures>) {
    let row = |what: &str, f: &dyn Fn(&Figures) -> String| {
        let t = tls.map_or(String::new(), |x| format!("{:>18}", f(x)));
        println!("  {what:<50}{:>18}{t}", f(tcp));
    };
    println!(
        "{n} followers + leader, peer processes on this machine{}",
        if tls.is_some() { "; plain TCP against mutual TLS with access control" } else { "" }
    );
    let plain = format!("{} links", a.plain_links().label());
    println!("  {:<50}{:>18}{}", "", plain, if tls.is_some() { format!("{:>18}", "tls") } else { String::new() });
    row("lock-step steps/s over zenoh", &|f| format!("{:.0}", f.net_rate));
    row("  wall s of the 2 s / long run", &|f| format!("{:.2} / {:.2}", f.t_short, f.t_long));
    row("  plain-zenoh floor, same pattern (agents / floor)", &|f| {
        if f.floor_rate.is_nan() {
            "—".into()
        } else {
            format!("{:.0} ({:.2})", f.floor_rate, f.net_rate / f.floor_rate)
        }
    });
    row(&format!("  with {} followers per agent process (--group)", tcp.group), &|f| {
        if f.grouped_rate.is_nan() {
            "—".into()
        } else {
            format!("{:.0}", f.grouped_rate)
        }
    });
    row("real time 1 kHz |period − 1 ms| p50/p99 µs", &|f| format!("{:.1} / {:.1}", f.period.0, f.period.1));
    row("  max µs (worst node)", &|f| format!("{:.1}", f.period.2));
    row("  silent neighbour-steps", &|f| f.silent.to_string());
    row("one-hop estimate latency p50/p99 µs (best of 3)", &|f| format!("{:.1} / {:.1}", f.estimate.0, f.estimate.1));
    row("one-hop plain zenoh latency p50/p99 µs", &|f| format!("{:.1} / {:.1}", f.plain.0, f.plain.1));
    row("opening a client session (handshake) ms", &|f| format!("{:.2}", f.open_ms));
    row("clock offset exchange round trip p50/p99 µs", &|f| format!("{:.1} / {:.1}", f.time_rtt.0, f.time_rtt.1));
    // An agent asks 4 times a second: its share of a core, both sides counted.
    row("clock offset exchange CPU, % of a core per agent", &|f| format!("{:.4}", f.time_cpu_us * 4.0 / 1e6 * 100.0));
}

/// `--agents`: the table of start-up, lock-step and real-time cost of the
/// generated rings of each size (one agent per process, and grouped).
fn print_scale(a: &BenchNetArgs) -> Result<(), Error> {
    let mut rows: Vec<Scale> = Vec::new();
    for (i, &n) in a.agents.0.iter().enumerate() {
        let port = a.base_port + 100 + 40 * i as u16;
        rows.push(scale(a, n, 1, port)?);
        let g = group_size(a, n as usize);
        if g > 1 {
            rows.push(scale(a, n, g, port + 20)?);
        }
    }
    println!("scale: generated rings (n/5 chords), clients of one router, plain TCP, on this machine");
    println!(
        "  {:>6} {:>12} {:>12} {:>18} {:>16} {:>16} {:>26} {:>8}",
        "agents",
        "per process",
        "start-up s",
        "lock-step steps/s",
        "(wall s, runs)",
        "floor (ratio)",
        "real time 100 Hz: CPU s",
        "silent"
    );
    for r in rows {
        println!(
            "  {:>6} {:>12} {:>12.2} {:>18.0} {:>16} {:>16} {:>26} {:>8}",
            r.agents,
            r.group,
            r.startup_s,
            r.rate,
            format!("{:.1} / {:.1}", r.t_short, r.t_long),
            if r.floor_rate.is_nan() {
                "—".into()
            } else {
                format!("{:.0} ({:.2})", r.floor_rate, r.rate / r.floor_rate)
            },
            format!("{:.4} per agent and run-s", r.cpu_per_agent_s),
            r.silent
        );
    }
    println!(
        "  (CPU: every process of the run — agents, leader, monitor, router — over the agents and the run \
         seconds; silent: source-steps counted silent)"
    );
    Ok(())
}

fn lockstep_sets(d: f64) -> Vec<String> {
    vec![format!("duration={d}"), "timing=lockstep".to_string()]
}

/// Every figure over one transport: plain TCP (`tls` None) or mutual TLS
/// with the certificates in `tls`, on ports from `port`.
fn measure(
    a: &BenchNetArgs,
    scenario: &formation_scenario::Scenario,
    tls: Option<&std::path::Path>,
    port: u16,
) -> Result<Figures, Error> {
    let kind = if tls.is_some() { "tls" } else { a.plain_links().arg() };
    let tmp = std::env::temp_dir().join(format!("formation-bench-net-{}-{kind}", std::process::id()));
    eprintln!("bench-net ({kind}): lock-step runs …");
    // 1. Lock-step: two runs of different length; the difference is the stepping.
    let short = SHORT_LOCKSTEP_S;
    let launch = |sets: &[String], p: u16, out: &str, run: &str| {
        let mut l = launch_args(a, sets, p, tmp.join(out), run);
        l.opts.tls = tls.map(std::path::Path::to_path_buf);
        if tls.is_some() {
            l.links = Some(Links::Tcp);
        }
        l
    };
    let t_short = timed_launch(&launch(&lockstep_sets(short), port, "ls-short", "bench-ls1"))?;
    let t_long = timed_launch(&launch(&lockstep_sets(a.lockstep_duration), port + 10, "ls-long", "bench-ls2"))?;
    let dsteps = ((a.lockstep_duration - short) / scenario.dt_s).round();
    let net_rate = dsteps / (t_long - t_short).max(1e-9);
    let group = group_size(a, scenario.followers.len());
    let grouped_rate = if tls.is_none() {
        eprintln!("bench-net ({kind}): lock-step runs, {group} followers per agent process …");
        let grouped = |sets: &[String], p: u16, out: &str, run: &str| {
            let mut l = launch(sets, p, out, run);
            l.group = group;
            l
        };
        let g_short = timed_launch(&grouped(&lockstep_sets(short), port + 30, "lsg-short", "bench-lsg1"))?;
        let g_long = timed_launch(&grouped(&lockstep_sets(a.lockstep_duration), port + 34, "lsg-long", "bench-lsg2"))?;
        dsteps / (g_long - g_short).max(1e-9)
    } else {
        f64::NAN
    };
    let floor_rate = if tls.is_none() {
        eprintln!("bench-net ({kind}): lock-step floor (plain zenoh, the same pattern) …");
        crate::floor::lockstep_rate(&a.scenario, &[], a.lockstep_duration, false, a.plain_links(), port + 90)?
    } else {
        f64::NAN
    };

    // 2. Real-time period error at 1 kHz.
    eprintln!("bench-net ({kind}): real time at 1 kHz …");
    let rt_sets = vec![format!("duration={}", a.realtime_duration), "timing=realtime".into(), "dt=0.001".into()];
    let mut l = launch(&rt_sets, port + 20, "rt", "bench-rt");
    l.opts.time_scale = Some(1.0);
    formation_launch::launch::run(&l)?;
    let net = network_json(&tmp.join("rt"), "the real-time run")?;
    let period = worst_period(&net);
    let silent =
        net["nodes"].as_object().into_iter().flat_map(|n| n.values()).filter_map(|v| v["silent"].as_u64()).sum();

    let _ = std::fs::remove_dir_all(&tmp);
    let nan = (f64::NAN, f64::NAN);
    Ok(Figures {
        net_rate,
        t_short,
        t_long,
        grouped_rate,
        group,
        floor_rate,
        period,
        silent,
        estimate: nan,
        plain: nan,
        open_ms: f64::NAN,
        time_rtt: nan,
        time_cpu_us: f64::NAN,
    })
}

/// The run folder `dir`'s network.json (`what`: the run, for the error).
/// One row of the scale table.
struct Scale {
    agents: u32,
    /// Followers per agent process.
    group: usize,
    startup_s: f64,
    rate: f64,
    t_short: f64,
    t_long: f64,
    /// The plain-zenoh floor of the same lock-step pattern (one process each only).
    floor_rate: f64,
    cpu_per_agent_s: f64,
    silent: u64,
}

/// CPU seconds (user + system) of this process so far.
fn process_cpu_s() -> f64 {
    cpu_s(libc::RUSAGE_SELF)
}

/// CPU seconds (user + system) of this process's waited-for children so far.
fn children_cpu_s() -> f64 {
    cpu_s(libc::RUSAGE_CHILDREN)
}

fn cpu_s(who: libc::c_int) -> f64 {
    // SAFETY: getrusage writes into the struct it is given, nothing else.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    if unsafe { libc::getrusage(who, &mut u) } != 0 {
        return f64::NAN;
    }
    let s = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    s(u.ru_utime) + s(u.ru_stime)
}

/// `n` agents on a generated ring as clients of one router, `group`
/// followers per agent process, ports from `port`.
fn scale(a: &BenchNetArgs, n: u32, group: usize, port: u16) -> Result<Scale, Error> {
    let tmp = std::env::temp_dir().join(format!("formation-bench-net-{}-scale{n}-{group}", std::process::id()));
    let file = crate::floor::ring_file(&tmp, n)?;
    let launch = |sets: Vec<String>, p: u16, out: &str, run: &str| {
        let mut l = launch_args(&BenchNetArgs { scenario: file.clone(), ..a.clone() }, &sets, p, tmp.join(out), run);
        l.mode = LaunchMode::Client;
        l.group = group;
        l
    };
    let what = format!("the {n}-agent run");
    let wall = |out: &str| network_json(&tmp.join(out), &what);
    eprintln!("bench-net (scale): {n} agents, {group} per process, lock-step …");
    // Lock-step: 200 and 1,200 steps at Δt = 1 ms; the difference is the stepping.
    let (short, long) = (0.2, 1.2);
    let t_short = timed_launch(&launch(lockstep_sets(short), port, "short", &format!("bench-s{n}a")))?;
    let t_long = timed_launch(&launch(lockstep_sets(long), port + 5, "long", &format!("bench-s{n}b")))?;
    let rate = ((long - short) / 0.001_f64).round() / (t_long - t_short).max(1e-9);
    let startup_s = wall("long")?["wall"]["startup_s"].as_f64().unwrap_or(f64::NAN);
    let floor_rate = if group == 1 {
        eprintln!("bench-net (scale): {n} agents, lock-step floor (plain zenoh, the same pattern) …");
        crate::floor::lockstep_rate(&file, &lockstep_sets(long), long, true, a.plain_links(), port + 35)?
    } else {
        f64::NAN
    };
    eprintln!("bench-net (scale): {n} agents, {group} per process, real time at 100 Hz …");
    let d = a.scale_realtime_duration;
    let sets =
        vec![format!("duration={d}"), "timing=realtime".into(), "dt=0.01".into(), "network.delay_steps=1".into()];
    let mut l = launch(sets, port + 10, "rt", &format!("bench-s{n}c"));
    l.opts.time_scale = Some(1.0);
    let cpu0 = children_cpu_s();
    formation_launch::launch::run(&l)?;
    let cpu = children_cpu_s() - cpu0;
    let net = wall("rt")?;
    let silent = net["nodes"].as_object().map_or(0, |m| m.values().map(|v| v["silent"].as_u64().unwrap_or(0)).sum());
    let _ = std::fs::remove_dir_all(&tmp);
    Ok(Scale {
        agents: n,
        group,
        startup_s,
        rate,
        t_short,
        t_long,
        floor_rate,
        cpu_per_agent_s: cpu / f64::from(n) / d,
        silent,
    })
}

/// Latency and session opening, the transports alternating over `ROUNDS`
/// rounds so that both see the same machine; the best round of each.
fn latencies(a: &BenchNetArgs, figures: &mut [(&mut Figures, Option<&std::path::Path>)]) -> Result<(), Error> {
    const ROUNDS: u16 = 3;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| Error::Run(format!("starting the async runtime: {e}")))?;
    for round in 0..ROUNDS {
        for (i, (f, tls)) in figures.iter_mut().enumerate() {
            let kind = if tls.is_some() { "tls" } else { "tcp" };
            eprintln!("bench-net ({kind}): latency, round {} of {ROUNDS} …", round + 1);
            let port = a.base_port + 40 + 50 * i as u16 + 2 * round;
            let l = runtime
                .block_on(latency(port, a.round_trips, *tls))
                .map_err(|e| Error::Run(format!("latency benchmark ({kind}): {e}")))?;
            // NaN (no round yet) or a better round.
            if f.time_rtt.0.is_nan() || l.time_rtt.0 < f.time_rtt.0 {
                (f.time_rtt, f.time_cpu_us) = (l.time_rtt, l.time_cpu_us);
            }
            if f.estimate.0.is_nan() || l.estimate.0 < f.estimate.0 {
                f.estimate = l.estimate;
            }
            if f.plain.0.is_nan() || l.plain.0 < f.plain.0 {
                f.plain = l.plain;
            }
            if f.open_ms.is_nan() || l.open_ms < f.open_ms {
                f.open_ms = l.open_ms;
            }
        }
    }
    Ok(())
}

#[derive(Default)]
struct Flag {
    hits: Mutex<u64>,
    cv: Condvar,
}

impl Flag {
    fn hit(&self) {
        *self.hits.lock().unwrap_or_else(|p| p.into_inner()) += 1;
        self.cv.notify_all();
    }
    fn wait_for(&self, n: u64) -> bool {
        let mut g = self.hits.lock().unwrap_or_else(|p| p.into_inner());
        while *g < n {
            let (ng, to) = self.cv.wait_timeout(g, Duration::from_secs(2)).unwrap_or_else(|p| p.into_inner());
            g = ng;
            if to.timed_out() {
                return false;
            }
        }
        true
    }
}

/// Receive path of an agent: decode + checks + inbox.
fn receive(inbox: &Mutex<Inbox>, key: &str, bytes: &[u8], neighbours: &[u32]) -> bool {
    let key_id = names::last_chunk(key).parse::<u32>().ok();
    let mut i = inbox.lock().unwrap_or_else(|p| p.into_inner());
    match inbox::check(key_id, bytes, false, neighbours) {
        Ok((Source::Neighbour(slot), m)) => {
            i.accept(slot, &m);
            true
        }
        _ => false,
    }
}

/// One round of the latency benchmark. The two sessions are agents 1 and 2
/// (with their identities under `tls`); the plain ping-pong uses the same
/// keys in another run's namespace, so the access-control policy lets it
/// through.
struct Latencies {
    /// One-hop latency (half round trip, µs), (p50, p99): through the
    /// agents' estimate path, and plain zenoh.
    estimate: (f64, f64),
    plain: (f64, f64),
    /// Median time to open a client session to a listening peer, ms.
    open_ms: f64,
    /// The offset exchange: round trip (p50, p99), µs, and this process's
    /// CPU per exchange (both sides), µs.
    time_rtt: (f64, f64),
    time_cpu_us: f64,
}

/// The arguments of a session with agent `id`'s identity.
fn as_agent(id: u32, tls: Option<&std::path::Path>) -> ZenohArgs {
    ZenohArgs {
        tls: tls.map(std::path::Path::to_path_buf),
        identity: Some(formation_protocol::names::agent_name(id)),
        ..Default::default()
    }
}

async fn latency(port: u16, n: usize, tls: Option<&std::path::Path>) -> Result<Latencies, Error> {
    let ep = format!("tcp/127.0.0.1:{port}");
    let a = session::open(&ZenohArgs { listen: vec![ep.clone()], ..as_agent(1, tls) }).await?;
    let b = session::open(&ZenohArgs {
        listen: vec![format!("tcp/127.0.0.1:{}", port + 1)],
        connect: vec![ep.clone()],
        ..as_agent(2, tls)
    })
    .await?;
    let open_ms = handshake_ms(&ep, tls).await?;
    let _answers = answer(&b).await?;
    let (pinger, _counters) = Pinger::declare(&a).await?;
    let (mut est, mut plain) = tokio::task::spawn_blocking(move || pinger.ping_pong(n))
        .await
        .map_err(|e| Error::Run(format!("the latency measurement panicked: {e}")))??;
    let (e50, e99, _) = timing::percentiles(&mut est);
    let (p50, p99, _) = timing::percentiles(&mut plain);
    let (time_rtt, time_cpu_us) = time_exchange(&a, &ep, tls, n).await?;
    let _ = a.close().await;
    let _ = b.close().await;
    Ok(Latencies { estimate: (e50, e99), plain: (p50, p99), open_ms, time_rtt, time_cpu_us })
}

/// Handshakes: a client of agent 2's identity opening to `ep`, 20 times;
/// the median, ms.
async fn handshake_ms(ep: &str, tls: Option<&std::path::Path>) -> Result<f64, Error> {
    let mut opens = Vec::with_capacity(20);
    for _ in 0..20 {
        let t = Instant::now();
        let c = session::open(&ZenohArgs {
            mode: Some(session::ZenohMode::Client),
            connect: vec![ep.to_string()],
            ..as_agent(2, tls)
        })
        .await?;
        opens.push(t.elapsed().as_secs_f64() * 1e3);
        let _ = c.close().await;
    }
    let (open_ms, _, _) = timing::percentiles(&mut opens);
    Ok(open_ms)
}

/// The run of the estimate ping-pong.
const LATENCY_RUN: &str = "bench-lat";

/// A publisher of the ping-pong: express, blocking when congested.
async fn publisher(s: &zenoh::Session, key: String) -> Result<Publisher<'static>, Error> {
    s.declare_publisher(key)
        .express(true)
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| Error::Run(e.to_string()))
}

/// Session B: echo plain pings, answer estimates from "follower 1" with its
/// own as "follower 2". The subscribers answer while they are held.
async fn answer(b: &zenoh::Session) -> Result<[Subscriber<()>; 2], Error> {
    let b_plain_pub = publisher(b, names::key("bench-ping", "estimate/2")).await?;
    let b_est_pub = publisher(b, names::key(LATENCY_RUN, "estimate/2")).await?;
    let plain = b
        .declare_subscriber(names::key("bench-ping", "estimate/1"))
        .callback(move |s| {
            let _ = b_plain_pub.put(s.payload().to_bytes().into_owned()).wait();
        })
        .await
        .map_err(|e| Error::Run(e.to_string()))?;
    let b_inbox = Arc::new(Mutex::new(Inbox::new(1, false)));
    let est = b
        .declare_subscriber(names::key(LATENCY_RUN, "estimate/1"))
        .callback(move |s| {
            let bytes = s.payload().to_bytes();
            if receive(&b_inbox, s.key_expr().as_str(), &bytes, &[1]) {
                let step = wire::decode(&bytes).map(|m| m.header.step).unwrap_or(0);
                let _ = b_est_pub.put(estimate(2, step)).wait();
            }
        })
        .await
        .map_err(|e| Error::Run(e.to_string()))?;
    Ok([plain, est])
}

/// Session A's side of the ping-pong: what it publishes and how many
/// answers came back. The plain ping-pong rides on the same key shapes in
/// another namespace.
struct Pinger {
    est_pub: Publisher<'static>,
    plain_pub: Publisher<'static>,
    est_flag: Arc<Flag>,
    plain_flag: Arc<Flag>,
}

impl Pinger {
    /// The publishers, and the subscribers that count answers (held as
    /// long as answers are counted).
    async fn declare(a: &zenoh::Session) -> Result<(Self, [Subscriber<()>; 2]), Error> {
        let plain_flag = Arc::new(Flag::default());
        let est_flag = Arc::new(Flag::default());
        let pf = plain_flag.clone();
        let plain = a
            .declare_subscriber(names::key("bench-ping", "estimate/2"))
            .callback(move |_| pf.hit())
            .await
            .map_err(|e| Error::Run(e.to_string()))?;
        let a_inbox = Arc::new(Mutex::new(Inbox::new(1, false)));
        let ef = est_flag.clone();
        let est = a
            .declare_subscriber(names::key(LATENCY_RUN, "estimate/2"))
            .callback(move |s| {
                if receive(&a_inbox, s.key_expr().as_str(), &s.payload().to_bytes(), &[2]) {
                    ef.hit();
                }
            })
            .await
            .map_err(|e| Error::Run(e.to_string()))?;
        let plain_pub = publisher(a, names::key("bench-ping", "estimate/1")).await?;
        let est_pub = publisher(a, names::key(LATENCY_RUN, "estimate/1")).await?;
        Ok((Self { est_pub, plain_pub, est_flag, plain_flag }, [plain, est]))
    }

    /// `n` interleaved round trips of each kind once both directions carry
    /// traffic: the one-hop latencies (half round trips), µs, estimate and
    /// plain. Blocks the thread.
    fn ping_pong(self, n: usize) -> Result<(Vec<f64>, Vec<f64>), Error> {
        let size = estimate(1, 0).len();
        let hits = |f: &Flag| *f.hits.lock().unwrap_or_else(|p| p.into_inner());
        let put = |p: &Publisher<'static>, bytes: Vec<u8>| p.put(bytes).wait().map_err(|e| Error::Run(e.to_string()));
        // Wait until both directions carry traffic.
        let t = Instant::now();
        let mut step = 0u64;
        loop {
            step += 1;
            put(&self.est_pub, estimate(1, step))?;
            put(&self.plain_pub, vec![0u8; size])?;
            std::thread::sleep(Duration::from_millis(20));
            if hits(&self.est_flag) > 0 && hits(&self.plain_flag) > 0 {
                break;
            }
            if t.elapsed() >= Duration::from_secs(10) {
                return Err(Error::Run("the two sessions did not connect".into()));
            }
        }
        std::thread::sleep(Duration::from_millis(100));
        let (mut e_done, mut p_done) = (hits(&self.est_flag), hits(&self.plain_flag));
        let (mut est, mut plain) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for _ in 0..n {
            step += 1;
            let t = Instant::now();
            put(&self.est_pub, estimate(1, step))?;
            e_done += 1;
            if !self.est_flag.wait_for(e_done) {
                return Err(Error::Run("estimate answer lost".into()));
            }
            est.push(t.elapsed().as_secs_f64() * 1e6 / 2.0);
            let t = Instant::now();
            put(&self.plain_pub, vec![0u8; size])?;
            p_done += 1;
            if !self.plain_flag.wait_for(p_done) {
                return Err(Error::Run("pong lost".into()));
            }
            plain.push(t.elapsed().as_secs_f64() * 1e6 / 2.0);
        }
        Ok((est, plain))
    }
}

/// The offset exchange: a session of the leader's identity (only it may
/// answer, under the TLS policy) answers, `a` asks as an agent, back to
/// back, `n` times: the round trip (p50, p99), µs, and the CPU of this
/// process (both sides) per exchange, µs.
async fn time_exchange(
    a: &zenoh::Session,
    ep: &str,
    tls: Option<&std::path::Path>,
    n: usize,
) -> Result<((f64, f64), f64), Error> {
    let keys = formation_protocol::names::Keys { run: "bench-net".into() };
    let leader = session::open(&ZenohArgs {
        connect: vec![ep.to_string()],
        identity: Some(formation_protocol::names::LEADER.to_string()),
        tls: tls.map(std::path::Path::to_path_buf),
        ..Default::default()
    })
    .await?;
    let clock = formation_net::clock::Clock::real();
    let _answers =
        formation_net::clock_sync::serve(&leader, &keys, formation_net::clock::Timebase::leader(&clock)).await?;
    let time_key = keys.time();
    let mut warm = 0;
    for _ in 0..200 {
        if formation_net::clock_sync::ask(a, &time_key, &clock).await.is_some() {
            warm += 1;
            if warm == 20 {
                break;
            }
        } else {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }
    if warm < 20 {
        return Err(Error::Run(format!("the leader's time answered {warm} of the first questions")));
    }
    let cpu0 = process_cpu_s();
    let mut rtts = Vec::with_capacity(n);
    for _ in 0..n {
        let t = Instant::now();
        if formation_net::clock_sync::ask(a, &time_key, &clock).await.is_none() {
            return Err(Error::Run("a time query went unanswered".into()));
        }
        rtts.push(t.elapsed().as_secs_f64() * 1e6);
    }
    let cpu_us = (process_cpu_s() - cpu0) * 1e6 / n.max(1) as f64;
    let (r50, r99, _) = timing::percentiles(&mut rtts);
    let _ = leader.close().await;
    Ok(((r50, r99), cpu_us))
}
