//! Kinematic controllers (docs/model.md §6): the tracking error (eq. 28–29, with
//! docs/model.md §1's sign), bioinspired backstepping (eq. 35–36) and conventional
//! backstepping (the paper's baseline).

use serde::{Deserialize, Serialize};

use crate::math::Shunting;
use formation_plant::wrap;
use formation_plant::{Pose, Velocity};

/// Which kinematic controller a follower runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum KinematicKind {
    /// Bioinspired backstepping: the x̂ term passes through a shunting model.
    Bio,
    /// Conventional backstepping: v_c = C_1 x̂ + v_ir cos θ̂.
    Conventional,
}

/// C_1, C_2, C_3 and the shunting model driven by x̂ (docs/model.md §10).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct KinematicGains {
    pub c1: f64,
    pub c2: f64,
    pub c3: f64,
    pub shunting: Shunting,
}

/// Body-frame tracking error (x̂, ŷ, θ̂).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BodyError {
    pub x: f64,
    pub y: f64,
    pub theta: f64,
}

/// The body-frame error of `pose` against the reference P_ir + (Δx, Δy)
/// (eq. 28–29 with docs/model.md §1's sign, reference minus actual):
/// e_x = x_ir + Δx − x, e_y = y_ir + Δy − y, e_θ = wrap(θ_ir − θ);
/// x̂ = cos θ e_x + sin θ e_y, ŷ = −sin θ e_x + cos θ e_y, θ̂ = e_θ.
pub fn body_error(leader_estimate: &Pose, offset: [f64; 2], pose: &Pose) -> BodyError {
    body_error_with(leader_estimate, offset, pose, pose.theta.sin_cos())
}

/// [`body_error`] with `pose.theta.sin_cos()` already computed (the
/// simulator's robot needs it too; same numbers).
pub fn body_error_with(leader_estimate: &Pose, offset: [f64; 2], pose: &Pose, (s, c): (f64, f64)) -> BodyError {
    let ex = leader_estimate.x + offset[0] - pose.x;
    let ey = leader_estimate.y + offset[1] - pose.y;
    BodyError { x: c * ex + s * ey, y: -s * ex + c * ey, theta: wrap(leader_estimate.theta - pose.theta) }
}

/// The body-frame error of `pose` against a reference pose given whole (a
/// slot in the leader's frame, docs/model.md §17): e_x = x_d − x, e_y = y_d − y,
/// e_θ = wrap(θ_d − θ), rotated as in [`body_error`].
pub fn body_error_to(reference: &Pose, pose: &Pose, (s, c): (f64, f64)) -> BodyError {
    let (ex, ey) = (reference.x - pose.x, reference.y - pose.y);
    BodyError { x: c * ex + s * ey, y: -s * ex + c * ey, theta: wrap(reference.theta - pose.theta) }
}

/// The velocity command (v_c, ω_c).
///
/// Bioinspired (eq. 35–36): v_c = C_1 V_s + v_ir cos θ̂, with V_s the shunting
/// state driven by x̂; conventional: v_c = C_1 x̂ + v_ir cos θ̂. Both:
/// ω_c = ω_ir + C_2 v_ir ŷ + C_3 v_ir sin θ̂.
pub fn command(kind: KinematicKind, g: &KinematicGains, v_s: f64, e: &BodyError, v_ir: f64, w_ir: f64) -> Velocity {
    let along = match kind {
        KinematicKind::Bio => v_s,
        KinematicKind::Conventional => e.x,
    };
    let (sin_theta, cos_theta) = e.theta.sin_cos();
    Velocity { v: g.c1 * along + v_ir * cos_theta, w: w_ir + g.c2 * v_ir * e.y + g.c3 * v_ir * sin_theta }
}

#[cfg(test)]
mod tests {
    use super::*;

    const G: KinematicGains =
        KinematicGains { c1: 3.0, c2: 2.0, c3: 1.0, shunting: Shunting { a: 4.0, b: 2.0, d: 2.0 } };

    #[test]
    fn body_error_rotates_into_the_robot_frame() {
        // Robot facing +y: a reference 1 m ahead along +y is x̂ = 1, ŷ = 0.
        let pose = Pose::new(0.0, 0.0, std::f64::consts::FRAC_PI_2);
        let e = body_error(&Pose::new(0.0, 1.0, std::f64::consts::FRAC_PI_2), [0.0, 0.0], &pose);
        assert!((e.x - 1.0).abs() < 1e-12 && e.y.abs() < 1e-12 && e.theta.abs() < 1e-12, "{e:?}");
        // Offsets shift the reference: 4 m to the robot's right (−x world) is ŷ = 4.
        let e = body_error(&Pose::new(0.0, 0.0, std::f64::consts::FRAC_PI_2), [-4.0, 0.0], &pose);
        assert!((e.y - 4.0).abs() < 1e-12, "{e:?}");
    }

    #[test]
    fn conventional_command_grows_with_the_error_bio_does_not() {
        let e = BodyError { x: 5.0, y: 0.0, theta: 0.0 };
        let conv = command(KinematicKind::Conventional, &G, 0.0, &e, 0.0, 0.0);
        assert_eq!(conv.v, 15.0);
        // The shunting state is at most B, so the bioinspired term is at most C_1 B.
        let bio = command(KinematicKind::Bio, &G, G.shunting.b, &e, 1.0, 0.0);
        assert_eq!(bio.v, G.c1 * G.shunting.b + 1.0);
    }

    #[test]
    fn zero_error_commands_the_leader_velocity() {
        let e = BodyError::default();
        for kind in [KinematicKind::Bio, KinematicKind::Conventional] {
            let c = command(kind, &G, 0.0, &e, 1.3, -0.4);
            assert_eq!((c.v, c.w), (1.3, -0.4));
        }
    }
}
