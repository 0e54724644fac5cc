//! Branch-and-bound correlative scan matching of a scan against a submap (Hess et al. 2016 §V.C,
//! after the multi-resolution correlative matcher of Olson 2009), docs/EQUATIONS.md §8.
//!
//! The submap is rasterised into a likelihood field ([`LookupGrid`]): each cell holds
//! exp(−d²/2σ²) for the distance d to the nearest occupied cell (σ one cell, cut at two cells),
//! stored as u8. A pose's score is the mean of the field over the scan's end points. For the
//! search, level h of the grid holds at each cell the maximum of level 0 over the 2ʰ × 2ʰ cells
//! from it, so a candidate at height h (a block of 2ʰ × 2ʰ translations at one rotation) has an
//! upper bound on the score of every translation in its block. The search visits candidates best
//! first, depth first, and cuts every block whose bound is not above the best score found: the
//! result is the exact optimum of the score over the discretised window (translations on the
//! cell grid, rotations in steps that move the farthest point by at most one cell).

use crate::grid::Grid;
use omni::Pose2;

/// A submap's likelihood field and its max-pooled levels.
#[derive(Debug, Clone)]
pub struct LookupGrid {
    resolution_m: f64,
    /// Cell of level 0's (0, 0).
    origin: (i32, i32),
    width: i32,
    height: i32,
    /// Level h covers cells from `origin − (2ʰ − 1)`, `width + 2ʰ − 1` by `height + 2ʰ − 1`.
    levels: Vec<Vec<u8>>,
}

impl LookupGrid {
    /// The field of `grid`'s cells with log-odds above `occupied_log_odds`, with `depth` + 1
    /// levels. `None` when the grid has no occupied cell.
    pub fn new(grid: &Grid, occupied_log_odds: f32, depth: u32) -> Option<Self> {
        let (i0, j0, i1, j1) = grid.known_bounds()?;
        const R: i32 = 2;
        let (ox, oy) = (i0 - R, j0 - R);
        let (w, h) = (i1 - i0 + 1 + 2 * R, j1 - j0 + 1 + 2 * R);
        let mut base = vec![0u8; (w * h) as usize];
        let kernel: Vec<(i32, i32, u8)> = (-R..=R)
            .flat_map(|dy| (-R..=R).map(move |dx| (dx, dy)))
            .filter_map(|(dx, dy)| {
                let d2 = (dx * dx + dy * dy) as f64;
                (d2 <= (R * R) as f64).then(|| (dx, dy, (255.0 * (-0.5 * d2).exp()).round() as u8))
            })
            .collect();
        let mut any = false;
        for j in j0..=j1 {
            for i in i0..=i1 {
                if grid.log_odds(i, j) <= occupied_log_odds {
                    continue;
                }
                any = true;
                for &(dx, dy, v) in &kernel {
                    let k = ((j + dy - oy) * w + (i + dx - ox)) as usize;
                    if base[k] < v {
                        base[k] = v;
                    }
                }
            }
        }
        if !any {
            return None;
        }
        let mut levels = vec![base];
        for level in 1..=depth {
            let prev = &levels[level as usize - 1];
            let (pw, ph) = (w + (1 << (level - 1)) - 1, h + (1 << (level - 1)) - 1);
            let step = 1i32 << (level - 1);
            let (nw, nh) = (w + (1 << level) - 1, h + (1 << level) - 1);
            // Level l at cell c (in its own indexing, shifted by 2^l − 1) is the max of level l−1
            // at c and c + 2^(l−1) along x, then along y. In level l−1's indexing a cell index
            // is shifted by 2^(l−1) − 1, so level l's (x, y) reads level l−1's (x − step, y − step)
            // and (x, y).
            let get = |x: i32, y: i32| -> u8 {
                if x < 0 || y < 0 || x >= pw || y >= ph { 0 } else { prev[(y * pw + x) as usize] }
            };
            let mut rows = vec![0u8; (nw * ph) as usize];
            for y in 0..ph {
                for x in 0..nw {
                    rows[(y * nw + x) as usize] = get(x - step, y).max(get(x, y));
                }
            }
            let getr = |x: i32, y: i32| -> u8 { if y < 0 || y >= ph { 0 } else { rows[(y * nw + x) as usize] } };
            let mut next = vec![0u8; (nw * nh) as usize];
            for y in 0..nh {
                for x in 0..nw {
                    next[(y * nw + x) as usize] = getr(x, y - step).max(getr(x, y));
                }
            }
            levels.push(next);
        }
        Some(Self { resolution_m: grid.resolution_m(), origin: (ox, oy), width: w, height: h, levels })
    }

    /// Levels above level 0.
    pub fn depth(&self) -> u32 {
        self.levels.len() as u32 - 1
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.levels.iter().map(Vec::len).sum()
    }

    /// Level `h`'s value at cell (i, j): the max of level 0 over [i, i + 2ʰ) × [j, j + 2ʰ).
    #[inline]
    pub fn get(&self, h: u32, i: i32, j: i32) -> u8 {
        let shift = (1 << h) - 1;
        let (w, hh) = (self.width + shift, self.height + shift);
        let (x, y) = (i - self.origin.0 + shift, j - self.origin.1 + shift);
        if x < 0 || y < 0 || x >= w || y >= hh {
            return 0;
        }
        self.levels[h as usize][(y * w + x) as usize]
    }

    /// The mean field value over `points` (body frame) at `pose` (submap frame), in [0, 1].
    pub fn score(&self, points: &[(f64, f64)], pose: &Pose2) -> f64 {
        if points.is_empty() {
            return 0.0;
        }
        let (s, c) = pose.theta_rad.sin_cos();
        let inv = 1.0 / self.resolution_m;
        let sum: u64 = points
            .iter()
            .map(|&(x, y)| {
                let (wx, wy) = (pose.x_m + c * x - s * y, pose.y_m + s * x + c * y);
                self.get(0, (wx * inv).floor() as i32, (wy * inv).floor() as i32) as u64
            })
            .sum();
        sum as f64 / (255.0 * points.len() as f64)
    }
}

/// The search window around an initial pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Window {
    /// Half-width in x and y, m.
    pub linear_m: f64,
    /// Half-width in θ, rad.
    pub angular_rad: f64,
}

/// The best pose found and its score.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Match {
    /// `submap_from_body`.
    pub pose: Pose2,
    /// Mean field value over the points, in [0, 1].
    pub score: f64,
}

/// One rotation's point cells relative to level 0's origin, and their box (min x, min y, max x, max y).
type RotatedCells = (Vec<(i32, i32)>, [i32; 4]);

struct Candidate {
    rotation: usize,
    dx: i32,
    dy: i32,
    score: u64,
}

/// The pose in `window` around `initial` (submap frame) with the best score over `points`
/// (body frame), if one scores at least `min_score` (mean field value in [0, 1]).
pub fn search(
    lookup: &LookupGrid,
    points: &[(f64, f64)],
    initial: &Pose2,
    window: Window,
    min_score: f64,
) -> Option<Match> {
    if points.is_empty() {
        return None;
    }
    let res = lookup.resolution_m;
    let inv = 1.0 / res;
    let max_range = points.iter().map(|p| p.0.hypot(p.1)).fold(0.0, f64::max).max(res);
    // The rotation step that moves the farthest point by about one cell.
    let dtheta = (1.0 - res * res / (2.0 * max_range * max_range)).clamp(-1.0, 1.0).acos().max(1e-4);
    let nth = (window.angular_rad / dtheta).ceil() as i32;
    let wc = (window.linear_m * inv).ceil() as i32;
    let depth = lookup.depth();
    // The points at each rotation, as cells relative to the initial translation's cell.
    let (ci, cj) = ((initial.x_m * inv).floor(), (initial.y_m * inv).floor());
    let (fx, fy) = (initial.x_m - ci * res, initial.y_m - cj * res);
    let rotations: Vec<(f64, Vec<(i32, i32)>)> = (-nth..=nth)
        .map(|k| {
            let th = initial.theta_rad + k as f64 * dtheta;
            let (s, c) = th.sin_cos();
            let cells = points
                .iter()
                .map(|&(x, y)| {
                    let (wx, wy) = (fx + c * x - s * y, fy + s * x + c * y);
                    ((wx * inv).floor() as i32 + ci as i32, (wy * inv).floor() as i32 + cj as i32)
                })
                .collect();
            (th, cells)
        })
        .collect();
    // Each rotation's cells relative to level 0's origin and their bounding box: a candidate
    // whose box lies inside a level sums without a bounds test per point.
    let rel: Vec<RotatedCells> = rotations
        .iter()
        .map(|(_, cells)| {
            let v: Vec<(i32, i32)> = cells.iter().map(|&(i, j)| (i - lookup.origin.0, j - lookup.origin.1)).collect();
            let b = v.iter().fold([i32::MAX, i32::MAX, i32::MIN, i32::MIN], |b, &(x, y)| {
                [b[0].min(x), b[1].min(y), b[2].max(x), b[3].max(y)]
            });
            (v, b)
        })
        .collect();
    // The summed field of rotation r's points at offset (dx, dy) on level h. It stops early, and
    // returns 0, once the points left cannot lift the sum above `floor` (the candidate is cut
    // whatever they hold: the search stays exact).
    let score_at = |h: u32, r: usize, dx: i32, dy: i32, floor: u64| -> u64 {
        let shift = (1i32 << h) - 1;
        let (w, hh) = (lookup.width + shift, lookup.height + shift);
        let level = &lookup.levels[h as usize];
        let (cells, b) = &rel[r];
        let (ox, oy) = (dx + shift, dy + shift);
        let inside = b[0] + ox >= 0 && b[1] + oy >= 0 && b[2] + ox < w && b[3] + oy < hh;
        let mut left = 255 * cells.len() as u64;
        let mut sum = 0u64;
        for chunk in cells.chunks(32) {
            sum += if inside {
                chunk.iter().map(|&(x, y)| level[((y + oy) * w + x + ox) as usize] as u64).sum::<u64>()
            } else {
                chunk
                    .iter()
                    .map(|&(x, y)| {
                        let (x, y) = (x + ox, y + oy);
                        if x < 0 || y < 0 || x >= w || y >= hh { 0 } else { level[(y * w + x) as usize] as u64 }
                    })
                    .sum::<u64>()
            };
            left -= 255 * chunk.len() as u64;
            if sum + left <= floor {
                return 0;
            }
        }
        sum
    };
    let n = points.len() as f64;
    let threshold = (min_score * 255.0 * n).ceil() as u64;
    let mut best: Option<(u64, usize, i32, i32)> = None;
    // Top level: blocks of 2^depth translations.
    let step = 1i32 << depth;
    let mut top = Vec::new();
    for r in 0..rotations.len() {
        let mut dx = -wc;
        while dx <= wc {
            let mut dy = -wc;
            while dy <= wc {
                top.push(Candidate {
                    rotation: r,
                    dx,
                    dy,
                    score: score_at(depth, r, dx, dy, threshold.saturating_sub(1)),
                });
                dy += step;
            }
            dx += step;
        }
    }
    top.sort_by_key(|c| std::cmp::Reverse(c.score));
    // Depth-first, best first; a block is cut when its bound is not above the best so far.
    fn descend(
        c: &Candidate,
        h: u32,
        wc: i32,
        threshold: u64,
        best: &mut Option<(u64, usize, i32, i32)>,
        score_at: &dyn Fn(u32, usize, i32, i32, u64) -> u64,
    ) {
        let floor = best.map_or(threshold.saturating_sub(1), |b| b.0);
        if c.score <= floor {
            return;
        }
        if h == 0 {
            *best = Some((c.score, c.rotation, c.dx, c.dy));
            return;
        }
        let half = 1 << (h - 1);
        let mut children = Vec::with_capacity(4);
        for (ox, oy) in [(0, 0), (half, 0), (0, half), (half, half)] {
            let (dx, dy) = (c.dx + ox, c.dy + oy);
            if dx > wc || dy > wc {
                continue;
            }
            children.push(Candidate {
                rotation: c.rotation,
                dx,
                dy,
                score: score_at(h - 1, c.rotation, dx, dy, floor),
            });
        }
        children.sort_by_key(|c| std::cmp::Reverse(c.score));
        for ch in &children {
            descend(ch, h - 1, wc, threshold, best, score_at);
        }
    }
    for c in &top {
        let floor = best.map_or(threshold.saturating_sub(1), |b| b.0);
        if c.score <= floor {
            break;
        }
        descend(c, depth, wc, threshold, &mut best, &score_at);
    }
    let (score, r, dx, dy) = best?;
    Some(Match {
        pose: Pose2 {
            x_m: initial.x_m + dx as f64 * res,
            y_m: initial.y_m + dy as f64 * res,
            theta_rad: omni::wrap_angle(rotations[r].0),
        },
        score: score as f64 / (255.0 * n),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::LogOddsParams;

    /// An L-shaped room with a pillar, scanned from (1, 1); the grid and the body-frame points.
    fn scene() -> (Grid, Vec<(f64, f64)>) {
        let lp = LogOddsParams::default();
        let mut g = Grid::new(0.05);
        let walls: Vec<((f64, f64), (f64, f64))> = vec![
            ((-2.0, -1.5), (6.0, -1.5)),
            ((6.0, -1.5), (6.0, 2.0)),
            ((6.0, 2.0), (2.0, 2.0)),
            ((2.0, 2.0), (2.0, 5.0)),
            ((2.0, 5.0), (-2.0, 5.0)),
            ((-2.0, 5.0), (-2.0, -1.5)),
            ((3.5, 0.0), (4.0, 0.0)),
            ((4.0, 0.0), (4.0, 0.5)),
        ];
        let ray = |o: (f64, f64), a: f64| -> Option<f64> {
            let (s, c) = a.sin_cos();
            let mut best: Option<f64> = None;
            for &((x1, y1), (x2, y2)) in &walls {
                let (ex, ey) = (x2 - x1, y2 - y1);
                let den = c * ey - s * ex;
                if den.abs() < 1e-12 {
                    continue;
                }
                let t = ((x1 - o.0) * ey - (y1 - o.1) * ex) / den;
                let u = ((x1 - o.0) * s - (y1 - o.1) * c) / den;
                if t > 0.0 && (0.0..=1.0).contains(&u) && best.is_none_or(|b| t < b) {
                    best = Some(t);
                }
            }
            best
        };
        for o in [(1.0, 1.0), (0.0, 3.0), (4.5, 1.0)] {
            for k in 0..720 {
                let a = (k as f64 * 0.5).to_radians();
                if let Some(r) = ray(o, a) {
                    let (s, c) = a.sin_cos();
                    g.cast(o, (o.0 + r * c, o.1 + r * s), true, &lp);
                }
            }
        }
        let mut pts = Vec::new();
        let o = (1.0, 1.0);
        for k in 0..360 {
            let a = (k as f64).to_radians();
            if let Some(r) = ray(o, a) {
                pts.push((r * a.cos(), r * a.sin()));
            }
        }
        (g, pts)
    }

    /// The max-pooled levels bound level 0 from above over their blocks.
    #[test]
    fn levels_bound_their_blocks() {
        let (g, _) = scene();
        let l = LookupGrid::new(&g, 0.0, 4).unwrap();
        for h in 1..=4u32 {
            for j in (l.origin.1 - 20..l.origin.1 + l.height + 5).step_by(3) {
                for i in (l.origin.0 - 20..l.origin.0 + l.width + 5).step_by(3) {
                    let m = (0..1 << h)
                        .flat_map(|dy| (0..1 << h).map(move |dx| (dx, dy)))
                        .map(|(dx, dy)| l.get(0, i + dx, j + dy))
                        .max()
                        .unwrap();
                    assert_eq!(l.get(h, i, j), m, "level {h} at ({i}, {j})");
                }
            }
        }
    }

    /// From 1.2 m and 0.3 rad off, the search finds the true pose within a cell and a step.
    #[test]
    fn finds_the_pose_from_far_off() {
        let (g, pts) = scene();
        let l = LookupGrid::new(&g, 0.0, 5).unwrap();
        let truth = Pose2 { x_m: 1.0, y_m: 1.0, theta_rad: 0.0 };
        let start = Pose2 { x_m: 2.0, y_m: 0.3, theta_rad: 0.3 };
        let m = search(&l, &pts, &start, Window { linear_m: 1.5, angular_rad: 0.5 }, 0.5).expect("a match");
        assert!((m.pose.x_m - truth.x_m).abs() <= 0.06 && (m.pose.y_m - truth.y_m).abs() <= 0.06, "{:?}", m);
        assert!(m.pose.theta_rad.abs() < 0.02, "{:?}", m);
        assert!(m.score > 0.8, "{:?}", m);
        // The exact optimum over the window: no pose on the grid scores more (brute force).
        let brute = l.score(&pts, &m.pose);
        assert!((brute - m.score).abs() < 0.01, "{brute} vs {}", m.score);
        // Too narrow a window: nothing above the threshold.
        assert!(search(&l, &pts, &start, Window { linear_m: 0.2, angular_rad: 0.05 }, 0.7).is_none());
    }
}
