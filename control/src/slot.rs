//! Where a follower's slot is (docs/model.md §17): the offset Δ_i in the
//! world frame (the paper's, eq. 28) or in the leader's, and the offsets a
//! follower holds over a run when the shape changes.
//!
//! # Examples
//!
//! A slot half a metre behind a leader that drives north: in the world frame
//! it stays west of the leader, in the leader's frame it is behind it.
//!
//! ```
//! use formation_control::slot::{reference, Frame};
//! use formation_leader::LeaderState;
//! use formation_plant::Pose;
//!
//! let north = std::f64::consts::FRAC_PI_2;
//! let leader = LeaderState { pose: Pose::new(0.0, 0.0, north), pose_rate: Pose::new(0.0, 1.0, 0.0), v: 1.0, w: 0.0 };
//! let world = reference(Frame::World, &leader, [-0.5, 0.0]);
//! let behind = reference(Frame::Leader, &leader, [-0.5, 0.0]);
//! assert_eq!((world.pose.x, world.pose.y), (-0.5, 0.0));
//! assert!(behind.pose.x.abs() < 1e-15 && (behind.pose.y + 0.5).abs() < 1e-15, "{:?}", behind.pose);
//! assert_eq!((behind.v, behind.w), (1.0, 0.0), "on a straight path the slot moves as the leader");
//! ```

use serde::{Deserialize, Serialize};

use formation_leader::LeaderState;
use formation_plant::Pose;

/// The frame a follower's offset is written in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Frame {
    /// The paper's (eq. 28): the slot is P_r + Δ_i, whatever the leader's heading.
    #[default]
    World,
    /// The leader's: the slot is P_r + R(θ_r) Δ_i, Δ_i = (ahead, to the left).
    Leader,
}

/// What a follower tracks at one step: the slot's pose, its speed and turn
/// rate (the reference robot of eq. 29–36), and the slot's velocity in the
/// world (the safety filter's, docs/model.md §16).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Reference {
    pub pose: Pose,
    pub v: f64,
    pub w: f64,
    pub rate: [f64; 2],
}

/// The reference of a slot at `offset` from `leader` (docs/model.md §17,
/// eq. 17.1–17.3). In the world frame this is the leader's own state moved by
/// Δ_i, as the paper has it. In the leader's frame the slot
/// p_d = p_r + R(θ_r) Δ moves at (v_r − ω_r Δy, ω_r Δx) in the leader's body
/// frame; its heading is that velocity's (the leader's when the slot stands
/// still), its speed that velocity's length, its turn rate ω_r.
pub fn reference(frame: Frame, leader: &LeaderState, offset: [f64; 2]) -> Reference {
    let p = leader.pose;
    match frame {
        Frame::World => Reference {
            pose: Pose::new(p.x + offset[0], p.y + offset[1], p.theta),
            v: leader.v,
            w: leader.w,
            rate: [leader.pose_rate.x, leader.pose_rate.y],
        },
        Frame::Leader => {
            let (s, c) = p.theta.sin_cos();
            let turned = [c * offset[0] - s * offset[1], s * offset[0] + c * offset[1]];
            // eq. 17.2: the slot's velocity in the leader's body frame.
            let (along, across) = (leader.v - leader.w * offset[1], leader.w * offset[0]);
            let speed = along.hypot(across);
            let heading = if speed > 0.0 { p.theta + across.atan2(along) } else { p.theta };
            Reference {
                pose: Pose::new(p.x + turned[0], p.y + turned[1], heading),
                v: speed,
                w: leader.w,
                // eq. 17.3: Ṗ_r's position part plus ω_r × R(θ_r) Δ.
                rate: [leader.pose_rate.x - leader.w * turned[1], leader.pose_rate.y + leader.w * turned[0]],
            }
        }
    }
}

/// The slot's position only (eq. 17.1), for the formation error (§11).
pub fn position(frame: Frame, leader: &Pose, offset: [f64; 2]) -> [f64; 2] {
    match frame {
        Frame::World => [leader.x + offset[0], leader.y + offset[1]],
        Frame::Leader => {
            let (s, c) = leader.theta.sin_cos();
            [leader.x + c * offset[0] - s * offset[1], leader.y + s * offset[0] + c * offset[1]]
        }
    }
}

/// The formation error |p_i − slot| (§11). In the world frame it is computed
/// as it always was, x − x_r − Δx, so that the paper's figures keep their bits.
#[inline]
pub fn formation_error(frame: Frame, p: &Pose, leader: &Pose, offset: [f64; 2]) -> f64 {
    match frame {
        Frame::World => norm(p.x - leader.x - offset[0], p.y - leader.y - offset[1]),
        Frame::Leader => {
            let [x, y] = position(frame, leader, offset);
            norm(p.x - x, p.y - y)
        }
    }
}

/// ‖(a, b)‖. Plain sqrt(a² + b²): `hypot`'s overflow guard costs a third of
/// a row and positions here are far from 1e154 m.
#[inline]
fn norm(a: f64, b: f64) -> f64 {
    (a * a + b * b).sqrt()
}

/// A follower's offsets over a run: `first` from step 0, then each change's
/// offset from its step on (docs/model.md §17, shape changes). Built once
/// when the scenario is read; looked up, never grown, in the step.
#[derive(Clone, Debug, PartialEq)]
pub struct Slots {
    first: [f64; 2],
    changes: Vec<(u64, [f64; 2])>,
}

impl Slots {
    /// One offset for the whole run.
    pub fn fixed(offset: [f64; 2]) -> Self {
        Self { first: offset, changes: Vec::new() }
    }

    /// `first`, then each (from step, offset); the steps must ascend.
    pub fn changing(first: [f64; 2], changes: Vec<(u64, [f64; 2])>) -> Self {
        debug_assert!(changes.windows(2).all(|w| w[0].0 <= w[1].0), "shape changes out of order");
        Self { first, changes }
    }

    /// The offset at step 0.
    pub fn first(&self) -> [f64; 2] {
        self.first
    }

    /// The offset in force at step k.
    pub fn at(&self, k: u64) -> [f64; 2] {
        self.changes.iter().rev().find(|(from, _)| k >= *from).map_or(self.first, |(_, o)| *o)
    }

    /// Each change: (from step, offset).
    pub fn changes(&self) -> &[(u64, [f64; 2])] {
        &self.changes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn on_circle(theta: f64, v: f64, w: f64) -> LeaderState {
        let (s, c) = theta.sin_cos();
        LeaderState { pose: Pose::new(1.0, 2.0, theta), pose_rate: Pose::new(v * c, v * s, w), v, w }
    }

    #[test]
    fn the_world_frame_is_the_leader_moved_by_the_offset() {
        let l = on_circle(0.7, 1.3, -0.4);
        let r = reference(Frame::World, &l, [4.0, -4.0]);
        assert_eq!(r.pose, Pose::new(1.0 + 4.0, 2.0 - 4.0, 0.7));
        assert_eq!((r.v, r.w, r.rate), (1.3, -0.4, [l.pose_rate.x, l.pose_rate.y]));
        assert_eq!(formation_error(Frame::World, &Pose::new(5.0, -2.0, 0.0), &l.pose, [4.0, -4.0]), 0.0);
    }

    #[test]
    fn a_leader_frame_slot_is_the_derivative_of_its_position() {
        // On an arc (v, ω constant) the slot is a unicycle too: its rate is the
        // derivative of p_r + R(θ_r) Δ, its heading the rate's direction, its
        // speed the rate's length and its turn rate ω_r.
        let (v, w, offset) = (0.12, 0.1, [-0.5, 0.25]);
        let at = |t: f64| {
            let theta = 0.3 + w * t;
            let centre = [1.0 - (v / w) * 0.3f64.sin(), 2.0 + (v / w) * 0.3f64.cos()];
            let l = LeaderState {
                pose: Pose::new(centre[0] + (v / w) * theta.sin(), centre[1] - (v / w) * theta.cos(), theta),
                pose_rate: Pose::new(v * theta.cos(), v * theta.sin(), w),
                v,
                w,
            };
            reference(Frame::Leader, &l, offset)
        };
        let (h, r) = (1e-6, at(2.0));
        let (ahead, behind) = (at(2.0 + h), at(2.0 - h));
        let rate = [(ahead.pose.x - behind.pose.x) / (2.0 * h), (ahead.pose.y - behind.pose.y) / (2.0 * h)];
        let heading_rate = (ahead.pose.theta - behind.pose.theta) / (2.0 * h);
        assert!((rate[0] - r.rate[0]).abs() < 1e-8 && (rate[1] - r.rate[1]).abs() < 1e-8, "{rate:?} vs {:?}", r.rate);
        assert!((r.v - rate[0].hypot(rate[1])).abs() < 1e-8, "speed {} vs {}", r.v, rate[0].hypot(rate[1]));
        assert!(
            (r.pose.theta - rate[1].atan2(rate[0])).abs() < 1e-8,
            "heading {} vs {}",
            r.pose.theta,
            rate[1].atan2(rate[0])
        );
        assert!((heading_rate - r.w).abs() < 1e-6, "turn rate {heading_rate} vs {}", r.w);
    }

    #[test]
    fn a_leader_frame_slot_turns_with_the_leader() {
        let north = std::f64::consts::FRAC_PI_2;
        let l = on_circle(north, 0.0, 0.0);
        let p = position(Frame::Leader, &l.pose, [1.0, 0.5]);
        assert!((p[0] - (1.0 - 0.5)).abs() < 1e-15 && (p[1] - (2.0 + 1.0)).abs() < 1e-15, "{p:?}");
        // A standing leader: the slot stands too, with the leader's heading.
        let r = reference(Frame::Leader, &l, [1.0, 0.5]);
        assert_eq!((r.v, r.w, r.pose.theta), (0.0, 0.0, north));
        let robot = Pose::new(p[0] + 0.3, p[1] - 0.4, 0.0);
        assert!((formation_error(Frame::Leader, &robot, &l.pose, [1.0, 0.5]) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn slots_hold_each_offset_from_its_step() {
        let s = Slots::changing([1.0, 0.0], vec![(10, [2.0, 0.0]), (20, [3.0, 0.0])]);
        let at: Vec<f64> = [0, 9, 10, 19, 20, 1000].iter().map(|&k| s.at(k)[0]).collect();
        assert_eq!(at, [1.0, 1.0, 2.0, 2.0, 3.0, 3.0]);
        assert_eq!(Slots::fixed([0.5, 0.5]).at(u64::MAX), [0.5, 0.5]);
    }
}
