//! `source = "stereo_vo"`: stereo features in the stereo_vo format (GTSAM's VO example, KITTI).

use std::path::Path;

use geometry::StereoPixels;
use nalgebra::Isometry3;
use shared_types::convert::mat3_to_row_major;
use shared_types::{STEREO_HAS_PIXELS, STEREO_HAS_TRACK_ID, StereoObservation};

use crate::sources::*;

/// Replay of stereo landmark observations (stereo_vo_large format): one message per frame,
/// stamped `frame_id / rate_hz`; the covariance of each point follows from the pixel noise.
pub struct StereoVoSource {
    frames: Vec<datasets::StereoFrame>,
    poses: Vec<datasets::stereo_vo::CameraPose>,
    rig: geometry::StereoRig,
    sigma_px: f64,
    rate_hz: f64,
    next: usize,
    rejected: u64,
    dir: std::path::PathBuf,
    track_ids: bool,
}

impl StereoVoSource {
    /// Loads the data set in `dir`.
    pub fn load(dir: &Path, settings: &crate::StereoVoSettings) -> Result<Self, SourceError> {
        let vo = datasets::StereoVo::load(dir)?;
        let c = vo.calibration;
        let rig = geometry::StereoRig {
            f_px: c.fx_px,
            cx_px: c.cx_px,
            cy_px: c.cy_px,
            baseline_m: c.baseline_m,
            width_px: (2.0 * c.cx_px).ceil() as u32,
            height_px: (2.0 * c.cy_px).ceil() as u32,
        };
        Ok(Self {
            frames: datasets::group_by_frame(&vo.factors),
            poses: vo.poses,
            rig,
            sigma_px: settings.pixel_sigma_px,
            rate_hz: settings.rate_hz,
            next: 0,
            rejected: 0,
            dir: dir.to_path_buf(),
            track_ids: settings.track_ids,
        })
    }
}

impl Source for StereoVoSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        let Some(frame) = self.frames.get(self.next) else { return Ok(None) };
        self.next += 1;
        let mut observations = Vec::with_capacity(frame.observations.len());
        for f in &frame.observations {
            let px = StereoPixels { u_left_px: f.u_left_px, u_right_px: f.u_right_px, v_px: f.v_px };
            match self.rig.triangulation_covariance(&px, self.sigma_px) {
                Ok(cov) => observations.push(StereoObservation {
                    point_cam_m: f.point_cam_m,
                    covariance_cam_m2: mat3_to_row_major(&cov),
                    pixels_ul_ur_v: [f.u_left_px, f.u_right_px, f.v_px],
                    source_id: f.landmark_id,
                    descriptor: [0; 32],
                    flags: STEREO_HAS_PIXELS | if self.track_ids { STEREO_HAS_TRACK_ID } else { 0 },
                    _reserved: 0,
                }),
                Err(e) => {
                    self.rejected += 1;
                    tracing::warn!(frame = frame.frame_id, landmark = f.landmark_id, "observation skipped: {e}");
                }
            }
        }
        Ok(Some(Item::Stereo { stamp_ns: stamp_from_s(frame.frame_id as f64 / self.rate_hz), observations }))
    }

    fn progress(&self) -> Option<f64> {
        Some(self.next as f64 / self.frames.len().max(1) as f64)
    }

    fn finish(&mut self, out_dir: &Path) -> Result<(), SourceError> {
        // The data set's own VO poses, for comparison with the SLAM trajectory (e.g. with evo).
        let poses: Vec<(f64, Isometry3<f64>)> = self
            .poses
            .iter()
            .map(|p| {
                let m = p.world_from_camera;
                let rot = nalgebra::Rotation3::from_matrix(&m.fixed_view::<3, 3>(0, 0).into_owned());
                let iso = Isometry3::from_parts(
                    nalgebra::Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
                    nalgebra::UnitQuaternion::from_rotation_matrix(&rot),
                );
                (p.frame_id as f64 / self.rate_hz, iso)
            })
            .collect();
        let path = out_dir.join("vo_camera_poses.tum");
        write_tum(&path, poses.iter().map(|(t, p)| (*t, p))).map_err(io_at(&path))?;
        Ok(())
    }

    fn warts(&self) -> std::collections::BTreeMap<&'static str, u64> {
        [("observations_rejected", self.rejected)].into_iter().filter(|(_, n)| *n > 0).collect()
    }

    fn describe(&self) -> String {
        format!(
            "stereo replay from {} ({} frames, {} observations)",
            self.dir.display(),
            self.frames.len(),
            self.frames.iter().map(|f| f.observations.len()).sum::<usize>()
        )
    }
}
