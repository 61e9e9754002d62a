//! zenoh's side of a node's TLS identity: the access-control policy of a
//! scenario's topology, the zenoh settings of `--tls`, and the revocation
//! list for zenoh's TLS link.
//!
//! With `--tls DIR`, a node checks its files at start
//! ([`formation_certs::identity`], and [`identity_for`]: the policy is the
//! one of this scenario's topology), and its session runs mutual TLS with
//! the authority as the only trust root, TLS-only links, and the policy
//! ([`zenoh_tls`]). `formation certs` makes the folder.

use std::path::Path;

use formation_scenario::Scenario;
use serde_json::{json, Value};

use formation_certs::{identity, node_dir, Identity, IdentityError, CRL, POLICY};

use formation_protocol::names::{agent_name, node_names, LEADER, MONITOR, ROUTER};

/// The environment variable the TLS link reads the revocation list from.
pub const CRL_ENV: &str = "ZENOH_TLS_CRL";

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
    /// Liveliness tokens it declares (crate::died).
    tokens: Vec<String>,
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
            tokens: vec![],
            publish: vec![
                any_run("estimate/0"),
                any_run("telemetry/0"),
                any_run("control/hello/0"),
                any_run("control/claim/0"),
                any_run("control/start"),
                any_run("control/abort"),
                any_run("control/denied/leader"),
            ],
            // Every estimate (lock-step pacing, and its own for twins) and telemetry (who finished).
            receive: vec![any_run("estimate/*"), any_run("telemetry/*"), control.clone()],
            // The run's timebase (crate::clock_sync); a standby leader
            // (crate::standby) asks it until it takes over.
            answer: vec![any_run("control/time")],
            ask: vec![any_run("control/time")],
        },
        Role {
            name: MONITOR.into(),
            tokens: vec![],
            publish: vec![
                any_run("control/hello/monitor"),
                any_run("control/ready/monitor"),
                any_run("control/ack"),
                any_run("control/denied/monitor"),
                // `formation leave`, an operator's command, speaks as the monitor.
                any_run("control/leave/*"),
                // Lock-step: the step a killed follower is cut off from (crate::died).
                any_run("control/died"),
            ],
            receive: vec![any_run("telemetry/*"), control.clone()],
            answer: vec![],
            ask: vec![],
        },
    ];
    for (index, &id) in scenario.graph.ids().iter().enumerate() {
        let mut receive: Vec<String> =
            scenario.sources_of(index).iter().map(|s| any_run(&format!("estimate/{s}"))).collect();
        // Its neighbours' telemetry: in lock-step it keeps repeating its last
        // messages until they report their final step (telemetry::watch_done).
        receive
            .extend(scenario.sources_of(index).iter().filter(|&&s| s != 0).map(|s| any_run(&format!("telemetry/{s}"))));
        // Its own estimate and telemetry: a second process with its identity is refused (twins).
        receive.push(any_run(&format!("estimate/{id}")));
        receive.push(any_run(&format!("telemetry/{id}")));
        receive.push(control.clone());
        let mut publish = vec![
            any_run(&format!("estimate/{id}")),
            any_run(&format!("telemetry/{id}")),
            any_run(&format!("control/hello/{id}")),
            any_run(&format!("control/ready/{id}")),
            any_run(&format!("control/claim/{id}")),
            any_run(&format!("control/denied/{}", agent_name(id))),
            // Lock-step: what it holds of a follower killed (crate::died).
            any_run(&format!("control/holds/{id}")),
        ];
        if scenario.control.guard.safety.is_some() {
            // Every robot's pose, for the safety filter (docs/model.md §16).
            receive.push(any_run("pose/*"));
            publish.insert(1, any_run(&format!("pose/{id}")));
        }
        let tokens = vec![any_run(&format!("alive/{id}"))];
        let ask = vec![any_run("control/time")];
        roles.push(Role { name: agent_name(id), tokens, publish, receive, answer: vec![], ask });
    }
    roles
}

/// zenoh's `access_control` section for a scenario: deny by default; each
/// node (known by its certificate's common name) may put only on its own
/// keys and declare subscribers and be sent puts only on the keys its role
/// reads; the router is trusted to forward. Enforced by every node that
/// loads it: the router for its clients, each peer for its own links.
pub fn policy(scenario: &Scenario) -> Value {
    let liveliness = ["liveliness_token", "declare_liveliness_subscriber", "liveliness_query"];
    let mut rules = vec![
        json!({ "id": "router-forwards",
                "messages": ["put", "declare_subscriber", "query", "declare_queryable", "reply",
                             liveliness[0], liveliness[1], liveliness[2]],
                "flows": ["ingress", "egress"], "permission": "allow", "key_exprs": ["formation/**"] }),
        // Every node hears the agents' liveliness tokens (crate::died): who
        // still runs, and who was killed; each agent declares only its own.
        json!({ "id": "hears-tokens", "messages": [liveliness[1], liveliness[2]],
                "flows": ["ingress", "egress"], "permission": "allow", "key_exprs": [any_run("alive/*")] }),
        json!({ "id": "is-told-tokens", "messages": [liveliness[0]],
                "flows": ["egress"], "permission": "allow", "key_exprs": [any_run("alive/*")] }),
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
        own.extend(["hears-tokens".to_string(), "is-told-tokens".to_string()]);
        if !r.tokens.is_empty() {
            let t = format!("{}-is-alive", r.name);
            rules.push(json!({ "id": t, "messages": ["liveliness_token"], "flows": ["ingress"],
                               "permission": "allow", "key_exprs": r.tokens }));
            own.push(t);
        }
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
