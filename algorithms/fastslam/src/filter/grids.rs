//! The spatial grids over landmark ids that give each observation its association candidates.

use super::*;

/// A grid over landmark ids by their first position: the candidates for association.
#[derive(Default)]
pub(super) struct Grid {
    pub(super) cell_m: f64,
    /// Landmark ids with the position they were created at and the trace of their initial
    /// covariance, m² (the same in every particle: a rotation keeps the trace).
    pub(super) cells: HashMap<[i32; 3], Vec<GridEntry>>,
    /// Landmarks of stereo observations by [`VIEW_CELL_M`] cell of their first position: those
    /// near the camera are projected into it to find the candidates of the stereo observations.
    pub(super) view: HashMap<[i32; 3], Vec<u32>>,
}

/// Cell of the coarse grid of stereo landmarks, m.
pub(super) const VIEW_CELL_M: f64 = 10.0;
/// Farthest a stereo observation's candidates are looked for, m.
pub(super) const MAX_VIEW_M: f64 = 300.0;

#[derive(Clone, Copy)]
pub(super) struct GridEntry {
    pub(super) id: u32,
    pub(super) created_m: Vector3<f64>,
    /// How far (m) from its creation position a particle's version of this landmark can be and
    /// still pass the duplicate gate for an observation with covariance trace zero: the gate
    /// distance √(χ²_dup·tr Σ₀) (an EKF update never grows Σ) plus `MEAN_MOTION_SIGMAS`·√tr Σ₀
    /// for the mean's motion since creation.
    pub(super) reach_m: f64,
}

/// How many initial σ a landmark's mean may move from where it was created (its initial error
/// plus its current error, each within 3σ) before the candidate search stops finding it.
pub(super) const MEAN_MOTION_SIGMAS: f64 = 6.0;

impl Grid {
    pub(super) fn key(&self, p: &Vector3<f64>) -> [i32; 3] {
        [(p.x / self.cell_m).floor() as i32, (p.y / self.cell_m).floor() as i32, (p.z / self.cell_m).floor() as i32]
    }

    pub(super) fn insert(&mut self, id: u32, created_m: Vector3<f64>, cov_trace_m2: f64, duplicate_gate_chi2: f64) {
        let t = cov_trace_m2.max(0.0);
        let reach_m = (duplicate_gate_chi2 * t).sqrt() + MEAN_MOTION_SIGMAS * t.sqrt();
        let key = self.key(&created_m);
        self.cells.entry(key).or_default().push(GridEntry { id, created_m, reach_m });
    }

    /// Ids created within `radius_m` (rounded up to whole cells, at least one) of `p` whose own
    /// reach plus `slack_m` also covers `p`.
    pub(super) fn candidates(&self, p: &Vector3<f64>, radius_m: f64, slack_m: f64, out: &mut Vec<u32>) {
        out.clear();
        let k = self.key(p);
        let n = ((radius_m / self.cell_m).ceil() as i32).clamp(1, 8);
        let r2 = radius_m * radius_m;
        for dx in -n..=n {
            for dy in -n..=n {
                for dz in -n..=n {
                    if let Some(entries) = self.cells.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) {
                        out.extend(
                            entries
                                .iter()
                                .filter(|e| {
                                    let d2 = (e.created_m - p).norm_squared();
                                    d2 <= r2 && d2 <= (e.reach_m + slack_m).powi(2)
                                })
                                .map(|e| e.id),
                        );
                    }
                }
            }
        }
    }
}

/// A grid over the (x/z, y/z) of stereo coordinates (about two points per cell).
pub(super) struct SGrid {
    pub(super) min: [f64; 2],
    pub(super) cell: f64,
    pub(super) nx: usize,
    pub(super) ny: usize,
    /// Points of cell k: `items[start[k]..start[k + 1]]`.
    pub(super) start: Vec<u32>,
    pub(super) items: Vec<u32>,
}

impl SGrid {
    pub(super) fn new(pts: &[(Vector3<f64>, Matrix3<f64>)]) -> Self {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for (s, _) in pts {
            for k in 0..2 {
                lo[k] = lo[k].min(s[k]);
                hi[k] = hi[k].max(s[k]);
            }
        }
        if pts.is_empty() {
            (lo, hi) = ([0.0; 2], [1.0; 2]);
        }
        let area = ((hi[0] - lo[0]) * (hi[1] - lo[1])).max(1e-9);
        let cell = (area / (pts.len().max(1) as f64 / 2.0)).sqrt().max((hi[0] - lo[0]).max(hi[1] - lo[1]) / 256.0);
        let nx = (((hi[0] - lo[0]) / cell).floor() as usize + 1).min(257);
        let ny = (((hi[1] - lo[1]) / cell).floor() as usize + 1).min(257);
        let key = |s: &Vector3<f64>| {
            let ix = (((s[0] - lo[0]) / cell) as usize).min(nx - 1);
            let iy = (((s[1] - lo[1]) / cell) as usize).min(ny - 1);
            iy * nx + ix
        };
        let mut start = vec![0u32; nx * ny + 1];
        for (s, _) in pts {
            start[key(s) + 1] += 1;
        }
        for k in 1..start.len() {
            start[k] += start[k - 1];
        }
        let mut fill = start.clone();
        let mut items = vec![0u32; pts.len()];
        for (i, (s, _)) in pts.iter().enumerate() {
            let k = key(s);
            items[fill[k] as usize] = i as u32;
            fill[k] += 1;
        }
        Self { min: lo, cell, nx, ny, start, items }
    }

    /// Points whose (a, b) may lie within ±(ra, rb) of (a, b).
    pub(super) fn query(&self, a: f64, b: f64, ra: f64, rb: f64, mut f: impl FnMut(usize)) {
        let lo_x = ((a - ra - self.min[0]) / self.cell).floor();
        let hi_x = ((a + ra - self.min[0]) / self.cell).floor();
        let lo_y = ((b - rb - self.min[1]) / self.cell).floor();
        let hi_y = ((b + rb - self.min[1]) / self.cell).floor();
        if !(hi_x >= 0.0 && hi_y >= 0.0 && lo_x < self.nx as f64 && lo_y < self.ny as f64) {
            return;
        }
        let (x0, x1) = (lo_x.max(0.0) as usize, (hi_x as usize).min(self.nx - 1));
        let (y0, y1) = (lo_y.max(0.0) as usize, (hi_y as usize).min(self.ny - 1));
        for y in y0..=y1 {
            for k in (y * self.nx + x0)..=(y * self.nx + x1) {
                for &i in &self.items[self.start[k] as usize..self.start[k + 1] as usize] {
                    f(i as usize);
                }
            }
        }
    }
}
