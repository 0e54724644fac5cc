//! The vehicle's attitude for turning body-frame odometry into the filter's planar motion
//! (docs/EQUATIONS.md §5.0).
//!
//! The filter's heading ψ and horizontal position need the *world* yaw increment and the
//! *horizontal* speed; odometry gives the body-frame rotation increment δθ and the speed along the
//! body's x axis. For a vehicle that pitches by θ (changing depth) and rolls by φ, the yaw rate is
//! (ω_y·sin φ + ω_z·cos φ)/cos θ and the horizontal speed v·cos θ: taking ω_z as the yaw rate and v
//! as the horizontal speed errs by 1 − cos θ (6 % at 20° of pitch) in every turn and every metre,
//! slowly, which the filter's white process noise does not describe.
//!
//! [`LevelledAttitude`] integrates δθ into an attitude, R ← R·R(δθ) ([3D] eq 6 with erratum §9),
//! and lets its roll and pitch relax towards level with time constant τ: a complementary filter
//! (Mahony, Hamel & Pflimlin 2008) whose low-frequency reference is the vehicle's hydrostatic trim
//! (an underwater vehicle is ballasted to lie level; without that reference the gyro-integrated
//! roll and pitch drift without bound). Only its increments are used: the yaw difference across
//! a step and the horizontal share of the body's x axis. An attitude sensor would replace τ's
//! assumption with a measurement.

use nalgebra::{UnitQuaternion, Vector3};

/// The attitude integrated from body-frame rotation increments, levelled with time constant
/// `time_constant_s` (0: no attitude, the body's z increment taken as the yaw increment and the
/// speed as horizontal, for a vehicle that stays level such as a ground robot).
#[derive(Debug, Clone, PartialEq)]
pub struct LevelledAttitude {
    world_from_body: UnitQuaternion<f64>,
    time_constant_s: f64,
}

/// One odometry step in the filter's terms ([`LevelledAttitude::step`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanarStep {
    /// World yaw increment over the step, rad.
    pub yaw_increment_rad: f64,
    /// The horizontal share of the body's forward speed, cos θ (1 when level).
    pub horizontal_fraction: f64,
}

impl LevelledAttitude {
    /// Level, with time constant `time_constant_s` (≥ 0).
    pub fn new(time_constant_s: f64) -> Self {
        Self { world_from_body: UnitQuaternion::identity(), time_constant_s: time_constant_s.max(0.0) }
    }

    /// Roll and pitch now, rad.
    pub fn roll_pitch_rad(&self) -> (f64, f64) {
        let (roll, pitch, _) = self.world_from_body.euler_angles();
        (roll, pitch)
    }

    /// Takes the body-frame rotation increment `delta_theta_rad` (applied as Rz·Ry·Rx of its
    /// angles, as the odometry message defines it) over `dt_s`; returns the world yaw increment
    /// and the horizontal fraction of the forward speed at the start of the step (the speed moves
    /// the body along its x axis at the current attitude, [3D] eq 1-7).
    pub fn step(&mut self, delta_theta_rad: &Vector3<f64>, dt_s: f64) -> PlanarStep {
        if self.time_constant_s <= 0.0 {
            return PlanarStep { yaw_increment_rad: delta_theta_rad.z, horizontal_fraction: 1.0 };
        }
        let before = self.world_from_body;
        let d = delta_theta_rad;
        let after = before * UnitQuaternion::from_euler_angles(d.x, d.y, d.z);
        let yaw = |q: &UnitQuaternion<f64>| {
            let x = q * Vector3::x();
            x.y.atan2(x.x)
        };
        let yaw_increment_rad = crate::wrap_angle(yaw(&after) - yaw(&before));
        let horizontal_fraction = (before * Vector3::x()).xy().norm();
        // Roll and pitch relax towards level: exp(−dt/τ) per step.
        let (roll, pitch, heading) = after.euler_angles();
        let k = (-dt_s.max(0.0) / self.time_constant_s).exp();
        self.world_from_body = UnitQuaternion::from_euler_angles(roll * k, pitch * k, heading);
        PlanarStep { yaw_increment_rad, horizontal_fraction }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn off_it_takes_the_body_increments_as_they_are() {
        let mut a = LevelledAttitude::new(0.0);
        let s = a.step(&Vector3::new(0.1, 0.2, 0.03), 0.02);
        assert_eq!(s, PlanarStep { yaw_increment_rad: 0.03, horizontal_fraction: 1.0 });
    }

    #[test]
    fn a_turn_while_pitched_turns_the_heading_by_more_than_the_body_z_increment() {
        // Pitch up 20° (about body y), then yaw at 0.2 rad/s in the world: the body sees the
        // world yaw rate split between its y and z axes, ω_z = ψ̇·cos θ.
        let mut a = LevelledAttitude::new(1e9);
        let pitch = 20f64.to_radians();
        a.step(&Vector3::new(0.0, -pitch, 0.0), 0.02);
        let (_, p) = a.roll_pitch_rad();
        assert!((p + pitch).abs() < 1e-9, "{p}");
        let (dt, rate) = (0.02, 0.2);
        let (mut yaw, mut horiz) = (0.0, 0.0);
        for _ in 0..500 {
            // The body-frame increment of a world-z rotation at this attitude.
            let (_, p, _) = a.world_from_body.euler_angles();
            let w = Vector3::new(-rate * p.sin(), 0.0, rate * p.cos());
            let s = a.step(&(w * dt), dt);
            yaw += s.yaw_increment_rad;
            horiz = s.horizontal_fraction;
        }
        assert!((yaw - rate * 10.0).abs() < 1e-3, "world yaw {yaw} after 10 s at {rate} rad/s");
        assert!((horiz - pitch.cos()).abs() < 1e-3, "{horiz}");
        // The body z increments alone give cos θ of the turn: 6 % short.
        let body_z: f64 = rate * 10.0 * pitch.cos();
        assert!((yaw - body_z) > 0.1, "{yaw} against {body_z}");
    }

    #[test]
    fn roll_and_pitch_relax_to_level_with_the_time_constant() {
        let mut a = LevelledAttitude::new(10.0);
        a.step(&Vector3::new(0.2, 0.1, 0.0), 0.0);
        let (r0, p0) = a.roll_pitch_rad();
        for _ in 0..500 {
            a.step(&Vector3::zeros(), 0.02);
        }
        let (r, p) = a.roll_pitch_rad();
        let k = (-1.0f64).exp();
        assert!((r - r0 * k).abs() < 1e-3 && (p - p0 * k).abs() < 1e-3, "after τ: {r}, {p} from {r0}, {p0}");
    }
}
