//! Simulator configuration (the `[processes.ingest.settings.sim]` table of a pipeline config).
//! Every value has a default that gives the reference mission of `config/default.toml`.

use geometry::StereoRig;
use serde::{Deserialize, Serialize};
use validation::{Issues, Validate};

/// The whole simulator configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimConfig {
    /// Seed: the same seed gives the same mission and the same measurements.
    pub seed: u64,
    /// The world.
    pub scene: SceneConfig,
    /// The survey path and vehicle.
    pub mission: MissionConfig,
    /// The sensors.
    pub sensors: SensorsConfig,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            scene: SceneConfig::default(),
            mission: MissionConfig::default(),
            sensors: SensorsConfig::default(),
        }
    }
}

/// The world.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SceneConfig {
    /// Size of the surveyed area (x, y) from the origin, m.
    pub extent_m: [f64; 2],
    /// Mean depth of the seabed below the surface, m.
    pub seabed_depth_m: f64,
    /// Amplitude of the seabed undulation, m.
    pub terrain_amplitude_m: f64,
    /// Seabed slope along x (dz/dx).
    pub seabed_slope: f64,
    /// Number of rocks.
    pub rocks: usize,
    /// Rock radius range, m.
    pub rock_radius_m: [f64; 2],
    /// Wreck centre (x, y), m.
    pub wreck_center_xy_m: [f64; 2],
    /// Wreck (length, beam, height), m.
    pub wreck_size_m: [f64; 3],
    /// Wreck heading, deg.
    pub wreck_yaw_deg: f64,
    /// Landmarks per 100 m² of seabed.
    pub landmarks_per_100m2: f64,
    /// Landmarks per m² of rock and wreck surface.
    pub landmarks_per_m2_objects: f64,
    /// A band of x with no seabed landmarks (sand): feature-scarce stretch, m.
    pub barren_x_m: [f64; 2],
    /// Buoys (x, y, z), m (z 0 at the surface, below it when moored at depth); at least 3, not
    /// all on one line.
    pub buoys_m: Vec<[f64; 3]>,
}

impl Default for SceneConfig {
    fn default() -> Self {
        Self {
            extent_m: [120.0, 80.0],
            seabed_depth_m: 30.0,
            terrain_amplitude_m: 1.5,
            seabed_slope: 0.02,
            rocks: 30,
            rock_radius_m: [0.5, 2.0],
            wreck_center_xy_m: [60.0, 40.0],
            wreck_size_m: [24.0, 7.0, 5.0],
            wreck_yaw_deg: 25.0,
            landmarks_per_100m2: 30.0,
            landmarks_per_m2_objects: 1.2,
            barren_x_m: [95.0, 110.0],
            buoys_m: vec![
                [-10.0, -10.0, 0.0],
                [130.0, -10.0, 0.0],
                [130.0, 90.0, 0.0],
                [-10.0, 90.0, 0.0],
                [60.0, 100.0, 0.0],
            ],
        }
    }
}

/// The survey: lawnmower legs at alternating depths, between a descent and a shallow transit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MissionConfig {
    /// Start position (x, y, z), m.
    pub start_m: [f64; 3],
    /// Number of survey legs (along x).
    pub legs: usize,
    /// Length of a leg, m.
    pub leg_length_m: f64,
    /// Spacing between legs (along y), m.
    pub leg_spacing_m: f64,
    /// Depths of the legs, m below the surface (cycled).
    pub leg_depths_m: Vec<f64>,
    /// Depth of the transit at the end (open water, out of stereo range of the seabed), m.
    pub transit_depth_m: f64,
    /// Cruise speed, m/s.
    pub speed_mps: f64,
    /// Largest turn rate, rad/s.
    pub max_turn_rate_rps: f64,
    /// Amplitude of the roll oscillation that exercises the third angle, deg.
    pub roll_amplitude_deg: f64,
    /// Period of the roll oscillation, s.
    pub roll_period_s: f64,
    /// Largest pitch while changing depth, deg.
    pub max_pitch_deg: f64,
    /// Mission time limit, s (the mission also ends after the last waypoint).
    pub max_duration_s: f64,
}

impl Default for MissionConfig {
    fn default() -> Self {
        Self {
            start_m: [5.0, 5.0, -6.0],
            legs: 4,
            leg_length_m: 90.0,
            leg_spacing_m: 14.0,
            leg_depths_m: vec![22.0, 24.0],
            transit_depth_m: 6.0,
            speed_mps: 1.5,
            max_turn_rate_rps: 0.25,
            roll_amplitude_deg: 4.0,
            roll_period_s: 20.0,
            max_pitch_deg: 20.0,
            max_duration_s: 900.0,
        }
    }
}

/// All sensors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct SensorsConfig {
    /// Odometry / input.
    pub odometry: OdometryConfig,
    /// Stereo landmark observations.
    pub stereo: StereoConfig,
    /// Buoy ranges.
    pub buoys: BuoyConfig,
    /// Depth-camera point clouds.
    pub depth_camera: DepthCameraConfig,
    /// Pressure depth.
    pub pressure: PressureConfig,
    /// Magnetic compass (heading).
    pub compass: CompassConfig,
}

/// Odometry: the true input plus white noise.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OdometryConfig {
    /// Rate, Hz (also the simulation step).
    pub rate_hz: f64,
    /// Noise σ of the speed, m/s.
    pub speed_sigma_mps: f64,
    /// Noise σ of each rotation increment per step, rad.
    pub turn_sigma_rad: f64,
}

impl Default for OdometryConfig {
    fn default() -> Self {
        Self { rate_hz: 50.0, speed_sigma_mps: 0.05, turn_sigma_rad: 0.0015 }
    }
}

/// Stereo camera: landmark observations triangulated from noisy pixels.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StereoConfig {
    /// Rate, Hz.
    pub rate_hz: f64,
    /// The rectified pair.
    pub rig: StereoRig,
    /// Pixel noise σ on uL, uR, v, px.
    pub pixel_sigma_px: f64,
    /// Largest range of a usable landmark, m.
    pub max_range_m: f64,
    /// Smallest disparity kept, px.
    pub min_disparity_px: f64,
    /// Camera pitch below body x, deg.
    pub pitch_down_deg: f64,
    /// Camera position in the body frame, m.
    pub offset_m: [f64; 3],
    /// Spurious detections as a fraction of real ones.
    pub spurious_fraction: f64,
}

impl Default for StereoConfig {
    fn default() -> Self {
        Self {
            rate_hz: 15.0,
            rig: StereoRig { f_px: 420.0, cx_px: 320.0, cy_px: 240.0, baseline_m: 0.3, width_px: 640, height_px: 480 },
            pixel_sigma_px: 0.5,
            max_range_m: 14.0,
            min_disparity_px: 6.0,
            pitch_down_deg: 35.0,
            offset_m: [0.5, 0.0, -0.2],
            spurious_fraction: 0.05,
        }
    }
}

/// Acoustic ranges to the surface buoys.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BuoyConfig {
    /// Rate, Hz.
    pub rate_hz: f64,
    /// Range noise σ, m.
    pub sigma_m: f64,
    /// Constant range bias (all buoys), m.
    pub bias_m: f64,
    /// Probability that a range is an outlier.
    pub outlier_probability: f64,
    /// Outliers are off by at least this much, m.
    pub outlier_min_m: f64,
    /// Outliers are off by up to this much, m (uniform between the two).
    pub outlier_max_m: f64,
    /// Outliers read long or short with equal odds (multipath locks and non-line-of-sight
    /// paths), instead of only long (a range that would go below 0.05 m reads long).
    pub outliers_both_signs: bool,
    /// The ranges that would be outliers are left out instead (a reference: "the same mission
    /// with the outliers removed", what a perfect outlier detector would leave). Every random
    /// number is drawn as with the outliers, so the other ranges are the same, noise and all.
    pub outliers_removed: bool,
    /// Probability that a range is missing.
    pub dropout_probability: f64,
}

impl Default for BuoyConfig {
    fn default() -> Self {
        Self {
            rate_hz: 1.0,
            sigma_m: 0.3,
            bias_m: 0.4,
            outlier_probability: 0.04,
            outlier_min_m: 0.0,
            outlier_max_m: 12.0,
            outliers_both_signs: false,
            outliers_removed: false,
            dropout_probability: 0.1,
        }
    }
}

/// Depth camera: a pinhole ray-cast into the scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DepthCameraConfig {
    /// Rate, Hz (0 = off).
    pub rate_hz: f64,
    /// Image width, px (up to 640).
    pub width_px: u32,
    /// Image height, px (up to 480).
    pub height_px: u32,
    /// Horizontal field of view, deg.
    pub hfov_deg: f64,
    /// Largest range, m.
    pub max_range_m: f64,
    /// Range noise σ, m.
    pub noise_sigma_m: f64,
    /// Camera pitch below body x, deg.
    pub pitch_down_deg: f64,
    /// Ray-casting threads.
    pub threads: usize,
}

impl Default for DepthCameraConfig {
    fn default() -> Self {
        Self {
            rate_hz: 5.0,
            width_px: 160,
            height_px: 120,
            hfov_deg: 70.0,
            max_range_m: 14.0,
            noise_sigma_m: 0.01,
            pitch_down_deg: 40.0,
            threads: 2,
        }
    }
}

/// Pressure depth sensor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PressureConfig {
    /// Rate, Hz (0 = off).
    pub rate_hz: f64,
    /// Noise σ, m.
    pub sigma_m: f64,
}

impl Default for PressureConfig {
    fn default() -> Self {
        Self { rate_hz: 10.0, sigma_m: 0.05 }
    }
}

/// Magnetic compass: the body's yaw (heading of body x in the world, about world z) plus white
/// noise.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CompassConfig {
    /// Rate, Hz (0 = off).
    pub rate_hz: f64,
    /// Noise σ, deg.
    pub sigma_deg: f64,
}

impl Default for CompassConfig {
    fn default() -> Self {
        Self { rate_hz: 10.0, sigma_deg: 2.0 }
    }
}

impl Validate for SimConfig {
    fn validate(&self, issues: &mut Issues) {
        let s = &self.sensors;
        let pos = |x: f64| x.is_finite() && x > 0.0;
        let nonneg = |x: f64| x.is_finite() && x >= 0.0;
        issues.check(
            pos(s.odometry.rate_hz) && s.odometry.rate_hz <= 1000.0,
            "sensors.odometry.rate_hz",
            "must be in (0, 1000]",
        );
        issues.check(nonneg(s.odometry.speed_sigma_mps), "sensors.odometry.speed_sigma_mps", "must be >= 0");
        issues.check(nonneg(s.odometry.turn_sigma_rad), "sensors.odometry.turn_sigma_rad", "must be >= 0");
        issues.check(
            nonneg(s.stereo.rate_hz) && s.stereo.rate_hz <= s.odometry.rate_hz,
            "sensors.stereo.rate_hz",
            "must be in [0, odometry rate]",
        );
        issues.check(
            pos(s.stereo.rig.f_px) && pos(s.stereo.rig.baseline_m),
            "sensors.stereo.rig",
            "focal length and baseline must be > 0",
        );
        issues.check(
            s.stereo.rig.width_px > 0 && s.stereo.rig.height_px > 0,
            "sensors.stereo.rig",
            "image size must be > 0",
        );
        issues.check(pos(s.stereo.pixel_sigma_px), "sensors.stereo.pixel_sigma_px", "must be > 0");
        issues.check(pos(s.stereo.max_range_m), "sensors.stereo.max_range_m", "must be > 0");
        issues.check(
            (0.0..=1.0).contains(&s.stereo.spurious_fraction),
            "sensors.stereo.spurious_fraction",
            "must be in [0, 1]",
        );
        issues.check(
            nonneg(s.buoys.rate_hz) && s.buoys.rate_hz <= s.odometry.rate_hz,
            "sensors.buoys.rate_hz",
            "must be in [0, odometry rate]",
        );
        issues.check(pos(s.buoys.sigma_m), "sensors.buoys.sigma_m", "must be > 0");
        issues.check(
            (0.0..=1.0).contains(&s.buoys.outlier_probability),
            "sensors.buoys.outlier_probability",
            "must be in [0, 1]",
        );
        issues.check(
            (0.0..=1.0).contains(&s.buoys.dropout_probability),
            "sensors.buoys.dropout_probability",
            "must be in [0, 1]",
        );
        let d = &s.depth_camera;
        issues.check(
            nonneg(d.rate_hz) && d.rate_hz <= s.odometry.rate_hz,
            "sensors.depth_camera.rate_hz",
            "must be in [0, odometry rate]",
        );
        issues.check(
            (1..=640).contains(&d.width_px) && (1..=480).contains(&d.height_px),
            "sensors.depth_camera",
            "resolution must be at most 640×480",
        );
        issues.check(d.hfov_deg > 1.0 && d.hfov_deg < 170.0, "sensors.depth_camera.hfov_deg", "must be in (1, 170)");
        issues.check((1..=64).contains(&d.threads), "sensors.depth_camera.threads", "must be 1..=64");
        issues.check(
            nonneg(s.compass.rate_hz) && s.compass.rate_hz <= s.odometry.rate_hz,
            "sensors.compass.rate_hz",
            "must be >= 0 and <= sensors.odometry.rate_hz",
        );
        issues.check(nonneg(s.compass.sigma_deg), "sensors.compass.sigma_deg", "must be >= 0");
        issues.check(
            nonneg(s.pressure.rate_hz) && s.pressure.rate_hz <= s.odometry.rate_hz,
            "sensors.pressure.rate_hz",
            "must be in [0, odometry rate]",
        );
        issues.check(self.scene.buoys_m.len() >= 3, "scene.buoys_m", "at least 3 buoys");
        issues.check(
            s.buoys.outlier_min_m.is_finite()
                && s.buoys.outlier_min_m >= 0.0
                && s.buoys.outlier_min_m <= s.buoys.outlier_max_m,
            "sensors.buoys.outlier_min_m",
            "must be in [0, sensors.buoys.outlier_max_m]",
        );
        issues.check(self.scene.extent_m.iter().all(|x| pos(*x)), "scene.extent_m", "must be > 0");
        issues.check(
            self.scene.rock_radius_m[0] > 0.0 && self.scene.rock_radius_m[0] <= self.scene.rock_radius_m[1],
            "scene.rock_radius_m",
            "must be 0 < min <= max",
        );
        issues.check(self.mission.legs >= 1, "mission.legs", "at least 1");
        issues.check(!self.mission.leg_depths_m.is_empty(), "mission.leg_depths_m", "at least one depth");
        issues.check(pos(self.mission.speed_mps), "mission.speed_mps", "must be > 0");
        issues.check(pos(self.mission.max_duration_s), "mission.max_duration_s", "must be > 0");
    }
}
