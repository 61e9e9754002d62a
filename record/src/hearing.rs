//! The hearing record: for every networked follower, step and source, which
//! step's message the follower used (or that the source was silent, or that
//! the fault table removed it), what ended the run for it and where a
//! restarted process resumed. A follower's step is a pure function of its
//! state and of the messages it used, so a run is determined by its scenario
//! and this record (`formation replay`).
//!
//! Run-length encoded per source: a real-time run changes its hearing a few
//! times a second, a lock-step run never. The run folder holds it as
//! `hearing.bin` (bincode 2, standard configuration: varints).

use formation_leader::LeaderState;
use serde::{Deserialize, Serialize};

/// What one follower heard of one source at one step.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Heard {
    /// The message stamped k − age was used at step k.
    Age(u32),
    /// Nothing within the silence timeout.
    Silent,
    /// Nothing used, and the fault table removed the message the step would
    /// have used.
    Removed,
}

const SILENT: u32 = u32::MAX;
const REMOVED: u32 = u32::MAX - 1;

impl Heard {
    /// The message of stamp `stamp` used at step `k`.
    pub fn used(k: u64, stamp: u64) -> Self {
        Heard::Age(u32::try_from(k.saturating_sub(stamp)).unwrap_or(REMOVED - 1).min(REMOVED - 1))
    }

    pub fn code(self) -> u32 {
        match self {
            Heard::Age(a) => a.min(REMOVED - 1),
            Heard::Silent => SILENT,
            Heard::Removed => REMOVED,
        }
    }

    pub fn from_code(c: u32) -> Self {
        match c {
            SILENT => Heard::Silent,
            REMOVED => Heard::Removed,
            a => Heard::Age(a),
        }
    }

    /// The stamp of the message used at step `k`, if one was.
    pub fn stamp(self, k: u64) -> Option<u64> {
        match self {
            Heard::Age(a) => k.checked_sub(u64::from(a)),
            _ => None,
        }
    }

    /// A short word for tables: "age 1", "silent", "removed".
    pub fn describe(self) -> String {
        match self {
            Heard::Age(a) => format!("age {a}"),
            Heard::Silent => "silent".into(),
            Heard::Removed => "removed".into(),
        }
    }
}

/// One follower's hearing over consecutive steps: per source slot (the
/// neighbours in ascending id, then the leader if heard), runs of
/// (code, steps).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct HeardRuns {
    /// Steps covered.
    pub steps: u32,
    pub slots: Vec<Vec<(u32, u32)>>,
}

impl HeardRuns {
    /// Empty, for `slots` sources, with room for `runs` runs per source.
    pub fn with_slots(slots: usize, runs: usize) -> Self {
        Self { steps: 0, slots: (0..slots).map(|_| Vec::with_capacity(runs)).collect() }
    }

    /// `steps` steps at which every one of `slots` sources was heard the same.
    pub fn uniform(slots: usize, steps: u32, heard: Heard) -> Self {
        let runs = if steps == 0 { vec![] } else { vec![(heard.code(), steps)] };
        Self { steps, slots: vec![runs; slots] }
    }

    /// Appends what one slot heard at the step being recorded (then
    /// [`HeardRuns::end_step`]).
    pub fn push_one(&mut self, slot: usize, heard: Heard) {
        let c = heard.code();
        let runs = &mut self.slots[slot];
        match runs.last_mut() {
            Some((code, n)) if *code == c && *n < u32::MAX => *n += 1,
            _ => runs.push((c, 1)),
        }
    }

    /// Closes a step recorded slot by slot with [`HeardRuns::push_one`].
    pub fn end_step(&mut self) {
        self.steps += 1;
    }

    /// Appends one step: what each slot heard, in slot order (as many as
    /// there are slots).
    pub fn push(&mut self, heard: impl IntoIterator<Item = Heard>) {
        let slots = self.slots.len();
        for (slot, h) in heard.into_iter().take(slots).enumerate() {
            self.push_one(slot, h);
        }
        self.end_step();
    }

    /// Whether every slot covers exactly `steps` steps (a batch as sent).
    pub fn is_consistent(&self) -> bool {
        self.slots.iter().all(|r| r.iter().map(|&(_, n)| u64::from(n)).sum::<u64>() == u64::from(self.steps))
    }

    /// Per step, what each slot heard (steps × slots).
    pub fn expand(&self) -> Vec<Vec<Heard>> {
        let mut out = vec![Vec::with_capacity(self.slots.len()); self.steps as usize];
        for runs in &self.slots {
            let mut i = 0usize;
            for &(c, n) in runs {
                for _ in 0..n {
                    if let Some(step) = out.get_mut(i) {
                        step.push(Heard::from_code(c));
                    }
                    i += 1;
                }
            }
        }
        out
    }

    /// Runs held, over every slot.
    pub fn runs(&self) -> usize {
        self.slots.iter().map(Vec::len).sum()
    }
}

/// A span of consecutive recorded steps of one follower, from `first_k`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Segment {
    pub first_k: u64,
    pub heard: HeardRuns,
}

impl Segment {
    pub fn end(&self) -> u64 {
        self.first_k + u64::from(self.heard.steps)
    }
}

/// A restarted process of a follower: from step `k` on, with its robot
/// stopped at `pose` (x, y, θ) and a fresh brain (docs/model.md §14).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Resume {
    pub k: u64,
    pub pose: [f64; 3],
}

/// What ended the run for a follower, as far as the monitor heard.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub enum End {
    /// It computed the final step.
    Completed,
    /// A state stopped being finite at step `k`.
    Diverged { k: u64, quantity: String },
    /// Its last process never said (killed, cut off, or the run was interrupted).
    #[default]
    Unknown,
    /// It left the run for good before step `k` (its process was told to stop).
    Left { k: u64, why: String },
}

/// One follower's part of the record.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FollowerHearing {
    pub id: u32,
    /// The sources by slot: neighbours in ascending id, then 0 (the leader) if heard.
    pub sources: Vec<u32>,
    /// The recorded steps, in order, not overlapping.
    pub segments: Vec<Segment>,
    pub resumes: Vec<Resume>,
    pub end: End,
}

impl FollowerHearing {
    pub fn new(id: u32, sources: Vec<u32>) -> Self {
        Self { id, sources, ..Default::default() }
    }

    /// Whether step `k` of this follower is recorded.
    pub fn covers(&self, k: u64) -> bool {
        self.segments.iter().any(|s| s.first_k <= k && k < s.end())
    }

    /// Appends step `k` (after the last one recorded).
    pub fn push(&mut self, k: u64, heard: &[Heard]) {
        let slots = self.sources.len();
        match self.segments.last_mut() {
            Some(s) if s.end() == k && s.heard.steps < u32::MAX => s.heard.push(heard.iter().copied()),
            _ => {
                let mut heard_runs = HeardRuns::with_slots(slots, 1);
                heard_runs.push(heard.iter().copied());
                self.segments.push(Segment { first_k: k, heard: heard_runs });
            }
        }
    }

    /// Notes a restart (once per step).
    pub fn resumed(&mut self, r: Resume) {
        if !self.resumes.iter().any(|x| x.k == r.k) {
            self.resumes.push(r);
            self.resumes.sort_by_key(|x| x.k);
        }
    }

    /// Steps recorded.
    pub fn steps(&self) -> u64 {
        self.segments.iter().map(|s| u64::from(s.heard.steps)).sum()
    }
}

/// A message a follower used whose sender's own record may not cover it:
/// when a source falls silent, its receivers send the messages of it they
/// used last, so that a sender killed before its last telemetry got out
/// can still be replayed up to where its neighbours heard it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Rescued {
    /// The sender's id (0: the leader).
    pub source: u32,
    pub stamp: u64,
    pub state: LeaderState,
    pub fresh: bool,
}

/// A follower's hearing read step by step (ascending steps), straight from
/// the runs: no per-step copy of the record.
pub struct Cursor<'a> {
    f: &'a FollowerHearing,
    seg: usize,
    /// Per slot: the run index and the steps of it already passed.
    run: Vec<(usize, u64)>,
    now: Vec<Heard>,
    /// The step `now` describes, in segment `seg`.
    at: Option<u64>,
}

impl<'a> Cursor<'a> {
    pub fn new(f: &'a FollowerHearing) -> Self {
        let n = f.sources.len();
        Self { f, seg: 0, run: vec![(0, 0); n], now: vec![Heard::Silent; n], at: None }
    }

    /// What was heard at step k, if it is recorded (ask in ascending k).
    pub fn at(&mut self, k: u64) -> Option<&[Heard]> {
        while self.f.segments.get(self.seg).is_some_and(|s| s.end() <= k) {
            self.seg += 1;
            self.at = None;
        }
        let seg = self.f.segments.get(self.seg)?;
        if k < seg.first_k {
            return None;
        }
        let from = match self.at {
            Some(a) if a <= k => a,
            _ => {
                self.run.iter_mut().for_each(|r| *r = (0, 0));
                seg.first_k
            }
        };
        let skip = k - from;
        for (slot, runs) in seg.heard.slots.iter().enumerate() {
            let (mut r, mut used) = self.run[slot];
            used += skip;
            while runs.get(r).is_some_and(|&(_, n)| used >= u64::from(n)) {
                used -= u64::from(runs[r].1);
                r += 1;
            }
            self.run[slot] = (r, used);
            self.now[slot] = Heard::from_code(runs.get(r)?.0);
        }
        self.at = Some(k);
        Some(&self.now)
    }
}

/// The scenario a run loaded, as text, so that a replay loads the same.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ScenarioSource {
    /// Where it was read from (for messages).
    pub label: String,
    pub text: String,
    /// The `--set` overrides, in order.
    pub overrides: Vec<String>,
}

/// The CSVs' settings (`--every`, `--no-csv`, `--mcap`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Density {
    pub every: u64,
    pub csv: bool,
    pub mcap: bool,
}

/// A networked run's hearing record (`hearing.bin`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HearingRecord {
    pub format: u32,
    pub scenario: ScenarioSource,
    /// The scenario's fingerprint as the nodes agreed on it.
    pub fingerprint: u64,
    pub density: Density,
    /// The leader's recorded steps, as spans [from, to).
    pub leader: Vec<(u64, u64)>,
    pub followers: Vec<FollowerHearing>,
    /// Messages rescued by their receivers, by (sender, stamp).
    pub rescued: Vec<Rescued>,
}

/// The record's format: a reader refuses another. Format 2 added the
/// trailing CRC-32.
pub const HEARING_FORMAT: u32 = 2;

/// The record's file name in the run folder.
pub const HEARING_FILE: &str = "hearing.bin";

/// Why a hearing record cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum HearingError {
    #[error("{0}: cannot read: {1}")]
    Io(String, std::io::Error),
    #[error("{0}: not a hearing record (it does not decode)")]
    Malformed(String),
    #[error("{0}: damaged: its checksum does not match its contents (changed since the monitor wrote it)")]
    Damaged(String),
    #[error("{0}: not a regular file")]
    NotAFile(String),
    #[error("{path}: {bytes} bytes, more than a hearing record can be ({max} bytes)")]
    TooLarge { path: String, bytes: u64, max: usize },
    #[error("{path}: hearing record format {found}, this build reads format {HEARING_FORMAT}")]
    Format { path: String, found: u32 },
}

fn config() -> bincode::config::Configuration {
    bincode::config::standard()
}

impl HearingRecord {
    /// The record in bincode, then the CRC-32 of those bytes (4 bytes, little-endian).
    pub fn encode(&self) -> Vec<u8> {
        let mut bytes = bincode::serde::encode_to_vec(self, config()).unwrap_or_default();
        let crc = crc32fast::hash(&bytes);
        bytes.extend_from_slice(&crc.to_le_bytes());
        bytes
    }

    /// Decodes a record (allocating at most what `decode_bounded` allows),
    /// refusing one whose checksum does not match.
    pub fn decode(bytes: &[u8], label: &str) -> Result<Self, HearingError> {
        let body = bytes.len().checked_sub(4).map(|n| bytes.split_at(n));
        let r: Self = match body.and_then(|(b, _)| crate::bounded::decode_bounded::<Self>(b)) {
            Some(r) => r,
            None => {
                // The format number comes first: name a record of another format as such.
                let limited = config().with_limit::<64>();
                return match bincode::serde::decode_from_slice::<u32, _>(bytes, limited) {
                    // Format 1 had no checksum: a format-1 record decodes whole.
                    Ok((1, _)) if crate::bounded::decode_bounded::<Self>(bytes).is_none() => {
                        Err(HearingError::Malformed(label.into()))
                    }
                    Ok((found, _)) if found != HEARING_FORMAT && found < 1000 => {
                        Err(HearingError::Format { path: label.into(), found })
                    }
                    _ => Err(HearingError::Malformed(label.into())),
                };
            }
        };
        if let Some((b, crc)) = body {
            if crc32fast::hash(b).to_le_bytes() != crc {
                return Err(HearingError::Damaged(label.into()));
            }
        }
        if r.format != HEARING_FORMAT {
            return Err(HearingError::Format { path: label.into(), found: r.format });
        }
        Ok(r)
    }

    /// Reads `hearing.bin` of a run folder.
    pub fn read(dir: &std::path::Path) -> Result<Self, HearingError> {
        let path = dir.join(HEARING_FILE);
        let label = path.display().to_string();
        let bytes = read_regular(&path, crate::bounded::MAX_INPUT)?;
        Self::decode(&bytes, &label)
    }

    /// Whether the leader's step `k` was recorded.
    pub fn leader_has(&self, k: u64) -> bool {
        self.leader.iter().any(|&(a, b)| a <= k && k < b)
    }
}

/// A regular file's bytes (a link to one is followed), at most `max` of
/// them: a FIFO, a device or a directory is refused without reading, and so
/// is a file longer than `max`.
pub fn read_regular(path: &std::path::Path, max: usize) -> Result<Vec<u8>, HearingError> {
    use std::io::Read;
    let label = path.display().to_string();
    let meta = std::fs::metadata(path).map_err(|e| HearingError::Io(label.clone(), e))?;
    if !meta.is_file() {
        return Err(HearingError::NotAFile(label));
    }
    let too_large = |bytes| HearingError::TooLarge { path: label.clone(), bytes, max };
    if meta.len() > max as u64 {
        return Err(too_large(meta.len()));
    }
    let file = std::fs::File::open(path).map_err(|e| HearingError::Io(label.clone(), e))?;
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    file.take(max as u64 + 1).read_to_end(&mut bytes).map_err(|e| HearingError::Io(label.clone(), e))?;
    if bytes.len() > max {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_compress_a_steady_hearing_and_expand_back() {
        let mut r = HeardRuns::with_slots(2, 4);
        let steps: Vec<[Heard; 2]> = (0..1000u64)
            .map(|k| {
                let a = if k % 250 == 0 { Heard::Age(2) } else { Heard::Age(1) };
                let b = if (400..450).contains(&k) { Heard::Removed } else { Heard::Age(1) };
                [a, b]
            })
            .collect();
        for s in &steps {
            r.push(s.iter().copied());
        }
        assert!(r.is_consistent());
        assert_eq!(r.runs(), 8 + 3, "{:?}", r.slots);
        let back = r.expand();
        assert_eq!(back.len(), 1000);
        assert!(back.iter().zip(&steps).all(|(a, b)| a.as_slice() == b.as_slice()));
    }

    #[test]
    fn the_cursor_reads_runs_step_by_step_as_expanded() {
        let mut f = FollowerHearing::new(1, vec![2, 0]);
        let heard = |k: u64| {
            let a = if k % 7 == 0 { Heard::Age(2) } else { Heard::Age(1) };
            let b = if (30..45).contains(&k) { Heard::Silent } else { Heard::Age(1) };
            [a, b]
        };
        for k in (0..60).chain(80..100) {
            f.push(k, &heard(k));
        }
        let mut c = Cursor::new(&f);
        // Every step, then every third step of a fresh cursor: the same answers.
        for k in 0..110 {
            let want = ((0..60).contains(&k) || (80..100).contains(&k)).then(|| heard(k).to_vec());
            assert_eq!(c.at(k).map(<[Heard]>::to_vec), want, "step {k}");
        }
        let mut c = Cursor::new(&f);
        for k in (0..110).step_by(3) {
            let want = ((0..60).contains(&k) || (80..100).contains(&k)).then(|| heard(k).to_vec());
            assert_eq!(c.at(k).map(<[Heard]>::to_vec), want, "step {k}, read every third step");
        }
    }

    #[test]
    fn codes_round_trip_and_name_the_stamp() {
        for h in [Heard::Age(0), Heard::Age(7), Heard::Silent, Heard::Removed] {
            assert_eq!(Heard::from_code(h.code()), h);
        }
        assert_eq!(Heard::used(10, 9), Heard::Age(1));
        assert_eq!(Heard::Age(1).stamp(10), Some(9));
        assert_eq!(Heard::Age(11).stamp(10), None);
        assert_eq!(Heard::Silent.stamp(10), None);
    }

    #[test]
    fn a_follower_record_splits_at_gaps_and_a_record_round_trips() {
        let mut f = FollowerHearing::new(3, vec![2, 4]);
        for k in (0..10).chain(20..25) {
            f.push(k, &[Heard::Age(0), Heard::Silent]);
        }
        assert_eq!(f.segments.len(), 2);
        assert_eq!((f.segments[1].first_k, f.segments[1].end()), (20, 25));
        assert_eq!(f.steps(), 15);
        // The cursor reads the recorded steps, and nothing in the gap.
        let mut c = Cursor::new(&f);
        let read: Vec<u64> = (0..30).filter(|&k| c.at(k).is_some()).collect();
        assert_eq!(read, (0..10).chain(20..25).collect::<Vec<_>>());
        f.resumed(Resume { k: 20, pose: [1.0, 2.0, 0.5] });
        f.resumed(Resume { k: 20, pose: [1.0, 2.0, 0.5] });
        assert_eq!(f.resumes.len(), 1);
        let rec = HearingRecord {
            format: HEARING_FORMAT,
            scenario: ScenarioSource { label: "s.toml".into(), text: "x".into(), overrides: vec![] },
            fingerprint: 7,
            density: Density { every: 1, csv: true, mcap: false },
            leader: vec![(0, 25)],
            followers: vec![f],
            rescued: vec![Rescued { source: 2, stamp: 9, state: LeaderState::default(), fresh: true }],
        };
        let bytes = rec.encode();
        assert_eq!(HearingRecord::decode(&bytes, "h").expect("decodes"), rec);
        assert!(matches!(HearingRecord::decode(&bytes[..bytes.len() - 1], "h"), Err(HearingError::Malformed(_))));
        let mut other = rec.clone();
        other.format = 9;
        assert!(matches!(HearingRecord::decode(&other.encode(), "h"), Err(HearingError::Format { found: 9, .. })));
        assert!(rec.leader_has(24) && !rec.leader_has(25));
        // Any flipped bit is named as damage, not replayed.
        for bit in [40, 8 * bytes.len() / 2, 8 * bytes.len() - 1] {
            let mut flipped = bytes.clone();
            flipped[bit / 8] ^= 1 << (bit % 8);
            let r = HearingRecord::decode(&flipped, "h");
            assert!(matches!(r, Err(HearingError::Damaged(_)) | Err(HearingError::Malformed(_))), "bit {bit}: {r:?}");
        }
        // A first length field of 2^62 is refused, not allocated.
        let mut huge = vec![HEARING_FORMAT as u8, 0xff];
        huge.extend_from_slice(&(1u64 << 62).to_le_bytes());
        huge.extend_from_slice(&[0; 8]);
        assert!(matches!(HearingRecord::decode(&huge, "h"), Err(HearingError::Malformed(_))));
    }
}
