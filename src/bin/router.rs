//! A zenoh router for `formation` nodes in client mode.
//!
//! `router [--listen tcp/127.0.0.1:7447] [--config FILE.json5]`: prints one
//! line `router listening on <endpoints>` to stdout once open, then runs
//! until SIGINT/SIGTERM and closes the session. Multicast scouting is off.

use anyhow::Context;
use clap::Parser;
use formation::net::session::{self, ZenohArgs, ZenohMode};

#[derive(Parser, Debug)]
#[command(about = "Zenoh router for formation nodes (loopback by default, no multicast)")]
struct Cli {
    #[command(flatten)]
    zenoh: ZenohArgs,
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    let mut args = Cli::parse().zenoh;
    args.mode = Some(ZenohMode::Router);
    args.identity = Some(formation::certs::ROUTER.to_string());
    let listen = args.to_config()?.get_json("listen/endpoints").unwrap_or_default();
    let listen = serde_json::from_str::<Vec<String>>(&listen).map_or(listen, |v| v.join(", "));
    let session = session::open(&args).await?;
    println!("router listening on {listen} (zid {})", session.zid());

    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .context("installing the SIGTERM handler")?;
    tokio::select! {
        r = tokio::signal::ctrl_c() => r.context("waiting for SIGINT")?,
        _ = term.recv() => {}
    }
    session.close().await.map_err(|e| anyhow::anyhow!("closing the router session: {e}"))?;
    Ok(())
}
