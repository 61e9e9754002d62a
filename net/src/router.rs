//! The zenoh router of a formation in client mode: one implementation, run
//! by the `router` binary and by `formation node router`.

use std::future::Future;
use std::time::Duration;

use crate::session::{self, ZenohArgs, ZenohMode};
use formation_exit::Error;
use formation_protocol::names::ROUTER;

/// `router` arguments.
#[derive(Clone, Debug, Default)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct RouterArgs {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub zenoh: ZenohArgs,
    /// The run's scenario: the router then holds every key to what the run
    /// sends (sizes; in real time, each estimate's rate and `Drop` for every
    /// put). Without it, size limits only (see docs/security.md).
    #[cfg_attr(feature = "clap", arg(long, value_name = "FILE"))]
    pub scenario: Option<std::path::PathBuf>,
    /// Override a scenario value, as `formation sim --set` (repeatable).
    #[cfg_attr(feature = "clap", arg(long = "set", value_name = "KEY=VALUE", requires = "scenario"))]
    pub overrides: Vec<String>,
}

/// A zenoh router until `shutdown` resolves (the binaries': SIGINT or
/// SIGTERM). Prints one line `router listening on <endpoints> (zid …)` to
/// stdout once open (what `launch` and the lab wait for).
pub async fn run(router: &RouterArgs, shutdown: impl Future) -> Result<(), Error> {
    let mut args = router.zenoh.clone();
    args.mode = Some(ZenohMode::Router);
    args.identity = Some(ROUTER.to_string());
    if let Some(path) = &router.scenario {
        let scenario =
            formation_scenario::Scenario::load(path, &router.overrides).map_err(|e| Error::Input(e.to_string()))?;
        args.traffic = Some(crate::limits::Traffic { router: true, ..crate::limits::Traffic::of(&scenario) });
    }
    let listen = args.to_config()?.get_json("listen/endpoints").unwrap_or_default();
    let listen = serde_json::from_str::<Vec<String>>(&listen).map_or(listen, |v| v.join(", "));
    crate::node::warn_if_unauthenticated(&args);
    let session = session::open(&args).await?;
    println!("router listening on {listen} (zid {})", session.zid());
    // What its access control refuses, to each run's monitor.
    tokio::spawn(crate::denials::report(session.clone(), ROUTER.to_string(), None));
    shutdown.await;
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    Ok(())
}
