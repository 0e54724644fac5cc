//! TUM trajectory files (`t tx ty tz qx qy qz qw`, t in s, one pose per line, `#` comments): the
//! format evo and the TUM RGB-D tools read. The pose is `world_from_body`.

use std::io::Write;
use std::path::Path;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

/// Writes a trajectory.
pub fn write_tum<'a>(path: &Path, poses: impl Iterator<Item = (f64, &'a Isometry3<f64>)>) -> std::io::Result<()> {
    let mut w = std::io::BufWriter::new(std::fs::File::create(path)?);
    for (t, p) in poses {
        let v = p.translation.vector;
        let q = p.rotation.quaternion().coords; // (x, y, z, w)
        writeln!(w, "{t:.9} {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}", v.x, v.y, v.z, q[0], q[1], q[2], q[3])?;
    }
    w.flush()
}

/// Reads a trajectory; errors name the file and line.
pub fn read_tum(path: &Path) -> Result<Vec<(f64, Isometry3<f64>)>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut out = vec![];
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v: Vec<f64> = line
            .split_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|e| format!("{}:{}: {e}", path.display(), i + 1))?;
        if v.len() != 8 || v.iter().any(|x| !x.is_finite()) {
            return Err(format!("{}:{}: expected 8 finite numbers (t tx ty tz qx qy qz qw)", path.display(), i + 1));
        }
        let q = UnitQuaternion::from_quaternion(Quaternion::new(v[7], v[4], v[5], v[6]));
        out.push((v[0], Isometry3::from_parts(Translation3::new(v[1], v[2], v[3]), q)));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_trajectory_survives_a_round_trip_and_bad_lines_name_their_line() {
        let dir = std::env::temp_dir().join(format!("tum-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("t.tum");
        let poses = [
            (1.5, Isometry3::new(nalgebra::Vector3::new(1.0, -2.0, 3.0), nalgebra::Vector3::new(0.1, 0.2, -0.3))),
            (2.0, Isometry3::identity()),
        ];
        write_tum(&p, poses.iter().map(|(t, p)| (*t, p))).unwrap();
        let back = read_tum(&p).unwrap();
        assert_eq!(back.len(), 2);
        for ((t0, p0), (t1, p1)) in poses.iter().zip(&back) {
            assert!((t0 - t1).abs() < 1e-9);
            assert!((p0.translation.vector - p1.translation.vector).norm() < 1e-6);
            assert!(p0.rotation.angle_to(&p1.rotation) < 1e-8);
        }
        std::fs::write(&p, "# c\n1 2 3\n").unwrap();
        let e = read_tum(&p).unwrap_err();
        assert!(e.contains("t.tum:2"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
