//! `source = "sim"`: the simulated underwater mission (`sim`), its sensors in data-time order.

use std::path::Path;

use nalgebra::Isometry3;
use shared_types::convert::{mat3_to_row_major, quat_to_xyzw};
use shared_types::{
    BuoyRange, DepthReading, HeadingReading, OdometryInput, STEREO_HAS_DESCRIPTOR, STEREO_HAS_PIXELS, StereoObservation,
};

use crate::sources::*;

/// The built-in simulator as a source.
pub struct SimSource {
    sim: sim::Simulator,
    expected_s: f64,
}

impl SimSource {
    /// Builds the simulator and writes `scene.json` into `out_dir`.
    pub fn new(config: sim::SimConfig, out_dir: &Path) -> Result<Self, SourceError> {
        let sim = sim::Simulator::new(config)?;
        let scene = serde_json::json!({
            "scene": sim.scene(),
            "mission": sim.config().mission,
            "sensors": sim.config().sensors,
            "seed": sim.config().seed,
            "body_from_stereo_camera": {
                "translation_m": sim.body_from_stereo().translation.vector.as_slice(),
                "rotation_xyzw": quat_to_xyzw(&sim.body_from_stereo().rotation),
            },
        });
        write_scene(out_dir, &scene)?;
        let expected_s = sim.expected_duration_s();
        Ok(Self { sim, expected_s })
    }

    /// Converts one simulator event into a wire item.
    pub fn to_item(event: sim::SimEvent) -> Item {
        match event {
            sim::SimEvent::Odometry(o) => {
                let mut input_covariance = [0.0; 16];
                for (i, v) in o.variances.iter().enumerate() {
                    input_covariance[i * 5] = *v;
                }
                Item::Odometry {
                    stamp_ns: stamp_from_s(o.t_s),
                    input: OdometryInput {
                        v_mps: o.input.v_mps,
                        delta_theta_rad: o.input.delta_theta_rad.into(),
                        dt_s: o.input.dt_s,
                        input_covariance,
                    },
                }
            }
            sim::SimEvent::Stereo(f) => Item::Stereo {
                stamp_ns: stamp_from_s(f.t_s),
                observations: f
                    .observations
                    .iter()
                    .map(|o| StereoObservation {
                        point_cam_m: o.point_cam_m.into(),
                        covariance_cam_m2: mat3_to_row_major(&o.covariance_cam_m2),
                        pixels_ul_ur_v: [o.pixels.u_left_px, o.pixels.u_right_px, o.pixels.v_px],
                        source_id: o.landmark_id.unwrap_or(u64::MAX),
                        descriptor: o.descriptor,
                        flags: STEREO_HAS_DESCRIPTOR | STEREO_HAS_PIXELS,
                        _reserved: 0,
                    })
                    .collect(),
            },
            sim::SimEvent::Buoys(b) => Item::BuoyRanges {
                stamp_ns: stamp_from_s(b.t_s),
                ranges: b
                    .ranges
                    .iter()
                    .map(|r| BuoyRange { buoy_id: r.buoy_id, _reserved: 0, range_m: r.range_m, sigma_m: r.sigma_m })
                    .collect(),
            },
            sim::SimEvent::Cloud(c) => Item::Cloud {
                stamp_ns: stamp_from_s(c.t_s),
                world_from_sensor: Some(c.world_from_sensor),
                points: c.points_sensor_m,
            },
            sim::SimEvent::Compass(c) => Item::Heading {
                stamp_ns: stamp_from_s(c.t_s),
                reading: HeadingReading { yaw_rad: c.yaw_rad, sigma_rad: c.sigma_rad },
            },
            sim::SimEvent::Pressure(p) => Item::Depth {
                stamp_ns: stamp_from_s(p.t_s),
                reading: DepthReading { depth_m: p.depth_m, sigma_m: p.sigma_m },
            },
        }
    }
}

impl Source for SimSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        Ok(self.sim.next().map(Self::to_item))
    }

    fn progress(&self) -> Option<f64> {
        Some((self.sim.time_s() / self.expected_s).min(1.0))
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        Ok(())
    }

    fn truth(&self, from: usize, out: &mut Vec<(f64, Isometry3<f64>)>) {
        out.extend(self.sim.truth().iter().skip(from).map(|t| (t.t_s, t.world_from_body)));
    }

    fn describe(&self) -> String {
        format!(
            "simulated mission (seed {}, {} landmarks, ~{:.0} s of data)",
            self.sim.config().seed,
            self.sim.scene().landmark_count,
            self.expected_s
        )
    }
}
