//! What zenoh's access control refused, counted per node, subject, action
//! and key, and reported to the monitor (`network.json`'s `access_denied`,
//! and the live page).
//!
//! Zenoh has no API for its denials; it logs each at `trace` level (target
//! [`ACL_TARGET`]): "`<zid>` on `<subject>` is unauthorized to `<action>` on
//! `<key>`" the first time per link and key, then "Using cached result:
//! `<zid>` is unauthorized to …". A node's log layer hands those lines to
//! [`note`]; [`report`] publishes the tally on
//! `formation/<run>/control/denied/<node>` every 250 ms while it changes.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Mutex;
use std::time::Duration;

use formation_protocol::denied::{Denial, Report};

/// The tracing target of zenoh's access control.
pub const ACL_TARGET: &str = "zenoh::net::routing::interceptor::access_control";

/// Lines (zenoh 1.10.2) of the access control's "is authorized" events: the
/// log layer skips them without formatting them.
pub const ALLOWED_LINES: [u32; 4] = [78, 387, 417, 986];

/// The denials one process has seen.
#[derive(Debug, Default)]
pub struct Tally {
    /// zenoh id → subject name, learnt from the first (uncached) denial.
    names: HashMap<String, String>,
    counts: BTreeMap<(String, String, String), u64>,
    /// Bumped by every denial (so a reporter knows when to speak).
    pub version: u64,
}

/// A subject as zenoh names it (`Interface(lo)+CertCommonName(agent-2)+…`):
/// its certificate's name, if it has one.
fn common_name(subject: &str) -> String {
    subject.split_once("CertCommonName(").and_then(|(_, r)| r.split(')').next()).unwrap_or(subject).to_string()
}

impl Tally {
    /// Counts `line` if it is a denial; whether it was. `caching`: the key
    /// whose permissions zenoh is caching on this thread just now ("ACL
    /// (ingress): caching permissions for `key` ...", see [`note`]): it then
    /// decides, and logs, every kind of message for that key, about no
    /// message; those are not counted (they only teach the subject's name).
    pub fn note(&mut self, line: &str, caching: Option<&str>) -> bool {
        let Some((who, rest)) = line.split_once(" is unauthorized to ") else { return false };
        let Some((action, key)) = rest.rsplit_once(" on ") else { return false };
        let key = plain_key(key);
        let who = who.trim();
        let subject = match who.strip_prefix("Using cached result: ") {
            Some(zid) => self.names.get(zid).cloned().unwrap_or_else(|| zid.to_string()),
            None => match who.split_once(" on ") {
                Some((zid, name)) => {
                    let name = common_name(name);
                    self.names.insert(zid.to_string(), name.clone());
                    if caching == Some(key) {
                        return false;
                    }
                    name
                }
                None => who.to_string(),
            },
        };
        *self.counts.entry((subject, action.trim().to_string(), key.to_string())).or_insert(0) += 1;
        self.version += 1;
        true
    }

    /// The runs the refused keys belong to (`formation/<run>/…`).
    pub fn runs(&self) -> BTreeSet<String> {
        self.counts.keys().filter_map(|(_, _, k)| run_of(k)).map(str::to_string).collect()
    }

    /// The rows of one run's keys, most frequent first.
    pub fn rows(&self, run: &str) -> Vec<Denial> {
        let mut rows: Vec<Denial> = self
            .counts
            .iter()
            .filter(|((_, _, k), _)| run_of(k) == Some(run))
            .map(|((subject, action, key), &count)| Denial {
                subject: subject.clone(),
                action: action.clone(),
                key: key.clone(),
                count,
            })
            .collect();
        rows.sort_by(|a, b| b.count.cmp(&a.count).then_with(|| a.key.cmp(&b.key)));
        rows
    }
}

/// `formation/<run>/…` → run.
fn run_of(key: &str) -> Option<&str> {
    let mut parts = key.split('/');
    (parts.next() == Some("formation")).then(|| parts.next()).flatten().filter(|r| !r.contains('*'))
}

static TALLY: Mutex<Option<Tally>> = Mutex::new(None);
/// The tally's version, watched by every [`report`] of the process: they
/// sleep until it changes (a node without access control, or that refused
/// nothing, never wakes for it).
static CHANGED: std::sync::OnceLock<tokio::sync::watch::Sender<u64>> = std::sync::OnceLock::new();

fn changed() -> &'static tokio::sync::watch::Sender<u64> {
    CHANGED.get_or_init(|| tokio::sync::watch::channel(0).0)
}

thread_local! {
    /// The key zenoh began caching permissions for on this thread, and when.
    static CACHING: std::cell::RefCell<Option<(String, std::time::Instant)>> = const { std::cell::RefCell::new(None) };
}

/// At most how long after "caching permissions for `key`" the same
/// thread's decisions on that key can be the cache's. The cache decides
/// nine kinds of message in one go and logs the refused ones; the burst
/// ends at the first line about another key, or a decision taken from the
/// cache. (This was a 1 ms window alone: on a loaded host a thread
/// preempted inside the burst let its last lines through, liveliness and
/// deletes the formation never sends, and a TLS run was called disturbed.)
const CACHING_BURST: Duration = Duration::from_millis(250);

/// The key a decision line is about (`… is unauthorized to ACTION on KEY`).
fn decided_key(line: &str) -> Option<&str> {
    let (_, rest) = line.split_once(" is unauthorized to ").or_else(|| line.split_once(" is authorized to "))?;
    Some(plain_key(rest.rsplit_once(" on ")?.1))
}

/// A key as zenoh's line writes it (`k`, or `Some(k)` for an undeclaration), plain.
fn plain_key(key: &str) -> &str {
    let key = key.trim();
    key.strip_prefix("Some(").and_then(|k| k.strip_suffix(')')).unwrap_or(key).trim_matches('"')
}

/// Counts a log line of zenoh's access control (see the module docs).
pub fn note(line: &str) {
    if let Some(rest) = line.split_once("caching permissions for `").map(|(_, r)| r) {
        let key = rest.split('`').next().unwrap_or("").to_string();
        // (A log hook of the whole process, no node's: this host's clock.)
        let now = crate::clock::Clock::real().instant();
        CACHING.with(|c| *c.borrow_mut() = Some((key, now)));
        return;
    }
    let from_cache = line.contains("Using cached result: ");
    let key = decided_key(line);
    let now = crate::clock::Clock::real().instant();
    let caching = CACHING.with(|c| {
        let mut c = c.borrow_mut();
        let in_burst = c.as_ref().is_some_and(|(k, at)| {
            !from_cache && key == Some(k.as_str()) && now.saturating_duration_since(*at) < CACHING_BURST
        });
        if !in_burst {
            *c = None;
        }
        c.as_ref().map(|(k, _)| k.clone())
    });
    let mut t = TALLY.lock().unwrap_or_else(|p| p.into_inner());
    let before = t.as_ref().map(|t| t.version);
    let tally = t.get_or_insert_with(Tally::default);
    tally.note(line, caching.as_deref());
    if before != Some(tally.version) {
        changed().send_replace(tally.version);
    }
}

fn with_tally<R>(f: impl FnOnce(&Tally) -> R) -> R {
    let mut t = TALLY.lock().unwrap_or_else(|p| p.into_inner());
    f(t.get_or_insert_with(Tally::default))
}

/// How often a node says what its access control refused, while it changes.
pub const REPORT_PERIOD: Duration = Duration::from_millis(250);

/// Publishes this process's denials for every run they concern (only
/// `run`, if given), at most every [`REPORT_PERIOD`] while they change, as
/// `node`; asleep while they do not. Runs until the session closes.
pub async fn report(session: zenoh::Session, node: String, run: Option<String>) {
    let mut said = 0u64;
    let mut version = changed().subscribe();
    version.mark_changed(); // what was refused before this started
    loop {
        if version.changed().await.is_err() {
            return;
        }
        tokio::time::sleep(REPORT_PERIOD).await;
        if session.is_closed() {
            return;
        }
        let (version, reports) = with_tally(|t| {
            let runs: Vec<String> = match &run {
                Some(r) => vec![r.clone()],
                None => t.runs().into_iter().collect(),
            };
            (t.version, runs.into_iter().map(|r| (r.clone(), t.rows(&r))).collect::<Vec<_>>())
        });
        if version == said {
            continue;
        }
        said = version;
        for (r, rows) in reports.into_iter().filter(|(_, rows)| !rows.is_empty()) {
            let body = serde_json::to_vec(&Report { node: node.clone(), rows }).unwrap_or_default();
            let _ = session
                .put(format!("formation/{r}/control/denied/{node}"), body)
                .congestion_control(zenoh::qos::CongestionControl::Drop)
                .await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A permissions cache's burst is not counted even when the thread is
    /// held up inside it; a decision from the cache, and one after the
    /// burst, are.
    #[test]
    fn a_cache_burst_held_up_is_not_counted() {
        std::thread::spawn(|| {
            let key = "formation/burst/estimate/4";
            let uncached = |action: &str| {
                format!(
                    "5c on Interface(lo)+CertCommonName(agent-2)+Transport(Tls) is unauthorized to {action} on {key}"
                )
            };
            note(&format!("ACL (egress): caching permissions for `{key}` ..."));
            note(&uncached("Delete (egress)"));
            std::thread::sleep(Duration::from_millis(5));
            note(&uncached("Declare Liveliness Subscriber (egress)"));
            assert!(with_tally(|t| t.rows("burst")).is_empty(), "{:?}", with_tally(|t| t.rows("burst")));
            note(&format!("Using cached result: 5c is unauthorized to Put (egress) on {key}"));
            note(&uncached("Put (egress)"));
        })
        .join()
        .expect("thread");
        let rows = with_tally(|t| t.rows("burst"));
        assert_eq!(rows.len(), 1, "{rows:?}");
        assert_eq!((rows[0].subject.as_str(), rows[0].action.as_str(), rows[0].count), ("agent-2", "Put (egress)", 2));
    }

    #[test]
    fn denials_are_counted_by_subject_action_and_key() {
        let mut t = Tally::default();
        let caching = Some("formation/r/control/abort");
        assert!(!t.note("Using cached result: 1a2b is authorized to Put (ingress) on formation/r/estimate/2", None));
        // Caching a link's permissions decides every kind of message: not counted.
        let line =
            "5c on Interface(lo)+CertCommonName(router)+Transport(Tls)+5c is unauthorized to Delete (ingress) on \
                    formation/r/control/abort";
        assert!(!t.note(line, caching));
        let line = "1a2b on Interface(lo)+CertCommonName(agent-2)+Transport(Tls) is unauthorized to Put (ingress) on \
                    formation/r/estimate/3";
        assert!(t.note(line, caching));
        assert!(t.note("Using cached result: 1a2b is unauthorized to Put (ingress) on formation/r/estimate/3", None));
        let line = "Using cached result: 9f is unauthorized to Declare Subscriber (ingress) on formation/q/estimate/1";
        assert!(t.note(line, None));
        let line =
            "Using cached result: 1a2b is unauthorized to Undeclare Subscriber (ingress) on Some(formation/r/telemetry/1)";
        assert!(t.note(line, None));
        assert_eq!(t.runs().into_iter().collect::<Vec<_>>(), ["q", "r"]);
        let rows = t.rows("r");
        assert_eq!(rows.len(), 2, "{rows:?}");
        assert_eq!(
            rows[0],
            Denial {
                subject: "agent-2".into(),
                action: "Put (ingress)".into(),
                key: "formation/r/estimate/3".into(),
                count: 2
            }
        );
        assert_eq!(rows[1].key, "formation/r/telemetry/1");
        // A zid never named (its first denial was before we listened): the zid.
        assert_eq!(t.rows("q")[0].subject, "9f");
    }
}
