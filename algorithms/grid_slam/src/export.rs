//! The grid as an image: occupancy in percent, the map_server files (`.pgm` + `.yaml`, the format
//! ROS's map_server and nav2 load) and a PNG with a path drawn over the map.

use crate::GridSlamError;
use crate::grid::Grid;
use omni::Pose2;
use std::io::Write;
use std::path::Path;

/// Occupancy of a rectangle of cells: −1 unknown, else 0..=100 (percent), row-major with the
/// first row at the *lowest* y (as nav_msgs/OccupancyGrid).
#[derive(Debug, Clone, PartialEq)]
pub struct Occupancy {
    /// Cells along x.
    pub width: usize,
    /// Cells along y.
    pub height: usize,
    /// Cell side, m.
    pub resolution_m: f64,
    /// World position of the lower-left corner of cell (0, 0), m.
    pub origin_m: (f64, f64),
    /// Values, `width × height`.
    pub data: Vec<i8>,
}

impl Occupancy {
    /// The known part of `grid` (plus `margin` cells on each side).
    pub fn from_grid(grid: &Grid, margin: i32) -> Occupancy {
        let res = grid.resolution_m();
        let Some((i0, j0, i1, j1)) = grid.known_bounds() else {
            return Occupancy { width: 0, height: 0, resolution_m: res, origin_m: (0.0, 0.0), data: Vec::new() };
        };
        let (i0, j0, i1, j1) = (i0 - margin, j0 - margin, i1 + margin, j1 + margin);
        let (w, h) = ((i1 - i0 + 1) as usize, (j1 - j0 + 1) as usize);
        let mut data = vec![-1i8; w * h];
        for j in j0..=j1 {
            for i in i0..=i1 {
                let l = grid.log_odds(i, j);
                if l != 0.0 {
                    let p = 1.0 - 1.0 / (1.0 + (l as f64).exp());
                    data[(j - j0) as usize * w + (i - i0) as usize] = (p * 100.0).round() as i8;
                }
            }
        }
        Occupancy { width: w, height: h, resolution_m: res, origin_m: (i0 as f64 * res, j0 as f64 * res), data }
    }

    /// The value at cell (x, y) of the image (y up), or −1 outside.
    pub fn at(&self, x: i64, y: i64) -> i8 {
        if x < 0 || y < 0 || x as usize >= self.width || y as usize >= self.height {
            return -1;
        }
        self.data[y as usize * self.width + x as usize]
    }

    /// The cell of world point (x, y), if inside.
    pub fn cell_of(&self, x_m: f64, y_m: f64) -> (i64, i64) {
        (
            ((x_m - self.origin_m.0) / self.resolution_m).floor() as i64,
            ((y_m - self.origin_m.1) / self.resolution_m).floor() as i64,
        )
    }

    /// Writes `<stem>.pgm` and `<stem>.yaml` (map_server: occupied above 0.65 black, free below
    /// 0.196 white, unknown grey 205; `negate: 0`; the image's first row is the *highest* y).
    pub fn write_map_server(&self, dir: &Path, stem: &str) -> Result<(), GridSlamError> {
        let io = |path: &Path| {
            let p = path.display().to_string();
            move |e| GridSlamError::Io { path: p, source: e }
        };
        let pgm = dir.join(format!("{stem}.pgm"));
        let mut bytes =
            format!("P5\n# grid_slam map, {} m/cell\n{} {}\n255\n", self.resolution_m, self.width, self.height)
                .into_bytes();
        for y in (0..self.height).rev() {
            for x in 0..self.width {
                let v = self.data[y * self.width + x];
                bytes.push(match v {
                    -1 => 205,
                    v if v as f64 > 65.0 => 0,
                    v if (v as f64) < 19.6 => 254,
                    _ => 205,
                });
            }
        }
        std::fs::write(&pgm, bytes).map_err(io(&pgm))?;
        let yaml = dir.join(format!("{stem}.yaml"));
        let text = format!(
            "image: {stem}.pgm\nmode: trinary\nresolution: {}\norigin: [{}, {}, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n",
            self.resolution_m, self.origin_m.0, self.origin_m.1
        );
        std::fs::write(&yaml, text).map_err(io(&yaml))?;
        Ok(())
    }

    /// Writes a PNG of the map (occupied black, free white, unknown grey) with `path` drawn in
    /// red (y up, like the map).
    pub fn write_png(&self, path_png: &Path, path: &[Pose2]) -> Result<(), GridSlamError> {
        let (w, h) = (self.width.max(1), self.height.max(1));
        let mut rgb = vec![0u8; w * h * 3];
        for y in 0..self.height {
            for x in 0..self.width {
                let v = self.data[y * self.width + x];
                let g = if v < 0 { 180 } else { (255.0 * (1.0 - v as f64 / 100.0)) as u8 };
                let k = ((h - 1 - y) * w + x) * 3;
                rgb[k..k + 3].copy_from_slice(&[g, g, g]);
            }
        }
        for p in path {
            let (x, y) = self.cell_of(p.x_m, p.y_m);
            if x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height {
                let k = ((h - 1 - y as usize) * w + x as usize) * 3;
                rgb[k..k + 3].copy_from_slice(&[220, 30, 30]);
            }
        }
        let err = |e: std::io::Error| GridSlamError::Io { path: path_png.display().to_string(), source: e };
        let file = std::fs::File::create(path_png).map_err(err)?;
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w as u32, h as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let png_err = |e: png::EncodingError| GridSlamError::Io {
            path: path_png.display().to_string(),
            source: std::io::Error::other(e.to_string()),
        };
        let mut writer = enc.write_header().map_err(png_err)?;
        writer.write_image_data(&rgb).map_err(png_err)?;
        writer.finish().map_err(png_err)?;
        Ok(())
    }
}

/// Writes a planar trajectory as TUM lines (`t x y z qx qy qz qw`, z = 0, yaw as a quaternion).
pub fn write_tum2(path: &Path, traj: &[(f64, Pose2)]) -> Result<(), GridSlamError> {
    let err = |e: std::io::Error| GridSlamError::Io { path: path.display().to_string(), source: e };
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).map_err(err)?);
    for (t, p) in traj {
        let (s, c) = (p.theta_rad / 2.0).sin_cos();
        writeln!(f, "{t:.6} {:.6} {:.6} 0 0 0 {s:.9} {c:.9}", p.x_m, p.y_m).map_err(err)?;
    }
    f.flush().map_err(err)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::LogOddsParams;

    #[test]
    fn the_map_server_files_hold_the_map_with_the_highest_row_first() {
        let mut g = Grid::new(0.1);
        let p = LogOddsParams::default();
        for _ in 0..6 {
            g.cast((0.05, 0.05), (0.05, 1.05), true, &p);
        }
        let occ = Occupancy::from_grid(&g, 0);
        assert_eq!((occ.width, occ.height), (1, 11));
        assert!(occ.at(0, 10) > 65 && occ.at(0, 0) < 20, "{:?}", occ.data);
        let dir = tempfile::tempdir().expect("tmp");
        occ.write_map_server(dir.path(), "grid").expect("write");
        let pgm = std::fs::read(dir.path().join("grid.pgm")).expect("pgm");
        let header = b"P5\n# grid_slam map, 0.1 m/cell\n1 11\n255\n";
        assert_eq!(&pgm[..header.len()], header);
        assert_eq!(pgm[header.len()], 0, "the first row is the top (occupied) one");
        assert_eq!(*pgm.last().expect("data"), 254);
        let yaml = std::fs::read_to_string(dir.path().join("grid.yaml")).expect("yaml");
        assert!(yaml.contains("resolution: 0.1") && yaml.contains("origin: [0, 0, 0.0]"), "{yaml}");
        occ.write_png(&dir.path().join("grid.png"), &[Pose2::default()]).expect("png");
    }
}
