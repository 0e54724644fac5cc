//! Kinematics of a three-wheel omni-directional base ([2D3D] eq 1-3, docs/EQUATIONS.md).
//!
//! Frames: the body frame has x forward, y left, z up, its origin at the base's centre; the world
//! frame is the map's (x, y, yaw θ). The three wheels sit at `center_to_wheel_m` (L) from the
//! centre, 120° apart (α = 120°), each rolling along its drive direction; its rollers let it slide
//! across, so the base is holonomic: it strafes as well as it drives.
//!
//! [2D3D] eq 1 gives the wheels' linear rim speeds from the body velocity (v_x, v_y, ω):
//!
//! ```text
//! v_1 =  sin(α/2)·v_x + cos(α/2)·v_y + L·ω
//! v_2 = −sin(α/2)·v_x + cos(α/2)·v_y + L·ω
//! v_3 =              − v_y           + L·ω
//! ```
//!
//! (drive directions at 30°, 150° and 270° from the body's x axis); eq 2 rotates the body velocity
//! into the world by θ; eq 3 is eq 1 applied to the world velocity rotated back. Odometry is the
//! inverse of eq 1 (the 3×3 matrix is invertible for L > 0) integrated over each interval at
//! constant body velocity, exactly (the SE(2) exponential), not by an Euler step.

use serde::{Deserialize, Serialize};

/// Errors of the kinematics.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OmniError {
    /// A geometry value that is not a finite positive number.
    #[error("{what} must be a finite number > 0, got {value}")]
    Geometry {
        /// Which value.
        what: &'static str,
        /// The value given.
        value: f64,
    },
}

/// The base's geometry.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OmniBase {
    /// Distance from the base's centre to each wheel's contact point, m (L).
    pub center_to_wheel_m: f64,
    /// Wheel radius, m (rim speed = radius × angular speed).
    pub wheel_radius_m: f64,
}

/// A velocity in the body frame.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct BodyVelocity {
    /// Forward, m/s.
    pub vx_mps: f64,
    /// Left (strafe), m/s.
    pub vy_mps: f64,
    /// Yaw rate, counter-clockwise, rad/s.
    pub omega_radps: f64,
}

/// A velocity in the world frame ([2D3D] eq 2: Ẋ, Ẏ, θ̇).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct WorldVelocity {
    /// m/s along the world's x.
    pub x_mps: f64,
    /// m/s along the world's y.
    pub y_mps: f64,
    /// Yaw rate, rad/s.
    pub theta_radps: f64,
}

/// A planar pose `world_from_body`: position and yaw.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Pose2 {
    /// m.
    pub x_m: f64,
    /// m.
    pub y_m: f64,
    /// Yaw, rad, in (−π, π].
    pub theta_rad: f64,
}

/// sin and cos of α/2 = 60°.
const S: f64 = 0.866_025_403_784_438_6; // sin 60° = √3/2
const C: f64 = 0.5; // cos 60°

/// Wraps an angle into (−π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let w = a.rem_euclid(std::f64::consts::TAU);
    if w > std::f64::consts::PI { w - std::f64::consts::TAU } else { w }
}

impl OmniBase {
    /// A base with wheels at `center_to_wheel_m` of radius `wheel_radius_m`.
    pub fn new(center_to_wheel_m: f64, wheel_radius_m: f64) -> Result<Self, OmniError> {
        for (what, value) in [("center_to_wheel_m", center_to_wheel_m), ("wheel_radius_m", wheel_radius_m)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(OmniError::Geometry { what, value });
            }
        }
        Ok(Self { center_to_wheel_m, wheel_radius_m })
    }

    /// [2D3D] eq 1: the wheels' rim speeds (m/s) for a body velocity.
    pub fn wheel_speeds(&self, v: BodyVelocity) -> [f64; 3] {
        let l = self.center_to_wheel_m * v.omega_radps;
        [S * v.vx_mps + C * v.vy_mps + l, -S * v.vx_mps + C * v.vy_mps + l, -v.vy_mps + l]
    }

    /// The wheels' angular speeds (rad/s) for a body velocity.
    pub fn wheel_rates(&self, v: BodyVelocity) -> [f64; 3] {
        self.wheel_speeds(v).map(|s| s / self.wheel_radius_m)
    }

    /// The inverse of eq 1: the body velocity from the wheels' rim speeds (m/s), as odometry
    /// measures it.
    pub fn body_velocity(&self, wheels: [f64; 3]) -> BodyVelocity {
        let [v1, v2, v3] = wheels;
        // v1 − v2 = 2S·vx; v1 + v2 − 2·v3 = (2C + 2)·vy = 3·vy; v1 + v2 + v3 = (2C − 1)·vy + 3Lω = 3Lω.
        BodyVelocity {
            vx_mps: (v1 - v2) / (2.0 * S),
            vy_mps: (v1 + v2 - 2.0 * v3) / (2.0 * C + 2.0),
            omega_radps: (v1 + v2 + v3) / (3.0 * self.center_to_wheel_m),
        }
    }

    /// The body velocity from the wheels' angular speeds (rad/s).
    pub fn body_velocity_from_rates(&self, rates: [f64; 3]) -> BodyVelocity {
        self.body_velocity(rates.map(|r| r * self.wheel_radius_m))
    }

    /// [2D3D] eq 3: the wheels' rim speeds for a world velocity at yaw θ.
    pub fn wheel_speeds_from_world(&self, theta_rad: f64, w: WorldVelocity) -> [f64; 3] {
        let (s, c) = theta_rad.sin_cos();
        self.wheel_speeds(BodyVelocity {
            vx_mps: c * w.x_mps + s * w.y_mps,
            vy_mps: -s * w.x_mps + c * w.y_mps,
            omega_radps: w.theta_radps,
        })
    }
}

/// [2D3D] eq 2: the world velocity of a body velocity at yaw θ.
pub fn world_velocity(theta_rad: f64, v: BodyVelocity) -> WorldVelocity {
    let (s, c) = theta_rad.sin_cos();
    WorldVelocity { x_mps: c * v.vx_mps - s * v.vy_mps, y_mps: s * v.vx_mps + c * v.vy_mps, theta_radps: v.omega_radps }
}

/// The body's motion over `dt_s` at constant body velocity `v`, in the body frame at its start
/// (the SE(2) exponential of the twist): (dx, dy, dθ).
pub fn body_increment(v: BodyVelocity, dt_s: f64) -> Pose2 {
    let dth = v.omega_radps * dt_s;
    let (dx, dy) = (v.vx_mps * dt_s, v.vy_mps * dt_s);
    // V(dθ) = [[sin dθ/dθ, −(1−cos dθ)/dθ], [(1−cos dθ)/dθ, sin dθ/dθ]], by series near 0.
    let (a, b) = if dth.abs() < 1e-6 {
        (1.0 - dth * dth / 6.0, dth / 2.0 - dth * dth * dth / 24.0)
    } else {
        (dth.sin() / dth, (1.0 - dth.cos()) / dth)
    };
    Pose2 { x_m: a * dx - b * dy, y_m: b * dx + a * dy, theta_rad: dth }
}

impl Pose2 {
    /// `self ⊕ delta`: `delta` (in this pose's body frame) composed onto this pose.
    pub fn compose(&self, delta: &Pose2) -> Pose2 {
        let (s, c) = self.theta_rad.sin_cos();
        Pose2 {
            x_m: self.x_m + c * delta.x_m - s * delta.y_m,
            y_m: self.y_m + s * delta.x_m + c * delta.y_m,
            theta_rad: wrap_angle(self.theta_rad + delta.theta_rad),
        }
    }

    /// `self⁻¹ ⊕ other`: `other` in this pose's body frame.
    pub fn between(&self, other: &Pose2) -> Pose2 {
        let (s, c) = self.theta_rad.sin_cos();
        let (dx, dy) = (other.x_m - self.x_m, other.y_m - self.y_m);
        Pose2 { x_m: c * dx + s * dy, y_m: -s * dx + c * dy, theta_rad: wrap_angle(other.theta_rad - self.theta_rad) }
    }
}

/// Odometry: the pose after `dt_s` with wheel rim speeds `wheels` held constant over it.
pub fn integrate(base: &OmniBase, pose: &Pose2, wheels: [f64; 3], dt_s: f64) -> Pose2 {
    pose.compose(&body_increment(base.body_velocity(wheels), dt_s))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn base() -> OmniBase {
        OmniBase::new(0.2, 0.05).expect("valid")
    }

    #[test]
    fn the_drive_directions_are_120_degrees_apart_and_a_spin_turns_every_wheel_alike() {
        let b = base();
        let spin = b.wheel_speeds(BodyVelocity { omega_radps: 1.0, ..Default::default() });
        assert!(spin.iter().all(|s| (s - 0.2).abs() < 1e-12), "{spin:?}");
        // A translation in any direction: the rim speeds sum to zero.
        for deg in (0..360).step_by(15) {
            let a = (deg as f64).to_radians();
            let w = b.wheel_speeds(BodyVelocity { vx_mps: a.cos(), vy_mps: a.sin(), omega_radps: 0.0 });
            assert!(w.iter().sum::<f64>().abs() < 1e-12, "{deg}°: {w:?}");
        }
        // Driving along a wheel's drive direction (30°) moves that wheel at full speed.
        let a = 30f64.to_radians();
        let w = b.wheel_speeds(BodyVelocity { vx_mps: a.cos(), vy_mps: a.sin(), omega_radps: 0.0 });
        assert!((w[0] - 1.0).abs() < 1e-12, "{w:?}");
        assert!(OmniBase::new(0.0, 0.05).is_err() && OmniBase::new(0.2, f64::NAN).is_err());
    }

    #[test]
    fn eq_3_is_eq_1_of_the_world_velocity_rotated_into_the_body() {
        let b = base();
        let theta: f64 = 0.7;
        let (s, c) = theta.sin_cos();
        let w = WorldVelocity { x_mps: 0.3, y_mps: -0.4, theta_radps: 0.25 };
        let [v1, v2, v3] = b.wheel_speeds_from_world(theta, w);
        // The rows of eq 3 as the paper writes them (α/2 = 60°).
        let h = std::f64::consts::FRAC_PI_3;
        let l = b.center_to_wheel_m;
        let e1 = (h - theta).sin() * w.x_mps + (h - theta).cos() * w.y_mps + l * w.theta_radps;
        let e2 = -(h + theta).sin() * w.x_mps + (h + theta).cos() * w.y_mps + l * w.theta_radps;
        let e3 = s * w.x_mps - c * w.y_mps + l * w.theta_radps;
        assert!((v1 - e1).abs() < 1e-12 && (v2 - e2).abs() < 1e-12 && (v3 - e3).abs() < 1e-12);
    }

    #[test]
    fn a_strafe_and_a_circle_integrate_exactly() {
        let b = base();
        // Strafing left at 0.5 m/s for 2 s while facing +y: the base moves along −x, yaw unchanged.
        let start = Pose2 { x_m: 1.0, y_m: 2.0, theta_rad: std::f64::consts::FRAC_PI_2 };
        let wheels = b.wheel_speeds(BodyVelocity { vy_mps: 0.5, ..Default::default() });
        let end = integrate(&b, &start, wheels, 2.0);
        assert!((end.x_m - 0.0).abs() < 1e-12 && (end.y_m - 2.0).abs() < 1e-12, "{end:?}");
        assert!((end.theta_rad - start.theta_rad).abs() < 1e-12);
        // A full circle of radius 1 m in 100 steps ends where it started, whatever the step.
        let v = BodyVelocity { vx_mps: 1.0, vy_mps: 0.0, omega_radps: 1.0 };
        let wheels = b.wheel_speeds(v);
        let mut p = Pose2::default();
        for _ in 0..100 {
            p = integrate(&b, &p, wheels, std::f64::consts::TAU / 100.0);
        }
        assert!(p.x_m.abs() < 1e-9 && p.y_m.abs() < 1e-9 && p.theta_rad.abs() < 1e-9, "{p:?}");
    }

    proptest! {
        #[test]
        fn wheel_speeds_and_odometry_are_inverse(vx in -2.0..2.0f64, vy in -2.0..2.0f64, w in -3.0..3.0f64) {
            let b = base();
            let v = BodyVelocity { vx_mps: vx, vy_mps: vy, omega_radps: w };
            let back = b.body_velocity(b.wheel_speeds(v));
            prop_assert!((back.vx_mps - vx).abs() < 1e-12 && (back.vy_mps - vy).abs() < 1e-12);
            prop_assert!((back.omega_radps - w).abs() < 1e-12);
            let rates = b.body_velocity_from_rates(b.wheel_rates(v));
            prop_assert!((rates.vx_mps - vx).abs() < 1e-12);
        }

        #[test]
        fn world_velocity_rotates_the_body_velocity(vx in -2.0..2.0f64, vy in -2.0..2.0f64, th in -3.1..3.1f64) {
            let v = BodyVelocity { vx_mps: vx, vy_mps: vy, omega_radps: 0.1 };
            let w = world_velocity(th, v);
            prop_assert!(((w.x_mps.powi(2) + w.y_mps.powi(2)) - (vx * vx + vy * vy)).abs() < 1e-9);
            let b = base();
            let direct = b.wheel_speeds(v);
            let via_world = b.wheel_speeds_from_world(th, w);
            for i in 0..3 {
                prop_assert!((direct[i] - via_world[i]).abs() < 1e-12);
            }
        }

        #[test]
        fn between_undoes_compose(x in -5.0..5.0f64, y in -5.0..5.0f64, t in -3.0..3.0f64,
                                  dx in -1.0..1.0f64, dy in -1.0..1.0f64, dt in -1.0..1.0f64) {
            let a = Pose2 { x_m: x, y_m: y, theta_rad: t };
            let d = Pose2 { x_m: dx, y_m: dy, theta_rad: dt };
            let e = a.between(&a.compose(&d));
            prop_assert!((e.x_m - dx).abs() < 1e-9 && (e.y_m - dy).abs() < 1e-9);
            prop_assert!(wrap_angle(e.theta_rad - dt).abs() < 1e-9);
        }
    }
}
