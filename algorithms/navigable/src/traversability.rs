//! A 2.5-D traversability grid from a [`Discovery`]: what a planner for a vehicle on (or just
//! above) the ground takes. One cell per column of voxels (x, y at the voxels' resolution), with
//! its class, height and slope:
//! - **navigable**: the column holds a voxel of a navigable region and no obstacle voxel; the
//!   height is that voxel's plane at the cell's centre, the slope its normal's angle to world z
//!   (of the largest region's voxel when several regions pass through the column, the highest
//!   of them when one region does twice);
//! - **obstacle**: the column holds an obstacle or a wall voxel; the height is the highest mean
//!   of the points of those voxels (the slope is not defined: NaN);
//! - **unknown**: neither (height and slope NaN).
//!
//! Written as the map_server files of the 2-D grid (`<stem>.pgm` + `<stem>.yaml`: navigable
//! white 254, obstacle black 0, unknown grey 205, `mode: trinary`), plus two float layers in
//! PFM (`<stem>_height.pfm`, `<stem>_slope.pfm`: one little-endian `f32` a cell, rows from the
//! lowest y up, as PFM stores them; NaN where undefined), which OpenCV and most image tools
//! read.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use crate::{Discovery, NavigableError, PointAccumulator, VoxelClass, io_err};

/// What a cell is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CellClass {
    /// Nothing classified in the column.
    Unknown,
    /// Part of a navigable region.
    Navigable,
    /// Part of an obstacle.
    Obstacle,
}

/// A 2.5-D traversability grid (see the module's documentation). Row-major, the first row at
/// the lowest y (as nav_msgs/OccupancyGrid).
#[derive(Debug, Clone, PartialEq)]
pub struct TraversabilityGrid {
    /// Cells along x.
    pub width: usize,
    /// Cells along y.
    pub height: usize,
    /// Cell side, m (the voxels').
    pub resolution_m: f64,
    /// World position of the lower-left corner of cell (0, 0), m.
    pub origin_m: (f64, f64),
    /// Class per cell.
    pub class: Vec<CellClass>,
    /// Height per cell, world z, m (NaN: unknown).
    pub height_m: Vec<f32>,
    /// Slope per navigable cell, deg (NaN elsewhere).
    pub slope_deg: Vec<f32>,
}

/// The files [`TraversabilityGrid::write`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct TraversabilityFiles {
    /// The classes (map_server image).
    pub pgm: PathBuf,
    /// Its map_server description.
    pub yaml: PathBuf,
    /// The height layer.
    pub height_pfm: PathBuf,
    /// The slope layer.
    pub slope_pfm: PathBuf,
}

impl TraversabilityGrid {
    /// The grid of `d` (computed over `acc`): every column with a classified voxel in a region
    /// or an obstacle, and the unknown cells between them.
    pub fn from_discovery(acc: &PointAccumulator, d: &Discovery) -> TraversabilityGrid {
        let res = acc.resolution_m();
        // Per column: (region index, height, slope) of the navigable voxel kept.
        let mut ground: HashMap<[i32; 2], (usize, f64, f64)> = HashMap::new();
        for (r, region) in d.regions.iter().enumerate() {
            for k in &region.voxels {
                let Some(VoxelClass::Navigable(p)) = d.classes.get(k) else { continue };
                let (x, y) = ((k[0] as f64 + 0.5) * res, (k[1] as f64 + 0.5) * res);
                if p.normal.z.abs() < 1e-6 {
                    continue;
                }
                // The plane n·(q − c) = 0 at (x, y).
                let z = p.centroid_m.z
                    - (p.normal.x * (x - p.centroid_m.x) + p.normal.y * (y - p.centroid_m.y)) / p.normal.z;
                let e = ground.entry([k[0], k[1]]).or_insert((r, z, p.slope_deg()));
                if r < e.0 || (r == e.0 && z > e.1) {
                    *e = (r, z, p.slope_deg());
                }
            }
        }
        let mut blocked: HashMap<[i32; 2], f64> = HashMap::new();
        for o in d.obstacles.iter().map(|o| &o.voxels).chain(d.walls.iter().map(|w| &w.voxels)) {
            for k in o {
                let z = acc.cells().get(k).and_then(|s| s.mean()).map_or((k[2] as f64 + 0.5) * res, |m| m.z);
                let e = blocked.entry([k[0], k[1]]).or_insert(z);
                *e = e.max(z);
            }
        }
        let columns = ground.keys().chain(blocked.keys());
        let (mut lo, mut hi) = ([i32::MAX; 2], [i32::MIN; 2]);
        for c in columns {
            for a in 0..2 {
                lo[a] = lo[a].min(c[a]);
                hi[a] = hi[a].max(c[a]);
            }
        }
        if lo[0] > hi[0] {
            return TraversabilityGrid {
                width: 0,
                height: 0,
                resolution_m: res,
                origin_m: (0.0, 0.0),
                class: vec![],
                height_m: vec![],
                slope_deg: vec![],
            };
        }
        let (w, h) = ((hi[0] - lo[0] + 1) as usize, (hi[1] - lo[1] + 1) as usize);
        let mut g = TraversabilityGrid {
            width: w,
            height: h,
            resolution_m: res,
            origin_m: (lo[0] as f64 * res, lo[1] as f64 * res),
            class: vec![CellClass::Unknown; w * h],
            height_m: vec![f32::NAN; w * h],
            slope_deg: vec![f32::NAN; w * h],
        };
        let cell = |c: &[i32; 2]| (c[1] - lo[1]) as usize * w + (c[0] - lo[0]) as usize;
        for (c, (_, z, slope)) in &ground {
            let i = cell(c);
            g.class[i] = CellClass::Navigable;
            g.height_m[i] = *z as f32;
            g.slope_deg[i] = *slope as f32;
        }
        for (c, z) in &blocked {
            let i = cell(c);
            g.class[i] = CellClass::Obstacle;
            g.height_m[i] = *z as f32;
            g.slope_deg[i] = f32::NAN;
        }
        g
    }

    /// The cell of world point (x, y) (may lie outside the grid).
    pub fn cell_of(&self, x_m: f64, y_m: f64) -> (i64, i64) {
        (
            ((x_m - self.origin_m.0) / self.resolution_m).floor() as i64,
            ((y_m - self.origin_m.1) / self.resolution_m).floor() as i64,
        )
    }

    /// Index of cell (x, y) in the layers, if inside.
    pub fn index(&self, x: i64, y: i64) -> Option<usize> {
        (x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height)
            .then(|| y as usize * self.width + x as usize)
    }

    /// Cells by class: (navigable, obstacle, unknown).
    pub fn counts(&self) -> (usize, usize, usize) {
        let n = |c: CellClass| self.class.iter().filter(|x| **x == c).count();
        (n(CellClass::Navigable), n(CellClass::Obstacle), n(CellClass::Unknown))
    }

    /// Writes `<stem>.pgm`, `<stem>.yaml`, `<stem>_height.pfm` and `<stem>_slope.pfm` into `dir`.
    pub fn write(&self, dir: &Path, stem: &str) -> Result<TraversabilityFiles, NavigableError> {
        let files = TraversabilityFiles {
            pgm: dir.join(format!("{stem}.pgm")),
            yaml: dir.join(format!("{stem}.yaml")),
            height_pfm: dir.join(format!("{stem}_height.pfm")),
            slope_pfm: dir.join(format!("{stem}_slope.pfm")),
        };
        let mut bytes = format!(
            "P5\n# traversability: navigable 254, obstacle 0, unknown 205; {} m/cell\n{} {}\n255\n",
            self.resolution_m, self.width, self.height
        )
        .into_bytes();
        // map_server's image: the first row is the highest y.
        for y in (0..self.height).rev() {
            bytes.extend(self.class[y * self.width..(y + 1) * self.width].iter().map(|c| match c {
                CellClass::Navigable => 254u8,
                CellClass::Obstacle => 0,
                CellClass::Unknown => 205,
            }));
        }
        std::fs::write(&files.pgm, bytes).map_err(io_err(&files.pgm))?;
        let yaml = format!(
            "image: {stem}.pgm\nmode: trinary\nresolution: {}\norigin: [{}, {}, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n# float layers (PFM, rows from the lowest y up, NaN where undefined): {stem}_height.pfm (world z, m), {stem}_slope.pfm (deg, navigable cells)\n",
            self.resolution_m, self.origin_m.0, self.origin_m.1
        );
        std::fs::write(&files.yaml, yaml).map_err(io_err(&files.yaml))?;
        for (path, layer) in [(&files.height_pfm, &self.height_m), (&files.slope_pfm, &self.slope_deg)] {
            // PFM: "Pf" (one channel), size, a negative scale for little-endian, then the rows
            // from the bottom up.
            let mut bytes = format!("Pf\n{} {}\n-1.0\n", self.width, self.height).into_bytes();
            bytes.reserve(layer.len() * 4);
            for v in layer {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
            std::fs::write(path, bytes).map_err(io_err(path))?;
        }
        Ok(files)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{NsdConfig, discover};
    use nalgebra::Vector3;

    #[test]
    fn a_sloped_floor_with_a_box_gives_heights_slopes_and_the_box_blocked() {
        let res = 0.1;
        let mut acc = PointAccumulator::new(res);
        // A floor rising 10° along x over [0, 2] × [0, 1] m, points every centimetre, with a
        // 0.4 m cube standing on it at x, y in [0.8, 1.2] × [0.3, 0.7].
        let z0 = |x: f64| 0.033 + x * 10f64.to_radians().tan();
        let inside = |x: f64, y: f64| (0.8..1.2).contains(&x) && (0.3..0.7).contains(&y);
        for i in 0..200 {
            for j in 0..100 {
                let (x, y) = (i as f64 * 0.01 + 0.005, j as f64 * 0.01 + 0.005);
                if !inside(x, y) {
                    acc.add(&Vector3::new(x, y, z0(x)));
                }
            }
        }
        for a in 0..40 {
            for b in 0..40 {
                let (u, v) = (a as f64 * 0.01 + 0.005, b as f64 * 0.01 + 0.005);
                for (x, y) in [(0.8 + u, 0.3), (0.8 + u, 0.6999), (0.8, 0.3 + u), (1.1999, 0.3 + u)] {
                    let z = z0(x) + v;
                    acc.add(&Vector3::new(x, y, z));
                }
                acc.add(&Vector3::new(0.8 + u, 0.3 + v, z0(1.2) + 0.4));
            }
        }
        let d = discover(&acc, |_| true, &NsdConfig::default()).unwrap();
        let g = TraversabilityGrid::from_discovery(&acc, &d);
        assert_eq!((g.width, g.height), (20, 10));
        assert_eq!(g.origin_m, (0.0, 0.0));
        let (nav, obstacle, unknown) = g.counts();
        assert_eq!(nav + obstacle + unknown, 200);
        assert!(nav >= 170 && (14..=24).contains(&obstacle), "{:?}", g.counts());
        // A floor cell: its height on the floor's plane, its slope 10°.
        let i = g.index(3, 8).unwrap();
        assert_eq!(g.class[i], CellClass::Navigable);
        assert!((g.height_m[i] as f64 - z0(0.35)).abs() < 0.005, "{} against {}", g.height_m[i], z0(0.35));
        assert!((g.slope_deg[i] - 10.0).abs() < 0.5, "{}", g.slope_deg[i]);
        // The box's middle: blocked, as high as its top.
        let (x, y) = g.cell_of(1.0, 0.5);
        let i = g.index(x, y).unwrap();
        assert_eq!(g.class[i], CellClass::Obstacle);
        assert!(g.height_m[i] as f64 > z0(1.0) + 0.3, "{}", g.height_m[i]);
        assert!(g.slope_deg[i].is_nan());
        // The files: the image upside down (first row the highest y), the PFMs bottom up.
        let dir = std::env::temp_dir().join(format!("trav-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let files = g.write(&dir, "traversability").unwrap();
        let pgm = std::fs::read(&files.pgm).unwrap();
        let header = "P5\n# traversability: navigable 254, obstacle 0, unknown 205; 0.1 m/cell\n20 10\n255\n";
        assert!(pgm.starts_with(header.as_bytes()));
        let image = &pgm[header.len()..];
        assert_eq!(image.len(), 200);
        assert_eq!(image[(9 - 5) * 20 + 10], 0, "the box, row y = 5 from the top");
        assert_eq!(image[20 + 3], 254, "a floor cell, row y = 8 from the top");
        let yaml = std::fs::read_to_string(&files.yaml).unwrap();
        assert!(yaml.contains("image: traversability.pgm") && yaml.contains("resolution: 0.1"), "{yaml}");
        let pfm = std::fs::read(&files.height_pfm).unwrap();
        let head = b"Pf\n20 10\n-1.0\n";
        assert!(pfm.starts_with(head));
        let at = |x: usize, y: usize| {
            let o = head.len() + (y * 20 + x) * 4;
            f32::from_le_bytes(pfm[o..o + 4].try_into().unwrap())
        };
        assert_eq!(at(3, 8), g.height_m[g.index(3, 8).unwrap()]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
