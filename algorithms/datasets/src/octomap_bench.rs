//! The scene of the OctoMap reference benchmark (`../shared/bench/octomap`, written by its
//! `gen_scene.py --out DIR`): `scans.bin`, the depth frames as world points with each frame's
//! sensor origin, and `scene.txt`, the solids the frames were ray-cast against (a room's inside,
//! axis-aligned boxes, vertical capped cylinders), which are the scene's truth.
//!
//! `scans.bin` (little-endian): the magic `OCTSCAN1`, `u32` frames, `f32` maximum range, then per
//! frame the `f32` sensor origin (x, y, z, m), a `u32` point count and that many `f32` points
//! (x, y, z, m, world frame). `scene.txt`: `#` comments, then lines `room xmin ymin zmin xmax
//! ymax zmax`, `box xmin ymin zmin xmax ymax zmax name`, `cyl cx cy radius zmin zmax name` and
//! `camera ...` (the intrinsics, not read).

use std::path::Path;

use crate::error::{DatasetError, FileErrorKind, LineErrorKind, Result};
use crate::lines::{LineReader, io_error};

/// One depth frame of `scans.bin`.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchFrame {
    /// The sensor's position, world frame, m.
    pub origin_m: [f32; 3],
    /// The points, world frame, m.
    pub points_m: Vec<[f32; 3]>,
}

/// A solid of the scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum BenchSolid {
    /// An axis-aligned box, corners in m.
    Box {
        /// Lowest corner.
        min_m: [f64; 3],
        /// Highest corner.
        max_m: [f64; 3],
    },
    /// A vertical capped cylinder.
    Cylinder {
        /// Axis position (x, y), m.
        centre_m: [f64; 2],
        /// Radius, m.
        radius_m: f64,
        /// Bottom and top, m.
        z_m: [f64; 2],
    },
}

impl BenchSolid {
    /// The axis-aligned bounds (lowest, highest corner), m.
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        match *self {
            BenchSolid::Box { min_m, max_m } => (min_m, max_m),
            BenchSolid::Cylinder { centre_m: c, radius_m: r, z_m: z } => {
                ([c[0] - r, c[1] - r, z[0]], [c[0] + r, c[1] + r, z[1]])
            }
        }
    }

    /// Whether `p` lies in the solid or within `tol_m` of it.
    pub fn near(&self, p: [f64; 3], tol_m: f64) -> bool {
        match *self {
            BenchSolid::Box { min_m, max_m } => (0..3).all(|k| p[k] >= min_m[k] - tol_m && p[k] <= max_m[k] + tol_m),
            BenchSolid::Cylinder { centre_m: c, radius_m: r, z_m: z } => {
                (p[0] - c[0]).hypot(p[1] - c[1]) <= r + tol_m && p[2] >= z[0] - tol_m && p[2] <= z[1] + tol_m
            }
        }
    }
}

/// What the scene holds at a point ([`BenchScene::at`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BenchTruth {
    /// Object `i` (touching solids are one object: the table and the box on it).
    Object(u32),
    /// One of the room's four walls.
    Wall,
    /// The room's floor.
    Floor,
    /// The room's ceiling.
    Ceiling,
    /// Nothing of the scene.
    Nothing,
}

/// The scene of `scene.txt`.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchScene {
    /// The room's inside (free): lowest and highest corner, m; its faces are the floor, the
    /// ceiling and the walls.
    pub room_m: ([f64; 3], [f64; 3]),
    /// The solids with their names, and the object each belongs to (touching solids share one).
    pub solids: Vec<(String, BenchSolid, u32)>,
}

impl BenchScene {
    /// What lies at `p` within `tol_m`: a solid's object first, then a wall, the floor, the
    /// ceiling.
    pub fn at(&self, p: [f64; 3], tol_m: f64) -> BenchTruth {
        if let Some((_, _, object)) = self.solids.iter().find(|(_, s, _)| s.near(p, tol_m)) {
            return BenchTruth::Object(*object);
        }
        let (a, b) = self.room_m;
        if !(0..3).all(|k| p[k] >= a[k] - tol_m && p[k] <= b[k] + tol_m) {
            return BenchTruth::Nothing;
        }
        if (0..2).any(|k| (p[k] - a[k]).abs() <= tol_m || (p[k] - b[k]).abs() <= tol_m) {
            BenchTruth::Wall
        } else if (p[2] - a[2]).abs() <= tol_m {
            BenchTruth::Floor
        } else if (p[2] - b[2]).abs() <= tol_m {
            BenchTruth::Ceiling
        } else {
            BenchTruth::Nothing
        }
    }

    /// The number of objects.
    pub fn objects(&self) -> usize {
        let mut ids: Vec<u32> = self.solids.iter().map(|s| s.2).collect();
        ids.sort_unstable();
        ids.dedup();
        ids.len()
    }
}

fn file_error(path: &Path, what: String) -> DatasetError {
    DatasetError::File { path: path.to_path_buf(), kind: FileErrorKind::OctomapBench { what } }
}

/// Reads `scans.bin`.
pub fn read_bench_scans(path: impl AsRef<Path>) -> Result<Vec<BenchFrame>> {
    let path = path.as_ref();
    let b = std::fs::read(path).map_err(|e| io_error(path, e))?;
    if b.get(..8) != Some(b"OCTSCAN1".as_slice()) {
        return Err(file_error(path, "not an OCTSCAN1 file (its first 8 bytes)".into()));
    }
    let word = |at: usize| -> Result<[u8; 4]> {
        b.get(at..at + 4)
            .and_then(|w| w.try_into().ok())
            .ok_or_else(|| file_error(path, format!("truncated at byte {at} of {}", b.len())))
    };
    let frames = u32::from_le_bytes(word(8)?) as usize;
    let mut at = 16;
    let mut out = Vec::with_capacity(frames.min(1 << 16));
    for frame in 0..frames {
        let mut origin_m = [0.0f32; 3];
        for (k, o) in origin_m.iter_mut().enumerate() {
            *o = f32::from_le_bytes(word(at + 4 * k)?);
        }
        let n = u32::from_le_bytes(word(at + 12)?) as usize;
        at += 16;
        let end = at.checked_add(n.saturating_mul(12)).filter(|e| *e <= b.len()).ok_or_else(|| {
            file_error(path, format!("frame {frame}: {n} points do not fit in the {} bytes", b.len()))
        })?;
        let points_m: Vec<[f32; 3]> = b[at..end]
            .chunks_exact(12)
            .map(|c| std::array::from_fn(|k| f32::from_le_bytes([c[4 * k], c[4 * k + 1], c[4 * k + 2], c[4 * k + 3]])))
            .collect();
        if let Some(i) = points_m.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(file_error(path, format!("frame {frame}: point {i} is not finite")));
        }
        if !origin_m.iter().all(|v| v.is_finite()) {
            return Err(file_error(path, format!("frame {frame}: the origin is not finite")));
        }
        at = end;
        out.push(BenchFrame { origin_m, points_m });
    }
    if at != b.len() {
        return Err(file_error(path, format!("{} bytes after the {frames} frames", b.len() - at)));
    }
    Ok(out)
}

/// Reads `scene.txt`; touching solids (bounds that meet) are one object.
pub fn read_bench_scene(path: impl AsRef<Path>) -> Result<BenchScene> {
    let path = path.as_ref();
    let mut reader = LineReader::open(path, true)?;
    let mut room = None;
    let mut solids: Vec<(String, BenchSolid)> = vec![];
    while let Some(line) = reader.next_line()? {
        let fields: Vec<&str> = line.fields().collect();
        let numbers = |n: usize| -> Result<Vec<f64>> {
            if fields.len() < n + 1 {
                return Err(line.error(LineErrorKind::ColumnCount { expected: n + 1, got: fields.len() }));
            }
            (1..=n).map(|c| line.number::<f64>(c + 1, fields[c])).collect()
        };
        let name = |n: usize| fields.get(n + 1).map_or_else(String::new, |s| s.to_string());
        match fields.first().copied() {
            Some("room") => {
                let v = numbers(6)?;
                room = Some(([v[0], v[1], v[2]], [v[3], v[4], v[5]]));
            }
            Some("box") => {
                let v = numbers(6)?;
                solids.push((name(6), BenchSolid::Box { min_m: [v[0], v[1], v[2]], max_m: [v[3], v[4], v[5]] }));
            }
            Some("cyl") => {
                let v = numbers(5)?;
                solids.push((
                    name(5),
                    BenchSolid::Cylinder { centre_m: [v[0], v[1]], radius_m: v[2], z_m: [v[3], v[4]] },
                ));
            }
            // The camera's intrinsics (`camera W H fx fy cx cy stride max min`): not needed here.
            Some("camera") => {}
            Some(other) => {
                return Err(line.error(LineErrorKind::UnknownRecord { text: other.to_string() }));
            }
            None => {}
        }
    }
    let room_m = room.ok_or_else(|| file_error(path, "no `room` line".into()))?;
    let mut object: Vec<u32> = (0..solids.len() as u32).collect();
    for i in 0..solids.len() {
        for j in 0..i {
            let ((a0, a1), (b0, b1)) = (solids[i].1.bounds(), solids[j].1.bounds());
            if (0..3).all(|k| a0[k] <= b1[k] + 1e-6 && b0[k] <= a1[k] + 1e-6) {
                let (from, to) = (object[i], object[j]);
                object.iter_mut().filter(|o| **o == from).for_each(|o| *o = to);
            }
        }
    }
    // Objects numbered 0.. in the order of their first solid.
    let mut first: Vec<u32> = vec![];
    let solids = solids
        .into_iter()
        .zip(object)
        .map(|((name, s), o)| {
            let id = first.iter().position(|f| *f == o).unwrap_or_else(|| {
                first.push(o);
                first.len() - 1
            });
            (name, s, id as u32)
        })
        .collect();
    Ok(BenchScene { room_m, solids })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn a_scene_file_gives_its_room_and_solids_and_touching_solids_are_one_object() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("scene.txt");
        std::fs::write(
            &path,
            "# comment\nroom 0 0 0 10 6 3\nbox 2 1 0 3.2 1.8 0.75 table\nbox 2.3 1.2 0.75 2.6 1.5 1.05 box_on_table\n\
             cyl 6.5 2.5 0.25 0 3 pillar\n",
        )
        .unwrap();
        let s = read_bench_scene(&path).unwrap();
        assert_eq!(s.solids.iter().map(|x| x.2).collect::<Vec<_>>(), [0, 0, 1]);
        assert_eq!(s.objects(), 2);
        assert_eq!(s.at([2.5, 1.5, 1.0], 0.05), BenchTruth::Object(0));
        assert_eq!(s.at([6.7, 2.5, 2.0], 0.05), BenchTruth::Object(1));
        assert_eq!(s.at([0.01, 3.0, 1.0], 0.05), BenchTruth::Wall);
        assert_eq!(s.at([5.0, 3.0, 0.02], 0.05), BenchTruth::Floor);
        assert_eq!(s.at([5.0, 3.0, 2.98], 0.05), BenchTruth::Ceiling);
        assert_eq!(s.at([5.0, 3.0, 1.5], 0.05), BenchTruth::Nothing);
        std::fs::write(&path, "room 0 0 0 10 6 3\ncone 1 2 3\n").unwrap();
        let e = read_bench_scene(&path).unwrap_err();
        assert_eq!(e.line(), Some(2), "{e}");
        assert!(e.to_string().contains("cone"), "{e}");
        std::fs::write(&path, "box 0 0 0 1 1 x\n").unwrap();
        assert!(read_bench_scene(&path).unwrap_err().to_string().contains(":1: column 7"));
    }

    #[test]
    fn a_scans_file_gives_its_frames_and_a_truncated_one_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("scans.bin");
        let mut b = b"OCTSCAN1".to_vec();
        b.extend(1u32.to_le_bytes());
        b.extend(6.0f32.to_le_bytes());
        for v in [1.0f32, 2.0, 1.5] {
            b.extend(v.to_le_bytes());
        }
        b.extend(2u32.to_le_bytes());
        for v in [3.0f32, 2.0, 0.0, 3.0, 2.5, 0.0] {
            b.extend(v.to_le_bytes());
        }
        std::fs::File::create(&path).unwrap().write_all(&b).unwrap();
        let f = read_bench_scans(&path).unwrap();
        assert_eq!(f, [BenchFrame { origin_m: [1.0, 2.0, 1.5], points_m: vec![[3.0, 2.0, 0.0], [3.0, 2.5, 0.0]] }]);
        std::fs::write(&path, &b[..b.len() - 4]).unwrap();
        let e = read_bench_scans(&path).unwrap_err();
        assert!(e.to_string().contains("frame 0: 2 points do not fit"), "{e}");
        std::fs::write(&path, b"OCTSCAN2").unwrap();
        assert!(read_bench_scans(&path).unwrap_err().to_string().contains("not an OCTSCAN1 file"));
    }
}
