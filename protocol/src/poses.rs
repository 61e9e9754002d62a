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
//!   initial pose before any; [`Seen::Stale`] with its age once the newest
//!   heard is older than the scenario's silence time-out, and no longer
//!   growing once older than `network.gone_after` (taken for gone).
//!
//! A robot that is not running is still there ([`Seen::Still`]): one absent
//! at the start at its initial pose (until, in real time, it is heard); one
//! that left the run before step k_L at the last pose it published, that
//! of step k_L, marked `left` (where its robot stopped), from step k_L + 1
//! on, as the simulator's leave row has it; one killed (lock-step, its
//! links cut from L) at its pose of step L − 2, the last it sent, from
//! step L on, as the died row has it ([`Poses::died`]).

use std::time::Duration;

use crate::wire::{self, Header, PoseMsg, Reject, FORMAT_VERSION};
use formation_control::Seen;
use formation_plant::Pose;
use formation_scenario::Scenario;

use crate::Now;

/// Poses kept per robot (lock-step: its step k − 1 and what runs ahead).
const RING: usize = 4;

/// Whether another robot runs.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Presence {
    Running,
    /// Absent at the start (a quorum start): at its initial pose.
    Absent,
    /// Left the run before step `at_k`, its robot stopped at `pose` (its pose of step `at_k`).
    Left {
        at_k: u64,
        pose: Pose,
    },
    /// Killed (lock-step, crate::died): its robot stands from step
    /// `from_k` on at its pose of step `from_k` − 1, the last it sent (the
    /// initial pose if none before step 0).
    Died {
        from_k: u64,
    },
}

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
    presence: Vec<Presence>,
    initial: Vec<Pose>,
    /// The view of the step being computed, and how each robot is seen.
    view: Vec<Pose>,
    seen: Vec<Seen>,
    /// Real time: older than `silence` is stale, older than `gone` (if the
    /// scenario sets `network.gone_after`) taken for gone (both at the
    /// run's pace); the run's epoch, when the initial poses were "heard".
    silence: Duration,
    gone: Option<Duration>,
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
            lockstep: scenario.timing == formation_scenario::Timing::Lockstep,
            ring: vec![[None; RING]; n],
            newest: vec![None; n],
            presence: vec![Presence::Running; n],
            view: initial.clone(),
            seen: vec![Seen::Live; n],
            initial,
            silence: Duration::from_secs_f64(scenario.silence_steps() as f64 * scenario.dt_s),
            gone: scenario.network.gone_after_s.map(Duration::from_secs_f64),
            epoch: Now::ZERO,
            ahead: RING as u64 - 1,
            sent: [None, None],
        }
    }

    /// Real time: the run's epoch and pace (the silence and gone time-outs
    /// are scaled as the period is); a pose may run 0.1 s ahead (clocks
    /// differ), as an estimate may.
    pub fn start(&mut self, epoch: Now, time_scale: f64, dt_s: f64) {
        self.epoch = epoch;
        self.silence = self.silence.div_f64(time_scale);
        self.gone = self.gone.map(|g| g.div_f64(time_scale));
        self.ahead = ((0.1 * time_scale / dt_s).ceil() as u64).max(crate::inbox::REALTIME_AHEAD);
    }

    /// Follower `id` was absent at the start: at its initial pose, not
    /// waited for; in real time, until it is heard.
    pub fn absent(&mut self, id: u32) {
        if let Some(j) = self.ids.iter().position(|&i| i == id).filter(|&j| j != self.own) {
            if self.presence[j] == Presence::Running {
                self.presence[j] = Presence::Absent;
            }
        }
    }

    /// The newest step of follower `id`'s pose received and that pose
    /// (None: none, or this follower's own).
    pub fn newest_of(&self, id: u32) -> Option<(u64, Pose)> {
        let j = self.ids.iter().position(|&i| i == id).filter(|&j| j != self.own)?;
        let (k, _) = self.newest[j]?;
        self.at(j, k).map(|p| (k, p))
    }

    /// Whether every other robot that runs was heard with a pose of step
    /// `k` or later ([`crate::follower::FollowerMachine::heard_past`]).
    pub fn heard_past(&self, k: u64) -> bool {
        (0..self.ids.len()).all(|j| {
            j == self.own
                || self.presence[j] != Presence::Running
                || self.newest[j].is_some_and(|(newest, _)| newest >= k)
        })
    }

    /// Follower `id` died, cut off from step `at_k` (lock-step,
    /// [`crate::died`]): its robot stands at its pose of step `at_k` − 2,
    /// the last it sent, from step `at_k` − 1 on (the filters of step
    /// `at_k` − 1 see that pose as sent, those of `at_k` on as still), as
    /// the simulator's died row has it. Before any pose, at its initial
    /// pose.
    ///
    /// The pose of step `at_k` − 2 may still be on its way (someone holds
    /// it, so the router forwards it here too): until it is in, the robot
    /// is missing for step `at_k` − 1 on, as any pose not yet heard.
    pub fn died(&mut self, id: u32, at_k: u64) {
        let Some(j) = self.ids.iter().position(|&i| i == id).filter(|&j| j != self.own) else { return };
        if self.presence[j] == Presence::Running {
            self.presence[j] = Presence::Died { from_k: at_k.saturating_sub(1) };
        }
    }

    /// Follower `id`'s pose of step `k`, where no message of it came (the
    /// last of one that died, from the monitor's [`crate::died::Died`]):
    /// kept if nothing as new is held.
    pub fn fill(&mut self, id: u32, k: u64, pose: [f64; 3], now: Now) {
        let Some(j) = self.ids.iter().position(|&i| i == id).filter(|&j| j != self.own) else { return };
        if self.newest[j].is_some_and(|(newest, _)| newest >= k) {
            return;
        }
        self.ring[j][(k as usize) % RING] = Some((k, Pose::new(pose[0], pose[1], pose[2])));
        self.newest[j] = Some((k, now));
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
        let pose = Pose::new(x, y, theta);
        self.ring[j][(k as usize) % RING] = Some((k, pose));
        if self.newest[j].is_none_or(|(newest, _)| k >= newest) {
            self.newest[j] = Some((k, now));
        }
        self.presence[j] = match (msg.left, self.presence[j]) {
            (true, _) => Presence::Left { at_k: k, pose },
            // Real time: an absent robot joins with its first pose.
            (false, Presence::Absent) if !self.lockstep => Presence::Running,
            (false, p) => p,
        };
        Ok(())
    }

    /// This follower's scenario index.
    pub fn own(&self) -> usize {
        self.own
    }

    /// Lock-step: every other robot's pose of step k − 1 is in (or the
    /// robot does not run then).
    pub fn has_all(&self, k: u64) -> bool {
        k == 0
            || (0..self.ring.len())
                .all(|j| j == self.own || self.still(j, k - 1).is_some() || self.at(j, k - 1).is_some())
    }

    /// The robots still missing for step k (lock-step), by id.
    pub fn missing(&self, k: u64) -> impl Iterator<Item = u32> + '_ {
        (0..self.ring.len())
            .filter(move |&j| j != self.own && k > 0 && self.still(j, k - 1).is_none() && self.at(j, k - 1).is_none())
            .map(|j| self.ids[j])
    }

    /// Where robot j stands at step `s` if it does not run then: absent, or
    /// left before a step before `s`.
    fn still(&self, j: usize, s: u64) -> Option<Pose> {
        match self.presence[j] {
            Presence::Running => None,
            Presence::Absent => Some(self.initial[j]),
            Presence::Left { at_k, pose } => (s >= at_k).then_some(pose),
            Presence::Died { from_k } if s >= from_k => match from_k.checked_sub(1) {
                Some(last) => self.at(j, last),
                None => Some(self.initial[j]),
            },
            Presence::Died { .. } => None,
        }
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

    /// The view of step k at `now`: (poses, how each is seen, lost) by
    /// scenario index, this follower's own entry unused. Lost (real time,
    /// with `network.gone_after`): every other robot that runs was last
    /// heard longer ago than that. Lock-step: call after [`Poses::has_all`].
    pub fn view(&mut self, k: u64, now: Now) -> (&[Pose], &[Seen], bool) {
        let s = k.saturating_sub(1);
        let (mut running, mut unheard) = (0, 0);
        for j in 0..self.view.len() {
            if j == self.own {
                continue;
            }
            if let Some(p) = self.still(j, s) {
                (self.view[j], self.seen[j]) = (p, Seen::Still);
                continue;
            }
            if self.lockstep {
                self.seen[j] = Seen::Live;
                self.view[j] = if k == 0 { self.initial[j] } else { self.at(j, s).unwrap_or(self.initial[j]) };
                continue;
            }
            let heard_at = self.newest[j].map_or(self.epoch, |(_, at)| at);
            let age = now.saturating_sub(heard_at);
            self.view[j] = self.pose_for(j, s).unwrap_or(self.initial[j]);
            self.seen[j] = match self.gone {
                _ if age <= self.silence => Seen::Live,
                Some(gone) if age > gone => Seen::Stale { age_s: gone.as_secs_f64(), growing: false },
                _ => Seen::Stale { age_s: age.as_secs_f64(), growing: true },
            };
            running += 1;
            unheard += usize::from(self.gone.is_some_and(|g| age > g));
        }
        (&self.view, &self.seen, running > 0 && unheard == running)
    }

    /// This follower's own pose of step k, for the wire (kept for repeats);
    /// `left`: its last, where its robot stopped, as it leaves before step k.
    pub fn publish(&mut self, k: u64, pose: Pose, left: bool, now: Now, dt_s: f64) -> Vec<u8> {
        let msg = PoseMsg {
            header: Header {
                version: FORMAT_VERSION,
                sender: self.id,
                step: k,
                time_s: k as f64 * dt_s,
                sent_ns: now.as_nanos() as i64,
            },
            pose: [pose.x, pose.y, pose.theta],
            left,
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
        scenario_with(timing, &[])
    }

    fn scenario_with(timing: &str, more: &[&str]) -> Scenario {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/turtlebot.toml");
        let mut o = vec![format!("timing={timing}")];
        o.extend(more.iter().map(|m| m.to_string()));
        Scenario::load(&path, &o).expect("the turtlebot scenario")
    }

    fn initial(s: &Scenario) -> Vec<Pose> {
        s.followers.iter().map(|f| f.pose).collect()
    }

    fn message(sender: u32, k: u64, x: f64) -> Vec<u8> {
        let header = Header { version: FORMAT_VERSION, sender, step: k, time_s: 0.0, sent_ns: 0 };
        wire::encode_pose(&PoseMsg { header, pose: [x, 0.0, 0.0], left: false })
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
        let (view, seen, lost) = p.view(1, Now::ZERO);
        assert_eq!(view[1].x, ids[1] as f64);
        assert!(seen.iter().all(|s| *s == Seen::Live) && !lost, "{seen:?}");
        assert_eq!(p.view(0, Now::ZERO).0[1], s.followers[1].pose);
    }

    /// docs/model.md §14's died row, as follower 1's filter sees follower
    /// 2 die before step 10 (the monitor named L = 10): its pose of step 8,
    /// the last it sent, as sent at step 9 and as still from step 10 on;
    /// waited for while it is on its way; never waited for after it.
    #[test]
    fn a_robot_that_died_stands_at_its_last_pose_sent_once_that_pose_is_in() {
        let s = scenario("lockstep");
        let ids = s.graph.ids().to_vec();
        let dead = ids[1];
        let mut p = Poses::new(&s, 0, initial(&s));
        for k in 0..8 {
            for &id in &ids[1..] {
                p.handle(Some(id), &message(id, k, k as f64), Now::ZERO, k).unwrap();
            }
        }
        assert_eq!(p.newest_of(dead).map(|(k, pose)| (k, pose.x)), Some((7, 7.0)));
        assert_eq!(p.newest_of(ids[0]), None, "its own");
        p.died(dead, 10);
        for &id in &ids[2..] {
            p.handle(Some(id), &message(id, 8, 8.0), Now::ZERO, 8).unwrap();
        }
        assert_eq!(p.missing(9).collect::<Vec<_>>(), vec![dead], "its pose of step 8 is still on its way");
        p.handle(Some(dead), &message(dead, 8, 8.5), Now::ZERO, 8).unwrap();
        assert!(p.has_all(9));
        let (view, seen, _) = p.view(9, Now::ZERO);
        assert_eq!((view[1].x, seen[1]), (8.5, Seen::Live), "step 9: its pose of step 8, as sent");
        for k in 9..12 {
            for &id in &ids[2..] {
                p.handle(Some(id), &message(id, k, k as f64), Now::ZERO, k).unwrap();
            }
            assert!(p.has_all(k + 1), "step {}: missing {:?}", k + 1, p.missing(k + 1).collect::<Vec<_>>());
            let (view, seen, _) = p.view(k + 1, Now::ZERO);
            assert_eq!((view[1].x, seen[1]), (8.5, Seen::Still), "step {}: standing at its pose of step 8", k + 1);
        }
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
        assert_eq!(p.view(0, epoch).1[1], Seen::Live, "fresh at the start");
        assert!(stale(p.view(0, epoch + silence + Duration::from_millis(1)).1[1]), "never heard past the time-out");
        let at = epoch + Duration::from_secs(1);
        p.handle(Some(id), &message(id, 7, 1.5), at, 50).unwrap();
        p.handle(Some(id), &message(id, 5, 0.5), at, 50).unwrap();
        let (view, seen, _) = p.view(50, at);
        assert_eq!((view[1].x, seen[1]), (1.5, Seen::Live), "the newest, not the last to arrive");
        p.handle(Some(id), &message(id, 51, 2.5), at, 50).unwrap();
        p.handle(Some(id), &message(id, 50, 2.0), at, 50).unwrap();
        assert_eq!(p.view(51, at).0[1].x, 2.0, "step 51 takes the pose of step 50, as the model");
        assert_eq!(p.view(49, at).0[1].x, 0.5, "the newest kept of step 48 or before (7 gave its slot to 51)");
        assert_eq!(p.view(3, at).0[1].x, 0.5, "none of step 2 or before kept: the oldest kept");
        assert!(stale(p.view(60, at + silence + Duration::from_millis(1)).1[1]));
    }

    fn stale(s: Seen) -> bool {
        matches!(s, Seen::Stale { .. })
    }

    fn left(sender: u32, k: u64, x: f64) -> Vec<u8> {
        let header = Header { version: FORMAT_VERSION, sender, step: k, time_s: 0.0, sent_ns: 0 };
        wire::encode_pose(&PoseMsg { header, pose: [x, 0.0, 0.0], left: true })
    }

    /// Lock-step: a robot that left before step k_L is waited for up to its
    /// pose of step k_L (where it stopped, marked left), then held there,
    /// still, without waiting; one absent at the start stands at its
    /// initial pose from step 0 (as the simulator's leave rows have it).
    #[test]
    fn lock_step_holds_a_robot_that_left_where_it_stopped_and_an_absent_one_at_its_initial_pose() {
        let s = scenario("lockstep");
        let ids = s.graph.ids().to_vec();
        let mut p = Poses::new(&s, 0, initial(&s));
        p.absent(ids[3]);
        let at = |p: &mut Poses, k: u64| {
            let (view, seen, _) = p.view(k, Now::ZERO);
            (view.to_vec(), seen.to_vec())
        };
        for k in 0..5 {
            p.handle(Some(ids[1]), &message(ids[1], k, k as f64), Now::ZERO, k).unwrap();
            p.handle(Some(ids[2]), &message(ids[2], k, 10.0 + k as f64), Now::ZERO, k).unwrap();
        }
        // Follower 3 leaves before step 5: its last pose is that of step 5.
        p.handle(Some(ids[1]), &message(ids[1], 5, 5.0), Now::ZERO, 5).unwrap();
        assert!(!p.has_all(6), "its pose of step 5 is still to come");
        assert_eq!(p.missing(6).collect::<Vec<_>>(), vec![ids[2]]);
        p.handle(Some(ids[2]), &left(ids[2], 5, 15.5), Now::ZERO, 5).unwrap();
        assert!(p.has_all(6));
        assert!(!p.has_all(7), "follower 2 still runs");
        let (view, seen) = at(&mut p, 5);
        assert_eq!((view[2].x, seen[2]), (14.0, Seen::Live), "step 5 takes its pose of step 4, running then");
        assert_eq!((view[3], seen[3]), (s.followers[3].pose, Seen::Still), "the absent one, from step 0");
        let (view, seen) = at(&mut p, 6);
        assert_eq!((view[2].x, seen[2]), (15.5, Seen::Still), "step 6: where it stopped, still");
        p.handle(Some(ids[1]), &message(ids[1], 6, 6.0), Now::ZERO, 6).unwrap();
        assert!(p.has_all(7), "nothing waited for from the one that left: {:?}", p.missing(7).collect::<Vec<_>>());
        assert_eq!(at(&mut p, 7).0[2].x, 15.5);
        assert_eq!(at(&mut p, 0).1[3], Seen::Still, "absent at step 0 too");
    }

    /// Real time: a stale robot's age is the time since it was last heard,
    /// its bound stops growing once it is taken for gone (network.gone_after);
    /// a follower that hears no robot for that long is lost; one that left
    /// is still at its last pose, never stale; an absent one joins when heard.
    #[test]
    fn real_time_ages_stale_robots_takes_them_for_gone_and_holds_those_that_left() {
        let s = scenario_with("realtime", &["network.gone_after=2"]);
        let ids = s.graph.ids().to_vec();
        let mut p = Poses::new(&s, 0, initial(&s));
        let epoch = Duration::from_secs(100);
        p.start(epoch, 1.0, s.dt_s);
        p.absent(ids[3]);
        let t = |s: f64| epoch + Duration::from_secs_f64(s);
        p.handle(Some(ids[1]), &message(ids[1], 50, 1.0), t(1.0), 50).unwrap();
        p.handle(Some(ids[2]), &left(ids[2], 50, 2.0), t(1.0), 50).unwrap();
        let (_, seen, lost) = p.view(60, t(1.0));
        assert_eq!((seen[1], seen[2], seen[3], lost), (Seen::Live, Seen::Still, Seen::Still, false));
        let (_, seen, lost) = p.view(100, t(2.5));
        assert_eq!(seen[1], Seen::Stale { age_s: 1.5, growing: true });
        assert!(!lost);
        let (view, seen, lost) = p.view(200, t(3.5));
        assert_eq!(seen[1], Seen::Stale { age_s: 2.0, growing: false }, "taken for gone after 2 s");
        assert_eq!((view[2].x, seen[2]), (2.0, Seen::Still), "the one that left is never stale");
        assert!(lost, "no robot that runs heard for 2.5 s");
        p.handle(Some(ids[3]), &message(ids[3], 150, 3.0), t(3.5), 150).unwrap();
        let (view, seen, lost) = p.view(151, t(3.5));
        assert_eq!((view[3].x, seen[3], lost), (3.0, Seen::Live, false), "the absent one joined");
    }
}
