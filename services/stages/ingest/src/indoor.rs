//! The simulated indoor mission of the omni-directional robot (`source = "indoor"`,
//! `sim::indoor`): planar odometry from its wheel encoders (50 Hz, with the wheel speeds and body
//! velocity), 2-D laser scans (10 Hz) and depth-camera clouds (2 Hz, in the camera's optical frame,
//! with the camera's true pose in the header for reference maps; a mapper with `pose_source =
//! "grid_slam"` places them at the SLAM pose instead). Ground truth as it goes;
//! `scene.json` holds the scene's boxes (the true occupancy) for evaluating the 3-D map.

use std::collections::VecDeque;
use std::path::Path;

use nalgebra::Isometry3;
use shared_types::{LASER_MAX_IS_NO_RETURN, LaserScanHeader, ODOM_HAS_VELOCITY, ODOM_HAS_WHEELS, PlanarOdometry};
use sim::indoor::{IndoorConfig, IndoorEvent, IndoorSim};

use crate::{Item, Source, SourceError};

fn stamp_ns(t_s: f64) -> u64 {
    (t_s * 1e9).round() as u64
}

/// The source.
pub struct IndoorSource {
    sim: IndoorSim,
    queue: VecDeque<Item>,
    t_s: f64,
}

impl IndoorSource {
    /// A source for `cfg`; writes `scene.json` into `out_dir`.
    pub fn new(cfg: IndoorConfig, out_dir: &Path) -> Result<Self, SourceError> {
        let sim = IndoorSim::new(cfg)?;
        let scene = serde_json::json!({
            "kind": "indoor",
            "boxes": sim.scene().boxes,
            "body_from_camera": {
                "offset_m": sim.config().depth.offset_m,
                "pitch_down_deg": sim.config().depth.pitch_down_deg,
            },
        });
        crate::sources::write_scene_json(out_dir, &scene)?;
        Ok(Self { sim, queue: VecDeque::new(), t_s: 0.0 })
    }

    fn to_item(&self, e: IndoorEvent) -> Item {
        match e {
            IndoorEvent::Odometry { t_s, pose, velocity, wheel_speeds_mps } => Item::PlanarOdometry {
                stamp_ns: stamp_ns(t_s),
                odometry: PlanarOdometry {
                    position_m: [pose.x_m, pose.y_m],
                    yaw_rad: pose.theta_rad,
                    velocity: [velocity.vx_mps, velocity.vy_mps, velocity.omega_radps],
                    wheel_speeds_mps,
                    flags: ODOM_HAS_WHEELS | ODOM_HAS_VELOCITY,
                    _reserved: 0,
                },
            },
            IndoorEvent::Laser { t_s, ranges } => {
                let l = &self.sim.config().laser;
                let header = LaserScanHeader {
                    angle_min_rad: -std::f64::consts::PI,
                    angle_increment_rad: std::f64::consts::TAU / l.beams as f64,
                    range_min_m: 0.05,
                    range_max_m: l.max_range_m,
                    body_from_laser_xy_m: l.offset_m,
                    body_from_laser_yaw_rad: 0.0,
                    beams: ranges.len() as u32,
                    flags: LASER_MAX_IS_NO_RETURN,
                    ..Default::default()
                };
                Item::Laser { stamp_ns: stamp_ns(t_s), header, ranges }
            }
            // The true camera pose goes along (CLOUD_HAS_POSE), as the underwater simulator's does:
            // a mapper with `pose_source = "cloud"` builds the reference map from it.
            IndoorEvent::Cloud { t_s, world_from_camera, points } => {
                Item::Cloud { stamp_ns: stamp_ns(t_s), world_from_sensor: Some(world_from_camera), points }
            }
        }
    }
}

impl Source for IndoorSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        if self.queue.is_empty() {
            let Some(events) = self.sim.next_events() else { return Ok(None) };
            for e in events {
                self.t_s = e.t_s();
                let item = self.to_item(e);
                self.queue.push_back(item);
            }
        }
        Ok(self.queue.pop_front())
    }

    fn progress(&self) -> Option<f64> {
        Some((self.t_s / self.sim.duration_s()).min(1.0))
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        Ok(())
    }

    fn truth(&self, from: usize, out: &mut Vec<(f64, Isometry3<f64>)>) {
        out.extend(self.sim.truth().iter().skip(from).map(|(t, p)| (*t, IndoorSim::iso(p))));
    }

    fn describe(&self) -> String {
        let c = self.sim.config();
        format!(
            "simulated indoor mission of an omni-directional robot (seed {}, {}, ~{:.0} s; laser {} beams at {} Hz, \
             depth {}x{} at {} Hz)",
            c.seed,
            match c.building {
                sim::indoor::Building::TwoRooms => format!("two rooms and a corridor, {} laps", c.laps),
                sim::indoor::Building::Ring => "a 148 m corridor ring, one lap and 12 m more".to_string(),
            },
            self.sim.duration_s(),
            c.laser.beams,
            c.laser.rate_hz,
            c.depth.width_px,
            c.depth.height_px,
            c.depth.rate_hz
        )
    }
}
