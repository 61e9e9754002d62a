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

use std::path::PathBuf;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use clap::Args;
use formation_agent::LeaderState;
use formation_topology::wire::{self, EstimateMsg, Header, FORMAT_VERSION};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

use crate::cli::ScenarioArgs;
use crate::error::Error;
use crate::launch::{LaunchArgs, LaunchMode, RunOptions};
use crate::net::inbox::{self, Inbox, Source};
use crate::net::keys;
use crate::net::session::{self, ZenohArgs};
use crate::net::timing;
use crate::sim::{NoRecord, Simulation};

#[derive(Args, Debug, Clone)]
pub struct BenchNetArgs {
    /// The scenario (the paper's 4 followers by default).
    #[arg(long, default_value = "scenarios/paper.toml")]
    pub scenario: PathBuf,
    /// Lock-step: run-time seconds of the long run (the short one is 2 s).
    #[arg(long, default_value_t = 20.0)]
    pub lockstep_duration: f64,
    /// Real time: run-time seconds at 1 kHz.
    #[arg(long, default_value_t = 5.0)]
    pub realtime_duration: f64,
    /// Latency: round trips per kind.
    #[arg(long, default_value_t = 5000)]
    pub round_trips: usize,
    /// First loopback port to use (about 20 consecutive ports).
    #[arg(long, default_value_t = 17900)]
    pub base_port: u16,
    /// Also measure with mutual TLS, with the certificates in DIR (made by
    /// `formation certs SCENARIO --out DIR`), side by side with plain TCP.
    #[arg(long, value_name = "DIR")]
    pub tls: Option<PathBuf>,
}

fn launch_args(a: &BenchNetArgs, sets: &[String], port: u16, out: PathBuf, run: &str) -> LaunchArgs {
    LaunchArgs {
        opts: RunOptions {
            scenario: ScenarioArgs { scenario: a.scenario.clone(), overrides: sets.to_vec() },
            out: Some(out),
            run: Some(run.to_string()),
            time_scale: None,
            quiet: true,
            tls: a.tls.clone(),
        },
        mode: LaunchMode::Peer,
        base_port: Some(port),
    }
}

fn timed_launch(l: &LaunchArgs) -> Result<f64, Error> {
    let t = Instant::now();
    crate::launch::run(l)?;
    Ok(t.elapsed().as_secs_f64())
}

pub fn run(a: &BenchNetArgs) -> Result<(), Error> {
    crate::cli::at_least_one("--round-trips", a.round_trips as u64)?;
    let tmp = std::env::temp_dir().join(format!("formation-bench-net-{}", std::process::id()));
    let scenario = formation_topology::Scenario::load(&a.scenario, &[]).map_err(|e| Error::Input(e.to_string()))?;
    let n = scenario.followers.len();

    // 1. Lock-step over zenoh vs in process.
    let sets = |d: f64| vec![format!("duration={d}"), "timing=lockstep".to_string()];
    let short = 2.0;
    let t_short = timed_launch(&launch_args(a, &sets(short), a.base_port, tmp.join("ls-short"), "bench-ls1"))?;
    let t_long =
        timed_launch(&launch_args(a, &sets(a.lockstep_duration), a.base_port + 10, tmp.join("ls-long"), "bench-ls2"))?;
    let dsteps = ((a.lockstep_duration - short) / scenario.dt_s).round();
    let net_rate = dsteps / (t_long - t_short).max(1e-9);
    let sim_s = formation_topology::Scenario::load(&a.scenario, &sets(a.lockstep_duration))
        .map_err(|e| Error::Input(e.to_string()))?;
    let t = Instant::now();
    Simulation::new(&sim_s).run(&mut NoRecord, |_| {}).map_err(|e| Error::Run(e.to_string()))?;
    let sim_rate = sim_s.steps() as f64 / t.elapsed().as_secs_f64();
    println!("lock-step, {n} followers + leader over zenoh (peer processes): {net_rate:>10.0} steps/s");
    println!("  (runs of {short} s and {} s took {t_short:.2} s and {t_long:.2} s wall)", a.lockstep_duration);
    println!("in-process simulator, same scenario:                     {sim_rate:>10.0} steps/s");

    // 2. Real-time period error at 1 kHz.
    let rt_sets = vec![format!("duration={}", a.realtime_duration), "timing=realtime".into(), "dt=0.001".into()];
    let mut l = launch_args(a, &rt_sets, a.base_port + 20, tmp.join("rt"), "bench-rt");
    l.opts.time_scale = Some(1.0);
    crate::launch::run(&l)?;
    let net: serde_json::Value = std::fs::read_to_string(tmp.join("rt").join("network.json"))
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .ok_or_else(|| Error::Run("reading the real-time run's network.json".into()))?;
    println!("real time at 1 kHz, {n} agents + leader: |period − 1 ms| (µs) p50 / p99 / max, wake-up lateness p99:");
    if let Some(nodes) = net["nodes"].as_object() {
        for (name, v) in nodes {
            let l = &v["loop"];
            let f = |k: &str| l[k].as_f64().unwrap_or(f64::NAN);
            println!(
                "  {:>8}: {:>7.1} / {:>7.1} / {:>8.1}   lateness p99 {:>8.1}   silent neighbour-steps {}",
                name,
                f("period_error_p50_us"),
                f("period_error_p99_us"),
                f("period_error_max_us"),
                f("lateness_p99_us"),
                v["silent"]
            );
        }
    }

    // 3. Latency.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| Error::Run(format!("starting the async runtime: {e}")))?;
    let (estimate, plain) = runtime
        .block_on(latency(a.base_port + 40, a.round_trips))
        .map_err(|e| Error::Run(format!("latency benchmark: {e}")))?;
    println!("one-hop latency (half round trip, µs), {} round trips each, interleaved:", a.round_trips);
    println!("  estimate message (agent path): p50 {:>7.1}  p99 {:>7.1}", estimate.0, estimate.1);
    println!("  plain zenoh ping-pong:         p50 {:>7.1}  p99 {:>7.1}", plain.0, plain.1);
    println!("  ratio p50 {:.2}", estimate.0 / plain.0);
    let _ = std::fs::remove_dir_all(&tmp);
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

fn estimate(sender: u32, step: u64) -> Vec<u8> {
    wire::encode(&EstimateMsg {
        header: Header { version: FORMAT_VERSION, sender, step, time_s: step as f64 * 1e-3 },
        state: LeaderState { v: 1.0, w: 0.5, ..Default::default() },
        fresh: true,
    })
}

/// Receive path of an agent: decode + checks + inbox.
fn receive(inbox: &Mutex<Inbox>, key: &str, bytes: &[u8], neighbours: &[u32]) -> bool {
    let key_id = keys::last_chunk(key).parse::<u32>().ok();
    let mut i = inbox.lock().unwrap_or_else(|p| p.into_inner());
    match inbox::check(key_id, bytes, false, neighbours) {
        Ok((Source::Neighbour(slot), m)) => {
            i.accept(slot, &m);
            true
        }
        _ => false,
    }
}

/// ((p50, p99) estimate one-hop, (p50, p99) plain one-hop), µs.
async fn latency(port: u16, n: usize) -> anyhow::Result<((f64, f64), (f64, f64))> {
    let ep = format!("tcp/127.0.0.1:{port}");
    let a = session::open(&ZenohArgs { listen: vec![ep.clone()], ..Default::default() }).await?;
    let b = session::open(&ZenohArgs {
        listen: vec![format!("tcp/127.0.0.1:{}", port + 1)],
        connect: vec![ep],
        ..Default::default()
    })
    .await?;
    let run = "bench-lat";
    let k = |rest: &str| session::key(run, rest);
    // B: echo plain pings, answer estimates from "follower 1" with its own as "follower 2".
    let b_plain_pub = b
        .declare_publisher(k("pong"))
        .express(true)
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let b_est_pub = b
        .declare_publisher(k("estimate/2"))
        .express(true)
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let _b_plain = b
        .declare_subscriber(k("ping"))
        .callback(move |s| {
            let _ = b_plain_pub.put(s.payload().to_bytes().into_owned()).wait();
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let b_inbox = Arc::new(Mutex::new(Inbox::new(1, false)));
    let bi = b_inbox.clone();
    let _b_est = b
        .declare_subscriber(k("estimate/1"))
        .callback(move |s| {
            let bytes = s.payload().to_bytes();
            if receive(&bi, s.key_expr().as_str(), &bytes, &[1]) {
                let step = wire::decode(&bytes).map(|m| m.header.step).unwrap_or(0);
                let _ = b_est_pub.put(estimate(2, step)).wait();
            }
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    // A: count answers.
    let plain_flag = Arc::new(Flag::default());
    let est_flag = Arc::new(Flag::default());
    let pf = plain_flag.clone();
    let _a_plain =
        a.declare_subscriber(k("pong")).callback(move |_| pf.hit()).await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let a_inbox = Arc::new(Mutex::new(Inbox::new(1, false)));
    let (ai, ef) = (a_inbox.clone(), est_flag.clone());
    let _a_est = a
        .declare_subscriber(k("estimate/2"))
        .callback(move |s| {
            if receive(&ai, s.key_expr().as_str(), &s.payload().to_bytes(), &[2]) {
                ef.hit();
            }
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let a_plain_pub = a
        .declare_publisher(k("ping"))
        .express(true)
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let a_est_pub = a
        .declare_publisher(k("estimate/1"))
        .express(true)
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let size = estimate(1, 0).len();

    let measured = tokio::task::spawn_blocking(move || -> anyhow::Result<(Vec<f64>, Vec<f64>)> {
        // Wait until both directions carry traffic.
        let t = Instant::now();
        let mut step = 0u64;
        loop {
            step += 1;
            a_est_pub.put(estimate(1, step)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
            a_plain_pub.put(vec![0u8; size]).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
            std::thread::sleep(Duration::from_millis(20));
            if *est_flag.hits.lock().unwrap_or_else(|p| p.into_inner()) > 0
                && *plain_flag.hits.lock().unwrap_or_else(|p| p.into_inner()) > 0
            {
                break;
            }
            anyhow::ensure!(t.elapsed() < Duration::from_secs(10), "the two sessions did not connect");
        }
        std::thread::sleep(Duration::from_millis(100));
        let (mut e_done, mut p_done) = (
            *est_flag.hits.lock().unwrap_or_else(|p| p.into_inner()),
            *plain_flag.hits.lock().unwrap_or_else(|p| p.into_inner()),
        );
        let (mut est, mut plain) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for _ in 0..n {
            step += 1;
            let t = Instant::now();
            a_est_pub.put(estimate(1, step)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
            e_done += 1;
            anyhow::ensure!(est_flag.wait_for(e_done), "estimate answer lost");
            est.push(t.elapsed().as_secs_f64() * 1e6 / 2.0);
            let t = Instant::now();
            a_plain_pub.put(vec![0u8; size]).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
            p_done += 1;
            anyhow::ensure!(plain_flag.wait_for(p_done), "pong lost");
            plain.push(t.elapsed().as_secs_f64() * 1e6 / 2.0);
        }
        Ok((est, plain))
    })
    .await??;
    let (mut est, mut plain) = measured;
    let (e50, e99, _) = timing::percentiles(&mut est);
    let (p50, p99, _) = timing::percentiles(&mut plain);
    let _ = a.close().await;
    let _ = b.close().await;
    Ok(((e50, e99), (p50, p99)))
}
