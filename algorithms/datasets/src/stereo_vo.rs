//! GTSAM's stereo visual-odometry example data ("VO large", features from a KITTI drive).
//!
//! Files (whitespace separated):
//! - `VO_calibration.txt`: one line `fx fy skew u0 v0 baseline_m` (pixels, metres);
//! - `VO_stereo_factors_large.txt`: `frame_id landmark_id uL uR v X Y Z`, with (X, Y, Z) the
//!   triangulated landmark in that frame's camera optical frame (x right, y down, z forward), m;
//! - `VO_camera_poses_large.txt`: `frame_id` then 16 numbers, the row-major 4×4 camera-to-world
//!   transform (a VO estimate, not ground truth).
//!
//! The data set is non-commercial (KITTI) and is not part of this repository.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use nalgebra::Matrix4;

use crate::error::{DatasetError, FileErrorKind, LineErrorKind, Result};
use crate::lines::LineReader;

/// File name of the calibration.
pub const CALIBRATION_FILE: &str = "VO_calibration.txt";
/// File name of the stereo observations.
pub const FACTORS_FILE: &str = "VO_stereo_factors_large.txt";
/// File name of the camera poses.
pub const POSES_FILE: &str = "VO_camera_poses_large.txt";

/// Rectified stereo calibration (`VO_calibration.txt`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StereoCalibration {
    /// Focal length along u, px.
    pub fx_px: f64,
    /// Focal length along v, px.
    pub fy_px: f64,
    /// Skew, px.
    pub skew_px: f64,
    /// Principal point u0, px.
    pub cx_px: f64,
    /// Principal point v0, px.
    pub cy_px: f64,
    /// Stereo baseline, m.
    pub baseline_m: f64,
}

/// One stereo observation of a landmark (a line of `VO_stereo_factors_large.txt`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StereoFactor {
    /// Camera frame id.
    pub frame_id: u32,
    /// The data set's landmark id.
    pub landmark_id: u64,
    /// Column in the left image, px.
    pub u_left_px: f64,
    /// Column in the right image, px.
    pub u_right_px: f64,
    /// Row (both images), px.
    pub v_px: f64,
    /// Triangulated landmark in the camera optical frame (x right, y down, z forward), m.
    pub point_cam_m: [f64; 3],
}

/// A camera pose (a line of `VO_camera_poses_large.txt`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraPose {
    /// Camera frame id.
    pub frame_id: u32,
    /// Homogeneous camera-to-world transform (maps camera optical frame points to world), m.
    pub world_from_camera: Matrix4<f64>,
}

/// The observations of one camera frame.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoFrame {
    /// Camera frame id.
    pub frame_id: u32,
    /// The frame's observations, in file order.
    pub observations: Vec<StereoFactor>,
}

/// The three files of the data set.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoVo {
    /// The stereo calibration.
    pub calibration: StereoCalibration,
    /// All observations, in file order (the file is sorted by landmark, not by frame).
    pub factors: Vec<StereoFactor>,
    /// Camera poses, in file order, frame ids unique.
    pub poses: Vec<CameraPose>,
}

impl StereoVo {
    /// Loads `VO_calibration.txt`, `VO_stereo_factors_large.txt` and `VO_camera_poses_large.txt`
    /// from `dir`.
    pub fn load(dir: impl AsRef<Path>) -> Result<Self> {
        let dir = dir.as_ref();
        Ok(Self {
            calibration: read_calibration(dir.join(CALIBRATION_FILE))?,
            factors: read_stereo_factors(dir.join(FACTORS_FILE))?,
            poses: read_camera_poses(dir.join(POSES_FILE))?,
        })
    }

    /// The observations grouped by frame, frames in increasing id order.
    pub fn frames(&self) -> Vec<StereoFrame> {
        group_by_frame(&self.factors)
    }

    /// The pose of frame `frame_id`.
    pub fn pose(&self, frame_id: u32) -> Option<&CameraPose> {
        self.poses.iter().find(|p| p.frame_id == frame_id)
    }
}

/// Reads `VO_calibration.txt`: exactly one data line `fx fy skew u0 v0 baseline_m`.
pub fn read_calibration(path: impl AsRef<Path>) -> Result<StereoCalibration> {
    let path = path.as_ref();
    let mut reader = LineReader::open(path, true)?;
    let calibration = match reader.next_line()? {
        Some(line) => {
            let [fx_px, fy_px, skew_px, cx_px, cy_px, baseline_m] = line.numbers::<f64, 6>()?;
            StereoCalibration { fx_px, fy_px, skew_px, cx_px, cy_px, baseline_m }
        }
        None => return Err(DatasetError::File { path: path.to_path_buf(), kind: FileErrorKind::NoData }),
    };
    if let Some(line) = reader.next_line()? {
        return Err(line.error(LineErrorKind::ExtraDataLine));
    }
    Ok(calibration)
}

/// Reads `VO_stereo_factors_large.txt`: lines `frame_id landmark_id uL uR v X Y Z`.
pub fn read_stereo_factors(path: impl AsRef<Path>) -> Result<Vec<StereoFactor>> {
    let mut reader = LineReader::open(path.as_ref(), true)?;
    let mut factors = Vec::new();
    while let Some(line) = reader.next_line()? {
        let f = line.fields_exact::<8>()?;
        factors.push(StereoFactor {
            frame_id: line.id(1, f[0])?,
            landmark_id: line.id(2, f[1])?,
            u_left_px: line.number(3, f[2])?,
            u_right_px: line.number(4, f[3])?,
            v_px: line.number(5, f[4])?,
            point_cam_m: [line.number(6, f[5])?, line.number(7, f[6])?, line.number(8, f[7])?],
        });
    }
    Ok(factors)
}

/// Reads `VO_camera_poses_large.txt`: lines `frame_id` + 16 numbers (row-major 4×4
/// camera-to-world). Frame ids must be unique and the bottom row must be (0, 0, 0, 1).
pub fn read_camera_poses(path: impl AsRef<Path>) -> Result<Vec<CameraPose>> {
    let mut reader = LineReader::open(path.as_ref(), true)?;
    let mut first_line = HashMap::new();
    let mut poses = Vec::new();
    while let Some(line) = reader.next_line()? {
        let f = line.fields_exact::<17>()?;
        let frame_id: u32 = line.id(1, f[0])?;
        let mut m = [0.0; 16];
        for (i, v) in m.iter_mut().enumerate() {
            *v = line.number(i + 2, f[i + 1])?;
        }
        let bottom_row = [m[12], m[13], m[14], m[15]];
        if bottom_row != [0.0, 0.0, 0.0, 1.0] {
            return Err(line.error(LineErrorKind::NotHomogeneous { bottom_row }));
        }
        if let Some(&first) = first_line.get(&frame_id) {
            return Err(line.error(LineErrorKind::DuplicateFrame { frame_id, first_line: first }));
        }
        first_line.insert(frame_id, line.no);
        poses.push(CameraPose { frame_id, world_from_camera: Matrix4::from_row_slice(&m) });
    }
    Ok(poses)
}

/// Groups observations by frame: frames in increasing id order, each frame's observations in
/// their order in `factors`.
pub fn group_by_frame(factors: &[StereoFactor]) -> Vec<StereoFrame> {
    let mut frames: BTreeMap<u32, Vec<StereoFactor>> = BTreeMap::new();
    for f in factors {
        frames.entry(f.frame_id).or_default().push(*f);
    }
    frames.into_iter().map(|(frame_id, observations)| StereoFrame { frame_id, observations }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;
    use std::path::PathBuf;

    const CALIB: &str = "721.5377 721.5377 0.0 609.5593 172.854 0.537150588";
    const FACTORS: &str = "\
1 3 209.979 185.87 61.5418 -8.90263 -2.48003 16.0758
2 3 183.871 158.526 58.5288 -9.02175 -2.42293 15.2918
1 4 300 290 100 1 2 30
";
    const POSES: &str = "\
1  1  0  0  0  0  1  0  0 -0  0  1  0  0  0  0  1
2    0.999997 -0.00240146  0.00061075  0.00314304   0.0024019    0.999997 -0.00071977  0.00414596 \
-0.00060902 0.000721235           1     0.95998           0           0           0           1
";

    fn fixture(calib: &str, factors: &str, poses: &str) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        fs::write(dir.path().join(CALIBRATION_FILE), calib).unwrap();
        fs::write(dir.path().join(FACTORS_FILE), factors).unwrap();
        fs::write(dir.path().join(POSES_FILE), poses).unwrap();
        dir
    }

    #[test]
    fn parses_inline_fixture() {
        let dir = fixture(CALIB, FACTORS, POSES);
        let vo = StereoVo::load(dir.path()).unwrap();
        assert_eq!(
            vo.calibration,
            StereoCalibration {
                fx_px: 721.5377,
                fy_px: 721.5377,
                skew_px: 0.0,
                cx_px: 609.5593,
                cy_px: 172.854,
                baseline_m: 0.537150588
            }
        );
        assert_eq!(vo.factors.len(), 3);
        assert_eq!(
            vo.factors[0],
            StereoFactor {
                frame_id: 1,
                landmark_id: 3,
                u_left_px: 209.979,
                u_right_px: 185.87,
                v_px: 61.5418,
                point_cam_m: [-8.90263, -2.48003, 16.0758]
            }
        );
        let frames = vo.frames();
        assert_eq!(frames.iter().map(|f| f.frame_id).collect::<Vec<_>>(), [1, 2]);
        assert_eq!(frames[0].observations.iter().map(|o| o.landmark_id).collect::<Vec<_>>(), [3, 4]);
        assert_eq!(frames[1].observations.len(), 1);
        assert_eq!(vo.poses.len(), 2);
        assert_eq!(vo.pose(1).unwrap().world_from_camera, Matrix4::identity());
        let p2 = vo.pose(2).unwrap().world_from_camera;
        assert_eq!(p2[(0, 1)], -0.00240146); // row-major: second number is row 0, column 1
        assert_eq!(p2[(1, 0)], 0.0024019);
        assert_eq!(p2[(2, 3)], 0.95998);
    }

    fn err_rest(dir: &tempfile::TempDir, file: &str, e: DatasetError) -> String {
        let s = e.to_string();
        let prefix = format!("{}:", dir.path().join(file).display());
        s.strip_prefix(&prefix).unwrap_or_else(|| panic!("`{s}` does not start with `{prefix}`")).to_string()
    }

    #[test]
    fn malformed_lines() {
        let cases: [(&str, &str, &str, &str, &str); 7] = [
            (CALIBRATION_FILE, "1 2 3 4 5", FACTORS, POSES, "1: expected 6 numbers, got 5"),
            (
                CALIBRATION_FILE,
                "1 2 3 4 5 6\n1 2 3 4 5 6\n",
                FACTORS,
                POSES,
                "2: unexpected extra data line (the file holds exactly one)",
            ),
            (CALIBRATION_FILE, "\n", FACTORS, POSES, " no data lines"),
            (
                FACTORS_FILE,
                CALIB,
                "1 3 1 2 3 4 5 6\n1 3 1 2 3 4 5 nan\n",
                POSES,
                "2: column 8: `nan` is not a finite number",
            ),
            (FACTORS_FILE, CALIB, "1 3 1 2 3 4 5\n", POSES, "1: expected 8 numbers, got 7"),
            (
                POSES_FILE,
                CALIB,
                FACTORS,
                "1 1 0 0 0 0 1 0 0 0 0 1 0 0 0 1 1\n",
                "1: bottom row of the 4x4 transform is [0.0, 0.0, 1.0, 1.0], expected [0, 0, 0, 1]",
            ),
            (
                POSES_FILE,
                CALIB,
                FACTORS,
                "1 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n\n1 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n",
                "3: frame id 1 appears twice (first on line 1)",
            ),
        ];
        for (file, calib, factors, poses, expected) in cases {
            let dir = fixture(calib, factors, poses);
            let e = StereoVo::load(dir.path()).unwrap_err();
            assert_eq!(err_rest(&dir, file, e), expected);
        }
        let dir = fixture(CALIB, "x 3 1 2 3 4 5 6\n", POSES);
        let e = StereoVo::load(dir.path()).unwrap_err();
        assert_eq!(err_rest(&dir, FACTORS_FILE, e), "1: column 1: `x` is not a valid non-negative integer id");
    }

    #[test]
    fn full_data_set_if_present() {
        let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/stereo_vo_large");
        if !crate::shared_data_present(dir.join(FACTORS_FILE), "full_data_set_if_present") {
            return;
        }
        let vo = StereoVo::load(&dir).unwrap();
        assert_eq!(vo.calibration.baseline_m, 0.537150588);
        assert_eq!(vo.factors.len(), 8189);
        assert_eq!(vo.poses.len(), 26);
        let frames = vo.frames();
        assert_eq!(frames.len(), 26);
        assert_eq!(frames.iter().map(|f| f.frame_id).collect::<Vec<_>>(), (1..=26).collect::<Vec<u32>>());
        assert_eq!(frames.iter().map(|f| f.observations.len()).sum::<usize>(), 8189);
        let landmarks: std::collections::HashSet<u64> = vo.factors.iter().map(|f| f.landmark_id).collect();
        assert_eq!(landmarks.len(), 2634);
        assert!(vo.factors.iter().all(|f| f.point_cam_m[2] > 0.0 && f.u_left_px > f.u_right_px));
        assert_eq!(vo.pose(26).unwrap().world_from_camera[(2, 3)], 22.9037);
    }
}
