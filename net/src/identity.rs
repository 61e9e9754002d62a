//! A node's identity for a secure deployment: the files a certificate
//! folder holds for it (checked at start), the access-control policy of a
//! scenario's topology, and the zenoh settings of `--tls`.
//!
//! With `--tls DIR`, a node checks its files at start ([`identity`]), and
//! its session runs mutual TLS with the authority as the only trust root,
//! TLS-only links, and the policy ([`zenoh_tls`]). `formation certs` makes
//! the folder.

use std::path::{Path, PathBuf};

use formation_topology::Scenario;
use serde_json::{json, Value};

use crate::names::{agent_name, node_names, LEADER, MONITOR, ROUTER};

/// A TLS identity or policy that cannot be used: the file and what is wrong with it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct IdentityError(pub String);

/// The authority's certificate and key in a certificate folder.
pub const CA_CERT: &str = "ca.pem";
pub const CA_KEY: &str = "ca.key";
/// The authority's own folder in what `formation certs` writes: its key,
/// which no node needs, stays there.
pub const CA_DIR: &str = "ca";
/// The access-control policy in a certificate folder.
pub const POLICY: &str = "policy.json5";
/// The authority's signature of the policy: a certificate it issued to
/// [`POLICY_SUBJECT`] that names the policy's SHA-256 ([`policy_digest_name`]).
pub const POLICY_CERT: &str = "policy.pem";
pub const POLICY_SUBJECT: &str = "formation policy";
/// The authority's certificate revocation list.
pub const CRL: &str = "revoked.crl";
/// The environment variable the TLS link reads the revocation list from.
pub const CRL_ENV: &str = "ZENOH_TLS_CRL";

/// The folder that holds `name`'s files: `DIR/<name>/` (what `formation
/// certs` writes), or `DIR` itself (a node's folder copied to its host).
pub fn node_dir(dir: &Path, name: &str) -> PathBuf {
    let sub = dir.join(name);
    if sub.is_dir() {
        sub
    } else {
        dir.to_path_buf()
    }
}

/// The DNS name a policy certificate carries for a policy file: the file's
/// SHA-256 in hex, in two labels of 32 (a label holds at most 63).
pub fn policy_digest_name(policy: &[u8]) -> String {
    use sha2::Digest;
    let hex: String = sha2::Sha256::digest(policy).iter().map(|b| format!("{b:02x}")).collect();
    format!("{}.{}.sha256.formation-policy", &hex[..32], &hex[32..])
}

/// `ZENOH_TLS_CRL` for this process: the revocation list of `name`'s folder
/// (the TLS link of this project's zenoh reads it when a session opens).
/// Call before any thread starts.
pub fn export_crl(dir: &Path, name: &str) {
    let crl = node_dir(dir, name).join(CRL);
    if crl.is_file() {
        std::env::set_var(CRL_ENV, &crl);
    }
}

/// What one node may publish (`put` in) and receive (subscribe to, `put`
/// out), answer (a queryable: `query` out, `reply` in) and ask (`query`
/// in, `reply` out).
struct Role {
    name: String,
    publish: Vec<String>,
    receive: Vec<String>,
    answer: Vec<String>,
    ask: Vec<String>,
}

/// Any run's key: `formation/*/<rest>` (certificates are per scenario, not per run).
fn any_run(rest: &str) -> String {
    format!("formation/*/{rest}")
}

fn roles(scenario: &Scenario) -> Vec<Role> {
    let control = any_run("control/**");
    let mut roles = vec![
        Role {
            name: LEADER.into(),
            publish: vec![
                any_run("estimate/0"),
                any_run("telemetry/0"),
                any_run("control/hello/0"),
                any_run("control/start"),
                any_run("control/abort"),
                any_run("control/denied/leader"),
            ],
            // Every estimate (lock-step pacing, and its own for twins) and telemetry (who finished).
            receive: vec![any_run("estimate/*"), any_run("telemetry/*"), control.clone()],
            // The run's timebase (crate::timesync).
            answer: vec![any_run("control/time")],
            ask: vec![],
        },
        Role {
            name: MONITOR.into(),
            publish: vec![
                any_run("control/hello/monitor"),
                any_run("control/ready/monitor"),
                any_run("control/ack"),
                any_run("control/denied/monitor"),
            ],
            receive: vec![any_run("telemetry/*"), control.clone()],
            answer: vec![],
            ask: vec![],
        },
    ];
    for (index, &id) in scenario.graph.ids().iter().enumerate() {
        let mut receive: Vec<String> =
            scenario.sources_of(index).iter().map(|s| any_run(&format!("estimate/{s}"))).collect();
        // Its own estimate and telemetry: a second process with its identity is refused (twins).
        receive.push(any_run(&format!("estimate/{id}")));
        receive.push(any_run(&format!("telemetry/{id}")));
        receive.push(control.clone());
        roles.push(Role {
            name: agent_name(id),
            publish: vec![
                any_run(&format!("estimate/{id}")),
                any_run(&format!("telemetry/{id}")),
                any_run(&format!("control/hello/{id}")),
                any_run(&format!("control/ready/{id}")),
                any_run(&format!("control/denied/{}", agent_name(id))),
            ],
            receive,
            answer: vec![],
            ask: vec![any_run("control/time")],
        });
    }
    roles
}

/// zenoh's `access_control` section for a scenario: deny by default; each
/// node (known by its certificate's common name) may put only on its own
/// keys and declare subscribers and be sent puts only on the keys its role
/// reads; the router is trusted to forward. Enforced by every node that
/// loads it: the router for its clients, each peer for its own links.
pub fn policy(scenario: &Scenario) -> Value {
    let mut rules = vec![
        json!({ "id": "router-forwards",
                "messages": ["put", "declare_subscriber", "query", "declare_queryable", "reply"],
                "flows": ["ingress", "egress"], "permission": "allow", "key_exprs": ["formation/**"] }),
        // Subscriber and queryable declarations travel to every node, so that
        // publishers and queriers know where to send; what is sent is what
        // the rules below allow.
        json!({ "id": "declarations-out", "messages": ["declare_subscriber", "declare_queryable"],
                "flows": ["egress"], "permission": "allow", "key_exprs": ["formation/**"] }),
    ];
    let mut subjects = vec![json!({ "id": ROUTER, "cert_common_names": [ROUTER] })];
    let mut policies = vec![json!({ "rules": ["router-forwards"], "subjects": [ROUTER] })];
    for r in roles(scenario) {
        let (publish, receive) = (format!("{}-publishes", r.name), format!("{}-receives", r.name));
        let subscribe = format!("{}-subscribes", r.name);
        rules.push(json!({ "id": publish, "messages": ["put"], "flows": ["ingress"],
                           "permission": "allow", "key_exprs": r.publish }));
        rules.push(json!({ "id": subscribe, "messages": ["declare_subscriber"], "flows": ["ingress"],
                           "permission": "allow", "key_exprs": r.receive }));
        rules.push(json!({ "id": receive, "messages": ["put"], "flows": ["egress"],
                           "permission": "allow", "key_exprs": r.receive }));
        let mut own = vec![publish, subscribe, receive, "declarations-out".to_string()];
        if !r.answer.is_empty() {
            let (a_in, a_out) = (format!("{}-answers", r.name), format!("{}-is-asked", r.name));
            rules.push(json!({ "id": a_in, "messages": ["declare_queryable", "reply"], "flows": ["ingress"],
                               "permission": "allow", "key_exprs": r.answer }));
            rules.push(json!({ "id": a_out, "messages": ["query"], "flows": ["egress"],
                               "permission": "allow", "key_exprs": r.answer }));
            own.extend([a_in, a_out]);
        }
        if !r.ask.is_empty() {
            let (q_in, q_out) = (format!("{}-asks", r.name), format!("{}-is-answered", r.name));
            rules.push(json!({ "id": q_in, "messages": ["query"], "flows": ["ingress"],
                               "permission": "allow", "key_exprs": r.ask }));
            rules.push(json!({ "id": q_out, "messages": ["reply"], "flows": ["egress"],
                               "permission": "allow", "key_exprs": r.ask }));
            own.extend([q_in, q_out]);
        }
        subjects.push(json!({ "id": r.name, "cert_common_names": [r.name] }));
        policies.push(json!({ "rules": own, "subjects": [r.name] }));
    }
    json!({ "enabled": true, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies })
}

/// A node's files in a certificate folder, checked.
#[derive(Clone, Debug)]
pub struct Identity {
    pub ca: PathBuf,
    pub cert: PathBuf,
    pub key: PathBuf,
    pub policy: Value,
    pub crl: PathBuf,
}

/// Checks `dir` for node `name`: the authority, the node's certificate
/// (issued by the authority, for this node, valid now, not revoked) and key
/// (matching it), and the policy (signed by the authority). Each problem is
/// one line.
pub fn identity(dir: &Path, name: &str) -> Result<Identity, IdentityError> {
    use x509_parser::prelude::*;
    let top = dir;
    let dir = &node_dir(top, name);
    let (ca, cert, key) = (dir.join(CA_CERT), dir.join(format!("{name}.pem")), dir.join(format!("{name}.key")));
    if top.join(CA_KEY).exists() && !dir.join(POLICY_CERT).exists() {
        return Err(IdentityError(format!(
            "--tls {}: made by an older `formation certs` (the authority's key beside the nodes' files, no signed \
             policy): make it again with `formation certs SCENARIO --out {} --force`",
            top.display(),
            top.display()
        )));
    }
    if !ca.exists() && top.join(CA_DIR).join(CA_CERT).exists() && !dir.join(format!("{name}.pem")).exists() {
        return Err(IdentityError(format!(
            "--tls {}: no folder {name}/ for node {name} (run `formation certs` with the scenario of this run)",
            top.display()
        )));
    }
    let read = |p: &Path| -> Result<Vec<u8>, IdentityError> {
        std::fs::read(p)
            .map_err(|e| IdentityError(format!("--tls {}: cannot read {}: {e}", dir.display(), p.display())))
    };
    let pem_of = |p: &Path, bytes: &[u8]| -> Result<Pem, IdentityError> {
        let (_, pem) =
            parse_x509_pem(bytes).map_err(|e| IdentityError(format!("{}: not a PEM certificate: {e}", p.display())))?;
        Ok(pem)
    };
    let ca_bytes = read(&ca)?;
    let ca_pem = pem_of(&ca, &ca_bytes)?;
    let ca_x509 =
        ca_pem.parse_x509().map_err(|e| IdentityError(format!("{}: not a certificate: {e}", ca.display())))?;
    let cert_bytes = read(&cert)?;
    let cert_pem = pem_of(&cert, &cert_bytes)?;
    let x509 =
        cert_pem.parse_x509().map_err(|e| IdentityError(format!("{}: not a certificate: {e}", cert.display())))?;
    let cn = x509.subject().iter_common_name().next().and_then(|c| c.as_str().ok()).unwrap_or("").to_string();
    if cn != name {
        return Err(IdentityError(format!("{} is the certificate of {cn:?}, not of {name}", cert.display())));
    }
    if x509.verify_signature(Some(ca_x509.public_key())).is_err() {
        return Err(IdentityError(format!("{} was not issued by the authority {}", cert.display(), ca.display())));
    }
    let now = ASN1Time::now();
    let validity = x509.validity();
    if now < validity.not_before {
        return Err(IdentityError(format!(
            "{} is not valid yet: valid from {} (now {})",
            cert.display(),
            validity.not_before,
            now
        )));
    }
    if now > validity.not_after {
        return Err(IdentityError(format!("{} expired on {} (now {})", cert.display(), validity.not_after, now)));
    }
    let key_text = String::from_utf8(read(&key)?)
        .map_err(|_| IdentityError(format!("{}: not a PEM private key", key.display())))?;
    let pair = rcgen::KeyPair::from_pem(&key_text)
        .map_err(|e| IdentityError(format!("{}: not a private key: {e}", key.display())))?;
    if rcgen::PublicKeyData::der_bytes(&pair) != &x509.public_key().subject_public_key.data[..] {
        return Err(IdentityError(format!("{} is not the key of {}", key.display(), cert.display())));
    }
    let policy_path = dir.join(POLICY);
    let policy_bytes = read(&policy_path)?;
    signed_policy(dir, &policy_path, &policy_bytes, &ca_x509, &read)?;
    let text =
        String::from_utf8(policy_bytes).map_err(|_| IdentityError(format!("{}: not UTF-8", policy_path.display())))?;
    let policy: Value = json5::from_str(&text).map_err(|e| IdentityError(format!("{}: {e}", policy_path.display())))?;
    let crl = dir.join(CRL);
    not_revoked(&crl, &read(&crl)?, &ca_x509, &x509, name)?;
    Ok(Identity { ca, cert, key, policy, crl })
}

/// The policy file is the one the authority signed: `policy.pem` was issued
/// by it to [`POLICY_SUBJECT`] and names the file's SHA-256.
fn signed_policy(
    dir: &Path,
    policy_path: &Path,
    policy: &[u8],
    ca: &x509_parser::certificate::X509Certificate<'_>,
    read: &dyn Fn(&Path) -> Result<Vec<u8>, IdentityError>,
) -> Result<(), IdentityError> {
    use x509_parser::prelude::*;
    let sig_path = dir.join(POLICY_CERT);
    let bytes = read(&sig_path)?;
    let refused = |why: &str| {
        IdentityError(format!(
            "{} is refused: {why} (a policy that is not the authority's is never loaded; run `formation certs` again)",
            policy_path.display()
        ))
    };
    let (_, pem) =
        parse_x509_pem(&bytes).map_err(|_| refused(&format!("{} is not a certificate", sig_path.display())))?;
    let x509 = pem.parse_x509().map_err(|_| refused(&format!("{} is not a certificate", sig_path.display())))?;
    let cn = x509.subject().iter_common_name().next().and_then(|c| c.as_str().ok()).unwrap_or("");
    if cn != POLICY_SUBJECT || x509.verify_signature(Some(ca.public_key())).is_err() {
        return Err(refused(&format!("{} is not the authority's signature of a policy", sig_path.display())));
    }
    let want = policy_digest_name(policy);
    let names: Vec<String> = x509
        .subject_alternative_name()
        .ok()
        .flatten()
        .map(|san| {
            san.value
                .general_names
                .iter()
                .filter_map(|g| match g {
                    GeneralName::DNSName(n) => Some(n.to_string()),
                    _ => None,
                })
                .collect()
        })
        .unwrap_or_default();
    if !names.contains(&want) {
        return Err(refused(&format!(
            "it is not the file the authority signed ({} names another SHA-256)",
            sig_path.display()
        )));
    }
    Ok(())
}

/// The node's certificate is not on the authority's revocation list (which
/// must be the authority's).
fn not_revoked(
    crl_path: &Path,
    bytes: &[u8],
    ca: &x509_parser::certificate::X509Certificate<'_>,
    cert: &x509_parser::certificate::X509Certificate<'_>,
    name: &str,
) -> Result<(), IdentityError> {
    use x509_parser::prelude::*;
    let bad = |why: String| IdentityError(format!("{}: {why}", crl_path.display()));
    let (_, pem) = parse_x509_pem(bytes).map_err(|e| bad(format!("not a PEM revocation list: {e}")))?;
    let (_, crl) = parse_x509_crl(&pem.contents).map_err(|e| bad(format!("not a revocation list: {e}")))?;
    if crl.verify_signature(ca.public_key()).is_err() {
        return Err(bad("not signed by the authority".into()));
    }
    if let Some(r) = crl.iter_revoked_certificates().find(|r| r.raw_serial() == cert.raw_serial()) {
        return Err(IdentityError(format!(
            "{name}'s certificate (serial {}) was revoked on {}: this node may not join (issue it a new one with \
             `formation certs SCENARIO --out DIR --node {name}`)",
            cert.raw_serial_as_string(),
            r.revocation_date
        )));
    }
    Ok(())
}

/// `identity` for a node of `scenario`, whose policy must also be the one
/// the scenario's topology gives.
pub fn identity_for(dir: &Path, name: &str, scenario: &Scenario) -> Result<Identity, IdentityError> {
    checked(dir, name, scenario, &policy(scenario))
}

/// Every node of `scenario` has its files in `dir` (what `launch`, `lab`
/// and `bench-net` check before they start any process).
pub fn check_all(dir: &Path, scenario: &Scenario) -> Result<(), IdentityError> {
    let expected = policy(scenario);
    node_names(scenario).iter().try_for_each(|name| checked(dir, name, scenario, &expected).map(drop))
}

fn checked(dir: &Path, name: &str, scenario: &Scenario, expected: &Value) -> Result<Identity, IdentityError> {
    let id = identity(dir, name)?;
    if &id.policy != expected {
        return Err(IdentityError(format!(
            "--tls {}: {POLICY} was made for another topology than scenario {}'s (run `formation certs` again)",
            dir.display(),
            scenario.name
        )));
    }
    Ok(id)
}

/// The zenoh settings of `--tls`: mutual TLS with the authority as the
/// only root, names checked on connect, TLS-only links, and the policy.
pub fn zenoh_tls(id: &Identity) -> Vec<(&'static str, Value)> {
    let p = |p: &Path| Value::from(p.display().to_string());
    vec![
        ("transport/link/tls/root_ca_certificate", p(&id.ca)),
        ("transport/link/tls/listen_certificate", p(&id.cert)),
        ("transport/link/tls/listen_private_key", p(&id.key)),
        ("transport/link/tls/connect_certificate", p(&id.cert)),
        ("transport/link/tls/connect_private_key", p(&id.key)),
        ("transport/link/tls/enable_mtls", Value::Bool(true)),
        ("transport/link/tls/verify_name_on_connect", Value::Bool(true)),
        ("transport/link/protocols", json!(["tls"])),
        ("access_control", id.policy.clone()),
    ]
}
