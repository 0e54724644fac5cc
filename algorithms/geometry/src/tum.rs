//! TUM trajectory files (`t tx ty tz qx qy qz qw`, t in s, one pose per line, `#` comments): the
//! format evo and the TUM RGB-D tools read. The pose is `world_from_body`.

use std::io::Write;
use std::path::Path;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

/// Appends one pose as a TUM line (with its newline) to `out`.
pub fn push_tum_line(out: &mut String, t_s: f64, world_from_body: &Isometry3<f64>) {
    use std::fmt::Write as _;
    let v = world_from_body.translation.vector;
    let q = world_from_body.rotation.quaternion().coords; // (x, y, z, w)
    let _ = writeln!(out, "{t_s:.9} {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}", v.x, v.y, v.z, q[0], q[1], q[2], q[3]);
}

/// Writes a trajectory.
pub fn write_tum<'a>(path: &Path, poses: impl Iterator<Item = (f64, &'a Isometry3<f64>)>) -> std::io::Result<()> {
    let mut w = std::io::BufWriter::new(std::fs::File::create(path)?);
    let mut line = String::with_capacity(128);
    for (t, p) in poses {
        line.clear();
        push_tum_line(&mut line, t, p);
        w.write_all(line.as_bytes())?;
    }
    w.flush()
}

/// An error reading a TUM file: it names the file, and the line where there is one.
#[derive(Debug, thiserror::Error)]
pub enum TumError {
    /// The file could not be read.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A line is not `t tx ty tz qx qy qz qw` in finite numbers.
    #[error("{}:{line}: {what}", path.display())]
    Line {
        /// The file.
        path: std::path::PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        what: String,
    },
}

/// Reads a trajectory; errors name the file and line. A last line without its newline that is
/// not a whole pose is a line still being appended (ground truth grows while a run goes on) and
/// is left out.
pub fn read_tum(path: &Path) -> Result<Vec<(f64, Isometry3<f64>)>, TumError> {
    let mut text = std::fs::read_to_string(path).map_err(|source| TumError::Io { path: path.to_path_buf(), source })?;
    let line_error = |line: usize, what: String| TumError::Line { path: path.to_path_buf(), line, what };
    if !text.ends_with('\n')
        && let Some(cut) = text.rfind('\n').map(|i| i + 1).or(Some(0))
        && text[cut..].split_whitespace().count() < 8
    {
        text.truncate(cut);
    }
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
            .map_err(|e: std::num::ParseFloatError| line_error(i + 1, e.to_string()))?;
        if v.len() != 8 || v.iter().any(|x| !x.is_finite()) {
            return Err(line_error(i + 1, "expected 8 finite numbers (t tx ty tz qx qy qz qw)".into()));
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
        assert!(matches!(e, TumError::Line { line: 2, .. }), "{e}");
        assert!(e.to_string().contains("t.tum:2: expected 8 finite numbers"), "{e}");
        // A last line still being appended (no newline, not a whole pose) is left out; a whole
        // last pose without its newline is read.
        std::fs::write(&p, "1 0 0 0 0 0 0 1\n2 0.5 0").unwrap();
        assert_eq!(read_tum(&p).unwrap().len(), 1);
        std::fs::write(&p, "1 0 0 0 0 0 0 1\n2 0.5 0 0 0 0 0 1").unwrap();
        assert_eq!(read_tum(&p).unwrap().len(), 2);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
