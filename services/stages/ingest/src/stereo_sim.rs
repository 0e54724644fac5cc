//! `source = "stereo_sim"`: the KITTI-like simulated stereo drive (`sim::road`).

use std::path::Path;

use nalgebra::Isometry3;
use shared_types::convert::{mat3_to_row_major, quat_to_xyzw};
use shared_types::{STEREO_HAS_PIXELS, STEREO_HAS_TRACK_ID, StereoObservation};

use crate::sources::*;

/// The KITTI-like simulated stereo drive (`sim::road`): one stereo message per published frame,
/// stamped at the frame's time; `ground_truth.tum` (the car's body pose) and `scene.json` (the
/// camera mounting) at the end.
pub struct StereoSimSource {
    sim: sim::road::RoadSim,
    track_ids: bool,
    features: u64,
}

impl StereoSimSource {
    /// Builds the drive and writes `scene.json` (the camera mounting) into `out_dir`.
    pub fn new(settings: &crate::StereoSimSettings, out_dir: &Path) -> Result<Self, SourceError> {
        let sim = sim::road::RoadSim::new(settings.drive.clone())?;
        let b = sim.body_from_camera();
        let scene = serde_json::json!({
            "drive": sim.config(),
            "landmarks": sim.landmark_count(),
            "path_length_m": sim.path_length_m(),
            "body_from_stereo_camera": {
                "translation_m": b.translation.vector.as_slice(),
                "rotation_xyzw": quat_to_xyzw(&b.rotation),
            },
        });
        write_scene(out_dir, &scene)?;
        Ok(Self { sim, track_ids: settings.track_ids, features: 0 })
    }
}

impl Source for StereoSimSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        let Some(frame) = self.sim.next() else { return Ok(None) };
        let flags = STEREO_HAS_PIXELS | if self.track_ids { STEREO_HAS_TRACK_ID } else { 0 };
        self.features += frame.observations.len() as u64;
        Ok(Some(Item::Stereo {
            stamp_ns: stamp_from_s(frame.t_s),
            observations: frame
                .observations
                .iter()
                .map(|o| StereoObservation {
                    point_cam_m: o.point_cam_m.into(),
                    covariance_cam_m2: mat3_to_row_major(&o.covariance_cam_m2),
                    pixels_ul_ur_v: [o.pixels.u_left_px, o.pixels.u_right_px, o.pixels.v_px],
                    source_id: o.track_id,
                    descriptor: [0; 32],
                    flags,
                    _reserved: 0,
                })
                .collect(),
        }))
    }

    fn progress(&self) -> Option<f64> {
        Some(self.sim.progress())
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        tracing::info!(
            dropped_frames = self.sim.dropped(),
            "{} frames dropped by the simulated camera, as configured",
            self.sim.dropped()
        );
        Ok(())
    }

    fn truth(&self, from: usize, out: &mut Vec<(f64, Isometry3<f64>)>) {
        out.extend(self.sim.truth().iter().skip(from).map(|t| (t.t_s, t.world_from_body)));
    }

    fn warts(&self) -> std::collections::BTreeMap<&'static str, u64> {
        [("frames_dropped_by_the_simulated_camera", self.sim.dropped() as u64)]
            .into_iter()
            .filter(|(_, n)| *n > 0)
            .collect()
    }

    fn describe(&self) -> String {
        let c = self.sim.config();
        format!(
            "simulated stereo drive (seed {}, {} frames, {} landmarks, {:.0} m{})",
            c.seed,
            c.frames,
            self.sim.landmark_count(),
            self.sim.path_length_m(),
            if self.track_ids { ", with track ids" } else { "" }
        )
    }
}
