//! The static world: seabed terrain (a smooth height field), rocks (spheres), a wreck (an
//! oriented box on the seabed), surface buoys, and natural landmarks scattered on all of them.
//! Ray casting against the scene gives the depth camera its points.

use nalgebra::{Point3, Rotation3, Vector3};
use rand::{Rng, RngExt};
use serde::{Deserialize, Serialize};

use crate::config::SceneConfig;

/// A rock: a sphere partly buried in the seabed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Rock {
    /// Centre, world frame, m.
    pub center_m: [f64; 3],
    /// Radius, m.
    pub radius_m: f64,
}

/// The wreck: a box resting on the seabed, rotated about world z.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Wreck {
    /// Centre, world frame, m.
    pub center_m: [f64; 3],
    /// Full edge lengths (length, beam, height), m.
    pub size_m: [f64; 3],
    /// Heading of its length axis about world z, rad.
    pub yaw_rad: f64,
}

/// What the scene holds at a point ([`Scene::truth_at`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SceneTruth {
    /// The seabed.
    Seabed,
    /// Rock `i` (index into [`Scene::rocks`]).
    Rock(usize),
    /// The wreck.
    Wreck,
    /// Nothing: open water.
    Nothing,
}

/// A natural landmark: a 3-D point with a constant 32-byte descriptor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneLandmark {
    /// Position, world frame, m.
    pub position_m: Vector3<f64>,
    /// Descriptor.
    pub descriptor: [u8; 32],
}

/// The scene.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Scene {
    /// The configuration it was built from.
    pub config: SceneConfig,
    /// Rocks.
    pub rocks: Vec<Rock>,
    /// The wreck.
    pub wreck: Wreck,
    /// Buoy positions (id = index), world frame, m.
    pub buoys_m: Vec<[f64; 3]>,
    /// Number of landmarks.
    pub landmark_count: usize,
    #[serde(skip)]
    landmarks: Vec<SceneLandmark>,
    #[serde(skip)]
    grid: Vec<Vec<u32>>,
    #[serde(skip)]
    grid_dims: (usize, usize),
}

const CELL_M: f64 = 4.0;

impl Scene {
    /// Builds the scene deterministically from `config` with `rng`.
    pub fn build(config: &SceneConfig, rng: &mut impl Rng) -> Self {
        let [sx, sy] = config.extent_m;
        let mut scene = Scene {
            config: config.clone(),
            rocks: vec![],
            wreck: Wreck {
                center_m: [0.0; 3],
                size_m: config.wreck_size_m,
                yaw_rad: config.wreck_yaw_deg.to_radians(),
            },
            buoys_m: config.buoys_m.clone(),
            landmark_count: 0,
            landmarks: vec![],
            grid: vec![],
            grid_dims: (0, 0),
        };
        let wc = config.wreck_center_xy_m;
        scene.wreck.center_m = [wc[0], wc[1], scene.terrain_z(wc[0], wc[1]) + config.wreck_size_m[2] / 2.0 - 0.3];
        for _ in 0..config.rocks {
            let x = rng.random_range(0.0..sx);
            let y = rng.random_range(0.0..sy);
            let r = rng.random_range(config.rock_radius_m[0]..=config.rock_radius_m[1]);
            scene.rocks.push(Rock { center_m: [x, y, scene.terrain_z(x, y) + 0.3 * r], radius_m: r });
        }
        // Landmarks: on the terrain (outside the barren band), on rocks, on the wreck.
        let area = sx * sy;
        let n_terrain = (area / 100.0 * config.landmarks_per_100m2) as usize;
        for _ in 0..n_terrain {
            let x = rng.random_range(0.0..sx);
            let y = rng.random_range(0.0..sy);
            if config.barren_x_m[0] <= x && x <= config.barren_x_m[1] {
                continue;
            }
            let p = Vector3::new(x, y, scene.terrain_z(x, y));
            scene.push_landmark(p, rng);
        }
        for rock in scene.rocks.clone() {
            let n =
                (4.0 * std::f64::consts::PI * rock.radius_m * rock.radius_m * config.landmarks_per_m2_objects) as usize;
            for _ in 0..n {
                let dir = random_unit(rng);
                let p = Vector3::from(rock.center_m) + dir * rock.radius_m;
                if p.z > scene.terrain_z(p.x, p.y) {
                    scene.push_landmark(p, rng);
                }
            }
        }
        let w = scene.wreck;
        let [l, b, h] = w.size_m;
        let faces = 2.0 * (l * b + l * h + b * h);
        let n = (faces * config.landmarks_per_m2_objects) as usize;
        let rot = Rotation3::from_axis_angle(&Vector3::z_axis(), w.yaw_rad);
        for _ in 0..n {
            // A random point on the box surface: pick a face weighted by area.
            let mut local = Vector3::new(
                rng.random_range(-l / 2.0..l / 2.0),
                rng.random_range(-b / 2.0..b / 2.0),
                rng.random_range(-h / 2.0..h / 2.0),
            );
            let pick = rng.random_range(0.0..faces / 2.0);
            if pick < l * b {
                local.z = if rng.random_bool(0.5) { h / 2.0 } else { -h / 2.0 };
            } else if pick < l * b + l * h {
                local.y = if rng.random_bool(0.5) { b / 2.0 } else { -b / 2.0 };
            } else {
                local.x = if rng.random_bool(0.5) { l / 2.0 } else { -l / 2.0 };
            }
            let p = Vector3::from(w.center_m) + rot * local;
            if p.z > scene.terrain_z(p.x, p.y) {
                scene.push_landmark(p, rng);
            }
        }
        scene.landmark_count = scene.landmarks.len();
        scene.build_grid();
        scene
    }

    fn push_landmark(&mut self, p: Vector3<f64>, rng: &mut impl Rng) {
        let mut descriptor = [0u8; 32];
        rng.fill_bytes(&mut descriptor);
        self.landmarks.push(SceneLandmark { position_m: p, descriptor });
    }

    fn build_grid(&mut self) {
        let nx = (self.config.extent_m[0] / CELL_M).ceil() as usize + 1;
        let ny = (self.config.extent_m[1] / CELL_M).ceil() as usize + 1;
        self.grid = vec![vec![]; nx * ny];
        self.grid_dims = (nx, ny);
        for (i, l) in self.landmarks.iter().enumerate() {
            let (cx, cy) = self.cell(l.position_m.x, l.position_m.y);
            self.grid[cy * nx + cx].push(i as u32);
        }
    }

    fn cell(&self, x: f64, y: f64) -> (usize, usize) {
        let (nx, ny) = self.grid_dims;
        (
            (x / CELL_M).floor().clamp(0.0, (nx - 1) as f64) as usize,
            (y / CELL_M).floor().clamp(0.0, (ny - 1) as f64) as usize,
        )
    }

    /// All landmarks (index = landmark id).
    pub fn landmarks(&self) -> &[SceneLandmark] {
        &self.landmarks
    }

    /// Indices of landmarks within `radius_m` (horizontally and vertically) of `p`.
    pub fn landmarks_near(&self, p: &Vector3<f64>, radius_m: f64, out: &mut Vec<u32>) {
        out.clear();
        let (x0, y0) = self.cell(p.x - radius_m, p.y - radius_m);
        let (x1, y1) = self.cell(p.x + radius_m, p.y + radius_m);
        let r2 = radius_m * radius_m;
        for cy in y0..=y1 {
            for cx in x0..=x1 {
                for &i in &self.grid[cy * self.grid_dims.0 + cx] {
                    if (self.landmarks[i as usize].position_m - p).norm_squared() <= r2 {
                        out.push(i);
                    }
                }
            }
        }
    }

    /// Seabed height at (x, y), world z (negative below the surface), m.
    pub fn terrain_z(&self, x: f64, y: f64) -> f64 {
        let c = &self.config;
        let a = c.terrain_amplitude_m;
        -c.seabed_depth_m
            + a * ((x / 9.0).sin() * (y / 13.0).cos() + 0.5 * ((x + 2.0 * y) / 23.0).sin())
            + c.seabed_slope * x
    }

    /// What the scene holds at `p` (world frame, m), within `tolerance_m` of a surface: a rock
    /// or the wreck first (they stand on the seabed), then the seabed, else nothing. The truth
    /// that navigable space and obstacles are scored against.
    pub fn truth_at(&self, p: &Vector3<f64>, tolerance_m: f64) -> SceneTruth {
        for (i, r) in self.rocks.iter().enumerate() {
            if (p - Vector3::from(r.center_m)).norm() <= r.radius_m + tolerance_m {
                return SceneTruth::Rock(i);
            }
        }
        let w = &self.wreck;
        let d = p - Vector3::from(w.center_m);
        let (s, c) = w.yaw_rad.sin_cos();
        let local = [c * d.x + s * d.y, -s * d.x + c * d.y, d.z];
        if local.iter().zip(&w.size_m).all(|(v, size)| v.abs() <= 0.5 * size + tolerance_m) {
            return SceneTruth::Wreck;
        }
        if (p.z - self.terrain_z(p.x, p.y)).abs() <= tolerance_m {
            return SceneTruth::Seabed;
        }
        SceneTruth::Nothing
    }

    /// Lipschitz bound of [`Scene::terrain_z`] (max slope), used by the ray marcher.
    fn terrain_lipschitz(&self) -> f64 {
        let a = self.config.terrain_amplitude_m;
        a * (1.0 / 9.0 + 1.0 / 13.0 + 0.5 * 5f64.sqrt() / 23.0) + self.config.seabed_slope.abs()
    }

    /// Distance along the unit ray `dir` from `origin` to the first surface, if within `max_m`.
    pub fn ray_cast(&self, origin: &Point3<f64>, dir: &Vector3<f64>, max_m: f64) -> Option<f64> {
        let mut best = self.ray_terrain(origin, dir, max_m);
        let limit = |b: Option<f64>| b.unwrap_or(max_m);
        for rock in &self.rocks {
            if let Some(t) = ray_sphere(origin, dir, &Point3::from(rock.center_m), rock.radius_m)
                && t < limit(best)
            {
                best = Some(t);
            }
        }
        if let Some(t) = self.ray_wreck(origin, dir)
            && t < limit(best)
        {
            best = Some(t);
        }
        best.filter(|t| *t <= max_m)
    }

    fn ray_terrain(&self, o: &Point3<f64>, d: &Vector3<f64>, max_m: f64) -> Option<f64> {
        // Sphere tracing on the height field: the vertical gap over √(1+L²) never overshoots.
        let k = 1.0 / (1.0 + self.terrain_lipschitz().powi(2)).sqrt();
        let mut t = 0.0;
        for _ in 0..256 {
            let p = o + d * t;
            let gap = p.z - self.terrain_z(p.x, p.y);
            if gap < 0.005 {
                return Some(t);
            }
            t += (gap * k).max(0.002);
            if t > max_m {
                return None;
            }
        }
        None
    }

    fn ray_wreck(&self, o: &Point3<f64>, d: &Vector3<f64>) -> Option<f64> {
        let w = &self.wreck;
        let inv = Rotation3::from_axis_angle(&Vector3::z_axis(), -w.yaw_rad);
        let lo = inv * (o - Point3::from(w.center_m));
        let ld = inv * d;
        let half = Vector3::from(w.size_m) / 2.0;
        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
        for i in 0..3 {
            if ld[i].abs() < 1e-12 {
                if lo[i].abs() > half[i] {
                    return None;
                }
            } else {
                let a = (-half[i] - lo[i]) / ld[i];
                let b = (half[i] - lo[i]) / ld[i];
                t0 = t0.max(a.min(b));
                t1 = t1.min(a.max(b));
                if t0 > t1 {
                    return None;
                }
            }
        }
        (t0 > 0.0).then_some(t0)
    }
}

fn ray_sphere(o: &Point3<f64>, d: &Vector3<f64>, c: &Point3<f64>, r: f64) -> Option<f64> {
    let oc = o - c;
    let b = oc.dot(d);
    let disc = b * b - (oc.norm_squared() - r * r);
    if disc < 0.0 {
        return None;
    }
    let t = -b - disc.sqrt();
    (t > 0.0).then_some(t)
}

fn random_unit(rng: &mut impl Rng) -> Vector3<f64> {
    loop {
        let v = Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
        let n = v.norm();
        if n > 1e-3 && n <= 1.0 {
            return v / n;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn the_truth_knows_rocks_the_wreck_the_seabed_and_open_water() {
        let scene = Scene::build(&SceneConfig::default(), &mut rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3));
        let tol = 0.1;
        for (i, r) in scene.rocks.iter().enumerate() {
            let top = Vector3::from(r.center_m) + Vector3::new(0.0, 0.0, r.radius_m + 0.05);
            let truth = scene.truth_at(&top, tol);
            // Rocks may overlap: the top of one may lie in an earlier one.
            assert!(matches!(truth, SceneTruth::Rock(j) if j <= i), "rock {i}'s top: {truth:?}");
            assert_ne!(scene.truth_at(&(top + Vector3::new(0.0, 0.0, 0.2)), tol), SceneTruth::Rock(i));
        }
        let w = &scene.wreck;
        let deck = Vector3::from(w.center_m) + Vector3::new(0.0, 0.0, 0.5 * w.size_m[2]);
        assert_eq!(scene.truth_at(&deck, tol), SceneTruth::Wreck);
        // Along the wreck's length axis, just inside its end and just beyond it.
        let (s, c) = w.yaw_rad.sin_cos();
        let along = |d: f64| Vector3::from(w.center_m) + Vector3::new(c * d, s * d, 0.0);
        assert_eq!(scene.truth_at(&along(0.5 * w.size_m[0] - 0.05), tol), SceneTruth::Wreck);
        assert_ne!(scene.truth_at(&along(0.5 * w.size_m[0] + 0.5), tol), SceneTruth::Wreck);
        // The seabed away from every object, and the water above it.
        let clear = |x: f64, y: f64| {
            let z = scene.terrain_z(x, y);
            let p = Vector3::new(x, y, z);
            let far = scene.rocks.iter().all(|r| (p - Vector3::from(r.center_m)).norm() > r.radius_m + 1.0)
                && (p - Vector3::from(w.center_m)).norm() > w.size_m.iter().cloned().fold(0.0, f64::max) + 1.0;
            far.then_some(p)
        };
        let p = (0..400)
            .find_map(|k| clear(-50.0 + (k % 20) as f64 * 5.0, -50.0 + (k / 20) as f64 * 5.0))
            .expect("a clear spot");
        assert_eq!(scene.truth_at(&p, tol), SceneTruth::Seabed);
        assert_eq!(scene.truth_at(&(p + Vector3::new(0.0, 0.0, 0.05)), tol), SceneTruth::Seabed);
        assert_eq!(scene.truth_at(&(p + Vector3::new(0.0, 0.0, 2.0)), tol), SceneTruth::Nothing);
    }
}
