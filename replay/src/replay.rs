//! `formation replay`: a networked run re-computed in one process from its
//! scenario and its hearing record (`hearing.bin`).
//!
//! A follower's step is a pure function of its state and of the messages it
//! used; a message is its sender's output of the step before its stamp (the
//! leader's: its state at the stamp). So every follower is stepped again in
//! step order, each taking the messages its record names, and the rows and
//! metrics go through the monitor's [`Recorder`]: a faithful record
//! gives the run's CSVs and `summary.json` byte for byte.
//!
//! The hearing can be replaced, wholly or for one link or one window of
//! steps, by the model's ([`HearingSource`]): every message used exactly
//! `network.delay_steps` after it was sent, the fault table applied, as
//! `formation sim` assumes. That is what `--explain` compares with.

use std::path::{Path, PathBuf};

use formation_control::slot::{Frame, Slots};
use formation_control::{LinkLoss, Message, Nearby};
use formation_leader::LeaderState;
use formation_plant::Pose;
use formation_record::hearing::{Cursor, End, FollowerHearing, HearingRecord};
use formation_record::{FollowerSample, Heard, RecordOptions, HEARING_FILE};
use formation_scenario::Scenario;
use formation_sim::SimFollower;

use formation_exit::Error;
use formation_recorder::{Recorder, KILLED};

/// A run folder's scenario and hearing record, checked against each other.
pub struct Loaded {
    pub dir: PathBuf,
    pub scenario: Scenario,
    pub record: HearingRecord,
    /// The handovers' gaps as network.json records them: steps [from, to)
    /// with no leader message (docs/model.md §14).
    pub handover_gaps: Vec<(u64, u64)>,
    /// Followers absent at the start that joined, as network.json records
    /// them: (id, the first step each took).
    pub joins: Vec<(u32, u64)>,
}

impl Loaded {
    /// The scenario of the run's model: the run's, with each follower that
    /// left for good (its hearing record ends `Left`) cut off from then on.
    pub fn model_scenario(&self) -> Scenario {
        let (mut leaves, mut died) = (Vec::new(), Vec::new());
        for f in &self.record.followers {
            match &f.end {
                End::Left { k, why } if why == KILLED => died.push((f.id, *k)),
                End::Left { k, .. } => leaves.push((f.id, *k)),
                _ => {}
            }
        }
        let s = self.scenario.with_leaves(&leaves).with_died(&died);
        s.with_handovers(&self.handover_gaps).with_joins(&self.joins)
    }

    /// Lock-step: the step L before which follower `index` was killed
    /// (its record ends `Left` with [`KILLED`]), if it was. A replay
    /// computes its steps lost with its process, up to the last round it
    /// finished (L − 2), with the model's hearing (lock-step hears nothing
    /// else), so that its robot stands where the others' filters saw it;
    /// they have no row (the run has none).
    fn killed_at(&self, index: usize) -> Option<u64> {
        let lockstep = self.scenario.timing == formation_scenario::Timing::Lockstep;
        match &self.record.followers[index].end {
            End::Left { k, why } if why == KILLED && lockstep => Some(*k),
            _ => None,
        }
    }
}

/// network.json's joins: (follower, first step), for followers of the scenario.
fn joins(network: &serde_json::Value, scenario: &Scenario) -> Vec<(u32, u64)> {
    let rows = network["joined"].as_array().map_or(&[][..], Vec::as_slice);
    rows.iter()
        .filter_map(|j| Some((u32::try_from(j["follower"].as_u64()?).ok()?, j["step"].as_u64()?)))
        .filter(|&(id, k)| scenario.index_of(id).is_some() && k <= scenario.steps())
        .collect()
}

/// network.json's handovers as gaps: [the step after the newest heard, the
/// standby's first step).
fn handover_gaps(network: &serde_json::Value, steps: u64) -> Vec<(u64, u64)> {
    let rows = network["handovers"].as_array().map_or(&[][..], Vec::as_slice);
    rows.iter()
        .filter_map(|h| Some((h["heard_step"].as_u64()? + 1, h["step"].as_u64()?)))
        .filter(|&(from, to)| from < to && to <= steps + 1)
        .collect()
}

/// A leader steered live has no model: the run's own leader record is it
/// (docs/model.md §18).
fn leader_from_the_record(scenario: Scenario, dir: &Path) -> Result<Scenario, Error> {
    match scenario.live_leader().map(str::to_string) {
        Some(source) => scenario.with_recorded_leader(dir).map_err(|e| {
            Error::Input(format!(
                "{}: its leader was steered live (leader.source = \"{source}\"), and a replay plays it from the run's \
                 leader record: {e}",
                dir.display()
            ))
        }),
        None => Ok(scenario),
    }
}

/// Reads a run folder's hearing record and the scenario it carries.
pub fn load(dir: &Path) -> Result<Loaded, Error> {
    if !dir.is_dir() {
        return Err(Error::Input(format!("{}: no such run folder", dir.display())));
    }
    if std::fs::symlink_metadata(dir.join(HEARING_FILE)).is_err() {
        let off = std::fs::read_to_string(dir.join("network.json")).ok();
        let why = if off.as_deref().is_some_and(|t| t.contains("\"hearing_record\": false")) {
            "the run was recorded with network.hearing_record = false"
        } else if off.is_some() {
            "a networked run recorded before hearing records existed, or with network.hearing_record = false"
        } else {
            "not a networked run (formation sim needs no replay: it is deterministic)"
        };
        return Err(Error::Input(format!("{}: no {HEARING_FILE}: {why}", dir.display())));
    }
    let record = HearingRecord::read(dir).map_err(|e| Error::Input(e.to_string()))?;
    let s = &record.scenario;
    let scenario = Scenario::from_toml(&s.text, &s.label, "run", &s.overrides)
        .map_err(|e| Error::Input(format!("{}: the scenario it carries: {e}", dir.display())))?;
    if scenario.control.guard.safety.is_some() && scenario.timing == formation_scenario::Timing::Realtime {
        // docs/model.md §16: in real time each filter took the newest pose
        // it had heard, which hearing.bin does not hold (lock-step's are
        // every robot's pose of the step before, which it does).
        return Err(Error::Input(format!(
            "{}: a real-time run with the safety filter on: which of the other robots' poses each filter used is \
             not in its record, so it cannot be re-computed (lock-step runs with the filter replay)",
            dir.display()
        )));
    }
    if formation_protocol::barrier::fingerprint(&scenario) != record.fingerprint {
        return Err(Error::Input(format!(
            "{}: the scenario it carries does not give the run's fingerprint (a record of another build?)",
            dir.display()
        )));
    }
    // The record must be this folder's: network.json names the run's scenario.
    let network = match std::fs::read_to_string(dir.join("network.json")) {
        Ok(t) => Some(serde_json::from_str::<serde_json::Value>(&t).map_err(|e| {
            Error::Input(format!("{}: a damaged run folder: network.json is not JSON ({e})", dir.display()))
        })?),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => return Err(Error::Input(format!("{}: network.json: {e}", dir.display()))),
    };
    let handover_gaps = network.as_ref().map_or_else(Vec::new, |n| handover_gaps(n, scenario.steps()));
    let joins = network.as_ref().map_or_else(Vec::new, |n| joins(n, &scenario));
    if let Some(net) = network {
        let theirs = format!("{:016x}", record.fingerprint);
        let named = net["fingerprint"].as_str().map(|f| f == theirs).unwrap_or(true)
            && net["scenario"].as_str().map(|n| n == scenario.name).unwrap_or(true)
            && net["steps"].as_u64().map(|n| n == scenario.steps()).unwrap_or(true);
        if !named {
            return Err(Error::Input(format!(
                "{}: {HEARING_FILE} is another run's: it carries scenario '{}' ({} steps, fingerprint {theirs}), \
                 network.json names '{}' ({} steps, fingerprint {})",
                dir.display(),
                scenario.name,
                scenario.steps(),
                net["scenario"].as_str().unwrap_or("?"),
                net["steps"].as_u64().map(|n| n.to_string()).unwrap_or("?".into()),
                net["fingerprint"].as_str().unwrap_or("not recorded"),
            )));
        }
    }
    let scenario = leader_from_the_record(scenario, dir)?;
    if record.followers.len() != scenario.followers.len()
        || record.followers.iter().enumerate().any(|(i, f)| f.id != scenario.followers[i].id)
        || record.followers.iter().enumerate().any(|(i, f)| f.sources != scenario.sources_of(i))
    {
        return Err(Error::Input(format!("{}: the record's followers are not the scenario's", dir.display())));
    }
    // Every segment inside the run, one run list per source, each covering its steps.
    let steps = scenario.steps();
    for f in &record.followers {
        let mut end = 0;
        for seg in &f.segments {
            let ok = seg.heard.slots.len() == f.sources.len()
                && seg.heard.is_consistent()
                && seg.first_k >= end
                && seg.end() <= steps + 1;
            if !ok {
                return Err(Error::Input(format!(
                    "{}: follower {}'s record from step {} is malformed (not one run list per source covering its \
                     steps, or beyond the run)",
                    dir.display(),
                    f.id,
                    seg.first_k
                )));
            }
            end = seg.end();
        }
    }
    Ok(Loaded { dir: dir.to_path_buf(), scenario, record, handover_gaps, joins })
}

/// Which hearing a replay uses: the record's, except where the model's
/// replaces it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HearingSource {
    /// The run as recorded.
    Recorded,
    /// The model everywhere.
    Model,
    /// The model on one link: follower `index`'s source `slot`.
    Link { index: usize, slot: usize },
    /// The model on every link during steps [from_k, to_k).
    Window { from_k: u64, to_k: u64 },
}

impl HearingSource {
    fn model_at(self, index: usize, slot: usize, k: u64) -> bool {
        match self {
            HearingSource::Recorded => false,
            HearingSource::Model => true,
            HearingSource::Link { index: i, slot: s } => i == index && s == slot,
            HearingSource::Window { from_k, to_k } => from_k <= k && k < to_k,
        }
    }
}

/// The model's hearing of one follower (what the simulator's reception
/// does): the message of step k − d, delivered unless the fault table
/// removes it; otherwise the newest delivered one within the silence
/// timeout.
pub struct ModelEar {
    links: Vec<LinkLoss>,
    /// Per slot: no fault ever touches it (always the message of k − d).
    clear: bool,
    newest: Vec<Option<u64>>,
    delay: u64,
    timeout: u64,
}

impl ModelEar {
    pub fn new(scenario: &Scenario, index: usize) -> Self {
        let id = scenario.graph.id(index);
        let links: Vec<LinkLoss> = scenario.sources_of(index).iter().map(|&src| scenario.link_loss(src, id)).collect();
        let clear = links.iter().all(LinkLoss::is_empty);
        Self {
            newest: vec![None; links.len()],
            links,
            clear,
            delay: scenario.network.delay_steps,
            timeout: scenario.silence_steps(),
        }
    }

    /// What each slot hears at step k (call in step order, every step).
    pub fn hear(&mut self, k: u64, out: &mut [Heard]) {
        let sent = k.saturating_sub(self.delay);
        for (slot, h) in out.iter_mut().enumerate() {
            if self.clear {
                *h = Heard::used(k, sent);
                continue;
            }
            let lost = self.links[slot].lost(sent);
            if !lost && self.newest[slot].is_none_or(|s| s <= sent) {
                self.newest[slot] = Some(sent);
            }
            *h = match self.newest[slot] {
                Some(s) if s <= sent && sent - s <= self.timeout => Heard::used(k, s),
                _ if lost => Heard::Removed,
                _ => Heard::Silent,
            };
        }
    }
}

/// Where a replay receives what it computes.
pub trait Sink {
    /// The leader's state at step k; `recorded`: the run recorded it.
    fn leader(&mut self, k: u64, state: &LeaderState, recorded: bool) -> Result<(), Error>;
    /// Follower `index`'s sample of step k (a step the run recorded).
    fn follower(&mut self, index: usize, k: u64, sample: &FollowerSample, heard: &[Heard]) -> Result<(), Error>;
    /// Every follower has done step k.
    fn step_done(&mut self, _k: u64) -> Result<(), Error> {
        Ok(())
    }
    /// Follower `index`, killed (lock-step), stands at `pose` from now on.
    fn stands(&mut self, _index: usize, _pose: Pose) {}
    /// Stop the replay here (a playback that seeks backwards starts again).
    fn stop(&self) -> bool {
        false
    }
}

/// What a replay could not re-compute: the rows it lacks name it.
#[derive(Clone, Debug, PartialEq)]
pub struct Problem {
    pub follower: u32,
    pub k: u64,
    pub what: String,
}

/// Per follower, what the replay is doing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Track {
    Running,
    /// Stopped: its state past here is unknown (a gap, or a message it cannot rebuild).
    Stopped,
}

/// Re-computes the run with `hearing`, in step order, into `sink`.
/// Returns what could not be re-computed.
pub fn replay(loaded: &Loaded, hearing: HearingSource, sink: &mut impl Sink) -> Result<Vec<Problem>, Error> {
    let s = &loaded.scenario;
    let rec = &loaded.record;
    let n = s.followers.len();
    let steps = s.steps();
    let dt = s.dt_s;
    // A message is used at most the silence timeout after its step k − d.
    let ring = (s.silence_steps() + s.network.delay_steps + 2) as usize;
    let mut followers: Vec<SimFollower> = (0..n).map(|i| SimFollower::new(s, i)).collect();
    let mut sent: Vec<Vec<Option<(u64, Message)>>> = vec![vec![None; ring]; n];
    for (i, f) in followers.iter().enumerate() {
        sent[i][0] = Some((0, f.brain.tagged_message()));
    }
    let mut leader_sent: Vec<Option<(u64, LeaderState)>> = vec![None; ring];
    let mut recorded: Vec<Cursor> = rec.followers.iter().map(Cursor::new).collect();
    let model = loaded.model_scenario();
    let mut ears: Vec<ModelEar> = (0..n).map(|i| ModelEar::new(&model, i)).collect();
    let mut track = vec![Track::Running; n];
    let mut problems = Vec::new();
    let sources: Vec<Vec<Option<usize>>> =
        (0..n).map(|i| s.sources_of(i).iter().map(|&id| s.index_of(id)).collect()).collect();
    let rescued: std::collections::HashMap<(u32, u64), Message> =
        rec.rescued.iter().map(|r| ((r.source, r.stamp), Message { state: r.state, fresh: r.fresh })).collect();
    let ids: Vec<u32> = rec.followers.iter().map(|f| f.id).collect();
    let mut leader = s.leader();
    let (mut heard, mut model, mut inputs): (Vec<Heard>, Vec<Heard>, Vec<Message>) = Default::default();
    let mut views = Views::new(loaded);
    for k in 0..=steps {
        let t = k as f64 * dt;
        let state = leader.state(t);
        leader_sent[(k as usize) % ring] = Some((k, state));
        sink.leader(k, &state, rec.leader_has(k))?;
        let last = k == steps;
        for i in 0..n {
            let f = &mut followers[i];
            let id = rec.followers[i].id;
            if let Some(r) = rec.followers[i].resumes.iter().find(|r| r.k == k) {
                // A new process: everything as new (its noise stream too), then resumed.
                *f = SimFollower::new(s, i);
                f.resume(k, Pose::new(r.pose[0], r.pose[1], r.pose[2]));
                track[i] = Track::Running;
            }
            let slots = sources[i].len();
            model.clear();
            model.resize(slots, Heard::Silent);
            ears[i].hear(k, &mut model);
            // A follower killed (lock-step): its steps lost with its process, up to
            // L − 2, hear the model's (lock-step's own); no row (Loaded::killed_at).
            let gap = track[i] == Track::Running
                && loaded.killed_at(i).is_some_and(|l| k + 2 <= l)
                && recorded[i].at(k).is_none();
            heard.clear();
            if gap {
                heard.extend_from_slice(&model);
            } else {
                let Some(rec_heard) = recorded[i].at(k) else {
                    if track[i] == Track::Running {
                        problems.extend(lost_for_good(&rec.followers[i], k));
                    }
                    track[i] = Track::Stopped;
                    continue;
                };
                if track[i] == Track::Stopped {
                    continue;
                }
                heard.extend(rec_heard.iter().enumerate().map(|(slot, &h)| {
                    if hearing.model_at(i, slot, k) {
                        model[slot]
                    } else {
                        h
                    }
                }));
            }
            // The messages the step uses, neighbours in ascending id, then the leader.
            let from = Sent { sent: &sent, leader: &leader_sent, rescued: &rescued, ids: &ids, ring };
            let (leader_in, missing) = from.inputs(k, &heard, &sources[i], &mut inputs);
            if let Some((src, stamp)) = missing {
                problems.push(cannot_rebuild(id, k, src, stamp));
                track[i] = Track::Stopped;
                continue;
            }
            let (sample, next) =
                f.step_disturbed(f.robot.disturbance_at(t), dt, leader_in.as_ref(), &inputs, views.nearby(i), last);
            views.stepped(i, sample.pose);
            sent[i][((k + 1) as usize) % ring] = Some((k + 1, next));
            match gap {
                false => sink.follower(i, k, &sample, &heard)?,
                true if loaded.killed_at(i) == Some(k + 2) => sink.stands(i, sample.pose),
                true => {}
            }
        }
        views.step_done(k);
        sink.step_done(k)?;
        if sink.stop() {
            break;
        }
        leader.advance(&state, dt);
    }
    Ok(problems)
}

/// The safety filter's view in a replay: every robot's pose of step k − 1
/// (step 0: its initial pose), as lock-step's; a follower killed
/// (lock-step) as still from its step L on, as the run's filters saw it
/// (docs/model.md §16). Empty without the filter.
struct Views {
    on: bool,
    before: Vec<Pose>,
    now: Vec<Pose>,
    seen: Vec<formation_control::Seen>,
    killed_at: Vec<Option<u64>>,
}

impl Views {
    fn new(loaded: &Loaded) -> Self {
        let s = &loaded.scenario;
        let n = s.followers.len();
        let on = s.control.guard.safety.is_some();
        let before: Vec<Pose> = match on {
            true => (0..n).map(|i| formation_sim::SimRobot::new(s, i).seen_pose()).collect(),
            false => Vec::new(),
        };
        let killed_at = (0..n).map(|i| loaded.killed_at(i)).collect();
        Self { on, now: before.clone(), before, seen: vec![formation_control::Seen::Live; n], killed_at }
    }

    /// How follower `own`'s filter sees the others at this step.
    fn nearby(&self, own: usize) -> Nearby<'_> {
        match (self.on, self.killed_at.iter().any(Option::is_some)) {
            (false, _) => Nearby::NONE,
            (true, true) => Nearby { poses: &self.before, own, seen: &self.seen, lost: false },
            (true, false) => Nearby::fresh(&self.before, own),
        }
    }

    /// Follower `i` stepped to `pose`.
    fn stepped(&mut self, i: usize, pose: Pose) {
        if self.on {
            self.now[i] = pose;
        }
    }

    /// Every follower has done step k: the view of step k + 1.
    fn step_done(&mut self, k: u64) {
        self.before.copy_from_slice(&self.now);
        for (j, l) in self.killed_at.iter().enumerate() {
            if l.is_some_and(|l| k + 1 >= l) {
                self.seen[j] = formation_control::Seen::Still;
            }
        }
    }
}

/// A follower's steps from `k` missing from the record: a problem unless a
/// restart ends the gap (the gap is the restart's: nothing is lost to the
/// replay) or the record ends with it.
fn lost_for_good(f: &FollowerHearing, k: u64) -> Option<Problem> {
    let next = next_start(f, k)?;
    if f.resumes.iter().any(|r| r.k == next) {
        return None;
    }
    let what = format!(
        "steps {k}–{} are not in the record (telemetry lost for good) and no restart follows: not replayed from here",
        next - 1
    );
    Some(Problem { follower: f.id, k, what })
}

/// Follower `follower`'s step `k` used `src`'s (0: the leader's) message of
/// step `stamp`, which the record cannot rebuild: the problem that says so.
fn cannot_rebuild(follower: u32, k: u64, src: u32, stamp: u64) -> Problem {
    let who = if src == 0 { "the leader".to_string() } else { format!("follower {src}") };
    let what = format!(
        "used {who}'s message of step {stamp}, which the record cannot rebuild (its sender's steps \
         before it are not all recorded); not replayed from here"
    );
    Problem { follower, k, what }
}

/// The messages a replayed step can use: each follower's and the leader's
/// of the last `ring` steps, and those a killed sender's receivers rescued.
struct Sent<'a> {
    sent: &'a [Vec<Option<(u64, Message)>>],
    leader: &'a [Option<(u64, LeaderState)>],
    rescued: &'a std::collections::HashMap<(u32, u64), Message>,
    /// Each follower's id, by index.
    ids: &'a [u32],
    ring: usize,
}

impl Sent<'_> {
    /// Step `k`'s inputs as `heard` names them (into `inputs`, neighbours in
    /// ascending id), and the leader's; the (sender, step) of one that the
    /// record cannot rebuild, if any.
    fn inputs(
        &self,
        k: u64,
        heard: &[Heard],
        sources: &[Option<usize>],
        inputs: &mut Vec<Message>,
    ) -> (Option<LeaderState>, Option<(u32, u64)>) {
        inputs.clear();
        let (mut leader_in, mut missing) = (None, None);
        for (slot, h) in heard.iter().enumerate() {
            let Some(stamp) = h.stamp(k) else { continue };
            match sources[slot] {
                Some(j) => match self.sent[j][(stamp as usize) % self.ring] {
                    Some((st, m)) if st == stamp => inputs.push(m),
                    // A sender killed before its last telemetry got out:
                    // its receivers rescued what they used.
                    _ => match self.rescued.get(&(self.ids[j], stamp)) {
                        Some(m) => inputs.push(*m),
                        None => missing = Some((self.ids[j], stamp)),
                    },
                },
                None => match self.leader[(stamp as usize) % self.ring] {
                    Some((st, l)) if st == stamp => leader_in = Some(l),
                    _ => missing = Some((0, stamp)),
                },
            }
        }
        (leader_in, missing)
    }
}

/// The first recorded step of `f` after k, if any.
fn next_start(f: &FollowerHearing, k: u64) -> Option<u64> {
    f.segments.iter().map(|s| s.first_k).find(|&first| first > k)
}

/// The recorder takes a replay as the monitor's takes telemetry: rows and
/// metrics of the steps the run recorded.
impl Sink for Recorder {
    fn leader(&mut self, k: u64, state: &LeaderState, recorded: bool) -> Result<(), Error> {
        self.replayed_leader(k, recorded.then_some(state)).map_err(Error::from)
    }
    fn follower(&mut self, index: usize, k: u64, sample: &FollowerSample, heard: &[Heard]) -> Result<(), Error> {
        self.replayed_follower(index, k, *sample, heard);
        Ok(())
    }
    fn step_done(&mut self, _k: u64) -> Result<(), Error> {
        self.settle().map_err(Error::from)
    }
}

/// A replay into a run folder, with a progress call every 1000 steps.
struct Folder<'p> {
    recorder: Recorder,
    progress: &'p mut dyn FnMut(u64),
}

impl Sink for Folder<'_> {
    fn leader(&mut self, k: u64, state: &LeaderState, recorded: bool) -> Result<(), Error> {
        self.recorder.leader(k, state, recorded)
    }
    fn follower(&mut self, index: usize, k: u64, sample: &FollowerSample, heard: &[Heard]) -> Result<(), Error> {
        self.recorder.follower(index, k, sample, heard)
    }
    fn step_done(&mut self, k: u64) -> Result<(), Error> {
        if k % 1000 == 0 {
            (self.progress)(k);
        }
        self.recorder.step_done(k)
    }
    fn stands(&mut self, index: usize, pose: Pose) {
        self.recorder.replayed_stands(index, pose);
    }
}

/// Re-computes the run into the folder `out` (CSVs, `summary.json`, and a
/// copy of the hearing record); returns what could not be re-computed.
pub fn replay_to_folder(loaded: &Loaded, out: &Path) -> Result<Vec<Problem>, Error> {
    replay_to_folder_with(loaded, HearingSource::Recorded, out, &mut |_| {})
}

/// [`replay_to_folder`] with another hearing (the model's: the folder
/// `formation sim` writes for the scenario).
/// `progress(k)` every 1000 steps.
pub fn replay_to_folder_with(
    loaded: &Loaded,
    hearing: HearingSource,
    out: &Path,
    progress: &mut dyn FnMut(u64),
) -> Result<Vec<Problem>, Error> {
    let d = loaded.record.density;
    let opts = RecordOptions { dir: out.to_path_buf(), every: d.every, csv: d.csv, mcap: false, rosbag2: false };
    let mut recorder = Recorder::new(&loaded.scenario, &opts)?;
    recorder.set_source(loaded.record.scenario.clone());
    for (i, f) in loaded.record.followers.iter().enumerate() {
        recorder.replayed_hearing(i, &f.resumes, f.end.clone());
    }
    recorder.replayed_joins(&loaded.joins);
    let mut sink = Folder { recorder, progress };
    let problems = replay(loaded, hearing, &mut sink)?;
    sink.recorder.finish(formation_recorder::watch::Ending::Complete)?;
    Ok(problems)
}

/// The first place two run folders differ.
#[derive(Clone, Debug, PartialEq)]
pub struct Difference {
    pub file: String,
    /// The follower (`None`: the leader or summary.json).
    pub follower: Option<u32>,
    /// 1-based line of the file.
    pub line: usize,
    pub step: Option<u64>,
    pub column: Option<String>,
    pub run: String,
    pub replay: String,
    /// How the run's file is damaged, where the difference is damage
    /// rather than a different value: missing, cut short, not JSON.
    pub damage: Option<String>,
}

impl std::fmt::Display for Difference {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let who = match self.follower {
            Some(id) => format!("follower {id}, "),
            None => String::new(),
        };
        let at = match (self.step, &self.column) {
            (Some(k), Some(c)) => format!("step {k}, column {c}"),
            (Some(k), None) => format!("step {k}"),
            _ => format!("line {}", self.line),
        };
        write!(f, "{}: {who}{at}: the run has {:?}, the replay {:?}", self.file, self.run, self.replay)
    }
}

/// Compares the replay's CSVs and `summary.json` with the run's; the first
/// difference of each file that differs.
pub fn compare(run: &Path, replay: &Path, scenario: &Scenario) -> Vec<Difference> {
    let mut files: Vec<(String, Option<u32>)> =
        scenario.followers.iter().map(|f| (format!("follower_{}.csv", f.id), Some(f.id))).collect();
    files.push(("leader.csv".into(), None));
    files.push(("summary.json".into(), None));
    let mut out = Vec::new();
    for (name, follower) in files {
        let read = std::fs::read_to_string(run.join(&name));
        let b = std::fs::read_to_string(replay.join(&name)).ok();
        if read.as_ref().ok() == b.as_ref() {
            continue;
        }
        // Why the run's file could not be read, if it could not.
        let unread = read.as_ref().err().map(|e| match e.kind() {
            std::io::ErrorKind::NotFound => format!("{name} is missing"),
            std::io::ErrorKind::InvalidData => format!("{name} is not UTF-8 text"),
            _ => format!("{name} cannot be read ({e})"),
        });
        let (a, b) = (read.unwrap_or_default(), b.unwrap_or_default());
        let (la, lb): (Vec<&str>, Vec<&str>) = (a.lines().collect(), b.lines().collect());
        let line = (0..la.len().max(lb.len())).find(|&i| la.get(i) != lb.get(i)).unwrap_or(0);
        let (x, y) = (la.get(line).copied().unwrap_or("(no line)"), lb.get(line).copied().unwrap_or("(no line)"));
        let mut d = Difference {
            file: name.clone(),
            follower,
            line: line + 1,
            step: None,
            column: None,
            run: x.to_string(),
            replay: y.to_string(),
            damage: damage(&name, unread, &a, &la, &lb, line),
        };
        if name.ends_with(".csv") && line > 0 {
            let header: Vec<&str> = la.first().copied().unwrap_or_default().split(',').collect();
            let (fa, fb): (Vec<&str>, Vec<&str>) = (x.split(',').collect(), y.split(',').collect());
            let t = fa.first().or(fb.first()).and_then(|t| t.parse::<f64>().ok());
            d.step = t.map(|t| (t / scenario.dt_s).round() as u64);
            if let Some(c) = (0..fa.len().max(fb.len())).find(|&c| fa.get(c) != fb.get(c)) {
                d.column = header.get(c).map(|h| h.to_string());
                d.run = fa.get(c).unwrap_or(&"(none)").to_string();
                d.replay = fb.get(c).unwrap_or(&"(none)").to_string();
            }
        }
        out.push(d);
    }
    out
}

/// How the run's file `name` is damaged, if the first difference at
/// `line` (0-based) is damage: the file missing or unreadable (`unread`),
/// ending early, a line cut short of its header's columns, or summary.json
/// not JSON. A value that differs in a whole file is not damage.
fn damage(
    name: &str,
    unread: Option<String>,
    text: &str,
    run: &[&str],
    replay: &[&str],
    line: usize,
) -> Option<String> {
    if unread.is_some() {
        return unread;
    }
    if name.ends_with(".json") {
        return serde_json::from_str::<serde_json::Value>(text).err().map(|e| format!("{name} is not JSON ({e})"));
    }
    if line >= run.len() {
        return Some(format!("{name} ends at line {} of the replay's {}", run.len(), replay.len()));
    }
    if line + 1 == run.len() && !text.ends_with('\n') {
        return Some(format!("{name} ends mid-line, in line {} of the replay's {}", run.len(), replay.len()));
    }
    let columns = |l: &str| l.split(',').count();
    let header = run.first().map_or(0, |h| columns(h));
    (line > 0 && columns(run[line]) < header)
        .then(|| format!("{name}'s line {} has {} of its {header} columns", line + 1, columns(run[line])))
}

/// A replay's metrics only (no folder): per follower, the metrics of the
/// steps the run recorded, against the leader's state.
pub struct Metrics {
    frame: Frame,
    slots: Vec<Slots>,
    dt: f64,
    leader: Option<LeaderState>,
    pub acc: Vec<formation_record::MetricsAccumulator>,
}

impl Metrics {
    pub fn new(s: &Scenario) -> Self {
        Self {
            frame: s.control.frame,
            slots: (0..s.followers.len()).map(|i| s.slots(i)).collect(),
            dt: s.dt_s,
            leader: None,
            acc: s.followers.iter().map(|_| formation_record::MetricsAccumulator::for_scenario(s)).collect(),
        }
    }
}

impl Sink for Metrics {
    fn leader(&mut self, _k: u64, state: &LeaderState, recorded: bool) -> Result<(), Error> {
        // As the monitor: a sample whose leader state was not recorded has no row.
        self.leader = recorded.then_some(*state);
        Ok(())
    }
    fn follower(&mut self, index: usize, k: u64, sample: &FollowerSample, _heard: &[Heard]) -> Result<(), Error> {
        if let Some(l) = &self.leader {
            self.acc[index].push_sample(k, sample, l, self.frame, self.slots[index].at(k), self.dt);
        }
        Ok(())
    }
}
