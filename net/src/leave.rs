//! `formation leave --id ID`: asks follower ID of a running formation to
//! leave the run for good (docs/model.md §14), as SIGTERM to its agent
//! would, from any host that reaches the run: it puts on
//! `control/leave/<id>` until the follower's last telemetry says it left,
//! and says when. (With `--tls` it speaks with the monitor's certificate:
//! the operator's console.)

use std::time::Duration;

use formation_protocol::codec;
use formation_protocol::error::{zerr, Error};
use formation_protocol::names::MONITOR;
use formation_protocol::telemetry::{Telemetry, MAX_LEFT_WHY};

use crate::node::NodeArgs;

/// `formation leave` arguments.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct LeaveArgs {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub node: NodeArgs,
    /// The follower that leaves.
    #[cfg_attr(feature = "clap", arg(long, value_name = "ID"))]
    pub id: u32,
    /// Leave even if, without this follower, others no longer reach the
    /// leader (Lemma 1; else refused, naming them).
    #[cfg_attr(feature = "clap", arg(long))]
    pub even_if_cut_off: bool,
    /// Give up when the follower has not said it left within this long (s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 5.0, value_name = "SECONDS"))]
    pub timeout: f64,
}

/// How often the request is said until the follower answers.
const ASK_EVERY: Duration = Duration::from_millis(100);

/// Asks follower `--id` to leave; returns the line that says when it did.
pub async fn run(a: &LeaveArgs) -> Result<String, Error> {
    let (scenario, keys) = a.node.load(MONITOR)?;
    let id = a.id;
    if scenario.index_of(id).is_none() {
        let ids = formation_topology::graph::id_list(scenario.graph.ids());
        return Err(Error::Input(format!("scenario {} has no follower {id} (ids: {ids})", scenario.name)));
    }
    if !(a.timeout.is_finite() && a.timeout > 0.0) {
        return Err(Error::Input(format!("--timeout must be a positive number of seconds, not {}", a.timeout)));
    }
    let cut = scenario.graph.cut_off_without(&[id]);
    if let Some(cut) = cut.as_ref().filter(|_| !a.even_if_cut_off) {
        return Err(Error::Input(format!(
            "formation leave --id {id}: {cut}: their estimates of the leader would drift (--even-if-cut-off to \
             leave anyway)"
        )));
    }
    let session = a.node.open(MONITOR, &scenario).await?;
    let (tx, mut rx) = tokio::sync::mpsc::channel::<(u64, String)>(4);
    let _sub = session
        .declare_subscriber(keys.telemetry(id))
        .callback(move |s| {
            if let Some(Telemetry::Follower { id: from, left: Some(l), .. }) =
                codec::decode::<Telemetry>(&s.payload().to_bytes())
            {
                if from == id {
                    let _ =
                        tx.try_send((l.at_k, l.why.chars().filter(|c| !c.is_control()).take(MAX_LEFT_WHY).collect()));
                }
            }
        })
        .await
        .map_err(|e| zerr("listening to the follower's telemetry", e))?;
    let limit = tokio::time::Instant::now() + Duration::from_secs_f64(a.timeout);
    let left = loop {
        session.put(keys.leave(id), Vec::<u8>::new()).await.map_err(|e| zerr("asking the follower to leave", e))?;
        tokio::select! {
            l = rx.recv() => break l,
            _ = tokio::time::sleep(ASK_EVERY) => {}
        }
        if tokio::time::Instant::now() >= limit {
            break None;
        }
    };
    let _ = tokio::time::timeout(Duration::from_secs(1), session.close()).await;
    match left {
        Some((k, why)) => Ok(format!(
            "follower {id} left run {} at t = {:.3} s ({why}){}",
            keys.run,
            k as f64 * scenario.dt_s,
            if cut.is_none() { "" } else { " — the others it cut off from the leader now drift" }
        )),
        None => Err(Error::Run(format!(
            "follower {id} of run {} did not say it left within {} s: is its agent running, in this run (--run), \
             and reachable from here?",
            keys.run, a.timeout
        ))),
    }
}
