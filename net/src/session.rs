//! Opening zenoh sessions with this project's safety settings.
//!
//! Every session built here has multicast scouting **off** (only loopback
//! traffic is allowed on our machines, and zenoh's default scouting sends to
//! 224.0.0.224:7446) and never listens on all interfaces by default. See
//! `/work/shared/ZENOH.md` for the measurements behind the other defaults.
//!
//! # How a `--config` file and our settings combine
//!
//! 1. The file (json5/json/yaml, zenoh's own format) is loaded first.
//! 2. `--mode`, `--listen` and `--connect` given on the command line replace
//!    the file's `mode`, `listen/endpoints` and `connect/endpoints`.
//! 3. `scouting/multicast/enabled = false` is forced, always, whatever the
//!    file says.
//! 4. These are set only where the file left them unset:
//!    `scouting/delay = 0`, `connect/timeout_ms = -1` (wait for the peer or
//!    router instead of failing at once), `connect/exit_on_failure = false`,
//!    and `connect/retry/{period_init_ms: 50, period_max_ms: 50,
//!    period_increase_factor: 2}` (per field). The retry settings are what
//!    makes a client reconnect within a few tenths of a second after its
//!    link or router is back (docs/lab.md; zenoh's default retry is 1 s ×2
//!    up to 4 s): a follower that reconnects later
//!    has dead-reckoned longer, and pulls its neighbours harder. And
//!    `transport/link/tx/lease = 1000` where the file leaves zenoh's
//!    10 000 (with zenoh's 4 keep-alives per lease): a link cut without a
//!    FIN is noticed within about a second instead of 10 s. `--lease-ms`
//!    replaces both the file's lease and this one: `formation launch` gives
//!    the nodes it starts on one host 10 000 (see [`LAUNCH_LEASE_MS`]).
//!    A file that turns zenoh's QoS off (`transport/unicast/qos/enabled =
//!    false`) is refused: the formation's traffic relies on its priorities.
//! 5. Listen endpoints: `--listen` if given; else the file's if it set any
//!    (anything other than zenoh's built-in default); else
//!    `tcp/127.0.0.1:0` for a peer (a peer needs a listener of its own:
//!    routers do not forward between peers), `tcp/127.0.0.1:7447` for a
//!    router and nothing for a client. Zenoh's built-in default (all
//!    interfaces, `[::]`) is never used.

use std::path::PathBuf;

use serde_json::Value;

/// Zenoh node kind, as in zenoh's `mode` config key.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum ZenohMode {
    Peer,
    Client,
    Router,
}

impl ZenohMode {
    pub fn as_str(self) -> &'static str {
        match self {
            ZenohMode::Peer => "peer",
            ZenohMode::Client => "client",
            ZenohMode::Router => "router",
        }
    }
}

/// Zenoh connection options shared by every binary (`#[command(flatten)]`).
#[derive(Clone, Debug, Default)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct ZenohArgs {
    /// Zenoh mode [default: peer, or the config file's mode].
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub mode: Option<ZenohMode>,
    /// Endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable).
    /// Default: tcp/127.0.0.1:0 for a peer, tcp/127.0.0.1:7447 for a router.
    #[cfg_attr(feature = "clap", arg(long = "listen", value_name = "ENDPOINT"))]
    pub listen: Vec<String>,
    /// Endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable).
    #[cfg_attr(feature = "clap", arg(long = "connect", value_name = "ENDPOINT"))]
    pub connect: Vec<String>,
    /// Zenoh configuration file (json5); multicast scouting is forced off
    /// whatever it says.
    #[cfg_attr(feature = "clap", arg(long = "config", value_name = "FILE.json5"))]
    pub config: Option<PathBuf>,
    /// Mutual TLS on every link with the certificates and policy in DIR
    /// (made by `formation certs`): endpoints become tls/…, only the folder's
    /// authority is trusted, plain TCP is refused, and each node may publish
    /// and receive only what its role in the topology needs.
    #[cfg_attr(feature = "clap", arg(long = "tls", value_name = "DIR"))]
    pub tls: Option<PathBuf>,
    /// Peer mode: link only to the --connect endpoints and to whoever dials
    /// this node. By default zenoh's gossip makes every pair of peers dial
    /// each other: N(N−1)/2 links, which 100 nodes on one host do not
    /// survive. Off, a node hears only the peers it is linked to (peers do
    /// not relay), so the links must cover every pair that talks.
    #[cfg_attr(feature = "clap", arg(long = "no-gossip"))]
    pub no_gossip: bool,
    /// How long, in ms, the other end of a link waits for anything from
    /// this node before it declares the link dead and reconnects [default:
    /// 1000, or the config file's `transport/link/tx/lease`]. Short: a cut
    /// link is noticed fast. Long: a host short of CPU does not lose its
    /// links to a keep-alive sent late (`formation launch` uses 10000: on one
    /// host a dead process's links close at once anyway).
    #[cfg_attr(feature = "clap", arg(long = "lease-ms", value_name = "MS",
        value_parser = clap::value_parser!(u64).range(100..=3_600_000)))]
    pub lease_ms: Option<u64>,
    /// The node's name in its certificate (`router`, `leader`, `monitor`,
    /// `agent-<id>`): set by the node, not on the command line.
    #[cfg_attr(feature = "clap", arg(skip))]
    pub identity: Option<String>,
    /// What the run's traffic is (set by the node from its scenario): the
    /// limits of [`crate::limits`]. None: [`crate::limits::Traffic::unknown`].
    #[cfg_attr(feature = "clap", arg(skip))]
    pub traffic: Option<crate::limits::Traffic>,
}

/// Link lease, ms: a link silent this long is declared dead (overridable
/// with `--lease-ms`, or `transport/link/tx/lease` in a `--config` file).
pub const LEASE_MS: u64 = 1000;

/// The lease `formation launch` gives the nodes it starts on one host
/// (zenoh's own default). There a dead process's links close at once (the
/// kernel closes its sockets), so the lease only decides how long a node
/// starved of CPU may stay silent. With 1 s, 200 agents on the 2-core VM
/// lost hundreds of links at start-up; their reconnections raced inside
/// zenoh, and data reached subscribers of other keys (docs/performance.md).
pub const LAUNCH_LEASE_MS: u64 = 10_000;

/// Zenoh's own threads, unless the environment sets `ZENOH_RUNTIME`: every
/// zenoh runtime (receive, transmit, accept, network) handed over to one
/// application runtime of one worker. Zenoh's default (six threads, two of
/// them receiving) spreads one message over several thread wake-ups; on a
/// host shared by many nodes that costs CPU and, worse, late messages.
/// Lower one-hop latency and less CPU than zenoh's default
/// (docs/performance.md, "Zenoh's threads"). Nodes that forward nothing
/// only: see [`router_runtime`].
pub const RUNTIME: &str = "(rx: (handover: app), acc: (handover: app), tx: (handover: app), net: (handover: app), \
                           app: (worker_threads: 1))";

/// A router's zenoh threads in real time: as [`RUNTIME`] but with two
/// workers, so that one client that floods it cannot hold the only thread
/// that forwards, and its transmit tasks on zenoh's own TX thread, not
/// handed over: a forwarding thread that waits for room in one client's
/// full queue must never be a thread that empties the queues (a flood of
/// puts showed both: docs/performance.md, "Zenoh's threads").
pub const ROUTER_RUNTIME: &str =
    "(rx: (handover: app), acc: (handover: app), net: (handover: app), app: (worker_threads: 2))";

/// A router's command gets [`ROUTER_RUNTIME`] when the run is real time (unless
/// `ZENOH_RUNTIME` is set). Not in lock-step: there estimates are
/// non-droppable, and a forwarding task that waits for room in a full
/// transmit queue would hold the one thread that empties it (50 agents in
/// lock-step stalled at their first step that way). Real-time traffic is
/// droppable and never waits; and on one thread the router delivers far
/// fewer estimates a step late (docs/performance.md, "Zenoh's threads").
pub fn router_runtime(c: &mut std::process::Command, timing: formation_scenario::Timing) {
    if user_runtime() {
        return;
    }
    if timing == formation_scenario::Timing::Realtime {
        c.env("ZENOH_RUNTIME", ROUTER_RUNTIME);
    } else {
        // This process may have set it for itself (bench-net).
        c.env_remove("ZENOH_RUNTIME");
    }
}

/// Whether the user set `ZENOH_RUNTIME` (as this process found it the first
/// time it asked, before [`default_runtime`] sets it).
fn user_runtime() -> bool {
    static USER: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *USER.get_or_init(|| std::env::var_os("ZENOH_RUNTIME").is_some())
}

/// Sets [`RUNTIME`] for this process's zenoh unless `ZENOH_RUNTIME` is set.
/// Call first thing in `main`, before any thread starts (zenoh reads the
/// variable once, when it first needs a runtime; child processes inherit it).
pub fn default_runtime() {
    if !user_runtime() {
        std::env::set_var("ZENOH_RUNTIME", RUNTIME);
    }
}

/// Default listen endpoint of a peer: an ephemeral loopback port.
pub const PEER_DEFAULT_LISTEN: &str = "tcp/127.0.0.1:0";
/// Default listen endpoint of a router.
pub const ROUTER_DEFAULT_LISTEN: &str = "tcp/127.0.0.1:7447";

/// Why a zenoh session could not be configured or opened.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    /// The options or the configuration file are wrong: bad input.
    #[error("{0}")]
    Config(String),
    /// The session could not be opened (no router, a port in use, …).
    #[error("{0}")]
    Open(String),
}

impl From<SessionError> for formation_exit::Error {
    fn from(e: SessionError) -> Self {
        match e {
            SessionError::Config(m) => formation_exit::Error::Input(m),
            SessionError::Open(m) => formation_exit::Error::Run(m),
        }
    }
}

fn config_err(what: impl std::fmt::Display, e: impl std::fmt::Display) -> SessionError {
    SessionError::Config(format!("{what}: {e}"))
}

/// A zenoh configuration file, or one line saying what is wrong with it.
fn read_file(path: &std::path::Path) -> Result<zenoh::Config, SessionError> {
    let what = format!("zenoh config {}", path.display());
    std::fs::metadata(path).map_err(|e| config_err(&what, e))?;
    zenoh::Config::from_file(path).map_err(|e| config_err(&what, tidy_error(&e.to_string())))
}

/// Zenoh's error for a file it could not read, in one line: the message
/// and its place, without the debug formatting, the parser's drawing or
/// the location in zenoh's own source.
fn tidy_error(e: &str) -> String {
    // "… at /…/zenoh-config-1.10.2/src/lib.rs:1484."
    let e = match e.rfind(" at /") {
        Some(i) if e[i..].trim_end_matches('.').rsplit(':').next().is_some_and(|n| n.parse::<u32>().is_ok()) => &e[..i],
        _ => e,
    };
    let number = |after: &str| -> Option<u64> {
        let i = e.find(after)? + after.len();
        e[i..].chars().take_while(char::is_ascii_digit).collect::<String>().parse().ok()
    };
    // serde: Message { msg: "unknown field `x`, …", location: Some(Location { line: 1, column: 16 }) }
    if let Some(i) = e.find("msg: \"") {
        let rest = &e[i + 6..];
        let msg = rest.split("\", location").next().unwrap_or(rest).trim_end_matches("\" }");
        return match (number("line: "), number("column: ")) {
            (Some(l), Some(c)) => format!("{msg} (line {l}, column {c})"),
            _ => msg.to_string(),
        };
    }
    // json5's parser: " --> 2:1 | … = expected identifier or string"
    if let Some(i) = e.find("= ") {
        let msg = e[i + 2..].trim();
        let place = e.find("--> ").map(|j| e[j + 4..].split_whitespace().next().unwrap_or("").to_string());
        if let Some((l, c)) = place.as_deref().and_then(|p| p.split_once(':')) {
            return format!("{msg} (line {l}, column {c})");
        }
        return msg.to_string();
    }
    e.split_whitespace().collect::<Vec<_>>().join(" ")
}

fn get(config: &zenoh::Config, key: &str) -> Result<Value, SessionError> {
    let json = config.get_json(key).map_err(|e| config_err(format_args!("zenoh config key {key}"), e))?;
    serde_json::from_str(&json).map_err(|e| config_err(format_args!("zenoh config key {key}: {json}"), e))
}

fn set(config: &mut zenoh::Config, key: &str, value: &Value) -> Result<(), SessionError> {
    config
        .insert_json5(key, &value.to_string())
        .map_err(|e| config_err(format_args!("setting zenoh config {key} = {value}"), e))
}

fn set_if_unset(config: &mut zenoh::Config, key: &str, value: Value) -> Result<(), SessionError> {
    if get(config, key)?.is_null() {
        set(config, key, &value)?;
    }
    Ok(())
}

impl ZenohArgs {
    /// The mode the session will run in (flag, else config file, else peer).
    fn effective_mode(&self, config: &zenoh::Config) -> Result<ZenohMode, SessionError> {
        if let Some(m) = self.mode {
            return Ok(m);
        }
        Ok(match get(config, "mode")? {
            Value::String(s) if s == "client" => ZenohMode::Client,
            Value::String(s) if s == "router" => ZenohMode::Router,
            _ => ZenohMode::Peer,
        })
    }

    /// Build the zenoh configuration (see the module docs for the rules).
    pub fn to_config(&self) -> Result<zenoh::Config, SessionError> {
        let mut config = match &self.config {
            Some(path) => read_file(path)?,
            None => zenoh::Config::default(),
        };
        let mode = self.effective_mode(&config)?;
        set(&mut config, "mode", &Value::from(mode.as_str()))?;

        // Zenoh's priorities (QoS): on, or the file is refused. Estimates
        // never wait behind telemetry only because each priority has a
        // queue of its own; and with one queue per link, zenoh's own
        // messages that may not be dropped (declarations) wait on its one
        // thread behind a lock-step run's estimates, for room that only
        // that thread can make, until zenoh closes the link 5 s later.
        if let Some(path) = &self.config {
            if get(&config, "transport/unicast/qos/enabled")? == false {
                return Err(SessionError::Config(format!(
                    "zenoh config {}: transport/unicast/qos/enabled = false is not supported: the formation needs \
                     zenoh's priorities (estimates before telemetry; without them lock-step runs stall)",
                    path.display()
                )));
            }
        }

        // Multicast scouting: off, always.
        set(&mut config, "scouting/multicast/enabled", &Value::Bool(false))?;
        set_if_unset(&mut config, "scouting/delay", Value::from(0))?;
        if self.no_gossip {
            set(&mut config, "scouting/gossip/enabled", &Value::Bool(false))?;
        }

        // A dead link is noticed within about a second (zenoh's default
        // lease is 10 s): keep-alives every 250 ms, lease 1 s.
        // (Only where the file left zenoh's defaults, 10 000 ms and 4.)
        // `--lease-ms` replaces both.
        if let Some(ms) = self.lease_ms {
            set(&mut config, "transport/link/tx/lease", &Value::from(ms))?;
        } else if get(&config, "transport/link/tx/lease")? == 10_000 {
            set(&mut config, "transport/link/tx/lease", &Value::from(LEASE_MS))?;
        }

        connect_fast(&mut config)?;
        if !self.connect.is_empty() {
            set(&mut config, "connect/endpoints", &Value::from(self.connect.clone()))?;
        }

        // Limits on what this node receives (crate::limits), where the file set none.
        let traffic = self.traffic.clone().unwrap_or_else(crate::limits::Traffic::unknown);
        for (key, value) in traffic.sections() {
            match get(&config, key)? {
                Value::Null => set(&mut config, key, &value)?,
                Value::Array(a) if a.is_empty() => set(&mut config, key, &value)?,
                _ => {}
            }
        }
        if let Some(dir) = &self.tls {
            let name = self
                .identity
                .as_deref()
                .ok_or_else(|| SessionError::Config(format!("--tls: this node has no name to look for")))?;
            let id = formation_certs::identity(dir, name).map_err(|e| SessionError::Config(e.0))?;
            for (key, value) in crate::identity::zenoh_tls(&id) {
                set(&mut config, key, &value)?;
            }
            let connect = get(&config, "connect/endpoints")?;
            set(&mut config, "connect/endpoints", &tls_endpoints(&connect, "connect")?)?;
        }

        self.set_listen(&mut config, mode)?;
        if self.tls.is_some() {
            let listen = get(&config, "listen/endpoints")?;
            set(&mut config, "listen/endpoints", &tls_endpoints(&listen, "listen")?)?;
        }
        Ok(config)
    }

    /// Listen: the node's own endpoints; else the file's, if it chose any;
    /// else the mode's default, never zenoh's all-interfaces one.
    fn set_listen(&self, config: &mut zenoh::Config, mode: ZenohMode) -> Result<(), SessionError> {
        let builtin_listen = get(&zenoh::Config::default(), "listen/endpoints")?;
        let listen: Option<Vec<String>> = if !self.listen.is_empty() {
            Some(self.listen.clone())
        } else if get(config, "listen/endpoints")? != builtin_listen {
            None // the file chose its own listeners: keep them
        } else {
            Some(match mode {
                ZenohMode::Peer => vec![PEER_DEFAULT_LISTEN.to_string()],
                ZenohMode::Router => vec![ROUTER_DEFAULT_LISTEN.to_string()],
                ZenohMode::Client => vec![],
            })
        };
        if let Some(listen) = listen {
            set(config, "listen/endpoints", &Value::from(listen))?;
        }
        Ok(())
    }
}

/// Connect: wait for the other side and retry fast (where the file set
/// nothing else).
fn connect_fast(config: &mut zenoh::Config) -> Result<(), SessionError> {
    set_if_unset(config, "connect/timeout_ms", Value::from(-1))?;
    set_if_unset(config, "connect/exit_on_failure", Value::Bool(false))?;
    let mut retry = match get(config, "connect/retry")? {
        Value::Object(m) => m,
        _ => Default::default(),
    };
    for (k, v) in [
        ("period_init_ms", Value::from(50)),
        ("period_max_ms", Value::from(50)),
        ("period_increase_factor", Value::from(2.0)),
    ] {
        if retry.get(k).is_none_or(Value::is_null) {
            retry.insert(k.to_string(), v);
        }
    }
    set(config, "connect/retry", &Value::Object(retry))?;
    Ok(())
}

/// `--tls`: every `tcp/` endpoint of a list becomes `tls/`; any other
/// protocol than tcp or tls is refused (it would bypass TLS).
fn tls_endpoints(list: &Value, what: &str) -> Result<Value, SessionError> {
    let convert = |e: &Value| -> Result<Value, SessionError> {
        let s =
            e.as_str().ok_or_else(|| SessionError::Config(format!("--tls: {what} endpoint {e} is not a string")))?;
        if let Some(rest) = s.strip_prefix("tcp/") {
            Ok(Value::from(format!("tls/{rest}")))
        } else if s.starts_with("tls/") {
            Ok(Value::from(s))
        } else {
            return Err(SessionError::Config(format!(
                "--tls: {what} endpoint {s} is not tcp/ or tls/ (every link must be TLS)"
            )));
        }
    };
    match list {
        Value::Array(a) => Ok(Value::Array(a.iter().map(convert).collect::<Result<_, SessionError>>()?)),
        // Mode-dependent lists ({ router: [...], peer: [...], client: [...] }).
        Value::Object(m) => Ok(Value::Object(
            m.iter().map(|(k, v)| Ok((k.clone(), tls_endpoints(v, what)?))).collect::<Result<_, SessionError>>()?,
        )),
        Value::Null => Ok(Value::Null),
        other => return Err(SessionError::Config(format!("--tls: {what} endpoints {other} are not a list"))),
    }
}

/// A zenoh configuration file that `formation launch` gives every node it
/// starts (`--zenoh-config`), checked once before anything starts.
#[derive(Clone, Debug)]
pub struct SharedFile {
    /// Absolute, so that every node finds it whatever its folder.
    pub path: PathBuf,
    /// The file's `transport/link/tx/lease`, if it set one other than
    /// zenoh's default: then the launch keeps it instead of its own.
    pub lease_ms: Option<u64>,
}

impl SharedFile {
    /// Reads and checks `path`: a node's rules for `--config` (QoS on, …),
    /// and no `id`, `mode`, `listen` or `connect` endpoints, which the launch
    /// decides for each node. One line on any error.
    pub fn check(path: &std::path::Path) -> Result<Self, SessionError> {
        let path = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
        ZenohArgs { config: Some(path.clone()), ..Default::default() }.to_config()?;
        let file = read_file(&path)?;
        let builtin = zenoh::Config::default();
        for key in ["id", "mode", "listen/endpoints", "connect/endpoints"] {
            if get(&file, key)? != get(&builtin, key)? {
                return Err(SessionError::Config(format!(
                    "zenoh config {}: {key} is set; formation launch gives each node its own id, mode and links \
                     (leave id, mode, listen and connect out of the file)",
                    path.display()
                )));
            }
        }
        let lease = get(&file, "transport/link/tx/lease")?;
        let lease_ms = (lease != get(&builtin, "transport/link/tx/lease")?).then(|| lease.as_u64()).flatten();
        Ok(Self { path, lease_ms })
    }
}

/// Endpoint lists of a config for messages: `listen [...], connect [...]`.
pub fn describe_endpoints(config: &zenoh::Config) -> String {
    let show = |key: &str| config.get_json(key).unwrap_or_else(|e| format!("<{e}>"));
    format!("listen {}, connect {}", show("listen/endpoints"), show("connect/endpoints"))
}

/// Open a zenoh session from the command-line arguments.
///
/// A client (or a peer with `--connect`) whose router is not up yet waits
/// for it (`connect/timeout_ms = -1`): wrap the call in a timeout if that
/// is not wanted. The wait runs on a thread of its own (zenoh's `open`
/// holds the thread that polls it while it waits), so a timeout around
/// this call does fire.
pub async fn open(args: &ZenohArgs) -> Result<zenoh::Session, SessionError> {
    use zenoh::Wait;
    let config = args.to_config()?;
    let mode = config.get_json("mode").unwrap_or_default();
    let endpoints = describe_endpoints(&config);
    let (tx, rx) = tokio::sync::oneshot::channel();
    std::thread::Builder::new()
        .name("zenoh-open".into())
        .spawn(move || {
            let _ = tx.send(zenoh::open(config).wait());
        })
        .map_err(|e| SessionError::Open(format!("cannot start a thread to open the zenoh session: {e}")))?;
    let session = rx
        .await
        .map_err(|_| SessionError::Open(format!("opening the zenoh session stopped without an answer")))?
        .map_err(|e| SessionError::Open(format!("cannot open zenoh session (mode {mode}, {endpoints}): {e}")))?;
    note_zid(&session.zid().to_string());
    Ok(session)
}

/// Set by `formation launch` on the nodes it starts: the file their zenoh
/// log lines go to (appended), instead of stderr.
pub const ZENOH_LOG_ENV: &str = "FORMATION_ZENOH_LOG";

/// What `formation launch` appends to the run folder's name for the folder
/// its nodes' zenoh logs go to while the run lasts.
pub const ZENOH_LOG_BESIDE: &str = ".zenoh-log";

/// The run folder's subfolder that keeps them after the run.
pub const ZENOH_LOG_SUBDIR: &str = "zenoh-log";

/// For a monitor whose `formation launch` is gone (killed with SIGKILL, so
/// its nodes were sent SIGTERM and it cannot gather their logs): moves the
/// launch's zenoh-log folder beside run folder `out` into it, as the launch
/// would have. `launched_by` is the monitor's parent process when it
/// started. Nothing happens for a node run by hand, or while the launch
/// lives (it moves them itself).
pub fn keep_zenoh_logs_of_a_gone_launch(out: &std::path::Path, launched_by: u32) {
    let Some(file) = std::env::var_os(ZENOH_LOG_ENV) else { return };
    let Some(dir) = std::path::Path::new(&file).parent() else { return };
    let kept = out.join(ZENOH_LOG_SUBDIR);
    if std::os::unix::process::parent_id() == launched_by
        || dir != formation_record::folder::beside(out, ZENOH_LOG_BESIDE)
        || kept.exists()
    {
        return;
    }
    let _ = std::fs::rename(dir, kept);
}

/// The line a node writes into its zenoh log ([`ZENOH_LOG_ENV`])
/// when a session opens, so that the launch can name the node behind a zid
/// in zenoh's own lines ("… to 30e9b3…. Closing transport!").
pub const ZID_NOTE: &str = "formation: this node's zenoh id is ";

fn note_zid(zid: &str) {
    use std::io::Write;
    let Some(path) = std::env::var_os(ZENOH_LOG_ENV) else { return };
    if let Ok(mut f) = std::fs::OpenOptions::new().create(true).append(true).open(path) {
        let _ = writeln!(f, "{ZID_NOTE}{zid}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn json(config: &zenoh::Config, key: &str) -> Value {
        get(config, key).unwrap()
    }

    fn file(contents: &str) -> tempfile::NamedTempFile {
        let mut f = tempfile::Builder::new().suffix(".json5").tempfile().unwrap();
        f.write_all(contents.as_bytes()).unwrap();
        f
    }

    #[test]
    fn defaults_are_safe() {
        let c = ZenohArgs::default().to_config().unwrap();
        assert_eq!(json(&c, "mode"), "peer");
        assert_eq!(json(&c, "scouting/multicast/enabled"), false);
        assert_eq!(json(&c, "scouting/delay"), 0);
        assert_eq!(json(&c, "listen/endpoints"), serde_json::json!(["tcp/127.0.0.1:0"]));
        assert_eq!(json(&c, "connect/timeout_ms"), -1);
        assert_eq!(json(&c, "connect/exit_on_failure"), false);
        let retry = json(&c, "connect/retry");
        assert_eq!(retry["period_init_ms"], 50);
        assert_eq!(retry["period_max_ms"], 50);
        assert_eq!(retry["period_increase_factor"], 2.0);
        assert_eq!(json(&c, "transport/link/tx/lease"), 1000);
        assert_eq!(json(&c, "transport/link/tx/keep_alive"), 4);
    }

    #[test]
    fn lease_option_replaces_ours_and_the_files() {
        let args = ZenohArgs { lease_ms: Some(LAUNCH_LEASE_MS), ..Default::default() };
        assert_eq!(json(&args.to_config().unwrap(), "transport/link/tx/lease"), 10_000);
        let f = file("{ transport: { link: { tx: { lease: 3000 } } } }");
        let from_file = ZenohArgs { config: Some(f.path().into()), ..Default::default() };
        assert_eq!(json(&from_file.to_config().unwrap(), "transport/link/tx/lease"), 3000);
        let both = ZenohArgs { lease_ms: Some(250), ..from_file };
        assert_eq!(json(&both.to_config().unwrap(), "transport/link/tx/lease"), 250);
    }

    #[test]
    fn a_file_that_turns_qos_off_is_refused_in_one_line() {
        let f = file("{ transport: { unicast: { qos: { enabled: false } } } }");
        let args = ZenohArgs { config: Some(f.path().into()), ..Default::default() };
        let Err(SessionError::Config(m)) = args.to_config() else { panic!("a QoS-off config was accepted") };
        assert!(m.contains("qos/enabled = false is not supported") && !m.contains('\n'), "{m}");
        let on = file("{ transport: { unicast: { qos: { enabled: true } } } }");
        let args = ZenohArgs { config: Some(on.path().into()), ..Default::default() };
        assert_eq!(json(&args.to_config().unwrap(), "transport/unicast/qos/enabled"), true);
    }

    /// `formation launch --zenoh-config`: the file is checked once, its
    /// lease kept, and what the launch decides per node refused in one line.
    #[test]
    fn a_launch_file_keeps_its_lease_and_leaves_the_links_to_the_launch() {
        let plain = file("{ transport: { link: { tx: { batch_size: 8192 } } } }");
        let f = SharedFile::check(plain.path()).unwrap();
        assert!(f.path.is_absolute(), "{}", f.path.display());
        assert_eq!(f.lease_ms, None);
        let lease = file("{ transport: { link: { tx: { lease: 3000 } } } }");
        assert_eq!(SharedFile::check(lease.path()).unwrap().lease_ms, Some(3000));
        for (text, key) in [
            (r#"{ id: "aabbcc" }"#, "id is set"),
            (r#"{ mode: "client" }"#, "mode is set"),
            (r#"{ listen: { endpoints: ["tcp/127.0.0.1:7998"] } }"#, "listen/endpoints"),
            (r#"{ connect: { endpoints: ["tcp/127.0.0.1:7999"] } }"#, "connect/endpoints"),
            ("{ transport: { unicast: { qos: { enabled: false } } } }", "qos/enabled"),
            ("{ transport: { nonsense: 1 } }", "unknown field `nonsense`"),
            ("{ transport: { ", "expected identifier or string (line 1, column 16)"),
        ] {
            let f = file(text);
            match SharedFile::check(f.path()) {
                Err(SessionError::Config(m)) => assert!(m.contains(key) && !m.contains('\n'), "{text}: {m}"),
                other => panic!("{text} was not refused: {other:?}"),
            }
        }
        let missing = SharedFile::check(std::path::Path::new("/nonexistent/zenoh.json5"));
        assert!(matches!(missing, Err(SessionError::Config(m)) if m.contains("/nonexistent/zenoh.json5")));
    }

    #[test]
    fn modes_and_endpoints() {
        let client = ZenohArgs {
            mode: Some(ZenohMode::Client),
            connect: vec!["tcp/127.0.0.1:7447".into()],
            ..Default::default()
        }
        .to_config()
        .unwrap();
        assert_eq!(json(&client, "mode"), "client");
        assert_eq!(json(&client, "listen/endpoints"), serde_json::json!([]));
        assert_eq!(json(&client, "connect/endpoints"), serde_json::json!(["tcp/127.0.0.1:7447"]));
        let router = ZenohArgs { mode: Some(ZenohMode::Router), ..Default::default() }.to_config().unwrap();
        assert_eq!(json(&router, "listen/endpoints"), serde_json::json!([ROUTER_DEFAULT_LISTEN]));
        let peer = ZenohArgs {
            listen: vec!["tcp/127.0.0.1:17000".into(), "tcp/127.0.0.1:17001".into()],
            ..Default::default()
        }
        .to_config()
        .unwrap();
        assert_eq!(json(&peer, "listen/endpoints"), serde_json::json!(["tcp/127.0.0.1:17000", "tcp/127.0.0.1:17001"]));
        assert!(ZenohArgs { listen: vec!["nonsense".into()], ..Default::default() }.to_config().is_err());
    }

    #[test]
    fn multicast_forced_off_but_file_settings_kept() {
        let f = file(
            r#"{ mode: "client",
                 scouting: { delay: 300, multicast: { enabled: true } },
                 connect: { endpoints: ["tcp/127.0.0.1:7999"], timeout_ms: 2000,
                            retry: { period_init_ms: 20 } },
                 listen: { endpoints: ["tcp/127.0.0.1:7998"] } }"#,
        );
        let args = ZenohArgs { config: Some(f.path().into()), ..Default::default() };
        let c = args.to_config().unwrap();
        assert_eq!(json(&c, "scouting/multicast/enabled"), false);
        assert_eq!(json(&c, "mode"), "client");
        assert_eq!(json(&c, "scouting/delay"), 300);
        assert_eq!(json(&c, "connect/timeout_ms"), 2000);
        assert_eq!(json(&c, "connect/exit_on_failure"), false);
        let retry = json(&c, "connect/retry");
        assert_eq!(retry["period_init_ms"], 20);
        assert_eq!(retry["period_max_ms"], 50);
        assert_eq!(json(&c, "connect/endpoints"), serde_json::json!(["tcp/127.0.0.1:7999"]));
        assert_eq!(json(&c, "listen/endpoints"), serde_json::json!(["tcp/127.0.0.1:7998"]));

        // Command-line flags win over the file.
        let args = ZenohArgs {
            mode: Some(ZenohMode::Peer),
            connect: vec!["tcp/127.0.0.1:7001".into()],
            listen: vec!["tcp/127.0.0.1:7002".into()],
            config: Some(f.path().into()),
            ..Default::default()
        };
        let c = args.to_config().unwrap();
        assert_eq!(json(&c, "mode"), "peer");
        assert_eq!(json(&c, "scouting/multicast/enabled"), false);
        assert_eq!(json(&c, "connect/endpoints"), serde_json::json!(["tcp/127.0.0.1:7001"]));
        assert_eq!(json(&c, "listen/endpoints"), serde_json::json!(["tcp/127.0.0.1:7002"]));
    }

    #[test]
    fn file_without_listen_gets_loopback() {
        let f = file(r#"{ scouting: { multicast: { enabled: true } } }"#);
        let c = ZenohArgs { config: Some(f.path().into()), ..Default::default() }.to_config().unwrap();
        assert_eq!(json(&c, "mode"), "peer");
        assert_eq!(json(&c, "scouting/multicast/enabled"), false);
        assert_eq!(json(&c, "scouting/delay"), 0);
        assert_eq!(json(&c, "listen/endpoints"), serde_json::json!([PEER_DEFAULT_LISTEN]));
    }

    #[test]
    fn missing_config_file_is_an_error() {
        let args = ZenohArgs { config: Some("/nonexistent/zenoh.json5".into()), ..Default::default() };
        let e = args.to_config().unwrap_err().to_string();
        assert!(e.contains("/nonexistent/zenoh.json5"), "{e}");
    }

    #[cfg(feature = "clap")]
    #[test]
    fn clap_parses_repeatable_flags() {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Cli {
            #[cfg_attr(feature = "clap", command(flatten))]
            zenoh: ZenohArgs,
        }
        let cli = Cli::parse_from([
            "x",
            "--mode",
            "client",
            "--connect",
            "tcp/127.0.0.1:1",
            "--connect",
            "tcp/127.0.0.1:2",
            "--listen",
            "tcp/127.0.0.1:3",
        ]);
        assert_eq!(cli.zenoh.mode, Some(ZenohMode::Client));
        assert_eq!(cli.zenoh.connect.len(), 2);
        assert_eq!(cli.zenoh.listen, vec!["tcp/127.0.0.1:3"]);
    }
}
