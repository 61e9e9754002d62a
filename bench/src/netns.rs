//! `formation bench-net --namespaces`: one-hop latency between two network
//! namespaces on the lab's bridge (as between two hosts on a LAN), for an
//! estimate (decoded and checked at each end, as an agent does), for plain
//! zenoh bytes of the same size, and for the clock offset exchange. One
//! process in each namespace: an echo and a pinger (this command, hidden
//! options `--echo` and `--ping`), their figures read from the pinger's
//! last line.

use std::io::{BufRead, BufReader};
use std::process::Stdio;
use std::time::{Duration, Instant};

use formation_leader::LeaderState;
use formation_net::clock::Timebase;
use formation_net::clock_sync;
use formation_net::session::{self, ZenohArgs};
use formation_protocol::loop_timing as timing;
use formation_protocol::names::Keys;
use formation_protocol::wire::{self, EstimateMsg, Header, FORMAT_VERSION};
use zenoh::Wait;

use formation_exit::Error;
use formation_launch::lab::netns;

const PORT: u16 = 7447;
const PING_EST: &str = "bench/ping/estimate";
const PONG_EST: &str = "bench/pong/estimate";
const PING_PLAIN: &str = "bench/ping/plain";
const PONG_PLAIN: &str = "bench/pong/plain";

/// An estimate message as agents send it, from `sender` for `step`.
pub fn estimate(sender: u32, step: u64) -> Vec<u8> {
    wire::encode(&EstimateMsg {
        header: Header { version: FORMAT_VERSION, sender, step, time_s: step as f64 * 1e-3, sent_ns: 0 },
        state: LeaderState { v: 1.0, w: 0.5, ..Default::default() },
        fresh: true,
        term: u32::from(sender == 0),
    })
}

/// (estimate p50, p99), (plain p50, p99), (offset exchange p50, p99), µs.
pub type Figures = ((f64, f64), (f64, f64), (f64, f64));

fn zerr(what: &str) -> impl Fn(zenoh::Error) -> Error + '_ {
    move |e| Error::Run(format!("{what}: {e}"))
}

/// The echo: answers every ping on the same kind of key, and the leader's time.
pub async fn echo(listen: &str) -> Result<(), Error> {
    let s = session::open(&ZenohArgs { listen: vec![listen.to_string()], ..Default::default() }).await?;
    let pong_est = s.declare_publisher(PONG_EST).express(true).await.map_err(zerr("declaring"))?;
    let pong_plain = s.declare_publisher(PONG_PLAIN).express(true).await.map_err(zerr("declaring"))?;
    let _e = s
        .declare_subscriber(PING_EST)
        .callback(move |m| {
            let bytes = m.payload().to_bytes();
            if wire::decode(&bytes).is_ok() {
                let _ = pong_est.put(bytes.into_owned()).wait();
            }
        })
        .await
        .map_err(zerr("declaring"))?;
    let _p = s
        .declare_subscriber(PING_PLAIN)
        .callback(move |m| {
            let _ = pong_plain.put(m.payload().to_bytes().into_owned()).wait();
        })
        .await
        .map_err(zerr("declaring"))?;
    let _t = clock_sync::serve(
        &s,
        &Keys { run: "bench-net".into() },
        Timebase::leader(&formation_net::clock::Clock::real()),
    )
    .await?;
    println!("echo ready");
    formation_exit::shutdown::signalled().await;
    Ok(())
}

/// The pinger: `n` round trips of each kind to the echo at `connect`;
/// prints `figures e50 e99 p50 p99 t50 t99` (µs).
pub async fn ping(connect: &str, n: usize) -> Result<(), Error> {
    let s = session::open(&ZenohArgs { connect: vec![connect.to_string()], ..Default::default() }).await?;
    let (tx, rx) = std::sync::mpsc::sync_channel::<u8>(16);
    let (tx_e, tx_p) = (tx.clone(), tx);
    let _e = s
        .declare_subscriber(PONG_EST)
        .callback(move |m| {
            if wire::decode(&m.payload().to_bytes()).is_ok() {
                let _ = tx_e.try_send(0);
            }
        })
        .await
        .map_err(zerr("declaring"))?;
    let _p = s
        .declare_subscriber(PONG_PLAIN)
        .callback(move |_| {
            let _ = tx_p.try_send(1);
        })
        .await
        .map_err(zerr("declaring"))?;
    let est = s.declare_publisher(PING_EST).express(true).await.map_err(zerr("declaring"))?;
    let plain = s.declare_publisher(PING_PLAIN).express(true).await.map_err(zerr("declaring"))?;
    let round_trips = |publisher: &zenoh::pubsub::Publisher<'_>, payload: Vec<u8>, want: u8, n: usize| {
        let mut out = Vec::with_capacity(n);
        let began = Instant::now();
        while out.len() < n {
            let t = Instant::now();
            let _ = publisher.put(payload.clone()).wait();
            match rx.recv_timeout(Duration::from_millis(500)) {
                Ok(k) if k == want => out.push(t.elapsed().as_secs_f64() * 1e6 / 2.0),
                _ if began.elapsed() > Duration::from_secs(30) => break,
                _ => {}
            }
        }
        out
    };
    let payload = estimate(1, 0);
    // Until both paths answer (subscriptions travel first), then measured.
    let began = Instant::now();
    while round_trips(&est, payload.clone(), 0, 1).is_empty()
        || round_trips(&plain, vec![0; payload.len()], 1, 1).is_empty()
    {
        if began.elapsed() > Duration::from_secs(20) {
            return Err(Error::Run("the echo did not answer within 20 s".into()));
        }
    }
    let mut e = round_trips(&est, payload.clone(), 0, n);
    let mut p = round_trips(&plain, vec![0; payload.len()], 1, n);
    let key = Keys { run: "bench-net".into() }.time();
    let mut t = Vec::with_capacity(n);
    for _ in 0..n {
        let at = Instant::now();
        if clock_sync::ask(&s, &key, &formation_net::clock::Clock::real()).await.is_some() {
            t.push(at.elapsed().as_secs_f64() * 1e6);
        }
    }
    let ((e50, e99, _), (p50, p99, _), (t50, t99, _)) =
        (timing::percentiles(&mut e), timing::percentiles(&mut p), timing::percentiles(&mut t));
    println!("figures {e50} {e99} {p50} {p99} {t50} {t99}");
    Ok(())
}

/// Two namespaces on a bridge, an echo in one and the pinger in the other.
pub fn measure(n: usize) -> Result<Figures, Error> {
    match netns::privilege().map_err(|e| Error::Input(e.0))? {
        netns::Privilege::Root => {}
        netns::Privilege::Unshare => return Err(Error::Input("--namespaces needs root".into())),
    }
    let exe = std::env::current_exe().map_err(|e| Error::Run(format!("locating this executable: {e}")))?;
    let lab = netns::Lab::create(&["ping", "echo"])?;
    let addr = lab.addr("echo").ok_or_else(|| Error::Run("the lab has no echo host".into()))?;
    let ep = format!("tcp/{addr}:{PORT}");
    let mut echo = lab
        .command("echo", &exe)
        .args(["bench-net", "--echo", &ep])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .spawn()
        .map_err(|e| Error::Run(format!("starting the echo: {e}")))?;
    let ready = echo.stdout.take().and_then(|o| BufReader::new(o).lines().next()).and_then(Result::ok);
    let result = (|| {
        if ready.as_deref() != Some("echo ready") {
            return Err(Error::Run(format!("the echo did not start: {ready:?}")));
        }
        let out = lab
            .command("ping", &exe)
            .args(["bench-net", "--ping", &ep, "--round-trips", &n.to_string()])
            .stdin(Stdio::null())
            .output()
            .map_err(|e| Error::Run(format!("running the pinger: {e}")))?;
        let text = String::from_utf8_lossy(&out.stdout);
        let line = text.lines().find(|l| l.starts_with("figures ")).ok_or_else(|| {
            Error::Run(format!("the pinger gave no figures: {}", String::from_utf8_lossy(&out.stderr).trim()))
        })?;
        let v: Vec<f64> = line.split_whitespace().skip(1).filter_map(|x| x.parse().ok()).collect();
        match v[..] {
            [e50, e99, p50, p99, t50, t99] => Ok(((e50, e99), (p50, p99), (t50, t99))),
            _ => Err(Error::Run(format!("the pinger's figures: {line}"))),
        }
    })();
    let _ = echo.kill();
    let _ = echo.wait();
    drop(lab);
    result
}

/// Runs `ping`/`echo` on a runtime of their own (the hidden options).
pub fn run_side(echo_at: Option<&str>, ping_at: Option<&str>, n: usize) -> Result<(), Error> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| Error::Run(format!("starting the async runtime: {e}")))?;
    match (echo_at, ping_at) {
        (Some(ep), _) => rt.block_on(echo(ep)),
        (_, Some(ep)) => rt.block_on(ping(ep, n)),
        _ => Ok(()),
    }
}
