//! The certificate folder of a secure deployment.
//!
//! `formation certs` writes it ([`generate`], behind the `generate`
//! feature, which only the `formation` crate turns on): an authority, for
//! every node a key and a certificate whose common name is the node's name,
//! the access-control policy signed by the authority, and a revocation
//! list. A node started with `--tls DIR` checks its files there before it
//! opens a session ([`identity`]).
//!
//! This crate knows files, X.509 and the folder's layout, nothing of the
//! network: it never imports tokio, zenoh or a crate of the workspace. What
//! the policy allows (key expressions, zenoh's `access_control` section)
//! and the zenoh settings of `--tls` are `formation_net::identity`'s; the
//! policy reaches [`generate`] as JSON through the `formation` binary.
//! Without `generate` nothing here makes a key or a certificate (no
//! rcgen).
//!
//! # Examples
//!
//! A certificate folder written for two nodes (feature `generate`, as
//! `formation certs` does), and one node's identity read back from it as the
//! node reads its own at start-up:
//!
//! ```
//! # #[cfg(feature = "generate")] {
//! use formation_certs::generate::{write_folder, NodeCert, Request};
//!
//! let dir = std::env::temp_dir().join(format!("formation-certs-doc-{}", std::process::id()));
//! let nodes = [NodeCert { name: "leader".into(), addresses: vec![] }, NodeCert { name: "agent-1".into(), addresses: vec![] }];
//! let policy = serde_json::json!({ "enabled": true, "default_permission": "deny", "rules": [], "subjects": [], "policies": [] });
//! let request = Request {
//!     dir: &dir, nodes: &nodes, scenario: "paper", policy: &policy, san: &[], days: 1,
//!     not_before: None, reissue: &[], revoke: &[], force: false,
//! };
//! write_folder(&request).expect("written");
//! let agent = formation_certs::identity(&dir, "agent-1").expect("its own certificate");
//! assert!(agent.ca.exists());
//! assert!(formation_certs::identity(&dir, "agent-9").is_err(), "no such node");
//! std::fs::remove_dir_all(&dir).unwrap();
//! # }
//! ```

#[cfg(feature = "generate")]
pub mod generate;
pub mod identity;

pub use identity::{identity, node_dir, policy_digest_name, Identity, IdentityError};
pub use identity::{CA_CERT, CA_DIR, CA_KEY, CRL, POLICY, POLICY_CERT, POLICY_SUBJECT};
