//! A simulated indoor mission of a three-wheel omni-directional robot ([2D3D], docs/EQUATIONS.md §8):
//! two furnished rooms joined by a door and a corridor, the base driving two laps of a loop through
//! them with
//! holonomic motion (its heading sways independently of the path: it strafes), a 2-D laser, wheel
//! encoders with slip, and a Kinect-like depth camera. Deterministic for a seed, with ground truth.
//!
//! The scene is a set of axis-aligned boxes ([`IndoorScene`]). Furniture differs between the
//! laser's plane and the rest of the 3-D scene: a table shows only its legs to the laser, a low
//! crate lies below the laser's plane, shelves and a pillar stand in both; the depth camera sees
//! them all (and the floor).
//!
//! Frames: world z up, the floor at z = 0; body x forward, y left, z up, at floor level; the laser
//! at `laser.offset_m` and `laser.height_m` in the body frame, scanning counter-clockwise from −π;
//! the depth camera's points in its optical frame (x right, y down, z forward), mounted per
//! `geometry::body_from_camera(offset, pitch_down)`.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use omni::{BodyVelocity, OmniBase, Pose2};
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;
use serde::{Deserialize, Serialize};
use validation::{Issues, Validate};

/// An axis-aligned box, m.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Box3 {
    /// Lower corner (x, y, z).
    pub min: [f64; 3],
    /// Upper corner.
    pub max: [f64; 3],
    /// What it is (wall, table top, leg, shelf, crate, pillar, floor).
    pub what: &'static str,
}

impl Box3 {
    fn new(what: &'static str, min: [f64; 3], max: [f64; 3]) -> Self {
        Self { min, max, what }
    }

    /// This wall piece grown `by` metres outwards from the building on side `side` (n, e, s, w).
    fn extended(mut self, side: char, by: f64) -> Self {
        match side {
            'w' => self.min[0] -= by,
            'e' => self.max[0] += by,
            'n' => self.max[1] += by,
            _ => self.min[1] -= by,
        }
        self
    }

    /// Whether the point is inside.
    pub fn contains(&self, p: &[f64; 3]) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }

    /// Distance along the ray `o + t·d` (t > 0) to the box, if it hits (slab method).
    fn hit(&self, o: &[f64; 3], d: &[f64; 3], dims: usize) -> Option<f64> {
        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
        for i in 0..dims {
            if d[i].abs() < 1e-12 {
                if o[i] < self.min[i] || o[i] > self.max[i] {
                    return None;
                }
            } else {
                let (a, b) = ((self.min[i] - o[i]) / d[i], (self.max[i] - o[i]) / d[i]);
                let (a, b) = if a < b { (a, b) } else { (b, a) };
                t0 = t0.max(a);
                t1 = t1.min(b);
                if t0 > t1 {
                    return None;
                }
            }
        }
        (t0 > 1e-9).then_some(t0)
    }
}

/// Which building the indoor mission drives through.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Building {
    /// [`IndoorScene::two_rooms`] with the loop [`WAYPOINTS`] (`laps` times).
    TwoRooms,
    /// [`IndoorScene::ring`]: one lap of a 148 m corridor ring ([`RING_WAYPOINTS`], `laps` is
    /// ignored), then 27 m more along the first corridor: the loop closes after 148 m.
    Ring,
}

/// What an indoor scene holds at a point ([`IndoorTruth::at`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IndoorTruthAt {
    /// The floor's top: where the robot drives.
    Floor,
    /// A wall of the building (its shell: walls, door jambs, pillars are furniture).
    Wall,
    /// Object `i`: a group of touching pieces of furniture (a table's top and legs are one
    /// table).
    Object(u32),
    /// Nothing the scene knows.
    Nothing,
}

/// The truth of an indoor scene: its boxes grouped into objects, for scoring a 3-D map's
/// navigable space and obstacles.
#[derive(Debug, Clone, PartialEq)]
pub struct IndoorTruth {
    /// (lower corner, upper corner, what the box is: the floor, a wall or an object), m.
    boxes: Vec<([f64; 3], [f64; 3], IndoorTruthAt)>,
    objects: u32,
}

impl IndoorTruth {
    /// Groups `boxes` (lower corner, upper corner, what: `floor`, `wall` or a kind of furniture):
    /// touching or overlapping pieces of furniture into objects; the walls are the building's.
    pub fn new<'a>(boxes: impl IntoIterator<Item = ([f64; 3], [f64; 3], &'a str)>) -> Self {
        let all: Vec<([f64; 3], [f64; 3], &str)> = boxes.into_iter().collect();
        let mut parent: Vec<usize> = (0..all.len()).collect();
        fn root(p: &mut [usize], mut i: usize) -> usize {
            while p[i] != i {
                p[i] = p[p[i]];
                i = p[i];
            }
            i
        }
        let touch = |a: &([f64; 3], [f64; 3], &str), b: &([f64; 3], [f64; 3], &str)| {
            (0..3).all(|k| a.0[k] <= b.1[k] + 1e-6 && b.0[k] <= a.1[k] + 1e-6)
        };
        for i in 0..all.len() {
            for j in i + 1..all.len() {
                let (a, b) = (&all[i], &all[j]);
                if ![a.2, b.2].iter().any(|w| *w == "floor" || *w == "wall") && touch(a, b) {
                    let (ri, rj) = (root(&mut parent, i), root(&mut parent, j));
                    parent[ri.max(rj)] = ri.min(rj);
                }
            }
        }
        let mut ids = std::collections::BTreeMap::new();
        let boxes = (0..all.len())
            .map(|i| {
                let (min, max, what) = all[i];
                let at = match what {
                    "floor" => IndoorTruthAt::Floor,
                    "wall" => IndoorTruthAt::Wall,
                    _ => {
                        let r = root(&mut parent, i);
                        let n = ids.len() as u32;
                        IndoorTruthAt::Object(*ids.entry(r).or_insert(n))
                    }
                };
                (min, max, at)
            })
            .collect();
        Self { boxes, objects: ids.len() as u32 }
    }

    /// Objects (groups of touching pieces of furniture).
    pub fn objects(&self) -> u32 {
        self.objects
    }

    /// What the scene holds at `p` (m), within `tolerance_m` of a box: an object first, then a
    /// wall, then the floor's top face, else nothing.
    pub fn at(&self, p: &Vector3<f64>, tolerance_m: f64) -> IndoorTruthAt {
        let near = |min: &[f64; 3], max: &[f64; 3]| {
            (0..3).all(|k| p[k] >= min[k] - tolerance_m && p[k] <= max[k] + tolerance_m)
        };
        let touching = || self.boxes.iter().filter(|b| near(&b.0, &b.1));
        if let Some(object) = touching().find(|b| matches!(b.2, IndoorTruthAt::Object(_))) {
            return object.2;
        }
        if touching().any(|b| b.2 == IndoorTruthAt::Wall) {
            return IndoorTruthAt::Wall;
        }
        let on_floor = self.boxes.iter().any(|(min, max, what)| {
            *what == IndoorTruthAt::Floor
                && (0..2).all(|k| p[k] >= min[k] - tolerance_m && p[k] <= max[k] + tolerance_m)
                && (p.z - max[2]).abs() <= tolerance_m
        });
        if on_floor { IndoorTruthAt::Floor } else { IndoorTruthAt::Nothing }
    }
}

/// The building: walls, furniture and floor.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct IndoorScene {
    /// Every box.
    pub boxes: Vec<Box3>,
}

impl IndoorScene {
    /// A ring of corridors 2 m wide around a 38 × 32 m block (outer walls 42 × 36 m; the
    /// corridors' centre line is a 40 × 34 m rectangle, 148 m), 2.5 m high, with what real
    /// corridors hold at irregular spacing so that no stretch of wall is featureless for the
    /// 12 m laser: door recesses (1.2 m wide, 0.4 m deep) in the outer wall, cabinets and
    /// radiators along both walls, a pillar in two outer corners.
    pub fn ring() -> Self {
        let h = 2.5;
        let t = 0.15;
        let (ox, oy, ix, iy) = (21.0, 18.0, 19.0, 16.0);
        let mut b = vec![
            Box3::new("floor", [-ox - 1.0, -oy - 1.0, -0.1], [ox + 1.0, oy + 1.0, 0.0]),
            // The inner block (solid: offices the robot does not enter).
            Box3::new("wall", [-ix, -iy, 0.0], [ix, iy, h]),
        ];
        // Door recesses in the outer wall: (side, position along it), irregular.
        let recesses: [(char, &[f64]); 4] = [
            ('w', &[-12.5, -3.0, 4.5, 13.0]),
            ('n', &[-14.0, -6.5, 1.0, 11.5, 17.0]),
            ('e', &[-11.0, -1.5, 8.0]),
            ('s', &[-16.0, -4.0, 3.5, 9.0, 15.5]),
        ];
        let half = 0.6;
        let depth = 0.4;
        // Each outer wall in segments between its recesses, and the recess' back wall.
        for (side, at) in recesses {
            let (lo, hi) = match side {
                'w' | 'e' => (-oy, oy),
                _ => (-ox, ox),
            };
            let mut cuts: Vec<f64> = at.to_vec();
            cuts.sort_by(f64::total_cmp);
            let mut from = lo - t;
            let mut pieces = vec![];
            for c in &cuts {
                pieces.push((from, c - half));
                from = c + half;
            }
            pieces.push((from, hi + t));
            let wall = |a: f64, b: f64, off: f64| -> Box3 {
                match side {
                    'w' => Box3::new("wall", [-ox - off - t, a, 0.0], [-ox - off, b, h]),
                    'e' => Box3::new("wall", [ox + off, a, 0.0], [ox + off + t, b, h]),
                    'n' => Box3::new("wall", [a, oy + off, 0.0], [b, oy + off + t, h]),
                    _ => Box3::new("wall", [a, -oy - off - t, 0.0], [b, -oy - off, h]),
                }
            };
            for (a, z) in pieces {
                b.push(wall(a, z, 0.0));
            }
            for c in &cuts {
                // Back and the two jambs of the recess.
                b.push(wall(c - half - t, c + half + t, depth));
                b.push(wall(c - half - t, c - half, 0.0).extended(side, depth));
                b.push(wall(c + half, c + half + t, 0.0).extended(side, depth));
            }
        }
        // Furniture along the corridors (in the laser's plane): (what, x0, y0, x1, y1).
        let items: [(&'static str, [f64; 4]); 14] = [
            ("cabinet", [-21.0, -7.0, -20.5, -6.0]),
            ("radiator", [-19.0, 1.0, -18.8, 2.8]),
            ("cabinet", [-21.0, 9.0, -20.4, 10.2]),
            ("radiator", [-9.5, 16.0, -7.5, 16.2]),
            ("cabinet", [4.0, 17.4, 5.5, 18.0]),
            ("radiator", [7.0, 16.0, 9.5, 16.2]),
            ("cabinet", [20.4, 12.0, 21.0, 13.5]),
            ("radiator", [18.8, 3.0, 19.0, 5.5]),
            ("cabinet", [20.5, -6.0, 21.0, -4.8]),
            ("radiator", [18.8, -14.0, 19.0, -12.0]),
            ("cabinet", [11.0, -18.0, 12.3, -17.4]),
            ("radiator", [-1.0, -16.2, 1.5, -16.0]),
            ("cabinet", [-10.0, -18.0, -9.0, -17.5]),
            ("radiator", [-15.5, -16.2, -13.5, -16.0]),
        ];
        for (what, [x0, y0, x1, y1]) in items {
            b.push(Box3::new(what, [x0, y0, 0.0], [x1, y1, 1.0]));
        }
        b.push(Box3::new("pillar", [20.4, 17.4, 0.0], [20.8, 17.8, h]));
        b.push(Box3::new("pillar", [-20.8, -17.8, 0.0], [-20.4, -17.4, h]));
        Self { boxes: b }
    }

    /// The building: two 8 × 10 m rooms joined by a 1.4 m door at x = 0, and a 16 × 1.9 m
    /// corridor along their north side that each room opens onto by a 1.2 m door; 2.5 m high.
    pub fn two_rooms() -> Self {
        let h = 2.5;
        let t = 0.1;
        let mut b = vec![
            Box3::new("floor", [-8.2, -5.2, -0.1], [8.2, 7.2, 0.0]),
            Box3::new("wall", [-8.0 - t, -5.0 - t, 0.0], [8.0 + t, -5.0, h]),
            Box3::new("wall", [-8.0 - t, 7.0, 0.0], [8.0 + t, 7.0 + t, h]),
            Box3::new("wall", [-8.0 - t, -5.0, 0.0], [-8.0, 7.0, h]),
            Box3::new("wall", [8.0, -5.0, 0.0], [8.0 + t, 7.0, h]),
            // Between the rooms and the corridor, with a door into each room.
            Box3::new("wall", [-8.0, 5.0, 0.0], [-4.6, 5.0 + t, h]),
            Box3::new("wall", [-3.4, 5.0, 0.0], [4.4, 5.0 + t, h]),
            Box3::new("wall", [5.6, 5.0, 0.0], [8.0, 5.0 + t, h]),
            Box3::new("wall", [-t / 2.0, -5.0, 0.0], [t / 2.0, -0.7, h]),
            Box3::new("wall", [-t / 2.0, 0.7, 0.0], [t / 2.0, 5.0, h]),
            // The corridor: a radiator and two cabinets on its north wall (in the laser's plane).
            Box3::new("radiator", [-1.0, 6.85, 0.1], [1.0, 7.0, 0.7]),
            Box3::new("cabinet", [-6.4, 6.5, 0.0], [-5.6, 7.0, 1.2]),
            Box3::new("cabinet", [2.6, 6.5, 0.0], [3.4, 7.0, 1.2]),
            // Room A: a table (legs only in the laser's plane), a shelf, a crate below the laser.
            Box3::new("shelf", [-7.0, 4.4, 0.0], [-5.5, 4.95, 1.8]),
            Box3::new("crate", [-3.8, -4.6, 0.0], [-3.2, -4.0, 0.15]),
            // Room B: a table, a shelf, a pillar.
            Box3::new("shelf", [5.0, -4.95, 0.0], [6.5, -4.4, 1.8]),
            Box3::new("pillar", [2.85, 1.85, 0.0], [3.15, 2.15, h]),
        ];
        for (cx, cy) in [(-4.0, 1.5), (4.0, -1.5)] {
            b.push(Box3::new("table_top", [cx - 0.6, cy - 0.4, 0.72], [cx + 0.6, cy + 0.4, 0.76]));
            for (sx, sy) in [(-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)] {
                let (lx, ly) = (cx + sx * 0.55, cy + sy * 0.35);
                b.push(Box3::new("table_leg", [lx - 0.025, ly - 0.025, 0.0], [lx + 0.025, ly + 0.025, 0.72]));
            }
        }
        Self { boxes: b }
    }

    /// Distance along a horizontal ray at height `z` (2-D laser), up to `max_m`.
    pub fn cast_2d(&self, x: f64, y: f64, z: f64, angle: f64, max_m: f64) -> Option<f64> {
        let (o, d) = ([x, y, z], [angle.cos(), angle.sin(), 0.0]);
        self.boxes
            .iter()
            .filter(|b| b.min[2] <= z && z <= b.max[2])
            .filter_map(|b| b.hit(&o, &d, 2))
            .filter(|t| *t <= max_m)
            .min_by(f64::total_cmp)
    }

    /// Distance along a 3-D ray (unit `d`), up to `max_m`.
    pub fn cast_3d(&self, o: &[f64; 3], d: &[f64; 3], max_m: f64) -> Option<f64> {
        self.boxes.iter().filter_map(|b| b.hit(o, d, 3)).filter(|t| *t <= max_m).min_by(f64::total_cmp)
    }

    /// Whether a world point is inside anything (the scene's true occupancy).
    pub fn occupied(&self, p: &[f64; 3]) -> bool {
        self.boxes.iter().any(|b| b.contains(p))
    }
}

/// The 2-D laser.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IndoorLaserConfig {
    /// Scans per second.
    pub rate_hz: f64,
    /// Beams over the full circle.
    pub beams: usize,
    /// Range noise σ, m.
    pub noise_sigma_m: f64,
    /// Maximum range (no return beyond: reported as this), m.
    pub max_range_m: f64,
    /// Probability that a beam drops out (reported as NaN).
    pub dropout_prob: f64,
    /// Height of the scan plane above the floor, m.
    pub height_m: f64,
    /// Position on the body (x, y), m.
    pub offset_m: [f64; 2],
}

impl Default for IndoorLaserConfig {
    fn default() -> Self {
        Self {
            rate_hz: 10.0,
            beams: 360,
            noise_sigma_m: 0.03,
            max_range_m: 12.0,
            dropout_prob: 0.01,
            height_m: 0.25,
            offset_m: [0.1, 0.0],
        }
    }
}

/// Wheel encoders of the three-wheel omni base.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OmniOdometryConfig {
    /// Samples per second.
    pub rate_hz: f64,
    /// Wheel distance from the centre, m.
    pub center_to_wheel_m: f64,
    /// Wheel radius, m.
    pub wheel_radius_m: f64,
    /// Relative noise σ of each wheel's measured speed.
    pub wheel_noise: f64,
    /// Systematic scale error of each wheel (unequal wear), relative.
    pub wheel_scale: [f64; 3],
    /// Slip events per second (a wheel loses traction).
    pub slip_rate_hz: f64,
    /// During a slip the wheel's measured speed is this many times the true one.
    pub slip_factor: f64,
    /// How long a slip lasts, s.
    pub slip_duration_s: f64,
}

impl Default for OmniOdometryConfig {
    fn default() -> Self {
        Self {
            rate_hz: 50.0,
            center_to_wheel_m: 0.2,
            wheel_radius_m: 0.05,
            wheel_noise: 0.02,
            wheel_scale: [0.01, -0.015, 0.005],
            slip_rate_hz: 0.05,
            slip_factor: 1.6,
            slip_duration_s: 0.5,
        }
    }
}

/// The Kinect-like depth camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IndoorDepthConfig {
    /// Frames per second (0: off).
    pub rate_hz: f64,
    /// Image width, px (decimated from 640).
    pub width_px: u32,
    /// Image height, px (decimated from 480).
    pub height_px: u32,
    /// Horizontal field of view, deg.
    pub hfov_deg: f64,
    /// Vertical field of view, deg.
    pub vfov_deg: f64,
    /// Nearest valid depth, m.
    pub min_range_m: f64,
    /// Farthest valid depth, m.
    pub max_range_m: f64,
    /// Depth noise σ at 1 m, growing with depth², m.
    pub noise_at_1m_m: f64,
    /// Position on the body, m.
    pub offset_m: [f64; 3],
    /// Pitch below body x, deg.
    pub pitch_down_deg: f64,
}

impl Default for IndoorDepthConfig {
    fn default() -> Self {
        Self {
            rate_hz: 2.0,
            width_px: 160,
            height_px: 120,
            hfov_deg: 57.0,
            vfov_deg: 43.0,
            min_range_m: 0.7,
            max_range_m: 6.0,
            noise_at_1m_m: 0.0015,
            offset_m: [0.1, 0.0, 0.6],
            pitch_down_deg: 10.0,
        }
    }
}

/// The mission.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IndoorConfig {
    /// Seed of every noise stream.
    pub seed: u64,
    /// Path speed, m/s.
    pub speed_mps: f64,
    /// Laps of the loop.
    pub laps: u32,
    /// Amplitude of the heading's sway about the path direction (the base strafes), rad.
    pub heading_sway_rad: f64,
    /// Period of the sway, s.
    pub sway_period_s: f64,
    /// Fastest turn, rad/s.
    pub max_turn_radps: f64,
    /// The laser.
    pub laser: IndoorLaserConfig,
    /// The wheel encoders.
    pub odometry: OmniOdometryConfig,
    /// The depth camera.
    pub depth: IndoorDepthConfig,
    /// The building and its path.
    pub building: Building,
}

impl Default for IndoorConfig {
    fn default() -> Self {
        Self {
            building: Building::TwoRooms,
            seed: 11,
            speed_mps: 0.4,
            laps: 2,
            heading_sway_rad: 0.6,
            sway_period_s: 25.0,
            max_turn_radps: 0.8,
            laser: IndoorLaserConfig::default(),
            odometry: OmniOdometryConfig::default(),
            depth: IndoorDepthConfig::default(),
        }
    }
}

impl Validate for IndoorConfig {
    fn validate(&self, issues: &mut Issues) {
        let mut pos = |k: &str, x: f64| issues.check(x.is_finite() && x > 0.0, k, format!("must be > 0, got {x}"));
        pos("speed_mps", self.speed_mps);
        pos("sway_period_s", self.sway_period_s);
        pos("max_turn_radps", self.max_turn_radps);
        pos("laser.rate_hz", self.laser.rate_hz);
        pos("laser.max_range_m", self.laser.max_range_m);
        pos("odometry.rate_hz", self.odometry.rate_hz);
        pos("odometry.center_to_wheel_m", self.odometry.center_to_wheel_m);
        pos("odometry.wheel_radius_m", self.odometry.wheel_radius_m);
        pos("depth.max_range_m", self.depth.max_range_m);
        if self.laps == 0 {
            issues.push("laps", "must be >= 1");
        }
        if self.laser.beams < 8 {
            issues.push("laser.beams", "must be >= 8");
        }
        if !(0.0..1.0).contains(&self.laser.dropout_prob) {
            issues.push("laser.dropout_prob", "must be within [0, 1)");
        }
        if self.depth.rate_hz < 0.0 || self.depth.width_px == 0 || self.depth.height_px == 0 {
            issues.push("depth", "rate must be >= 0 and the image non-empty");
        }
        if !(self.depth.min_range_m >= 0.0 && self.depth.min_range_m < self.depth.max_range_m) {
            issues.push("depth.min_range_m", "must be below max_range_m");
        }
    }
}

/// The loop's waypoints (m): up room A, through its door into the corridor, along it, into room B,
/// down room B and back through the middle door into room A.
pub const WAYPOINTS: [[f64; 2]; 10] = [
    [-6.0, -3.0],
    [-6.0, 3.2],
    [-4.0, 3.6],
    [-4.0, 6.0],
    [5.0, 6.0],
    [5.0, 3.8],
    [6.5, 3.0],
    [6.5, 0.3],
    [1.5, 0.0],
    [-1.5, 0.0],
];

/// The ring building's path ([`IndoorScene::ring`]): along the corridors' centre line
/// counter-clockwise from the west corridor, once round (148 m), then on to 12 m past the start
/// and back to it.
pub const RING_WAYPOINTS: [[f64; 2]; 6] =
    [[-20.0, -10.0], [-20.0, 17.0], [20.0, 17.0], [20.0, -17.0], [-20.0, -17.0], [-20.0, 2.0]];

/// What the simulator emits.
#[derive(Debug, Clone, PartialEq)]
pub enum IndoorEvent {
    /// Wheel odometry: the integrated pose, the measured body velocity and wheel rim speeds.
    Odometry {
        /// Time, s.
        t_s: f64,
        /// Odometry pose (its frame starts at the true start pose).
        pose: Pose2,
        /// Measured body velocity.
        velocity: BodyVelocity,
        /// Measured wheel rim speeds, m/s.
        wheel_speeds_mps: [f64; 3],
    },
    /// A laser scan (NaN: dropout; `max_range_m`: no return).
    Laser {
        /// Time, s.
        t_s: f64,
        /// Ranges, m, counter-clockwise from −π.
        ranges: Vec<f32>,
    },
    /// A depth-camera cloud, points in the optical frame.
    Cloud {
        /// Time, s.
        t_s: f64,
        /// The camera's true pose (`world_from_camera`), for building a reference map.
        world_from_camera: Isometry3<f64>,
        /// Points, m.
        points: Vec<[f32; 3]>,
    },
}

impl IndoorEvent {
    /// Time, s.
    pub fn t_s(&self) -> f64 {
        match self {
            IndoorEvent::Odometry { t_s, .. } | IndoorEvent::Laser { t_s, .. } | IndoorEvent::Cloud { t_s, .. } => *t_s,
        }
    }
}

/// The simulator: yields events in time order.
pub struct IndoorSim {
    cfg: IndoorConfig,
    scene: IndoorScene,
    base: OmniBase,
    /// Path as cumulative lengths.
    path: Vec<([f64; 2], f64)>,
    total_m: f64,
    dt_s: f64,
    truth: Vec<(f64, Pose2)>,
    heading: f64,
    odom: Pose2,
    next_laser_s: f64,
    next_depth_s: f64,
    next_odom_s: f64,
    slip: Option<(usize, f64)>,
    rng_odo: Xoshiro256PlusPlus,
    rng_laser: Xoshiro256PlusPlus,
    rng_depth: Xoshiro256PlusPlus,
    last_true: Pose2,
    done: bool,
}

impl IndoorSim {
    /// A simulator for `cfg`.
    pub fn new(cfg: IndoorConfig) -> Result<Self, crate::SimError> {
        cfg.issues().into_result().map_err(crate::SimError::Config)?;
        let base = OmniBase::new(cfg.odometry.center_to_wheel_m, cfg.odometry.wheel_radius_m).map_err(|e| {
            crate::SimError::Config(vec![validation::ConfigIssue { key: "odometry".into(), message: e.to_string() }])
        })?;
        let mut path = Vec::new();
        let mut s = 0.0;
        let (waypoints, laps): (&[[f64; 2]], u32) = match cfg.building {
            Building::TwoRooms => (&WAYPOINTS, cfg.laps),
            Building::Ring => (&RING_WAYPOINTS, 1),
        };
        for _ in 0..laps {
            for w in waypoints.iter() {
                if let Some((last, _)) = path.last() {
                    let last: &[f64; 2] = last;
                    s += (w[0] - last[0]).hypot(w[1] - last[1]);
                }
                path.push((*w, s));
            }
        }
        let first = waypoints[0];
        let last = path.last().map(|p| p.0).unwrap_or(first);
        s += (first[0] - last[0]).hypot(first[1] - last[1]);
        path.push((first, s));
        let seed = cfg.seed;
        let dt_s = 1.0 / cfg.odometry.rate_hz;
        let start_dir = (waypoints[1][1] - first[1]).atan2(waypoints[1][0] - first[0]);
        let start = Pose2 { x_m: first[0], y_m: first[1], theta_rad: start_dir };
        Ok(Self {
            scene: match cfg.building {
                Building::TwoRooms => IndoorScene::two_rooms(),
                Building::Ring => IndoorScene::ring(),
            },
            base,
            path,
            total_m: s,
            dt_s,
            truth: vec![(0.0, start)],
            heading: start_dir,
            odom: start,
            next_laser_s: 0.0,
            next_depth_s: 0.0,
            next_odom_s: dt_s,
            slip: None,
            rng_odo: Xoshiro256PlusPlus::seed_from_u64(seed ^ 0x0d0),
            rng_laser: Xoshiro256PlusPlus::seed_from_u64(seed ^ 0x1a5e),
            rng_depth: Xoshiro256PlusPlus::seed_from_u64(seed ^ 0xde9),
            last_true: start,
            cfg,
            done: false,
        })
    }

    /// The scene.
    pub fn scene(&self) -> &IndoorScene {
        &self.scene
    }

    /// The mission's duration, s.
    pub fn duration_s(&self) -> f64 {
        self.total_m / self.cfg.speed_mps
    }

    /// The true poses so far (`world_from_body`, planar).
    pub fn truth(&self) -> &[(f64, Pose2)] {
        &self.truth
    }

    /// The true pose as a 3-D isometry.
    pub fn iso(p: &Pose2) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(p.x_m, p.y_m, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, p.theta_rad),
        )
    }

    /// Path position and direction at arc length `s`.
    fn along(&self, s: f64) -> ([f64; 2], f64) {
        let s = s.clamp(0.0, self.total_m);
        let k = self.path.partition_point(|(_, c)| *c < s).clamp(1, self.path.len() - 1);
        let ((a, sa), (b, sb)) = (self.path[k - 1], self.path[k]);
        let f = if sb > sa { (s - sa) / (sb - sa) } else { 0.0 };
        ([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])], (b[1] - a[1]).atan2(b[0] - a[0]))
    }

    /// The true pose at time t (advancing the heading filter by one step).
    fn advance(&mut self, t: f64) -> Pose2 {
        let s = t * self.cfg.speed_mps;
        let (p, dir) = self.along(s);
        let target = dir + self.cfg.heading_sway_rad * (std::f64::consts::TAU * t / self.cfg.sway_period_s).sin();
        let err = omni::wrap_angle(target - self.heading);
        let step = self.cfg.max_turn_radps * self.dt_s;
        self.heading = omni::wrap_angle(self.heading + err.clamp(-step, step));
        Pose2 { x_m: p[0], y_m: p[1], theta_rad: self.heading }
    }

    fn laser_scan(&mut self, pose: &Pose2) -> Vec<f32> {
        let l = &self.cfg.laser;
        let o = pose.compose(&Pose2 { x_m: l.offset_m[0], y_m: l.offset_m[1], theta_rad: 0.0 });
        let noise = Normal::new(0.0, l.noise_sigma_m.max(1e-12)).expect("σ > 0");
        (0..l.beams)
            .map(|k| {
                let a = -std::f64::consts::PI + k as f64 * std::f64::consts::TAU / l.beams as f64;
                if self.rng_laser.random::<f64>() < l.dropout_prob {
                    return f32::NAN;
                }
                match self.scene.cast_2d(o.x_m, o.y_m, l.height_m, o.theta_rad + a, l.max_range_m) {
                    Some(r) => ((r + noise.sample(&mut self.rng_laser)).min(l.max_range_m)) as f32,
                    None => l.max_range_m as f32,
                }
            })
            .collect()
    }

    /// `body_from_camera` of the depth camera.
    pub fn body_from_camera(&self) -> Isometry3<f64> {
        let d = &self.cfg.depth;
        geometry::body_from_camera(&Vector3::from(d.offset_m), d.pitch_down_deg.to_radians())
    }

    fn depth_cloud(&mut self, pose: &Pose2) -> Vec<[f32; 3]> {
        let d = self.cfg.depth.clone();
        let world_from_cam = Self::iso(pose) * self.body_from_camera();
        let o = world_from_cam.translation.vector;
        let fx = (d.width_px as f64 / 2.0) / (d.hfov_deg.to_radians() / 2.0).tan();
        let fy = (d.height_px as f64 / 2.0) / (d.vfov_deg.to_radians() / 2.0).tan();
        let (cx, cy) = ((d.width_px as f64 - 1.0) / 2.0, (d.height_px as f64 - 1.0) / 2.0);
        let mut pts = Vec::with_capacity((d.width_px * d.height_px) as usize);
        let unit = Normal::new(0.0, 1.0).expect("unit");
        for v in 0..d.height_px {
            for u in 0..d.width_px {
                let ray_c = Vector3::new((u as f64 - cx) / fx, (v as f64 - cy) / fy, 1.0);
                let dir_w = world_from_cam.rotation * ray_c.normalize();
                let far = d.max_range_m * ray_c.norm() + 0.5;
                let Some(t) = self.scene.cast_3d(&[o.x, o.y, o.z], &[dir_w.x, dir_w.y, dir_w.z], far) else { continue };
                // Depth along the optical axis, as a Kinect measures it.
                let z = t / ray_c.norm();
                if z < d.min_range_m || z > d.max_range_m {
                    continue;
                }
                let z = z + d.noise_at_1m_m * z * z * unit.sample(&mut self.rng_depth);
                pts.push([(ray_c.x * z) as f32, (ray_c.y * z) as f32, z as f32]);
            }
        }
        pts
    }

    /// One odometry step: the true body velocity over the step, through the wheels with their
    /// errors, integrated.
    fn odometry(&mut self, t: f64, prev: &Pose2, now: &Pose2) -> IndoorEvent {
        let c = self.cfg.odometry.clone();
        let u = prev.between(now);
        let dt = self.dt_s;
        let v_true = BodyVelocity { vx_mps: u.x_m / dt, vy_mps: u.y_m / dt, omega_radps: u.theta_rad / dt };
        let mut w = self.base.wheel_speeds(v_true);
        if self.slip.is_none_or(|(_, until)| t > until) {
            self.slip = None;
            if self.rng_odo.random::<f64>() < c.slip_rate_hz * dt {
                let wheel = (self.rng_odo.random::<f64>() * 3.0) as usize % 3;
                self.slip = Some((wheel, t + c.slip_duration_s));
            }
        }
        let n = Normal::new(0.0, c.wheel_noise.max(1e-12)).expect("σ > 0");
        for (i, wi) in w.iter_mut().enumerate() {
            *wi *= 1.0 + c.wheel_scale[i] + n.sample(&mut self.rng_odo);
            if self.slip.is_some_and(|(k, _)| k == i) {
                *wi *= c.slip_factor;
            }
        }
        let v = self.base.body_velocity(w);
        self.odom = self.odom.compose(&omni::body_increment(v, dt));
        IndoorEvent::Odometry { t_s: t, pose: self.odom, velocity: v, wheel_speeds_mps: w }
    }

    /// The next events (all sensors due at the next odometry step, odometry first), or `None`
    /// at the end of the mission.
    pub fn next_events(&mut self) -> Option<Vec<IndoorEvent>> {
        if self.done {
            return None;
        }
        let t = self.next_odom_s;
        if t > self.duration_s() {
            self.done = true;
            return None;
        }
        self.next_odom_s += self.dt_s;
        let prev = self.last_true;
        let now = self.advance(t);
        self.last_true = now;
        self.truth.push((t, now));
        let mut out = vec![self.odometry(t, &prev, &now)];
        if t + 1e-9 >= self.next_laser_s {
            self.next_laser_s += 1.0 / self.cfg.laser.rate_hz;
            out.push(IndoorEvent::Laser { t_s: t, ranges: self.laser_scan(&now) });
        }
        if self.cfg.depth.rate_hz > 0.0 && t + 1e-9 >= self.next_depth_s {
            self.next_depth_s += 1.0 / self.cfg.depth.rate_hz;
            let world_from_camera = Self::iso(&now) * self.body_from_camera();
            out.push(IndoorEvent::Cloud { t_s: t, world_from_camera, points: self.depth_cloud(&now) });
        }
        Some(out)
    }

    /// The config.
    pub fn config(&self) -> &IndoorConfig {
        &self.cfg
    }
}

/// The scene's true occupancy at a point (for map agreement checks): `Point3` convenience.
pub fn truly_occupied(scene: &IndoorScene, p: &Point3<f64>) -> bool {
    scene.occupied(&[p.x, p.y, p.z])
}

#[cfg(test)]
mod tests {

    #[test]
    fn the_indoor_truth_groups_a_tables_parts_and_knows_the_floor() {
        let scene = IndoorScene::two_rooms();
        let truth = IndoorTruth::new(scene.boxes.iter().map(|b| (b.min, b.max, b.what)));
        let id_of = |what: &str| {
            let b = scene.boxes.iter().find(|b| b.what == what).expect(what);
            let c = Vector3::new((b.min[0] + b.max[0]) / 2.0, (b.min[1] + b.max[1]) / 2.0, (b.min[2] + b.max[2]) / 2.0);
            truth.at(&c, 0.05)
        };
        // A table's top and its legs are one object, a crate another; the walls are no object.
        let (top, leg, wall, krate) = (id_of("table_top"), id_of("table_leg"), id_of("wall"), id_of("crate"));
        assert!(matches!(top, IndoorTruthAt::Object(_)), "{top:?}");
        assert_eq!(top, leg);
        assert_eq!(wall, IndoorTruthAt::Wall);
        assert!(matches!(krate, IndoorTruthAt::Object(_)), "{krate:?}");
        assert_ne!(krate, top);
        // A cabinet against the corridor's north wall is an object of its own.
        let cabinet = scene.boxes.iter().find(|b| b.what == "cabinet").expect("cabinet");
        let back = Vector3::new((cabinet.min[0] + cabinet.max[0]) / 2.0, cabinet.max[1] - 0.01, 0.5);
        assert!(matches!(truth.at(&back, 0.05), IndoorTruthAt::Object(_)));
        // The floor's top, away from everything; the air above it.
        let floor = scene.boxes.iter().find(|b| b.what == "floor").expect("floor");
        let clear = (0..400)
            .map(|k| Vector3::new(-7.5 + 0.75 * (k % 20) as f64, -4.5 + 0.55 * (k / 20) as f64, floor.max[2]))
            .find(|p| truth.at(p, 0.05) == IndoorTruthAt::Floor)
            .expect("a free spot of floor");
        assert_eq!(truth.at(&(clear + Vector3::new(0.0, 0.0, 1.0)), 0.05), IndoorTruthAt::Nothing);
        assert!(truth.objects() >= 3);
    }

    use super::*;

    #[test]
    fn the_mission_is_deterministic_drives_two_laps_and_every_sensor_reports() {
        let cfg = IndoorConfig {
            depth: IndoorDepthConfig { width_px: 40, height_px: 30, ..Default::default() },
            ..Default::default()
        };
        let mut a = IndoorSim::new(cfg.clone()).expect("valid");
        let mut b = IndoorSim::new(cfg).expect("valid");
        let (mut odo, mut laser, mut clouds) = (0, 0, 0);
        let mut last_odo = Pose2::default();
        while let Some(ev) = a.next_events() {
            // Debug text compares NaN dropouts equal too.
            assert!(format!("{ev:?}") == format!("{:?}", b.next_events().expect("same length")), "not deterministic");
            for e in ev {
                match e {
                    IndoorEvent::Odometry { pose, .. } => {
                        odo += 1;
                        last_odo = pose;
                    }
                    IndoorEvent::Laser { ranges, .. } => {
                        laser += 1;
                        assert_eq!(ranges.len(), 360);
                        let valid = ranges.iter().filter(|r| r.is_finite() && **r < 12.0).count();
                        assert!(valid > 300, "{valid}");
                    }
                    IndoorEvent::Cloud { points, .. } => {
                        clouds += 1;
                        assert!(!points.is_empty());
                    }
                }
            }
        }
        let d = a.duration_s();
        assert!(d > 150.0, "{d}");
        assert_eq!(laser, (d * 10.0).ceil() as usize);
        assert!(odo > laser * 4 && clouds > laser / 6, "{odo} {laser} {clouds}");
        // The odometry drifts: it ends away from the truth, which ends where it started.
        let truth_end = a.truth().last().expect("truth").1;
        assert!((truth_end.x_m - -6.0).abs() < 0.1 && (truth_end.y_m - -3.0).abs() < 0.1, "{truth_end:?}");
        let drift = (last_odo.x_m - truth_end.x_m).hypot(last_odo.y_m - truth_end.y_m);
        assert!(drift > 0.3, "encoder errors and slip make the odometry drift: {drift}");
        // The base strafes: the heading is not the direction of motion.
        let t = a.truth();
        let strafing = t.windows(2).filter(|w| {
            let u = w[0].1.between(&w[1].1);
            u.y_m.abs() > 0.2 * u.x_m.hypot(u.y_m) && u.x_m.hypot(u.y_m) > 1e-4
        });
        assert!(strafing.count() > t.len() / 4);
    }

    #[test]
    fn the_laser_sees_table_legs_but_not_the_crate_or_the_table_top() {
        let s = IndoorScene::two_rooms();
        // Towards the crate (top at 0.15 m) at the laser's 0.25 m: the wall behind it.
        let r = s.cast_2d(-3.5, -2.0, 0.25, -std::f64::consts::FRAC_PI_2, 12.0).expect("wall");
        assert!((r - 3.0).abs() < 1e-9, "{r}");
        // At 0.1 m it hits the crate.
        let r = s.cast_2d(-3.5, -2.0, 0.1, -std::f64::consts::FRAC_PI_2, 12.0).expect("crate");
        assert!((r - 2.0).abs() < 1e-9, "{r}");
        // A table leg is in the laser's plane; the top is not.
        let leg = s.cast_2d(-6.0, 1.15, 0.25, 0.0, 12.0).expect("something");
        assert!((leg - (-4.55 - 0.025 + 6.0)).abs() < 1e-9, "{leg}");
        assert!(s.occupied(&[-4.0, 1.5, 0.74]) && !s.occupied(&[-4.0, 1.5, 0.25]));
    }
}
