//! OctoMap's plain-text point clouds: `scan.dat` (one `x y z` point per line, metres, sensor at
//! the origin) and the graph-style variant read by OctoMap's `ScanGraph::readPlainASCII`, where a
//! line `NODE x y z roll pitch yaw` starts a new scan taken from that sensor pose and the point
//! lines after it are in the sensor frame.
//!
//! Files ending in `.bz2` are decompressed on the fly. Blank lines and `#` comment lines are
//! skipped. Points before the first `NODE` line (or in a file without any) form a scan without a
//! pose, i.e. with the sensor at the origin of the world frame.

use std::path::Path;

use nalgebra::{Isometry3, Translation3, UnitQuaternion};

use crate::error::{LineErrorKind, Result};
use crate::lines::LineReader;

/// A 6-DoF sensor pose as OctoMap writes it (`octomath::Pose6D`): position and roll-pitch-yaw
/// with R = Rz(yaw)·Ry(pitch)·Rx(roll), mapping sensor-frame points to the world frame.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Pose6D {
    /// x, m (world frame).
    pub x_m: f64,
    /// y, m (world frame).
    pub y_m: f64,
    /// z, m (world frame).
    pub z_m: f64,
    /// Rotation about x, rad.
    pub roll_rad: f64,
    /// Rotation about y, rad.
    pub pitch_rad: f64,
    /// Rotation about z, rad.
    pub yaw_rad: f64,
}

impl Pose6D {
    /// The pose as a rigid transform `world_from_sensor`.
    pub fn world_from_sensor(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(self.x_m, self.y_m, self.z_m),
            UnitQuaternion::from_euler_angles(self.roll_rad, self.pitch_rad, self.yaw_rad),
        )
    }
}

/// One scan: its sensor pose and its points.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Scan {
    /// Sensor pose (`world_from_sensor`) from a `NODE` line; `None` means the sensor is at the
    /// world origin with identity orientation.
    pub pose: Option<Pose6D>,
    /// Points (x, y, z), m, in the sensor frame (the world frame when `pose` is `None`).
    pub points: Vec<[f32; 3]>,
}

impl Scan {
    /// The sensor pose as a rigid transform (identity when `pose` is `None`).
    pub fn world_from_sensor(&self) -> Isometry3<f64> {
        self.pose.map_or_else(Isometry3::identity, |p| p.world_from_sensor())
    }

    /// The points transformed into the world frame.
    pub fn points_world(&self) -> Vec<[f32; 3]> {
        let Some(pose) = self.pose else { return self.points.clone() };
        let t = pose.world_from_sensor();
        self.points
            .iter()
            .map(|p| {
                let q = t * nalgebra::Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                [q.x as f32, q.y as f32, q.z as f32]
            })
            .collect()
    }
}

/// Reads an OctoMap plain-text scan file (plain or `.bz2`).
///
/// Returns at least one scan: a file without `NODE` lines is one scan with `pose: None`; with
/// `NODE` lines, each starts a new scan (a scan without a pose comes first only if there are
/// point lines before the first `NODE`).
pub fn read_scan_file(path: impl AsRef<Path>) -> Result<Vec<Scan>> {
    let mut reader = LineReader::open(path.as_ref(), true)?;
    let mut scans = vec![Scan::default()];
    while let Some(line) = reader.next_line()? {
        if let Some(rest) = line.text.strip_prefix("NODE")
            && (rest.is_empty() || rest.starts_with(|c: char| c.is_ascii_whitespace()))
        {
            let mut v = [0.0f64; 6];
            let mut got = 0;
            for field in rest.split_ascii_whitespace() {
                if got < 6 {
                    v[got] = line.number(got + 2, field)?;
                }
                got += 1;
            }
            if got != 6 {
                return Err(line.error(LineErrorKind::NodeColumnCount { got }));
            }
            let [x_m, y_m, z_m, roll_rad, pitch_rad, yaw_rad] = v;
            let pose = Pose6D { x_m, y_m, z_m, roll_rad, pitch_rad, yaw_rad };
            // Drop the leading pose-less scan if nothing preceded the first NODE.
            if scans.len() == 1 && scans[0].pose.is_none() && scans[0].points.is_empty() {
                scans.clear();
            }
            scans.push(Scan { pose: Some(pose), points: Vec::new() });
        } else {
            let p = line.numbers::<f32, 3>()?;
            match scans.last_mut() {
                Some(scan) => scan.points.push(p),
                None => scans.push(Scan { pose: None, points: vec![p] }),
            }
        }
    }
    Ok(scans)
}

/// Reads an OctoMap plain-text scan file and returns all points in the world frame (each scan's
/// points transformed by its pose).
pub fn read_scan_points_world(path: impl AsRef<Path>) -> Result<Vec<[f32; 3]>> {
    Ok(read_scan_file(path)?.iter().flat_map(|s| s.points_world()).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;
    use std::fs;
    use std::io::Write;

    #[test]
    fn octomap_example_scan() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/octomap/scan.dat.bz2");
        let scans = read_scan_file(&path).unwrap();
        assert_eq!(scans.len(), 1);
        assert_eq!(scans[0].pose, None);
        let pts = &scans[0].points;
        assert_eq!(pts.len(), 88_206);
        assert_eq!(pts[0], [-0.0434742, -4.82982, 0.499645]);
        assert_eq!(pts[1], [0.0295245, -4.82834, 0.541775]);
    }

    #[test]
    fn plain_text_without_node() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("scan.dat");
        fs::write(&path, "# comment\n1 2 3\n\n4.5e0 -5 6\r\n").unwrap();
        let scans = read_scan_file(&path).unwrap();
        assert_eq!(scans, [Scan { pose: None, points: vec![[1.0, 2.0, 3.0], [4.5, -5.0, 6.0]] }]);
        fs::write(&path, "").unwrap();
        assert_eq!(read_scan_file(&path).unwrap(), [Scan::default()]);
    }

    #[test]
    fn node_lines_start_scans_with_poses() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("graph.dat");
        let text = format!("NODE 1 0 -0.5 0 0 0\n1 0 0\n2 0 0\nNODE 0 0 0 0 0 {FRAC_PI_2}\nNODE 10 0 0 0 0 0\n1 1 1\n");
        fs::write(&path, text).unwrap();
        let scans = read_scan_file(&path).unwrap();
        assert_eq!(scans.len(), 3);
        assert_eq!(scans[0].pose.unwrap().x_m, 1.0);
        assert_eq!(scans[0].pose.unwrap().z_m, -0.5);
        assert_eq!(scans[0].points, [[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]);
        assert_eq!(scans[1].pose.unwrap().yaw_rad, FRAC_PI_2);
        assert!(scans[1].points.is_empty());
        assert_eq!(scans[2].points, [[1.0, 1.0, 1.0]]);
        assert_eq!(scans[0].points_world(), [[2.0, 0.0, -0.5], [3.0, 0.0, -0.5]]);
        assert_eq!(scans[2].points_world(), [[11.0, 1.0, 1.0]]);
        // Yaw of 90°: sensor x maps to world y.
        let t = Pose6D { x_m: 0.0, y_m: 0.0, z_m: 0.0, roll_rad: 0.0, pitch_rad: 0.0, yaw_rad: FRAC_PI_2 };
        let q = t.world_from_sensor() * nalgebra::Point3::new(1.0, 0.0, 0.0);
        assert!((q - nalgebra::Point3::new(0.0, 1.0, 0.0)).norm() < 1e-12);
        assert_eq!(read_scan_points_world(&path).unwrap().len(), 3);
    }

    #[test]
    fn points_before_first_node_form_a_poseless_scan() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("mixed.dat");
        fs::write(&path, "1 2 3\nNODE 0 0 0 0 0 0\n4 5 6\n").unwrap();
        let scans = read_scan_file(&path).unwrap();
        assert_eq!(scans.len(), 2);
        assert_eq!(scans[0].pose, None);
        assert!(scans[1].pose.is_some());
    }

    #[test]
    fn bz2_is_detected_by_extension() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.dat.bz2");
        let mut enc = bzip2::write::BzEncoder::new(fs::File::create(&path).unwrap(), bzip2::Compression::fast());
        enc.write_all(b"NODE 0 0 0 0 0 0\n1 2 3\n").unwrap();
        enc.finish().unwrap();
        let scans = read_scan_file(&path).unwrap();
        assert_eq!(scans[0].points, [[1.0, 2.0, 3.0]]);
        // The same bytes without the extension are not text.
        let raw = dir.path().join("s.dat");
        fs::copy(&path, &raw).unwrap();
        assert!(read_scan_file(&raw).is_err());
    }

    #[test]
    fn malformed_lines() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.dat");
        let cases = [
            ("1 2 3\n1 2\n", "2: expected 3 numbers, got 2"),
            ("1 2 3\n1 2 3 4\n", "2: expected 3 numbers, got 4"),
            ("1 2 x\n", "1: column 3: `x` is not a number"),
            ("1 NaN 3\n", "1: column 2: `NaN` is not a finite number"),
            ("NODE 1 2 3 4 5\n", "1: NODE line: expected 6 numbers (x y z roll pitch yaw), got 5"),
            ("NODE 1 2 3 4 5 inf\n", "1: column 7: `inf` is not a finite number"),
            ("NODES 1 2\n", "1: column 1: `NODES` is not a number"),
            ("1 2 1e39\n", "1: column 3: `1e39` is not a finite number"),
        ];
        for (text, expected) in cases {
            fs::write(&path, text).unwrap();
            let e = read_scan_file(&path).unwrap_err().to_string();
            assert_eq!(e, format!("{}:{expected}", path.display()));
        }
    }

    #[test]
    fn truncated_bz2_is_an_io_error() {
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/octomap/scan.dat.bz2");
        let bytes = fs::read(&src).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cut.dat.bz2");
        fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        let e = read_scan_file(&path).unwrap_err();
        assert!(matches!(e, crate::DatasetError::Io { .. }), "{e}");
    }
}
