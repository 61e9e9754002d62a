//! The zenoh router of a formation in client mode: one implementation, run
//! by the `router` binary and by `formation node router`.

use std::time::Duration;

use crate::error::Error;
use crate::names::ROUTER;
use crate::session::{self, ZenohArgs, ZenohMode};

/// A zenoh router until SIGINT or SIGTERM. Prints one line `router
/// listening on <endpoints> (zid …)` to stdout once open (what `launch` and
/// the lab wait for).
pub async fn run(args: &ZenohArgs) -> Result<(), Error> {
    let mut args = args.clone();
    args.mode = Some(ZenohMode::Router);
    args.identity = Some(ROUTER.to_string());
    let listen = args.to_config()?.get_json("listen/endpoints").unwrap_or_default();
    let listen = serde_json::from_str::<Vec<String>>(&listen).map_or(listen, |v| v.join(", "));
    let session = session::open(&args).await?;
    println!("router listening on {listen} (zid {})", session.zid());
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(|e| Error::Run(format!("installing the SIGTERM handler: {e}")))?;
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        _ = term.recv() => {}
    }
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    Ok(())
}
