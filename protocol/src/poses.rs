//! What one follower knows of the other robots' poses, for its safety
//! filter (docs/model.md §16): only where the scenario turns the filter on.
//!
//! Every follower publishes its robot's pose of step k (the pose its step k
//! ran on) on `pose/<id>` and hears every other follower's. Step k's filter
//! takes, for every other robot:
//!
//! - lock-step: its pose of step k − 1, waited for as the estimates are
//!   (step 0: the scenario's initial pose), which is what the simulator
//!   uses, so a lock-step run equals `formation sim` bit for bit;
//! - real time: the newest pose heard of step k − 1 or before, as the
//!   model has it (one of step k, when the other robot stepped first, is
//!   kept for the next step; with none that old, the oldest kept), or the
//!   initial pose before any; marked stale once the newest heard is older
//!   than the scenario's silence time-out; a stale robot within
//!   `safety.radius` stops this one.
//!
//! The fault table does not act on poses (the model's filter sees every
//! robot); a network that cuts them makes them stale.

use std::time::Duration;

use formation_plant::Pose;
use formation_topology::wire::{self, Header, PoseMsg, Reject, FORMAT_VERSION};
use formation_topology::Scenario;

use crate::Now;

/// Poses kept per robot (lock-step: its step k − 1 and what runs ahead).
const RING: usize = 4;

/// The other robots' poses as one follower hears them.
#[derive(Clone, Debug)]
pub struct Poses {
    own: usize,
    id: u32,
    ids: Vec<u32>,
    lockstep: bool,
    /// Per robot, the last [`RING`] poses by step (slot k mod RING).
    ring: Vec<[Option<(u64, Pose)>; RING]>,
    /// Real time: per robot, the newest step heard and when.
    newest: Vec<Option<(u64, Now)>>,
    initial: Vec<Pose>,
    /// The view of the step being computed, and which of it is stale.
    view: Vec<Pose>,
    stale: Vec<bool>,
    /// Real time: older than this is stale (the scenario's silence time-out
    /// at the run's pace); the run's epoch, when the initial poses were "heard".
    silence: Duration,
    epoch: Now,
    /// How far ahead of this follower's step a genuine pose can be.
    ahead: u64,
    /// The last two pose messages this follower published (repeats).
    sent: [Option<Vec<u8>>; 2],
}

impl Poses {
    /// The view of follower `index` of `scenario`; `initial` is every
    /// robot's pose at step 0 as the simulator's filter sees it.
    pub fn new(scenario: &Scenario, index: usize, initial: Vec<Pose>) -> Self {
        let n = initial.len();
        Self {
            own: index,
            id: scenario.graph.id(index),
            ids: scenario.graph.ids().to_vec(),
            lockstep: scenario.timing == formation_topology::Timing::Lockstep,
            ring: vec![[None; RING]; n],
            newest: vec![None; n],
            view: initial.clone(),
            stale: vec![false; n],
            initial,
            silence: Duration::from_secs_f64(scenario.silence_steps() as f64 * scenario.dt_s),
            epoch: Now::ZERO,
            ahead: RING as u64 - 1,
            sent: [None, None],
        }
    }

    /// Real time: the run's epoch and pace (the silence time-out is scaled
    /// as the period is); a pose may run 0.1 s ahead (clocks differ), as
    /// an estimate may.
    pub fn start(&mut self, epoch: Now, time_scale: f64, dt_s: f64) {
        self.epoch = epoch;
        self.silence = self.silence.div_f64(time_scale);
        self.ahead = ((0.1 * time_scale / dt_s).ceil() as u64).max(crate::inbox::REALTIME_AHEAD);
    }

    /// A message on `pose/<key_id>`, received at `now`: kept, or why not.
    pub fn handle(&mut self, key_id: Option<u32>, bytes: &[u8], now: Now, step: u64) -> Result<(), Reject> {
        let msg = wire::decode_pose(bytes)?;
        let sender = msg.header.sender;
        if key_id != Some(sender) {
            return Err(Reject::WrongSender);
        }
        let j = match self.ids.iter().position(|&id| id == sender) {
            Some(j) if j != self.own => j,
            _ => return Err(Reject::NotNeighbour),
        };
        let k = msg.header.step;
        if k > step + self.ahead {
            return Err(Reject::Future);
        }
        if self.newest[j].is_some_and(|(newest, _)| k + RING as u64 <= newest) {
            return Err(Reject::Stale);
        }
        let [x, y, theta] = msg.pose;
        self.ring[j][(k as usize) % RING] = Some((k, Pose::new(x, y, theta)));
        if self.newest[j].is_none_or(|(newest, _)| k >= newest) {
            self.newest[j] = Some((k, now));
        }
        Ok(())
    }

    /// This follower's scenario index.
    pub fn own(&self) -> usize {
        self.own
    }

    /// Lock-step: every other robot's pose of step k − 1 is in.
    pub fn has_all(&self, k: u64) -> bool {
        k == 0 || (0..self.ring.len()).all(|j| j == self.own || self.at(j, k - 1).is_some())
    }

    /// The robots still missing for step k (lock-step), by id.
    pub fn missing(&self, k: u64) -> impl Iterator<Item = u32> + '_ {
        (0..self.ring.len())
            .filter(move |&j| j != self.own && k > 0 && self.at(j, k - 1).is_none())
            .map(|j| self.ids[j])
    }

    fn at(&self, j: usize, k: u64) -> Option<Pose> {
        self.ring[j][(k as usize) % RING].filter(|&(s, _)| s == k).map(|(_, p)| p)
    }

    /// Real time: robot j's newest pose of step `before` or earlier, else its oldest kept.
    fn pose_for(&self, j: usize, before: u64) -> Option<Pose> {
        let kept = self.ring[j].iter().flatten();
        let newest_before = kept.clone().filter(|(s, _)| *s <= before).max_by_key(|(s, _)| *s);
        newest_before.or_else(|| kept.min_by_key(|(s, _)| *s)).map(|(_, p)| *p)
    }

    /// The view of step k at `now`: (poses, stale) by scenario index, this
    /// follower's own entry unused. Lock-step: call after [`Poses::has_all`].
    pub fn view(&mut self, k: u64, now: Now) -> (&[Pose], &[bool]) {
        for j in 0..self.view.len() {
            if j == self.own {
                continue;
            }
            if self.lockstep {
                self.view[j] = if k == 0 { self.initial[j] } else { self.at(j, k - 1).unwrap_or(self.initial[j]) };
            } else {
                let heard_at = self.newest[j].map_or(self.epoch, |(_, at)| at);
                self.view[j] = self.pose_for(j, k.saturating_sub(1)).unwrap_or(self.initial[j]);
                self.stale[j] = now.saturating_sub(heard_at) > self.silence;
            }
        }
        (&self.view, &self.stale)
    }

    /// This follower's own pose of step k, for the wire (kept for repeats).
    pub fn publish(&mut self, k: u64, pose: Pose, now: Now, dt_s: f64) -> Vec<u8> {
        let msg = PoseMsg {
            header: Header {
                version: FORMAT_VERSION,
                sender: self.id,
                step: k,
                time_s: k as f64 * dt_s,
                sent_ns: now.as_nanos() as i64,
            },
            pose: [pose.x, pose.y, pose.theta],
        };
        let bytes = wire::encode_pose(&msg);
        self.sent = [self.sent[1].take(), Some(bytes.clone())];
        bytes
    }

    /// Lock-step repeats: the last two poses published.
    pub fn repeats(&self) -> impl Iterator<Item = &Vec<u8>> {
        self.sent.iter().flatten()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scenario(timing: &str) -> Scenario {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/turtlebot.toml");
        Scenario::load(&path, &[format!("timing={timing}")]).expect("the turtlebot scenario")
    }

    fn initial(s: &Scenario) -> Vec<Pose> {
        s.followers.iter().map(|f| f.pose).collect()
    }

    fn message(sender: u32, k: u64, x: f64) -> Vec<u8> {
        let header = Header { version: FORMAT_VERSION, sender, step: k, time_s: 0.0, sent_ns: 0 };
        wire::encode_pose(&PoseMsg { header, pose: [x, 0.0, 0.0] })
    }

    #[test]
    fn lock_step_waits_for_every_other_robots_pose_of_the_step_before() {
        let s = scenario("lockstep");
        let ids = s.graph.ids().to_vec();
        let mut p = Poses::new(&s, 0, initial(&s));
        assert!(p.has_all(0), "step 0 uses the initial poses");
        assert!(!p.has_all(1));
        for &id in &ids[1..] {
            assert_eq!(p.handle(Some(id), &message(id, 0, id as f64), Now::ZERO, 0), Ok(()));
        }
        assert!(p.has_all(1), "missing: {:?}", p.missing(1).collect::<Vec<_>>());
        assert!(!p.has_all(2));
        let (view, stale) = p.view(1, Now::ZERO);
        assert_eq!(view[1].x, ids[1] as f64);
        assert!(!stale.contains(&true));
        assert_eq!(p.view(0, Now::ZERO).0[1], s.followers[1].pose);
    }

    #[test]
    fn forged_foreign_and_far_future_poses_are_refused() {
        let s = scenario("lockstep");
        let ids = s.graph.ids().to_vec();
        let mut p = Poses::new(&s, 0, initial(&s));
        assert_eq!(p.handle(Some(ids[2]), &message(ids[1], 0, 0.0), Now::ZERO, 0), Err(Reject::WrongSender));
        assert_eq!(p.handle(Some(ids[0]), &message(ids[0], 0, 0.0), Now::ZERO, 0), Err(Reject::NotNeighbour));
        assert_eq!(p.handle(Some(99), &message(99, 0, 0.0), Now::ZERO, 0), Err(Reject::NotNeighbour));
        assert_eq!(p.handle(Some(ids[1]), &message(ids[1], 1_000_000, 0.0), Now::ZERO, 0), Err(Reject::Future));
        assert_eq!(p.handle(Some(ids[1]), b"garbage", Now::ZERO, 0), Err(Reject::Malformed));
        assert!(!p.has_all(1), "nothing refused was kept");
        p.handle(Some(ids[1]), &message(ids[1], 9, 0.0), Now::ZERO, 8).unwrap();
        assert_eq!(p.handle(Some(ids[1]), &message(ids[1], 2, 0.0), Now::ZERO, 8), Err(Reject::Stale));
    }

    #[test]
    fn real_time_takes_the_newest_and_marks_it_stale_after_the_silence_time_out() {
        let s = scenario("realtime");
        let id = s.graph.ids()[1];
        let mut p = Poses::new(&s, 0, initial(&s));
        let epoch = Duration::from_secs(100);
        p.start(epoch, 1.0, s.dt_s);
        let silence = Duration::from_secs_f64(s.silence_steps() as f64 * s.dt_s);
        assert!(!p.view(0, epoch).1[1], "fresh at the start");
        assert!(p.view(0, epoch + silence + Duration::from_millis(1)).1[1], "never heard past the time-out");
        let at = epoch + Duration::from_secs(1);
        p.handle(Some(id), &message(id, 7, 1.5), at, 50).unwrap();
        p.handle(Some(id), &message(id, 5, 0.5), at, 50).unwrap();
        let (view, stale) = p.view(50, at);
        assert_eq!((view[1].x, stale[1]), (1.5, false), "the newest, not the last to arrive");
        p.handle(Some(id), &message(id, 51, 2.5), at, 50).unwrap();
        p.handle(Some(id), &message(id, 50, 2.0), at, 50).unwrap();
        assert_eq!(p.view(51, at).0[1].x, 2.0, "step 51 takes the pose of step 50, as the model");
        assert_eq!(p.view(49, at).0[1].x, 0.5, "the newest kept of step 48 or before (7 gave its slot to 51)");
        assert_eq!(p.view(3, at).0[1].x, 0.5, "none of step 2 or before kept: the oldest kept");
        assert!(p.view(60, at + silence + Duration::from_millis(1)).1[1]);
    }
}
