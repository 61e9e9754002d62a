//! `formation certs SCENARIO --out DIR`: identities and permissions for a
//! secure deployment, written by [`formation_certs::generate`]: a
//! certificate authority and, for every node of the scenario (`router`,
//! `leader`, `monitor`, `agent-<id>`), a key and a certificate whose subject
//! common name is the node's name, valid for the addresses the node listens
//! on (loopback, the lab's, and any `--san`), and `policy.json5`: zenoh
//! access control derived from the topology
//! ([`formation_net::identity::policy`]), so that a node may publish only
//! its own estimate and telemetry and receive only what its role needs.
//!
//! With `--tls DIR`, a node checks its files at start
//! ([`formation_certs::identity`]), and its session runs mutual TLS with
//! the authority as the only trust root, TLS-only links, and the policy
//! ([`formation_net::identity::zenoh_tls`]).

use std::net::IpAddr;
use std::path::PathBuf;

use formation_certs::generate::{self, NodeCert, Request};
use formation_net::identity::policy;
use formation_protocol::names::node_names;

use formation_exit::Error;

/// `formation certs`.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct CertsArgs {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub scenario: formation_scenario::args::ScenarioArgs,
    /// Folder to write: `ca/` (the authority: keep its key off the nodes'
    /// hosts) and one folder per node (`router/`, `leader/`, `monitor/`,
    /// `agent-<id>/`) to copy to the host that runs it. An existing folder
    /// is refused unless --force, --node or --revoke says what to change.
    #[cfg_attr(feature = "clap", arg(long, value_name = "DIR", required_unless_present = "policy"))]
    pub out: Option<PathBuf>,
    /// Another address (IP or DNS name) that every node's certificate is
    /// valid for, e.g. the LAN address of the host that runs the router or a
    /// peer (repeatable). Loopback and the lab's addresses are always in.
    #[cfg_attr(feature = "clap", arg(long = "san", value_name = "ADDRESS"))]
    pub san: Vec<String>,
    /// How long the certificates are valid, in days (at most 36500).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 365, value_name = "DAYS"))]
    pub days: u32,
    /// First day of validity, YYYY-MM-DD [default: now]. With --days, makes
    /// expired or not-yet-valid certificates (for testing that they are refused).
    #[cfg_attr(feature = "clap", arg(long, value_name = "DATE"))]
    pub not_before: Option<String>,
    /// Only (re)issue these nodes' certificates, with the folder's authority
    /// (repeatable); a node's previous certificate is revoked.
    #[cfg_attr(feature = "clap", arg(long = "node", value_name = "NAME"))]
    pub nodes: Vec<String>,
    /// Revoke this node's certificate (repeatable): every node refuses it
    /// from the next start on. Copy the nodes' folders (their
    /// `revoked.crl`) to their hosts again.
    #[cfg_attr(feature = "clap", arg(long = "revoke", value_name = "NAME"))]
    pub revoke: Vec<String>,
    /// Replace an existing folder: a new authority and new keys for every
    /// node (certificates of the old authority are trusted by nobody).
    #[cfg_attr(feature = "clap", arg(long))]
    pub force: bool,
    /// Print the access-control policy derived from the topology and write nothing.
    #[cfg_attr(feature = "clap", arg(long))]
    pub policy: bool,
}

/// The lab's addresses of a node, in client mode (with a router, host
/// index i) and in peer mode (no router, index i − 1).
fn lab_addresses(index: usize) -> Vec<IpAddr> {
    let mut v = vec![IpAddr::V4(crate::lab::netns::host_addr(index))];
    if index > 0 {
        v.push(IpAddr::V4(crate::lab::netns::host_addr(index - 1)));
    }
    v
}

/// `formation certs`.
pub fn run(a: &CertsArgs) -> Result<(), Error> {
    let scenario = a.scenario.load().map_err(|e| Error::Input(e.to_string()))?;
    let policy = policy(&scenario);
    if a.policy {
        println!("{}", serde_json::to_string_pretty(&policy).unwrap_or_default());
        return Ok(());
    }
    let Some(dir) = a.out.as_deref() else {
        return Err(Error::Input("--out DIR is required (or --policy to print the policy)".into()));
    };
    let nodes: Vec<NodeCert> = node_names(&scenario)
        .into_iter()
        .enumerate()
        .map(|(index, name)| NodeCert { name, addresses: lab_addresses(index) })
        .collect();
    let report = generate::write_folder(&Request {
        dir,
        nodes: &nodes,
        scenario: &scenario.name,
        policy: &policy,
        san: &a.san,
        days: a.days,
        not_before: a.not_before.as_deref(),
        reissue: &a.nodes,
        revoke: &a.revoke,
        force: a.force,
    })?;
    for warning in report.warnings {
        eprintln!("{warning}");
    }
    for line in report.lines {
        println!("{line}");
    }
    Ok(())
}
