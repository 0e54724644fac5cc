//! Navigable space discovery and obstacles ([6D] §III-VI, EQUATIONS §7), on the occupied voxels of an
//! occupancy map and the points that fell into them.
//!
//! 1. [`PointAccumulator`] keeps, per voxel (`res`-sized cells, key ⌊x/res⌋), the count, sum
//!    and sum of outer products of the end points inserted: enough for a least-squares plane.
//! 2. [`fit_plane`]: PCA of a voxel's points; the normal is the eigenvector of the smallest
//!    eigenvalue of their covariance, and that eigenvalue is the MSE (mean squared distance of
//!    the points to the plane). A voxel is planar when it has `min_points` points and MSE ≤
//!    `max_plane_mse_m2`.
//! 3. Navigable regions ([6D] Alg 1 NSD): planar voxels whose slope (angle between the normal
//!    and world z) is at most `max_slope_deg` are navigable candidates; two adjacent candidates
//!    (26-neighbourhood) join one region when their planes meet at their common boundary: both
//!    planes, evaluated where the two voxels touch (the midpoint of their centres), agree within
//!    `max_step_m`, and their normals differ by at most `max_normal_angle_deg`. Regions are the
//!    connected components (union-find).
//! 4. Obstacles: seeds are the non-planar voxels; each grows through adjacent occupied voxels that
//!    are not navigable (non-planar, or planar but too steep: walls, box sides). Each obstacle is
//!    a Gaussian (mean and covariance of its points), and obstacles of different scans or maps
//!    are associated by the Bhattacharyya distance ([`associate_obstacles`]). Against the ground
//!    (the largest region) beside an obstacle, its foot: a region that rises above the foot is
//!    the obstacle's top and joins it; an obstacle whose shape lies within the foot's scatter is
//!    ground (EQUATIONS §7, "The ground and an obstacle's foot").
//! 5. [`write_navigable_ply`] and [`write_obstacles_ply`] write the two layers (navigable voxel
//!    patches with their region, obstacles as meshes of their voxels' outer faces).
//! 6. [`traversability::TraversabilityGrid`]: a 2.5-D grid of class, height and slope per
//!    column of voxels, as map_server files plus float layers.
//! 7. [`truth::score`] scores a discovery against a scene's truth (voxel classes, objects found,
//!    the largest region's share of the ground).
//!
//! A map that grows during a run keeps its voxels' plane fits in [`PlaneFits`], refreshed from
//! the voxels that gained points ([`PointAccumulator::take_changed`]); [`discover_with`] then
//! fits only the voxels changed since, with the same result as [`discover`].

pub mod traversability;
pub mod truth;

use std::collections::{BTreeMap, HashMap};

use rustc_hash::{FxHashMap, FxHashSet};
use std::io::Write;
use std::path::Path;

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use serde::{Deserialize, Serialize};
use validation::{Issues, Validate};

/// A voxel index, ⌊x/res⌋ per axis.
pub type VoxelKey = [i32; 3];

/// A map from voxels, hashed with the fast non-cryptographic Fx hash (the keys are ours, not an
/// attacker's; SipHash was a third of the discovery's time).
pub type VoxelMap<V> = FxHashMap<VoxelKey, V>;

/// Errors.
#[derive(Debug, thiserror::Error)]
pub enum NavigableError {
    /// A setting is out of range.
    #[error("{key}: {message}")]
    Config {
        /// The key.
        key: String,
        /// What is wrong.
        message: String,
    },
    /// Writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The error.
        source: std::io::Error,
    },
}

/// Point statistics of one voxel.
///
/// Besides the sums over all its points, a voxel keeps the scatter of each scan's points about
/// that scan's own mean, pooled over the scans ([`VoxelStats::within_scatter`]): a surface seen
/// from two poses that disagree by a few centimetres is two parallel sheets of points, which the
/// whole voxel's covariance calls thick, but each scan's points still lie on one plane. A voxel
/// filled point by point ([`VoxelStats::add`]) is one scan until it is merged with another.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct VoxelStats {
    /// Points.
    pub n: u32,
    /// Sum of the points, m.
    pub sum_m: Vector3<f64>,
    /// Sum of p·pᵀ, m² (upper triangle xx, xy, xz, yy, yz, zz; [`VoxelStats::sum_sq_m2`]).
    sum_sq: [f64; 6],
    /// The scans' scatter about their own means, summed (upper triangle xx, xy, xz, yy, yz, zz;
    /// m²); only meaningful when `scans > 0`.
    within_m2: [f32; 6],
    /// Scans merged (0: filled point by point, one scan).
    scans: u32,
}

fn packed(m: &Matrix3<f64>) -> [f32; 6] {
    [m[(0, 0)], m[(0, 1)], m[(0, 2)], m[(1, 1)], m[(1, 2)], m[(2, 2)]].map(|v| v as f32)
}

fn unpacked(p: &[f32; 6]) -> Matrix3<f64> {
    let v = p.map(f64::from);
    Matrix3::new(v[0], v[1], v[2], v[1], v[3], v[4], v[2], v[4], v[5])
}

impl VoxelStats {
    /// Adds a point (of the same scan as the points before it).
    pub fn add(&mut self, p: &Vector3<f64>) {
        self.n += 1;
        self.sum_m += p;
        for (s, v) in self.sum_sq.iter_mut().zip([p.x * p.x, p.x * p.y, p.x * p.z, p.y * p.y, p.y * p.z, p.z * p.z]) {
            *s += v;
        }
    }

    /// Merges another voxel's statistics (another scan's, or another set of scans').
    pub fn merge(&mut self, o: &VoxelStats) {
        if o.n == 0 {
            return;
        }
        if self.n == 0 {
            *self = *o;
            return;
        }
        let within = self.within_scatter() + o.within_scatter();
        self.scans = self.scans() + o.scans();
        self.within_m2 = packed(&within);
        self.n += o.n;
        self.sum_m += o.sum_m;
        for (s, v) in self.sum_sq.iter_mut().zip(o.sum_sq) {
            *s += v;
        }
    }

    /// Sum of p·pᵀ over the points, m².
    pub fn sum_sq_m2(&self) -> Matrix3<f64> {
        let v = &self.sum_sq;
        Matrix3::new(v[0], v[1], v[2], v[1], v[3], v[4], v[2], v[4], v[5])
    }

    /// Scans whose points are in the voxel.
    pub fn scans(&self) -> u32 {
        if self.n == 0 { 0 } else { self.scans.max(1) }
    }

    /// Σ over the scans of Σ (p − mean of the scan)(p − mean of the scan)ᵀ, m²: the scatter
    /// left when every scan's points are moved to a common mean (what is left of a surface when
    /// the poses' disagreement between scans is taken out).
    pub fn within_scatter(&self) -> Matrix3<f64> {
        if self.scans > 0 {
            unpacked(&self.within_m2)
        } else {
            match self.mean_cov() {
                Some((_, cov)) => cov * self.n as f64,
                None => Matrix3::zeros(),
            }
        }
    }

    /// Mean of the points, m (`None` without points): [`VoxelStats::mean_cov`]'s mean, without
    /// the covariance's work.
    #[inline]
    pub fn mean(&self) -> Option<Vector3<f64>> {
        (self.n > 0).then(|| self.sum_m / self.n as f64)
    }

    /// Mean and (population) covariance of the points.
    pub fn mean_cov(&self) -> Option<(Vector3<f64>, Matrix3<f64>)> {
        let mean = self.mean()?;
        let n = self.n as f64;
        let cov = self.sum_sq_m2() / n - mean * mean.transpose();
        Some((mean, (cov + cov.transpose()) * 0.5))
    }
}

/// The end points of the inserted scans, by voxel.
///
/// A voxel only gains points (its count grows with every change), which is what lets
/// [`PlaneFits`] tell a kept fit from a stale one by the count alone.
#[derive(Debug, Clone, Default)]
pub struct PointAccumulator {
    res_m: f64,
    cells: VoxelMap<VoxelStats>,
    /// With [`PointAccumulator::track_changes`]: the voxels that gained points since the last
    /// [`PointAccumulator::take_changed`].
    changed: Option<rustc_hash::FxHashSet<VoxelKey>>,
}

impl PointAccumulator {
    /// An empty accumulator with voxels of `res_m` (> 0).
    pub fn new(res_m: f64) -> Self {
        Self { res_m, cells: VoxelMap::default(), changed: None }
    }

    /// From now on, remembers which voxels gain points (for [`PointAccumulator::take_changed`]).
    pub fn track_changes(&mut self) {
        self.changed.get_or_insert_with(Default::default);
    }

    /// The voxels that gained points since the last call (or since
    /// [`PointAccumulator::track_changes`]); none without tracking.
    pub fn take_changed(&mut self) -> Vec<VoxelKey> {
        self.changed.as_mut().map(|c| c.drain().collect()).unwrap_or_default()
    }

    /// The voxel size, m.
    pub fn resolution_m(&self) -> f64 {
        self.res_m
    }

    /// The voxel of a point.
    pub fn key(&self, p: &Vector3<f64>) -> VoxelKey {
        [(p.x / self.res_m).floor() as i32, (p.y / self.res_m).floor() as i32, (p.z / self.res_m).floor() as i32]
    }

    /// Centre of a voxel, m.
    pub fn centre(&self, k: &VoxelKey) -> Vector3<f64> {
        Vector3::new(k[0] as f64 + 0.5, k[1] as f64 + 0.5, k[2] as f64 + 0.5) * self.res_m
    }

    /// Adds a point (non-finite points are skipped).
    pub fn add(&mut self, p: &Vector3<f64>) {
        if p.iter().all(|v| v.is_finite()) {
            let k = self.key(p);
            self.cells.entry(k).or_default().add(p);
            if let Some(c) = &mut self.changed {
                c.insert(k);
            }
        }
    }

    /// Adds every voxel of `other`, which must have the same voxel size (its keys are this one's).
    /// One lookup per voxel instead of one per point: a scan accumulated on its own (a small map,
    /// in cache) and merged costs a fraction of adding its points to a large map one by one.
    pub fn merge(&mut self, other: &PointAccumulator) -> Result<(), NavigableError> {
        if other.res_m != self.res_m {
            return Err(NavigableError::Config {
                key: "resolution_m".into(),
                message: format!("cannot merge voxels of {} m into voxels of {} m", other.res_m, self.res_m),
            });
        }
        for (k, v) in &other.cells {
            if v.n == 0 {
                continue;
            }
            self.cells.entry(*k).or_default().merge(v);
            if let Some(c) = &mut self.changed {
                c.insert(*k);
            }
        }
        Ok(())
    }

    /// The statistics of every voxel with points.
    pub fn cells(&self) -> &VoxelMap<VoxelStats> {
        &self.cells
    }
}

/// Settings of the discovery.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NsdConfig {
    /// Points a voxel needs for a plane fit.
    pub min_points: u32,
    /// A voxel is planar when the MSE of its plane fit is at most this, m².
    pub max_plane_mse_m2: f64,
    /// Steepest slope a robot can climb: navigable planes have normals within this of world z, deg.
    pub max_slope_deg: f64,
    /// Adjacent planes join a region when they differ by at most this at their boundary, m.
    pub max_step_m: f64,
    /// ... and their normals by at most this, deg.
    pub max_normal_angle_deg: f64,
    /// Obstacles with fewer voxels of their own shape (steep or not planar; sparse voxels they
    /// grew through do not count) are dropped: noise, or a surface the poses smeared.
    pub min_obstacle_voxels: usize,
    /// Navigable regions smaller than this are no space a vehicle can use (its footprint), m²:
    /// they join the obstacles they touch (planar patches on an object's surface) or are left
    /// as patches.
    pub min_region_area_m2: f64,
    /// A wall spans at least this along its plane ([`Wall`]), m (0: no walls, every steep
    /// surface is an obstacle's).
    pub min_wall_length_m: f64,
    /// ... and at least this tall, m.
    pub min_wall_height_m: f64,
}

impl Default for NsdConfig {
    fn default() -> Self {
        Self {
            min_points: 5,
            max_plane_mse_m2: 1e-4, // 1 cm RMS off the plane
            max_slope_deg: 30.0,
            max_step_m: 0.03,
            max_normal_angle_deg: 20.0,
            min_obstacle_voxels: 3,
            min_region_area_m2: 0.25,
            min_wall_length_m: 2.0,
            min_wall_height_m: 1.3,
        }
    }
}

impl Validate for NsdConfig {
    fn validate(&self, issues: &mut Issues) {
        issues.check(self.min_points >= 3, "min_points", "must be >= 3");
        issues.check(
            self.max_plane_mse_m2.is_finite() && self.max_plane_mse_m2 >= 0.0,
            "max_plane_mse_m2",
            "must be >= 0",
        );
        issues.check((0.0..=90.0).contains(&self.max_slope_deg), "max_slope_deg", "must be in [0, 90]");
        issues.check(self.max_step_m.is_finite() && self.max_step_m >= 0.0, "max_step_m", "must be >= 0");
        issues.check((0.0..=90.0).contains(&self.max_normal_angle_deg), "max_normal_angle_deg", "must be in [0, 90]");
        issues.check(
            self.min_region_area_m2.is_finite() && self.min_region_area_m2 >= 0.0,
            "min_region_area_m2",
            "must be >= 0",
        );
        issues.check(
            self.min_wall_length_m.is_finite() && self.min_wall_length_m >= 0.0,
            "min_wall_length_m",
            "must be >= 0",
        );
        issues.check(
            self.min_wall_height_m.is_finite() && self.min_wall_height_m >= 0.0,
            "min_wall_height_m",
            "must be >= 0",
        );
    }
}

/// A least-squares plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlaneFit {
    /// Centroid of the points, m.
    pub centroid_m: Vector3<f64>,
    /// Unit normal, pointing up (z ≥ 0).
    pub normal: Vector3<f64>,
    /// Mean squared distance of the points to the plane, m².
    pub mse_m2: f64,
    /// The points' spread along the plane's narrower in-plane direction (the middle eigenvalue),
    /// m²: about as small as `mse_m2` when the points lie along a line, which no plane fits.
    pub spread_m2: f64,
    /// The fit is of the scans' pooled scatter about their own means (the poses' disagreement
    /// between scans taken out), not of all the points together.
    pub within_scans: bool,
}

impl PlaneFit {
    /// Angle between the normal and world z, deg.
    pub fn slope_deg(&self) -> f64 {
        self.normal.z.clamp(-1.0, 1.0).acos().to_degrees()
    }

    /// The plane's point nearest to `p`.
    pub fn project(&self, p: &Vector3<f64>) -> Vector3<f64> {
        p - self.normal * self.normal.dot(&(p - self.centroid_m))
    }
}

/// PCA plane fit of a voxel's points (`None` under 3 points or with non-finite statistics).
///
/// The normal and the MSE come from the scans' pooled scatter about their own means
/// ([`VoxelStats::within_scatter`], divided by its degrees of freedom, points − scans) when the
/// voxel holds several scans with at least 3 degrees of freedom left; else from the covariance
/// of all its points. The centroid is the mean of all the points.
pub fn fit_plane(s: &VoxelStats) -> Option<PlaneFit> {
    if s.n < 3 {
        return None;
    }
    let (mean, cov) = s.mean_cov()?;
    if !cov.iter().all(|v| v.is_finite()) {
        return None;
    }
    let mut eig = SymmetricEigen::new(cov);
    let mut within_scans = false;
    let dof = s.n.saturating_sub(s.scans());
    if s.scans() > 1 && dof >= 3 {
        // Only when the scans' own points spread over the voxel (not each a line of one or two
        // points): at least half the RMS extent of all the points in the narrower direction.
        let within = SymmetricEigen::new(s.within_scatter() / dof as f64);
        if within.eigenvalues.iter().all(|v| v.is_finite())
            && middle(&within.eigenvalues) >= 0.25 * middle(&eig.eigenvalues)
        {
            eig = within;
            within_scans = true;
        }
    }
    let i = eig.eigenvalues.imin();
    let mut normal: Vector3<f64> = eig.eigenvectors.column(i).into_owned();
    if normal.z < 0.0 {
        normal = -normal;
    }
    Some(PlaneFit {
        centroid_m: mean,
        normal: normal.normalize(),
        mse_m2: eig.eigenvalues[i].max(0.0),
        spread_m2: middle(&eig.eigenvalues).max(0.0),
        within_scans,
    })
}

/// For a navigable voxel seen in several scans, the RMS distance of all its points to its
/// plane, m ([`Discovery::surface_sigma_m`] is the median).
fn surface_spread(s: &VoxelStats, c: &VoxelClass) -> Option<f64> {
    let VoxelClass::Navigable(p) = c else { return None };
    if s.scans() < 2 {
        return None;
    }
    let (_, cov) = s.mean_cov()?;
    Some((p.normal.transpose() * cov * p.normal)[(0, 0)].max(0.0).sqrt())
}

/// The median (the upper one of an even count; 0 when empty).
fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// The middle of three eigenvalues.
fn middle(v: &Vector3<f64>) -> f64 {
    v.x + v.y + v.z - v.max() - v.min()
}

/// What a voxel is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum VoxelClass {
    /// Planar and climbable: part of a navigable region.
    Navigable(PlaneFit),
    /// Planar but too steep (a wall, a box side).
    Steep(PlaneFit),
    /// Not planar (MSE over the threshold).
    NonPlanar,
    /// Planar and climbable, but in a patch smaller than `min_region_area_m2` that touches no
    /// obstacle: no region.
    Patch(PlaneFit),
    /// Too few points to tell.
    Sparse,
    /// Part of a wall ([`Wall`]): the plane it lies on (its own, or the wall's where its own
    /// points were too few to tell).
    Wall(PlaneFit),
}

/// A navigable region.
#[derive(Debug, Clone, PartialEq)]
pub struct NavigableRegion {
    /// Its voxels.
    pub voxels: Vec<VoxelKey>,
    /// Mean normal.
    pub normal: Vector3<f64>,
    /// Area (voxel faces), m².
    pub area_m2: f64,
}

/// An obstacle: a Gaussian over its points ([6D] §V).
#[derive(Debug, Clone, PartialEq)]
pub struct Obstacle {
    /// Its voxels.
    pub voxels: Vec<VoxelKey>,
    /// Mean of its points, m.
    pub mean_m: Vector3<f64>,
    /// Covariance of its points, m².
    pub cov_m2: Matrix3<f64>,
    /// Points.
    pub points: u32,
}

/// A wall: a vertical plane holding a piece at least `min_wall_length_m` long and
/// `min_wall_height_m` high with no top (a building's walls; the side of a box whose top was
/// seen is the box's), with the plane's other pieces as high and what lies on or behind it
/// (corners, door jambs and recesses). Not an obstacle: what stands in front of it is one of
/// its own (EQUATIONS §7 "Walls").
#[derive(Debug, Clone, PartialEq)]
pub struct Wall {
    /// Its voxels.
    pub voxels: Vec<VoxelKey>,
    /// Mean normal (horizontal sign arbitrary).
    pub normal: Vector3<f64>,
    /// Area (voxel faces), m².
    pub area_m2: f64,
}

/// The result of a discovery.
#[derive(Debug, Clone, Default)]
pub struct Discovery {
    /// Class per voxel considered.
    pub classes: ClassMap,
    /// Navigable regions, largest first.
    pub regions: Vec<NavigableRegion>,
    /// Obstacles, largest first.
    pub obstacles: Vec<Obstacle>,
    /// Walls, largest first.
    pub walls: Vec<Wall>,
    /// How thick the map's surfaces are: the median, over the navigable voxels seen in several
    /// scans, of the RMS distance of their points to their plane (the sensor's noise and the
    /// poses' disagreement between scans), m.
    pub surface_sigma_m: f64,
    /// The step regions do not cross and obstacles must rise by: `max_step_m`, or 3
    /// `surface_sigma_m` when larger, m.
    pub step_m: f64,
    /// Voxels this discovery fitted a plane to itself (the others' fits were kept in the
    /// [`PlaneFits`] given to [`discover_with`]).
    pub fitted: usize,
}

/// The class of each voxel a discovery considered, in the voxels' order ([`ClassMap::iter`]:
/// by key), looked up by key through the discovery's own index.
#[derive(Debug, Clone, Default)]
pub struct ClassMap {
    keys: Vec<VoxelKey>,
    classes: Vec<VoxelClass>,
    index: ChunkIndex,
}

impl ClassMap {
    /// The class of voxel `k`, if it was considered.
    pub fn get(&self, k: &VoxelKey) -> Option<&VoxelClass> {
        self.index.get(k).map(|i| &self.classes[i])
    }

    /// Voxels considered.
    pub fn len(&self) -> usize {
        self.keys.len()
    }

    /// Whether none was.
    pub fn is_empty(&self) -> bool {
        self.keys.is_empty()
    }

    /// The voxels, by key.
    pub fn keys(&self) -> impl Iterator<Item = &VoxelKey> {
        self.keys.iter()
    }

    /// Their classes, in the same order.
    pub fn values(&self) -> impl Iterator<Item = &VoxelClass> {
        self.classes.iter()
    }

    /// Voxel and class, by key.
    pub fn iter(&self) -> impl Iterator<Item = (&VoxelKey, &VoxelClass)> {
        self.keys.iter().zip(&self.classes)
    }
}

impl std::ops::Index<&VoxelKey> for ClassMap {
    type Output = VoxelClass;

    /// Panics when `k` was not considered.
    fn index(&self, k: &VoxelKey) -> &VoxelClass {
        self.get(k).unwrap_or_else(|| panic!("voxel {k:?} was not classified"))
    }
}

/// Classified voxels by class.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ClassCounts {
    /// [`VoxelClass::Navigable`].
    pub navigable: usize,
    /// [`VoxelClass::Steep`].
    pub steep: usize,
    /// [`VoxelClass::NonPlanar`].
    pub non_planar: usize,
    /// [`VoxelClass::Sparse`].
    pub sparse: usize,
    /// [`VoxelClass::Patch`].
    pub patch: usize,
    /// [`VoxelClass::Wall`].
    pub wall: usize,
}

impl Discovery {
    /// Counts by class.
    pub fn counts(&self) -> ClassCounts {
        let mut c = ClassCounts::default();
        for v in self.classes.values() {
            match v {
                VoxelClass::Navigable(_) => c.navigable += 1,
                VoxelClass::Steep(_) => c.steep += 1,
                VoxelClass::NonPlanar => c.non_planar += 1,
                VoxelClass::Sparse => c.sparse += 1,
                VoxelClass::Patch(_) => c.patch += 1,
                VoxelClass::Wall(_) => c.wall += 1,
            }
        }
        c
    }
}

fn find(parent: &mut [usize], mut i: usize) -> usize {
    while parent[i] != i {
        parent[i] = parent[parent[i]];
        i = parent[i];
    }
    i
}

/// The offsets from a voxel to its 26 neighbours, in the keys' order.
const OFFSETS: [[i32; 3]; 26] = {
    let mut out = [[0; 3]; 26];
    let (mut n, mut dx) = (0, -1);
    while dx <= 1 {
        let mut dy = -1;
        while dy <= 1 {
            let mut dz = -1;
            while dz <= 1 {
                if dx != 0 || dy != 0 || dz != 0 {
                    out[n] = [dx, dy, dz];
                    n += 1;
                }
                dz += 1;
            }
            dy += 1;
        }
        dx += 1;
    }
    out
};

/// Each of [`OFFSETS`] as a step between the cells of one chunk of [`ChunkIndex`].
const CELL_STEPS: [isize; 26] = {
    let mut out = [0; 26];
    let mut n = 0;
    while n < 26 {
        let d = OFFSETS[n];
        out[n] = ((d[0] << (2 * CHUNK_SHIFT)) + (d[1] << CHUNK_SHIFT) + d[2]) as isize;
        n += 1;
    }
    out
};

/// The offsets of [`OFFSETS`] after (0, 0, 0): each pair of neighbours once.
const FORWARD: std::ops::Range<usize> = 13..26;

fn neighbour(k: &VoxelKey, o: usize) -> VoxelKey {
    let d = OFFSETS[o];
    [k[0] + d[0], k[1] + d[1], k[2] + d[2]]
}

fn neighbours(k: &VoxelKey) -> impl Iterator<Item = VoxelKey> + '_ {
    (0..26).map(move |o| neighbour(k, o))
}

/// A voxel's plane fit as [`PlaneFits`] keeps it: what the classification reads, at the point
/// count it was fitted at (the centroid is the mean of the voxel's points, taken from its
/// statistics when used).
#[derive(Debug, Clone, Copy, PartialEq)]
struct KeptFit {
    /// Points the voxel had when fitted: the fit holds while the voxel still has this many.
    n: u32,
    /// Unit normal, z ≥ 0 (NaN: no fit, under 3 points or non-finite statistics).
    normal: [f32; 3],
    mse_m2: f32,
    spread_m2: f32,
    within_scans: bool,
}

impl KeptFit {
    fn of(s: &VoxelStats) -> Self {
        match fit_plane(s) {
            Some(p) => KeptFit {
                n: s.n,
                normal: [p.normal.x as f32, p.normal.y as f32, p.normal.z as f32],
                mse_m2: p.mse_m2 as f32,
                spread_m2: p.spread_m2 as f32,
                within_scans: p.within_scans,
            },
            None => KeptFit { n: s.n, normal: [f32::NAN; 3], mse_m2: 0.0, spread_m2: 0.0, within_scans: false },
        }
    }

    fn plane(&self, s: &VoxelStats) -> Option<PlaneFit> {
        if self.normal[0].is_nan() {
            return None;
        }
        let centroid_m = s.mean()?;
        Some(PlaneFit {
            centroid_m,
            normal: Vector3::new(self.normal[0] as f64, self.normal[1] as f64, self.normal[2] as f64).normalize(),
            mse_m2: self.mse_m2 as f64,
            spread_m2: self.spread_m2 as f64,
            within_scans: self.within_scans,
        })
    }
}

/// The voxels' plane fits, kept from one discovery to the next ([`discover_with`]): a voxel is
/// fitted again only when points were added to it since (its point count changed), so a mapper
/// that keeps them up to date during the run ([`PlaneFits::refresh`] with the voxels
/// [`PointAccumulator::take_changed`] names) leaves only the voxels changed since its last
/// refresh to the discovery at the end. The plane fits were about a quarter of a discovery's
/// time (docs/octree_mapper.md). The fits are kept in single precision (28 bytes a voxel): a
/// discovery with kept fits and one with fresh fits give the same result to the last bit.
#[derive(Debug, Clone, Default)]
pub struct PlaneFits {
    fits: VoxelMap<KeptFit>,
    fitted: u64,
}

impl PlaneFits {
    /// No fits yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Fits the voxels `keys` of `acc` whose fit is missing or older than their points (keys
    /// without points are skipped).
    pub fn refresh(&mut self, acc: &PointAccumulator, keys: impl IntoIterator<Item = VoxelKey>) {
        for k in keys {
            let Some(s) = acc.cells.get(&k) else { continue };
            if self.fits.get(&k).is_none_or(|f| f.n != s.n) {
                self.fits.insert(k, KeptFit::of(s));
                self.fitted += 1;
            }
        }
    }

    /// Voxels with a kept fit.
    pub fn len(&self) -> usize {
        self.fits.len()
    }

    /// Whether no fit is kept.
    pub fn is_empty(&self) -> bool {
        self.fits.is_empty()
    }

    /// Plane fits computed so far (refreshes and discoveries): against the voxels' count, how
    /// often a voxel was fitted again.
    pub fn fitted(&self) -> u64 {
        self.fitted
    }
}

/// Voxels per chunk edge of [`ChunkIndex`] (as a shift).
const CHUNK_SHIFT: i32 = 3;
const CHUNK_MASK: i32 = (1 << CHUNK_SHIFT) - 1;
const CHUNK_CELLS: usize = 1 << (3 * CHUNK_SHIFT);

/// The positions of the discovery's voxels in its sorted key list, by chunks of 8 × 8 × 8
/// voxels: a voxel's 26 neighbours lie in at most 8 chunks, which [`Near`] looks up once each
/// instead of hashing every neighbour's key (the neighbour lookups were half a discovery's time).
#[derive(Debug, Clone, Default)]
struct ChunkIndex {
    chunks: VoxelMap<Box<[u32; CHUNK_CELLS]>>,
}

fn chunk_of(k: &VoxelKey) -> ([i32; 3], usize) {
    let c = [k[0] >> CHUNK_SHIFT, k[1] >> CHUNK_SHIFT, k[2] >> CHUNK_SHIFT];
    let cell = (((k[0] & CHUNK_MASK) as usize) << (2 * CHUNK_SHIFT))
        | (((k[1] & CHUNK_MASK) as usize) << CHUNK_SHIFT)
        | ((k[2] & CHUNK_MASK) as usize);
    (c, cell)
}

impl ChunkIndex {
    fn new(keys: &[VoxelKey]) -> Self {
        let mut chunks: VoxelMap<Box<[u32; CHUNK_CELLS]>> = VoxelMap::default();
        for (i, k) in keys.iter().enumerate() {
            let (c, cell) = chunk_of(k);
            chunks.entry(c).or_insert_with(|| Box::new([u32::MAX; CHUNK_CELLS]))[cell] = i as u32;
        }
        Self { chunks }
    }

    /// The chunk at chunk coordinates `c`, if any voxel is in it.
    fn chunk(&self, c: &[i32; 3]) -> Option<&[u32; CHUNK_CELLS]> {
        self.chunks.get(c).map(|b| &**b)
    }

    /// The position of voxel `k`, if it is there.
    fn get(&self, k: &VoxelKey) -> Option<usize> {
        let (c, cell) = chunk_of(k);
        let i = self.chunk(&c)?[cell];
        (i != u32::MAX).then_some(i as usize)
    }

    /// A lookup cache of the chunks looked up last.
    fn near(&self) -> Near<'_> {
        Near { index: self, tags: [[i32::MIN; 3]; NEAR_SLOTS], chunks: [None; NEAR_SLOTS] }
    }
}

/// Chunks [`Near`] remembers: 4 × 4 × 4 by their coordinates' two lowest bits, so that the up to
/// 8 chunks around one voxel, and the chunks of the voxels after it, do not evict one another.
const NEAR_SLOTS: usize = 64;

/// Looks voxels up in a [`ChunkIndex`], remembering the chunks it found last: lookups of one
/// voxel's neighbours, and of the next voxel's, find their chunks without hashing.
struct Near<'a> {
    index: &'a ChunkIndex,
    /// The chunk coordinates of each slot (`i32::MIN`: none yet; no chunk has them).
    tags: [[i32; 3]; NEAR_SLOTS],
    chunks: [Option<&'a [u32; CHUNK_CELLS]>; NEAR_SLOTS],
}

impl<'a> Near<'a> {
    /// The chunk at chunk coordinates `c`, if any voxel is in it.
    #[inline]
    fn chunk(&mut self, c: [i32; 3]) -> Option<&'a [u32; CHUNK_CELLS]> {
        let slot = (((c[0] & 3) << 4) | ((c[1] & 3) << 2) | (c[2] & 3)) as usize;
        if self.tags[slot] != c {
            self.tags[slot] = c;
            self.chunks[slot] = self.index.chunk(&c);
        }
        self.chunks[slot]
    }

    /// The position of voxel `k` in the key list, if it is there.
    #[inline]
    fn get(&mut self, k: &VoxelKey) -> Option<usize> {
        let (c, cell) = chunk_of(k);
        self.chunk(c).and_then(|b| (b[cell] != u32::MAX).then_some(b[cell] as usize))
    }

    /// `f(o, j)` for each neighbour `k` + [`OFFSETS`]`[o]` (`o` in `offsets`, in order) that is in
    /// the key list, `j` its position. A voxel inside its chunk (not on the chunk's faces: 6³ of
    /// its 8³ cells) finds all its neighbours in that one chunk, at fixed steps from its own
    /// cell; the others look each neighbour up.
    #[inline]
    fn around(&mut self, k: &VoxelKey, offsets: std::ops::Range<usize>, mut f: impl FnMut(usize, usize)) {
        let inner = |v: i32| (1..CHUNK_MASK).contains(&(v & CHUNK_MASK));
        if inner(k[0]) && inner(k[1]) && inner(k[2]) {
            let (c, cell) = chunk_of(k);
            let Some(b) = self.chunk(c) else { return };
            for o in offsets {
                let j = b[cell.wrapping_add_signed(CELL_STEPS[o])];
                if j != u32::MAX {
                    f(o, j as usize);
                }
            }
        } else {
            for o in offsets {
                if let Some(j) = self.get(&neighbour(k, o)) {
                    f(o, j);
                }
            }
        }
    }
}

/// Below this many voxels a discovery's plane fits and occupancy tests stay on one thread (a
/// scan's own discovery, [`ObstacleTracker::update`]).
const PARALLEL_MIN_VOXELS: usize = 4096;

/// `f(offset, part)` over `out` split at `mid` (`offset` the part's start in `out`): the part
/// after `mid` on a second thread when `parallel`. The threads write into `out` and allocate
/// nothing large of their own: memory a thread's allocator arena keeps after it ends is not
/// the main thread's to reuse, and over a million voxels that raised the mapper's peak by
/// about 100 MiB (2026-12-06).
fn in_two<T: Send>(parallel: bool, out: &mut [T], mid: usize, f: &(dyn Fn(usize, &mut [T]) + Sync)) {
    if !parallel {
        return f(0, out);
    }
    let (a, b) = out.split_at_mut(mid);
    std::thread::scope(|s| {
        let other = s.spawn(|| f(mid, b));
        f(0, a);
        other.join().unwrap_or_else(|e| std::panic::resume_unwind(e));
    });
}

/// `f` over `0..len`, in two halves on two threads when `parallel`; the results in order.
fn two_ways<T: Send>(parallel: bool, len: usize, f: &(dyn Fn(std::ops::Range<usize>) -> Vec<T> + Sync)) -> Vec<T> {
    if !parallel {
        return f(0..len);
    }
    std::thread::scope(|s| {
        let other = s.spawn(|| f(len / 2..len));
        let mut v = f(0..len / 2);
        v.extend(other.join().unwrap_or_else(|e| std::panic::resume_unwind(e)));
        v
    })
}

/// A voxel key packed into one integer in the keys' order (21 bits a component), where every
/// component is within ±2²⁰ voxels (±105 km at 0.1 m).
fn packed_key(k: &VoxelKey) -> Option<u64> {
    const HALF: i64 = 1 << 20;
    let c = |v: i32| -> Option<u64> {
        let u = i64::from(v) + HALF;
        (0..2 * HALF).contains(&u).then_some(u as u64)
    };
    Some((c(k[0])? << 42) | (c(k[1])? << 21) | c(k[2])?)
}

fn unpacked_key(p: u64) -> VoxelKey {
    let c = |shift: u32| (((p >> shift) & ((1 << 21) - 1)) as i64 - (1 << 20)) as i32;
    [c(42), c(21), c(0)]
}

/// The voxels of a [`PointAccumulator`] in the keys' order.
enum SortedCells<'a> {
    /// Sorted as packed integer keys ([`packed_key`]: every key in range).
    Packed(Vec<(u64, &'a VoxelStats)>),
    /// Sorted as keys (some key out of the packed range).
    Plain(Vec<(VoxelKey, &'a VoxelStats)>),
}

impl<'a> SortedCells<'a> {
    fn len(&self) -> usize {
        match self {
            SortedCells::Packed(v) => v.len(),
            SortedCells::Plain(v) => v.len(),
        }
    }

    fn get(&self, i: usize) -> (VoxelKey, &'a VoxelStats) {
        match self {
            SortedCells::Packed(v) => (unpacked_key(v[i].0), v[i].1),
            SortedCells::Plain(v) => v[i],
        }
    }
}

/// The voxels of `acc` in the keys' order: sorted as packed integers, two halves on two threads
/// merged when `parallel` (the slowest step of a discovery before: 0.2 s for 2 M voxels), 16
/// bytes a voxel.
fn sorted_cells(acc: &PointAccumulator, parallel: bool) -> SortedCells<'_> {
    let packed: Option<Vec<(u64, &VoxelStats)>> = acc.cells.iter().map(|(k, s)| Some((packed_key(k)?, s))).collect();
    let Some(mut packed) = packed else {
        let mut all: Vec<(VoxelKey, &VoxelStats)> = acc.cells.iter().map(|(k, s)| (*k, s)).collect();
        all.sort_unstable_by_key(|(k, _)| *k);
        return SortedCells::Plain(all);
    };
    if !parallel {
        packed.sort_unstable_by_key(|(k, _)| *k);
        return SortedCells::Packed(packed);
    }
    let mid = packed.len() / 2;
    let (a, b) = packed.split_at_mut(mid);
    std::thread::scope(|s| {
        let other = s.spawn(|| b.sort_unstable_by_key(|(k, _)| *k));
        a.sort_unstable_by_key(|(k, _)| *k);
        other.join().unwrap_or_else(|e| std::panic::resume_unwind(e));
    });
    let (a, b) = packed.split_at(mid);
    let mut out = Vec::with_capacity(packed.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        if a[i].0 < b[j].0 {
            out.push(a[i]);
            i += 1;
        } else {
            out.push(b[j]);
            j += 1;
        }
    }
    out.extend_from_slice(&a[i..]);
    out.extend_from_slice(&b[j..]);
    SortedCells::Packed(out)
}

/// Navigable space and obstacles over the voxels of `acc` for which `occupied` is true (the
/// occupancy map's verdict; pass `|_| true` to use every voxel with points).
pub fn discover(
    acc: &PointAccumulator,
    occupied: impl Fn(&VoxelKey) -> bool + Sync,
    cfg: &NsdConfig,
) -> Result<Discovery, NavigableError> {
    discover_with(acc, occupied, cfg, &PlaneFits::new())
}

/// [`discover`] with the plane fits kept in `fits`: only the voxels whose points changed since
/// their kept fit are fitted (and not kept: [`PlaneFits::refresh`] keeps them); the result is
/// the same as [`discover`]'s, to the last bit.
pub fn discover_with(
    acc: &PointAccumulator,
    occupied: impl Fn(&VoxelKey) -> bool + Sync,
    cfg: &NsdConfig,
    fits: &PlaneFits,
) -> Result<Discovery, NavigableError> {
    discover_in(acc, |k| if occupied(k) { MapCell::Occupied } else { MapCell::Unknown }, cfg, fits)
}

/// What the occupancy map says of a voxel ([`discover_in`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MapCell {
    /// Occupied.
    Occupied,
    /// Observed free (a ray passed through it).
    Free,
    /// Not observed, or not known to the caller.
    Unknown,
}

/// How many voxels of a region are sampled for the side it was seen from.
const SIDE_SAMPLES: usize = 256;

/// [`discover_with`] on a map that also says which voxels are observed free (`cell`): a region
/// of at least a vehicle's footprint (`min_region_area_m2`) seen from below (free space under
/// most of its voxels, and under more of them than above them: a ceiling, an overhang's
/// underside) is no ground a vehicle stands on, and its voxels are left as patches
/// ([`VoxelClass::Patch`]), neither ground nor an obstacle. Without free space (`Unknown` for
/// all that is not occupied) the result is [`discover_with`]'s.
pub fn discover_in(
    acc: &PointAccumulator,
    cell: impl Fn(&VoxelKey) -> MapCell + Sync,
    cfg: &NsdConfig,
    fits: &PlaneFits,
) -> Result<Discovery, NavigableError> {
    if let Some(validation::ConfigIssue { key, message }) = cfg.issues().into_iter().next() {
        return Err(NavigableError::Config { key, message });
    }
    // On two threads when there are many: the occupancy tests, then the plane fits.
    let parallel = acc.cells.len() >= PARALLEL_MIN_VOXELS;
    // In the keys' order: neighbouring voxels one after the other, so that the occupancy tests
    // walk the same branches of an octree one after another (in the hash map's order each test
    // walked from the root through memory the last one had not touched: 3× slower).
    let all = sorted_cells(acc, parallel);
    let mut is_occupied = vec![false; all.len()];
    in_two(parallel, &mut is_occupied, all.len() / 2, &|offset, part| {
        for (i, o) in part.iter_mut().enumerate() {
            *o = cell(&all.get(offset + i).0) == MapCell::Occupied;
        }
    });
    let n = is_occupied.iter().filter(|o| **o).count();
    let (mut keys, mut stats) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for (i, _) in is_occupied.iter().enumerate().filter(|(_, o)| **o) {
        let (k, s) = all.get(i);
        keys.push(k);
        stats.push(s);
    }
    drop((all, is_occupied));
    let index = ChunkIndex::new(&keys);
    let mut near = index.near();
    // The class, and whether the voxel is thick only as far as the scans disagree.
    // tan² of half the angle neighbours' normals may differ by (the collinear test below).
    let half_angle_tan2 = (0.5 * cfg.max_normal_angle_deg).to_radians().tan().powi(2);
    let classify = |s: &VoxelStats, f: &KeptFit| -> (VoxelClass, bool) {
        if s.n < cfg.min_points {
            return (VoxelClass::Sparse, false);
        }
        match f.plane(s) {
            // Points along a line (a single scan line through the voxel): no plane to tell. The
            // normal's tilt about the points' long axis is uncertain by about
            // sqrt(mse / (n · spread)) rad; over half the angle neighbours may differ by, or
            // with the points all but collinear (a hundredth of the voxel), the voxel is left to
            // its neighbours.
            Some(p)
                if p.spread_m2 < (acc.res_m / 100.0).powi(2)
                    || p.mse_m2 > p.spread_m2 * s.n as f64 * half_angle_tan2 =>
            {
                (VoxelClass::Sparse, false)
            }
            // Steep or not planar over several scans that each say too little on their own: the
            // poses' disagreement between the scans can make a flat surface look so (two sheets
            // a few centimetres apart fit a tilted plane). Left to its neighbours, as a voxel
            // with too few points.
            Some(p)
                if !p.within_scans
                    && s.scans() > 1
                    && (p.mse_m2 > cfg.max_plane_mse_m2 || p.slope_deg() > cfg.max_slope_deg) =>
            {
                (VoxelClass::Sparse, true)
            }
            Some(p) if p.mse_m2 <= cfg.max_plane_mse_m2 => {
                if p.slope_deg() <= cfg.max_slope_deg {
                    (VoxelClass::Navigable(p), false)
                } else {
                    (VoxelClass::Steep(p), false)
                }
            }
            _ => (VoxelClass::NonPlanar, false),
        }
    };
    // The plane fits (the kept ones where the voxel's points did not change since, new ones
    // else: not kept, `fits` is the caller's to refresh), the classes, and each navigable
    // voxel's spread off its plane over all its scans, on two threads.
    // Written in place, each thread into its half (a class is 80 bytes: a million voxels' are
    // not copied from halves into a whole).
    let mut classes = vec![VoxelClass::Sparse; keys.len()];
    // Per voxel: THICK (left to its neighbours only because its scans disagree) and STEEP_FIT
    // (its own points, fewer than a class needs or from scans that disagree, fit a plane steeper
    // than `max_slope_deg`).
    let max_slope_cos = cfg.max_slope_deg.to_radians().cos();
    let mut flags = vec![0u8; keys.len()];
    let classify_into = |offset: usize, classes: &mut [VoxelClass], flags: &mut [u8]| -> (usize, Vec<f64>) {
        let (mut fitted, mut spread) = (0, vec![]);
        for (j, (c, t)) in classes.iter_mut().zip(flags.iter_mut()).enumerate() {
            let i = offset + j;
            let s = stats[i];
            let f = match fits.fits.get(&keys[i]) {
                Some(f) if f.n == s.n => *f,
                _ => {
                    fitted += 1;
                    KeptFit::of(s)
                }
            };
            let (class, thick) = classify(s, &f);
            *c = class;
            *t = if thick { THICK } else { 0 };
            if !f.normal[0].is_nan() && (f.normal[2] as f64) < max_slope_cos {
                *t |= STEEP_FIT;
            }
            spread.extend(surface_spread(s, c));
        }
        (fitted, spread)
    };
    let (fitted, mut spread) = if parallel {
        let half = keys.len() / 2;
        let (c0, c1) = classes.split_at_mut(half);
        let (t0, t1) = flags.split_at_mut(half);
        std::thread::scope(|s| {
            let other = s.spawn(|| classify_into(half, c1, t1));
            let (f0, mut s0) = classify_into(0, c0, t0);
            let (f1, s1) = other.join().unwrap_or_else(|e| std::panic::resume_unwind(e));
            s0.extend(s1);
            (f0 + f1, s0)
        })
    } else {
        classify_into(0, &mut classes, &mut flags)
    };
    // How thick the map's surfaces are: the points' spread off their voxel's plane, over all of
    // a voxel's scans (the sensor's noise plus the poses' disagreement between scans; the median
    // over the navigable voxels seen in several scans). Two planes of one surface may differ by
    // this much at their boundary, so the step a region does not cross is at least 3 of it.
    let surface_sigma_m = median(&mut spread);
    let step_m = cfg.max_step_m.max(3.0 * surface_sigma_m);
    // Navigable regions: union of adjacent navigable voxels whose planes meet.
    let max_cos = cfg.max_normal_angle_deg.to_radians().cos();
    let mut parent: Vec<usize> = (0..keys.len()).collect();
    let join = |parent: &mut Vec<usize>, i: usize, j: usize| {
        let (ri, rj) = (find(parent, i), find(parent, j));
        parent[ri.max(rj)] = ri.min(rj);
    };
    // The pairs to join are found on two threads, a block of voxels at a time (the pairs of a
    // block are few), and joined in order; a component's root is its lowest index whatever the
    // order of the joins.
    const BLOCK: usize = 1 << 16;
    for start in (0..keys.len()).step_by(BLOCK) {
        let end = (start + BLOCK).min(keys.len());
        let pairs: Vec<(u32, u32)> = two_ways(parallel, end - start, &|r| {
            let mut near = index.near();
            let mut pairs = vec![];
            for i in r.start + start..r.end + start {
                let VoxelClass::Navigable(a) = classes[i] else { continue };
                let k = &keys[i];
                near.around(k, FORWARD, |o, j| {
                    let VoxelClass::Navigable(b) = classes[j] else { return };
                    if a.normal.dot(&b.normal) < max_cos {
                        return;
                    }
                    // Where the two voxels touch: both planes must pass there within the step.
                    let touch = (acc.centre(k) + acc.centre(&neighbour(k, o))) * 0.5;
                    if (a.project(&touch) - b.project(&touch)).norm() <= step_m {
                        pairs.push((i as u32, j as u32));
                    }
                });
            }
            pairs
        });
        for (i, j) in pairs {
            join(&mut parent, i as usize, j as usize);
        }
    }
    // Voxels with too few points for a plane of their own join the regions of the navigable
    // neighbours whose plane their points' mean lies on (within the step), taking that plane: the
    // holes of a sparsely sampled surface are filled where the surface continues, and not across
    // a step; one that lies on two regions joins them. A voxel that joins puts its sparse
    // neighbours back on the work list, so a run of sparse voxels follows the surface.
    // Each sparse voxel's neighbours in the map are looked up once (a voxel may be examined
    // again each time a neighbour joins; most voxels of a map at poses that disagree start
    // sparse), as lists one after the other, of the neighbours that can matter to it (its
    // candidates, `around` below): the navigable ones whose plane its points' mean lies on,
    // flagged `ON_PLANE` (they stay so: only sparse voxels change in the loop below), and the
    // sparse ones (which may join a region before it, and which it puts back on the work list
    // when it joins). Its steep, non-planar and other navigable neighbours never do.
    const ON_PLANE: u32 = 1 << 31;
    let sparse: Vec<usize> = (0..keys.len()).filter(|i| classes[*i] == VoxelClass::Sparse).collect();
    let mut slot_of = vec![u32::MAX; keys.len()];
    for (slot, &j) in sparse.iter().enumerate() {
        slot_of[j] = slot as u32;
    }
    // Each half of the sparse voxels' lists on a thread of its own, in one pass (no count pass:
    // the lists stay in two halves, read where the voxel's slot falls).
    // With each voxel's mean (`None` without points), read from its statistics here on two
    // threads rather than one by one in the loop below.
    type Lists = (Vec<u32>, Vec<u32>, Vec<Option<Vector3<f64>>>);
    let build = |slots: std::ops::Range<usize>| -> Lists {
        let mut near = index.near();
        let mut offsets = Vec::with_capacity(slots.len() + 1);
        let mut flat = Vec::with_capacity(slots.len() * 8);
        let mut means = Vec::with_capacity(slots.len());
        offsets.push(0u32);
        for &j in &sparse[slots] {
            let mean = stats[j].mean();
            near.around(&keys[j], 0..26, |_, i| match classes[i] {
                VoxelClass::Sparse => flat.push(i as u32),
                VoxelClass::Navigable(b) if mean.is_some_and(|m| b.normal.dot(&(m - b.centroid_m)).abs() <= step_m) => {
                    flat.push(i as u32 | ON_PLANE)
                }
                _ => {}
            });
            offsets.push(flat.len() as u32);
            means.push(mean);
        }
        (offsets, flat, means)
    };
    let half = if parallel { sparse.len() / 2 } else { sparse.len() };
    let (low, high) = if parallel {
        std::thread::scope(|s| {
            let high = s.spawn(|| build(half..sparse.len()));
            let low = build(0..half);
            (low, high.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
        })
    } else {
        (build(0..sparse.len()), (vec![0], vec![], vec![]))
    };
    let around = |j: usize| {
        let s = slot_of[j] as usize;
        let ((offsets, flat, _), s) = if s < half { (&low, s) } else { (&high, s - half) };
        flat[offsets[s] as usize..offsets[s + 1] as usize]
            .iter()
            .map(|&e| ((e & !ON_PLANE) as usize, e & ON_PLANE != 0))
    };
    let mean_of = |j: usize| {
        let s = slot_of[j] as usize;
        if s < half { low.2[s] } else { high.2[s - half] }
    };
    let mut work: std::collections::VecDeque<usize> = sparse.iter().copied().collect();
    let mut queued = vec![false; keys.len()];
    for &j in &work {
        queued[j] = true;
    }
    while let Some(j) = work.pop_front() {
        queued[j] = false;
        if classes[j] != VoxelClass::Sparse {
            continue;
        }
        let Some(mean) = mean_of(j) else { continue };
        // A column of steep surface (this voxel's points and those of the voxel directly above it
        // fit planes steeper than `max_slope_deg`) is filled from its top down, never up: a
        // voxel of it joins a region only once the voxel above it has. A wall seen a line per
        // scan is such a column with no region at its top, and the floor no longer climbs it
        // one voxel after another; where passes over the seabed disagree, the upper sheet joins
        // the seabed first and the voxels under it follow (EQUATIONS §7). When the voxel above
        // joins, this one is put back on the work list (it is among its neighbours).
        if flags[j] & STEEP_FIT != 0
            && near
                .get(&[keys[j][0], keys[j][1], keys[j][2] + 1])
                .is_some_and(|a| flags[a] & STEEP_FIT != 0 && !matches!(classes[a], VoxelClass::Navigable(_)))
        {
            continue;
        }
        let mut plane = None;
        for (i, on_plane) in around(j) {
            if on_plane {
                if plane.is_none()
                    && let VoxelClass::Navigable(b) = classes[i]
                {
                    plane = Some(b);
                }
                join(&mut parent, i, j);
            } else if let VoxelClass::Navigable(b) = classes[i]
                && b.normal.dot(&(mean - b.centroid_m)).abs() <= step_m
            {
                plane.get_or_insert(b);
                join(&mut parent, i, j);
            }
        }
        let Some(plane) = plane else { continue };
        // A voxel thick only where the scans disagree is that surface where the map put it: the
        // plane through its points' mean. A voxel with too few points takes the plane it lies on
        // unchanged, so that a run of them cannot creep away from the surface a step at a time
        // (up a wall, one row of voxels after another).
        classes[j] =
            VoxelClass::Navigable(if flags[j] & THICK != 0 { PlaneFit { centroid_m: mean, ..plane } } else { plane });
        for (i, _) in around(j).filter(|(_, on_plane)| !on_plane) {
            if classes[i] == VoxelClass::Sparse && !queued[i] {
                queued[i] = true;
                work.push_back(i);
            }
        }
    }
    drop((low, high, slot_of));
    // Obstacles ([6D] §V: the occupied voxels that are not navigable): grown from the non-planar
    // and steep voxels through adjacent voxels that are not navigable (sparse ones included).
    let seed = |c: &VoxelClass| matches!(c, VoxelClass::NonPlanar | VoxelClass::Steep(_));
    let blocking = |c: &VoxelClass| !matches!(c, VoxelClass::Navigable(_) | VoxelClass::Wall(_));
    let mut obstacle_of: Vec<Option<usize>> = vec![None; keys.len()];
    let mut members_of: Vec<Vec<usize>> = vec![];
    for s in 0..keys.len() {
        if obstacle_of[s].is_some() || !seed(&classes[s]) {
            continue;
        }
        let o = members_of.len();
        let mut stack = vec![s];
        obstacle_of[s] = Some(o);
        let mut members = vec![];
        while let Some(i) = stack.pop() {
            members.push(i);
            near.around(&keys[i], 0..26, |_, j| {
                if obstacle_of[j].is_none() && blocking(&classes[j]) {
                    obstacle_of[j] = Some(o);
                    stack.push(j);
                }
            });
        }
        members_of.push(members);
    }
    // An obstacle that does not rise out of the surface around it by more than the step (a rough
    // or doubled patch of the seabed where two passes disagree) is that surface: its voxels take
    // the plane of the navigable voxels around it and join the regions they lie on.
    for members in members_of.iter_mut() {
        let mut around: Vec<usize> = vec![];
        for &i in members.iter() {
            for n in neighbours(&keys[i]) {
                if let Some(j) = near.get(&n)
                    && matches!(classes[j], VoxelClass::Navigable(_))
                {
                    around.push(j);
                }
            }
        }
        around.sort_unstable();
        around.dedup();
        if around.is_empty() {
            continue;
        }
        let (mut normal, mut centre) = (Vector3::zeros(), Vector3::zeros());
        for &j in &around {
            if let VoxelClass::Navigable(p) = classes[j] {
                normal += p.normal;
                centre += p.centroid_m;
            }
        }
        let (normal, centre) = (normal.normalize(), centre / around.len() as f64);
        let rises = members.iter().any(|&i| stats[i].mean().is_none_or(|m| normal.dot(&(m - centre)).abs() > step_m));
        if rises || !normal.iter().all(|v| v.is_finite()) {
            continue;
        }
        for &i in members.iter() {
            let Some(mean) = stats[i].mean() else { continue };
            classes[i] = VoxelClass::Navigable(PlaneFit {
                centroid_m: mean,
                normal,
                mse_m2: 0.0,
                spread_m2: 0.0,
                within_scans: false,
            });
            obstacle_of[i] = None;
            for n in neighbours(&keys[i]) {
                if let Some(j) = near.get(&n)
                    && let VoxelClass::Navigable(b) = classes[j]
                    && b.normal.dot(&(mean - b.centroid_m)).abs() <= step_m
                {
                    join(&mut parent, i, j);
                }
            }
        }
        members.clear();
    }
    // Obstacles with too few voxels of their own shape (steep or not planar; the sparse ones
    // they grew through show nothing) are noise, or surfaces the poses smeared: none (before
    // they could claim a region as their top).
    let shaped = |m: &Vec<usize>| m.iter().filter(|i| seed(&classes[**i])).count();
    for members in members_of.iter_mut().filter(|m| shaped(m) < cfg.min_obstacle_voxels) {
        for i in members.drain(..) {
            obstacle_of[i] = None;
        }
    }
    let mut regions: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (i, c) in classes.iter().enumerate() {
        if matches!(c, VoxelClass::Navigable(_)) {
            let r = find(&mut parent, i);
            regions.entry(r).or_default().push(i);
        }
    }
    // A region seen from below is an underside (a ceiling): the free space the sensor saw it
    // through lies under it. Judged on up to `SIDE_SAMPLES` of its voxels, evenly spread: the
    // voxel above and the one below each, free or not. One smaller than a vehicle's footprint
    // is left to the rule of small regions below (it joins the obstacle it touches: the
    // underside of a table top seen from a camera lower than it is the table's).
    let footprint_voxels = cfg.min_region_area_m2 / (acc.res_m * acc.res_m);
    let undersides: Vec<usize> = regions
        .iter()
        .filter(|(_, m)| m.len() as f64 >= footprint_voxels)
        .filter(|(_, m)| {
            let step = m.len().div_ceil(SIDE_SAMPLES).max(1);
            let (mut above, mut below, mut n) = (0usize, 0usize, 0usize);
            for &i in m.iter().step_by(step) {
                let k = keys[i];
                above += usize::from(cell(&[k[0], k[1], k[2] + 1]) == MapCell::Free);
                below += usize::from(cell(&[k[0], k[1], k[2] - 1]) == MapCell::Free);
                n += 1;
            }
            below > above && 2 * below > n
        })
        .map(|(r, _)| *r)
        .collect();
    for r in undersides {
        for i in regions.remove(&r).unwrap_or_default() {
            if let VoxelClass::Navigable(p) = classes[i] {
                classes[i] = VoxelClass::Patch(p);
            }
        }
    }
    // Walls (EQUATIONS §7 "Walls"): the large steep planes with no top are carved out of the
    // obstacles (and out of the small regions along them); what is left of an obstacle falls into
    // its connected pieces.
    let mut wall_of: Vec<u32> = vec![u32::MAX; keys.len()];
    let walls_members = carve_walls(
        &Voxels { keys: &keys, stats: &stats, index: &index, acc },
        &mut classes,
        &mut parent,
        &regions,
        &mut members_of,
        &mut obstacle_of,
        &mut wall_of,
        step_m,
        cfg,
    );
    if !walls_members.is_empty() {
        for members in regions.values_mut() {
            members.retain(|&i| matches!(classes[i], VoxelClass::Navigable(_)));
        }
        regions.retain(|_, m| !m.is_empty());
        // The pieces of obstacles the walls left, by the same rule.
        let shaped = |m: &Vec<usize>| m.iter().filter(|i| seed(&classes[**i])).count();
        for members in members_of.iter_mut().filter(|m| shaped(m) < cfg.min_obstacle_voxels) {
            for i in members.drain(..) {
                obstacle_of[i] = None;
            }
        }
    }
    // A region that lies on top of an obstacle (most of the obstacle voxels it touches are below
    // its own: a rock's or a wreck's top, a table) is that obstacle's top, not ground a vehicle
    // reaches: it joins the obstacle it touches most.
    // (root of the region, obstacle) → the obstacle voxels below the region's; root → the
    // obstacle voxels beside or above.
    let mut below: BTreeMap<(usize, usize), usize> = BTreeMap::new();
    let mut beside_or_above: BTreeMap<usize, usize> = BTreeMap::new();
    // The ground: the largest region. Each obstacle's foot: the ground's voxels beside it.
    let ground = regions.iter().max_by_key(|(root, m)| (m.len(), std::cmp::Reverse(**root))).map(|(r, _)| *r);
    let mut foot_of: Vec<Vec<usize>> = vec![vec![]; members_of.len()];
    for (o, members) in members_of.iter().enumerate() {
        for &j in members {
            for n in neighbours(&keys[j]) {
                let Some(i) = near.get(&n) else { continue };
                if !matches!(classes[i], VoxelClass::Navigable(_)) {
                    continue;
                }
                let root = find(&mut parent, i);
                if Some(root) == ground {
                    foot_of[o].push(i);
                }
                if keys[j][2] < n[2] {
                    *below.entry((root, o)).or_default() += 1;
                } else {
                    *beside_or_above.entry(root).or_default() += 1;
                }
            }
        }
    }
    let mut below_by_region: BTreeMap<usize, (usize, Vec<(usize, usize)>)> = BTreeMap::new();
    for ((root, o), n) in below {
        let e = below_by_region.entry(root).or_default();
        e.0 += n;
        e.1.push((o, n));
    }
    let mut tops = vec![];
    // Never the ground: where passes over the seabed disagree, a lower sheet of steep and
    // non-planar voxels can lie under most of it, and the whole seabed would become one obstacle.
    for (root, (n_below, by_obstacle)) in below_by_region {
        if Some(root) != ground
            && n_below > beside_or_above.get(&root).copied().unwrap_or(0)
            && let Some(&(o, _)) = by_obstacle.iter().max_by_key(|(o, n)| (*n, std::cmp::Reverse(*o)))
        {
            tops.push((root, o));
        }
    }
    for (root, o) in tops {
        for i in regions.remove(&root).unwrap_or_default() {
            obstacle_of[i] = Some(o);
            members_of[o].push(i);
        }
    }
    // A region that rises above the foot of an obstacle it touches is on that obstacle, whatever
    // the obstacle voxels around it (where passes disagree a rock's top is doubled, and parts of
    // its flank lie beside or above the top's voxels): the foot's plane (a least-squares plane
    // through the ground's voxels beside the obstacle) against the region's voxels, on median,
    // by more than the step and more than twice the foot's own scatter about its plane. The
    // ground itself, and a region at the foot's height (ground the obstacle's shadow cut off),
    // stay. A region that joins an obstacle brings the regions that touch it in the next pass.
    if let Some(ground) = ground {
        let mut foot_plane: Vec<Option<FootPlane>> = vec![None; members_of.len()];
        for (o, foot) in foot_of.iter_mut().enumerate() {
            foot.sort_unstable();
            foot.dedup();
            foot_plane[o] = FootPlane::fit(foot.iter().filter_map(|&i| stats[i].mean()));
        }
        loop {
            let mut joined = false;
            let roots: Vec<usize> = regions.keys().copied().filter(|r| *r != ground).collect();
            for root in roots {
                let members = &regions[&root];
                let mut touched: Vec<usize> = members
                    .iter()
                    .flat_map(|&i| {
                        neighbours(&keys[i])
                            .filter_map(|n| near.get(&n).and_then(|j| obstacle_of[j]))
                            .collect::<Vec<_>>()
                    })
                    .collect();
                touched.sort_unstable();
                touched.dedup();
                let on: Vec<usize> = touched
                    .into_iter()
                    .filter(|&o| {
                        foot_plane[o].is_some_and(|f| {
                            let mut h: Vec<f64> =
                                members.iter().filter_map(|&i| stats[i].mean()).map(|m| f.height(&m)).collect();
                            median(&mut h) > step_m.max(2.0 * f.sigma_m)
                        })
                    })
                    .collect();
                let Some(&into) = on.iter().max_by_key(|o| (members_of[**o].len(), std::cmp::Reverse(**o))) else {
                    continue;
                };
                for &o in on.iter().filter(|o| **o != into) {
                    for i in std::mem::take(&mut members_of[o]) {
                        obstacle_of[i] = Some(into);
                        members_of[into].push(i);
                    }
                    let foot = std::mem::take(&mut foot_of[o]);
                    foot_of[into].extend(foot);
                }
                if on.len() > 1 {
                    foot_of[into].sort_unstable();
                    foot_of[into].dedup();
                    foot_plane[into] = FootPlane::fit(foot_of[into].iter().filter_map(|&i| stats[i].mean()));
                }
                for i in regions.remove(&root).unwrap_or_default() {
                    obstacle_of[i] = Some(into);
                    members_of[into].push(i);
                }
                joined = true;
            }
            if !joined {
                break;
            }
        }
        // An obstacle whose shape lies within the ground beside it by the step and the ground's
        // scatter, above and below (a few steep voxels where two passes over the seabed
        // disagree, the foot's own voxels on both sheets), is that ground: its voxels take the
        // foot's plane and join the ground. Only what stands out of the ground's scatter is an
        // obstacle. (Below too: where the largest region is not the ground but an object's top,
        // as in a scan that sees mostly a boulder, the boulder's flanks hang below that "foot".)
        for (o, members) in members_of.iter_mut().enumerate() {
            let Some(f) = foot_plane[o] else { continue };
            if members.is_empty() {
                continue;
            }
            // Judged by the voxels that show a shape (steep, not planar, or a top it took): the
            // sparse voxels it grew through show none, and where passes disagree they are
            // thick, their means anywhere between the sheets.
            // Each against the ground near it: the plane through the 16 foot voxels nearest to it
            // horizontally and their scatter about it (a large obstacle's foot spans a curved
            // seabed, and where the ground region took in some raised voxels, a shelf's top
            // beside a wall, only its nearby part says where the floor is). The largest of k
            // heights off a Gaussian surface exceeds z(1 − 0.025/k)·σ with 5 % probability at
            // most (two-sided, Bonferroni): 1.96σ for one voxel, 2.39σ for 3, 2.84σ for 11; a
            // shape voxel beyond that, and beyond the step, stands out of the ground. Judged
            // voxel by voxel until one stands out; an obstacle whose judgement would take more
            // than `LOCAL_FOOT_WORK` distances stands (it is no patch of a few voxels).
            let shape: Vec<Vector3<f64>> = members
                .iter()
                .filter(|&&i| !matches!(classes[i], VoxelClass::Sparse))
                .filter_map(|&i| stats[i].mean())
                .collect();
            let foot: Vec<Vector3<f64>> = foot_of[o].iter().filter_map(|&i| stats[i].mean()).collect();
            if shape.is_empty() || foot.len() < 3 || shape.len() * foot.len() > LOCAL_FOOT_WORK {
                continue;
            }
            let z = geometry::stats::normal_quantile(1.0 - 0.025 / shape.len() as f64).unwrap_or(2.0);
            let mut near: Vec<(f64, usize)> = Vec::with_capacity(foot.len());
            let stands_out = shape.iter().any(|m| {
                near.clear();
                near.extend(foot.iter().enumerate().map(|(j, p)| ((p - m).xy().norm_squared(), j)));
                if near.len() > LOCAL_FOOT {
                    near.select_nth_unstable_by(LOCAL_FOOT, |a, b| a.0.total_cmp(&b.0));
                    near.truncate(LOCAL_FOOT);
                }
                FootPlane::fit(near.iter().map(|(_, j)| foot[*j]))
                    .is_none_or(|l| l.height(m).abs() > step_m.max(z * l.sigma_m))
            });
            if stands_out {
                continue;
            }
            let normal = Vector3::new(-f.slope[0], -f.slope[1], 1.0).normalize();
            for i in members.drain(..) {
                obstacle_of[i] = None;
                let Some(mean) = stats[i].mean() else { continue };
                classes[i] = VoxelClass::Navigable(PlaneFit {
                    centroid_m: mean,
                    normal,
                    mse_m2: 0.0,
                    spread_m2: 0.0,
                    within_scans: false,
                });
                regions.entry(ground).or_default().push(i);
            }
        }
    }
    // A region smaller than `min_region_area_m2` is no space a vehicle can use: when it touches
    // obstacles it is part of their surface (a planar patch on a rock's flank) and joins them
    // into one; otherwise its voxels are left as patches ([`VoxelClass::Patch`]).
    let res2 = acc.res_m * acc.res_m;
    let small: Vec<usize> =
        regions.iter().filter(|(_, m)| (m.len() as f64) * res2 < cfg.min_region_area_m2).map(|(r, _)| *r).collect();
    for root in small {
        let members = regions.remove(&root).unwrap_or_default();
        let mut touched: Vec<usize> = vec![];
        for &i in &members {
            touched.extend(neighbours(&keys[i]).filter_map(|n| near.get(&n).and_then(|j| obstacle_of[j])));
        }
        touched.sort_unstable();
        touched.dedup();
        let Some(&into) = touched.iter().max_by_key(|o| members_of[**o].len()) else {
            for &i in &members {
                if let VoxelClass::Navigable(p) = classes[i] {
                    classes[i] = VoxelClass::Patch(p);
                }
            }
            continue;
        };
        for &o in touched.iter().filter(|o| **o != into) {
            for i in std::mem::take(&mut members_of[o]) {
                obstacle_of[i] = Some(into);
                members_of[into].push(i);
            }
        }
        for i in members {
            obstacle_of[i] = Some(into);
            members_of[into].push(i);
        }
    }
    let mut regions: Vec<NavigableRegion> = regions
        .into_values()
        .map(|members| {
            let normal = members
                .iter()
                .map(|i| if let VoxelClass::Navigable(p) = classes[*i] { p.normal } else { Vector3::zeros() })
                .sum::<Vector3<f64>>()
                .normalize();
            NavigableRegion {
                voxels: members.iter().map(|i| keys[*i]).collect(),
                normal,
                area_m2: members.len() as f64 * res2,
            }
        })
        .collect();
    regions.sort_by_key(|r| std::cmp::Reverse(r.voxels.len()));
    let mut obstacles = vec![];
    for members in members_of {
        if members.len() < cfg.min_obstacle_voxels {
            continue;
        }
        let mut all = VoxelStats::default();
        for i in &members {
            all.merge(stats[*i]);
        }
        let Some((mean_m, cov_m2)) = all.mean_cov() else { continue };
        obstacles.push(Obstacle { voxels: members.iter().map(|i| keys[*i]).collect(), mean_m, cov_m2, points: all.n });
    }
    obstacles.sort_by_key(|o| std::cmp::Reverse(o.voxels.len()));
    let mut walls: Vec<Wall> = walls_members
        .into_iter()
        .filter(|m| !m.is_empty())
        .map(|members| {
            let mut normal = Vector3::zeros();
            for &i in &members {
                if let VoxelClass::Wall(p) = classes[i] {
                    normal += if normal.dot(&p.normal) < 0.0 { -p.normal } else { p.normal };
                }
            }
            Wall {
                voxels: members.iter().map(|i| keys[*i]).collect(),
                normal: normal.normalize(),
                area_m2: members.len() as f64 * res2,
            }
        })
        .collect();
    walls.sort_by_key(|w| std::cmp::Reverse(w.voxels.len()));
    Ok(Discovery {
        classes: ClassMap { keys, classes, index },
        regions,
        obstacles,
        walls,
        surface_sigma_m,
        step_m,
        fitted,
    })
}

/// What [`carve_walls`] reads of a discovery's voxels.
struct Voxels<'a> {
    keys: &'a [VoxelKey],
    stats: &'a [&'a VoxelStats],
    index: &'a ChunkIndex,
    acc: &'a PointAccumulator,
}

/// How far off a wall's plane a voxel's points' mean may lie and still be on it, m: the step, or
/// twice the points' own scatter along the plane's normal where that is larger (a far wall seen
/// by a depth camera whose noise grows with the range).
fn wall_tolerance(s: &VoxelStats, normal: &Vector3<f64>, step_m: f64) -> f64 {
    let sigma = s.mean_cov().map_or(0.0, |(_, c)| (normal.transpose() * c * normal)[(0, 0)].max(0.0).sqrt());
    step_m.max(2.0 * sigma)
}

/// Walls (EQUATIONS §7 "Walls"), carved out of the obstacles. The candidates: the obstacles'
/// voxels and the navigable voxels of every region but the largest (where a wall is seen a line
/// per scan, a voxel's points can fit a level plane: small regions along the wall). The columns
/// of candidates at least half `min_wall_height_m` tall vote, each with its voxels, for every
/// vertical plane through their means' horizontal centroid, by the plane's horizontal direction
/// ([`WALL_AZIMUTH_BIN_DEG`]) and offset (the voxel size): a Hough transform (Borrmann et al.
/// 2011, "The 3D Hough Transform for plane detection in point clouds", here in the plane of
/// the floor, for vertical planes). The planes with the most votes first: each refitted to the
/// candidates in its band and followed from them through the candidates whose means lie on it
/// ([`wall_tolerance`]); each connected piece is a wall when it spans `min_wall_length_m`
/// horizontally along its plane and `min_wall_height_m` vertically, and has no top: under half
/// of its highest voxels (per column) have, beside or just above them and at least two voxels
/// off the plane, a navigable voxel of a region of at least `min_region_area_m2` (a box's side
/// whose top was seen is the box's; a building's wall rises out of view). The wall voxels'
/// class becomes [`VoxelClass::Wall`] with the wall's plane, and each obstacle that lost voxels
/// falls into its connected pieces (new obstacles at the end of `members_of`). Returns each
/// wall's voxels.
#[allow(clippy::too_many_arguments)]
fn carve_walls(
    v: &Voxels,
    classes: &mut [VoxelClass],
    parent: &mut [usize],
    regions: &BTreeMap<usize, Vec<usize>>,
    members_of: &mut Vec<Vec<usize>>,
    obstacle_of: &mut [Option<usize>],
    wall_of: &mut [u32],
    step_m: f64,
    cfg: &NsdConfig,
) -> Vec<Vec<usize>> {
    let mut walls: Vec<Vec<usize>> = vec![];
    if cfg.min_wall_length_m <= 0.0 || members_of.is_empty() {
        return walls;
    }
    let (keys, stats, res) = (v.keys, v.stats, v.acc.res_m);
    let mut near = v.index.near();
    let max_slope_cos = cfg.max_slope_deg.to_radians().cos();
    // A wall of the least size has (length × height / res²) voxels; a plane needs a tenth of
    // them in votes to be followed.
    let min_votes = ((cfg.min_wall_length_m * cfg.min_wall_height_m / (res * res)) / 10.0).max(3.0) as u32;
    // Regions' sizes by root, and the largest (the ground).
    let size: FxHashMap<usize, u32> = regions.iter().map(|(r, m)| (*r, m.len() as u32)).collect();
    let ground = regions.iter().max_by_key(|(r, m)| (m.len(), std::cmp::Reverse(**r))).map(|(r, _)| *r);
    let mut candidate = vec![false; keys.len()];
    for &i in members_of.iter().flatten() {
        candidate[i] = stats[i].n > 0;
    }
    for (_, m) in regions.iter().filter(|(r, _)| Some(**r) != ground) {
        for &i in m {
            candidate[i] = stats[i].n > 0;
        }
    }
    // The columns: (x, y) → their candidates (and the means' horizontal centroid below).
    let mut columns: FxHashMap<(i32, i32), Vec<usize>> = FxHashMap::default();
    let candidates = members_of
        .iter()
        .flatten()
        .chain(regions.iter().filter(|(r, _)| Some(**r) != ground).flat_map(|(_, m)| m.iter()));
    for &i in candidates {
        if candidate[i] {
            columns.entry((keys[i][0], keys[i][1])).or_default().push(i);
        }
    }
    for col in columns.values_mut() {
        col.sort_unstable();
    }
    let min_column = ((0.5 * cfg.min_wall_height_m / res).ceil() as i32).max(1);
    let mut tall: Vec<(f64, f64, Vec<usize>)> = columns
        .into_values()
        .filter(|c| {
            let (lo, hi) = c.iter().fold((i32::MAX, i32::MIN), |(lo, hi), &i| (lo.min(keys[i][2]), hi.max(keys[i][2])));
            hi - lo + 1 >= min_column
        })
        .map(|c| {
            let sum = c.iter().filter_map(|&i| stats[i].mean()).fold(Vector3::zeros(), |a, m| a + m);
            let n = c.len() as f64;
            (sum.x / n, sum.y / n, c)
        })
        .collect();
    tall.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    if tall.is_empty() {
        return walls;
    }
    let bin_rad = WALL_AZIMUTH_BIN_DEG.to_radians();
    let az_bins = (std::f64::consts::PI / bin_rad).round() as usize;
    let directions: Vec<(f64, f64)> =
        (0..az_bins).map(|a| ((a as f64 * bin_rad).cos(), (a as f64 * bin_rad).sin())).collect();
    // The votes, per direction over the offsets the columns span.
    let reach = tall.iter().map(|(x, y, _)| x.hypot(*y)).fold(0.0, f64::max);
    let half = (reach / res).ceil() as i64 + 1;
    let mut votes = vec![0u32; az_bins * (2 * half as usize + 1)];
    let bin = |a: usize, x: f64, y: f64| {
        let (c, s) = directions[a];
        a * (2 * half as usize + 1) + (((c * x + s * y) / res).round() as i64 + half) as usize
    };
    for (x, y, _) in &tall {
        for a in 0..az_bins {
            votes[bin(a, *x, *y)] += 1;
        }
    }
    // A plane needs a quarter of the columns a wall of the least length has.
    let min_columns = ((0.25 * cfg.min_wall_length_m / res).ceil() as u32).max(3);
    // Per direction, the columns by their offset along it (a band's columns found by bisection).
    let by_offset: Vec<Vec<(f64, usize)>> = directions
        .iter()
        .map(|(c, s)| {
            let mut v: Vec<(f64, usize)> = tall.iter().enumerate().map(|(k, (x, y, _))| (c * x + s * y, k)).collect();
            v.sort_by(|a, b| a.0.total_cmp(&b.0));
            v
        })
        .collect();
    let mut peaks: Vec<(u32, usize)> =
        votes.iter().enumerate().filter(|(_, n)| **n >= min_columns).map(|(b, n)| (*n, b)).collect();
    peaks.sort_by_key(|(n, b)| (std::cmp::Reverse(*n), *b));
    // The navigable voxels of the regions but the largest (tops a piece's upper edge may have).
    let raised: Vec<usize> =
        regions.iter().filter(|(r, _)| Some(**r) != ground).flat_map(|(_, m)| m.iter().copied()).collect();
    let mut tried = vec![false; keys.len()];
    let mut cut = vec![false; members_of.len()];
    // Each wall's plane (a point on it, its normal) and how far off it its voxels may lie.
    let mut planes: Vec<(Vector3<f64>, Vector3<f64>, f64)> = vec![];
    // The peak each wall's plane came from (the pieces of one plane share it).
    let mut plane_of_wall: Vec<usize> = vec![];
    for (peak, (_, b)) in peaks.into_iter().enumerate() {
        let a = b / (2 * half as usize + 1);
        let offset = ((b % (2 * half as usize + 1)) as i64 - half) as f64 * res;
        // The seeds: the candidates not yet tried in the columns of the bin's band.
        let band = &by_offset[a];
        let from = band.partition_point(|(d, _)| *d < offset - 0.5 * res);
        let mut seeds: Vec<usize> = vec![];
        for &(_, k) in band[from..].iter().take_while(|(d, _)| *d <= offset + 0.5 * res) {
            seeds.extend(tall[k].2.iter().copied().filter(|&i| !tried[i] && wall_of[i] == u32::MAX));
        }
        if (seeds.len() as u32) < min_votes {
            continue;
        }
        // The band's columns must span half a wall's least length along it.
        let (c, s) = directions[a];
        let (alo, ahi) = band[from..]
            .iter()
            .take_while(|(d, _)| *d <= offset + 0.5 * res)
            .map(|&(_, k)| -s * tall[k].0 + c * tall[k].1)
            .fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
        if ahi - alo + res < 0.5 * cfg.min_wall_length_m {
            continue;
        }
        let means: Vec<Vector3<f64>> = seeds.iter().filter_map(|&i| stats[i].mean()).collect();
        let Some((centre, normal, _)) = plane_with_thinness(&means) else { continue };
        let along = Vector3::z().cross(&normal);
        if along.norm() < 1e-9 || normal.z.abs() >= max_slope_cos {
            continue;
        }
        let along = along.normalize();
        // The wall's own scatter about its plane (the seeds' median distance as a Gaussian σ):
        // a far wall seen by a depth camera is as thick as the camera's noise there.
        let mut off: Vec<f64> = means.iter().map(|m| normal.dot(&(m - centre)).abs()).collect();
        let within = step_m.max(3.0 * 1.4826 * median(&mut off));
        let on = |i: usize, wall_of: &[u32], tried: &[bool]| {
            !tried[i]
                && candidate[i]
                && wall_of[i] == u32::MAX
                && stats[i]
                    .mean()
                    .is_some_and(|m| normal.dot(&(m - centre)).abs() <= wall_tolerance(stats[i], &normal, within))
        };
        let mut taken = vec![];
        let mut sized = vec![];
        for &s in &seeds {
            if !on(s, wall_of, &tried) {
                continue;
            }
            // One connected piece of the plane.
            let mut piece = vec![s];
            tried[s] = true;
            let mut k = 0;
            while k < piece.len() {
                let i = piece[k];
                k += 1;
                let mut next = vec![];
                near.around(&keys[i], 0..26, |_, j| next.push(j));
                for j in next {
                    if on(j, wall_of, &tried) {
                        tried[j] = true;
                        piece.push(j);
                    }
                }
            }
            let (mut lo, mut hi, mut zlo, mut zhi) = (f64::MAX, f64::MIN, i32::MAX, i32::MIN);
            for &i in &piece {
                let a = along.dot(&v.acc.centre(&keys[i]));
                lo = lo.min(a);
                hi = hi.max(a);
                zlo = zlo.min(keys[i][2]);
                zhi = zhi.max(keys[i][2]);
            }
            if f64::from(zhi - zlo + 1) * res < cfg.min_wall_height_m {
                continue;
            }
            // A wall fills its extent (where nothing stands in front of it); a plane through a
            // rock meets only the rock's outline.
            let cells: FxHashSet<(i64, i32)> = piece
                .iter()
                .map(|&i| (((along.dot(&v.acc.centre(&keys[i])) - lo) / res).round() as i64, keys[i][2]))
                .collect();
            let fill = cells.len() as f64 / (((hi - lo) / res).round() + 1.0) / f64::from(zhi - zlo + 1);
            let long = hi - lo + res >= cfg.min_wall_length_m && fill >= WALL_MIN_FILL;
            sized.push((long, piece, lo, hi, zhi, zlo));
        }
        // Only a plane that holds a long piece can hold a wall: the tops are judged there alone.
        if !sized.iter().any(|p| p.0) {
            continue;
        }
        for (long, piece, lo, hi, zhi, zlo) in sized {
            // The top of the piece at each step along it: its highest voxel there.
            let mut top: HashMap<i64, VoxelKey> = HashMap::new();
            for &i in &piece {
                let k = keys[i];
                let t = top.entry(((along.dot(&v.acc.centre(&k)) - lo) / res).round() as i64).or_insert(k);
                if k[2] > t[2] {
                    *t = k;
                }
            }
            let min_top = (cfg.min_region_area_m2 / (res * res)).ceil().max(1.0) as u32;
            // A top: a region's voxel beside or just above the highest voxel of a column, at
            // least two voxels off the plane (not the voxels along the wall's own top edge,
            // whose points, a line per scan, can fit a level plane).
            // Judged along its upper edge (the steps whose top is within two voxels of the
            // piece's highest): a box's side meets the box's top there, and what the plane meets
            // beside the box (lower things on the floor beside it) is not judged.
            top.retain(|_, k| k[2] >= zhi - 2);
            let in_piece: FxHashSet<usize> = piece.iter().copied().collect();
            let cover = ((0.5 * cfg.min_wall_height_m / res).ceil() as i32).max(1);
            // A top reaches further off the plane than a thin wall is thick (its other face's
            // upper edge can fit level planes too).
            let off = (3.0 * res).max(WALL_TOP_OFF_M);
            let reach = (off / res).ceil() as i32 + 1;
            let covered = top
                .values()
                .filter(|[x, y, z]| {
                    // A surface of the map going on above it, over half the least wall height (a
                    // wall rises out of view; a side whose upper part went to another plane,
                    // where passes disagree, does not; a thin wall's other face, seen a little
                    // higher, is no such surface).
                    (-1..=1)
                        .flat_map(|dx| (-1..=1).flat_map(move |dy| (1..=cover).map(move |dz| [x + dx, y + dy, z + dz])))
                        .filter(|k| near.get(k).is_some_and(|j| !in_piece.contains(&j)))
                        .count()
                        >= cover as usize
                        || (-reach..=reach).any(|dx| {
                            (-reach..=reach).any(|dy| {
                                (-1..=1).any(|dz| {
                                    near.get(&[x + dx, y + dy, z + dz]).is_some_and(|j| {
                                        matches!(classes[j], VoxelClass::Navigable(_))
                                            && size.get(&find(parent, j)).is_some_and(|n| *n >= min_top)
                                            && stats[j].mean().is_some_and(|m| normal.dot(&(m - centre)).abs() >= off)
                                    })
                                })
                            })
                        })
                })
                .count();
            // Or a surface a vehicle could stand on lies above the piece's upper edge, within
            // the piece's height of its plane and along its extent: where passes disagree, a
            // box's side falls into pieces on several planes, and its top into a region beside
            // them.
            if 2 * covered >= top.len() {
                continue;
            }
            let height_m = f64::from(zhi - zlo + 1) * res;
            let above = raised
                .iter()
                .filter(|&&j| {
                    keys[j][2] > zhi
                        && size.get(&find(parent, j)).is_some_and(|n| *n >= min_top)
                        && stats[j].mean().is_some_and(|m| {
                            let a = along.dot(&m);
                            normal.dot(&(m - centre)).abs() <= height_m && a >= lo - res && a <= hi + res
                        })
                })
                .count();
            if (above as u32) < min_top {
                taken.push((long, piece));
            }
        }
        // The pieces of a plane that holds a wall (a piece long enough) are all that wall's, where
        // furniture in front of it or a wall across it cut it into pieces.
        if !taken.iter().any(|(long, _)| *long) {
            continue;
        }
        for (_, piece) in taken {
            let w = walls.len() as u32;
            for &i in &piece {
                wall_of[i] = w;
                if let Some(o) = obstacle_of[i].take() {
                    cut[o] = true;
                }
                let mean = stats[i].mean().unwrap_or(centre);
                classes[i] = VoxelClass::Wall(PlaneFit {
                    centroid_m: mean - normal * normal.dot(&(mean - centre)),
                    normal,
                    mse_m2: 0.0,
                    spread_m2: 0.0,
                    within_scans: false,
                });
            }
            walls.push(piece);
            planes.push((centre, normal, within));
            plane_of_wall.push(peak);
        }
    }
    // What is left of each obstacle that lost voxels, in connected pieces: the first keeps its
    // index.
    for o in (0..cut.len()).filter(|&o| cut[o]) {
        let mut left: Vec<usize> =
            std::mem::take(&mut members_of[o]).into_iter().filter(|&i| obstacle_of[i] == Some(o)).collect();
        left.sort_unstable();
        for &i in &left {
            obstacle_of[i] = None;
        }
        for &s in &left {
            if obstacle_of[s].is_some() {
                continue;
            }
            let into = if members_of[o].is_empty() { o } else { members_of.len() };
            if into != o {
                members_of.push(vec![]);
            }
            obstacle_of[s] = Some(into);
            let mut piece = vec![s];
            let mut k = 0;
            while k < piece.len() {
                let i = piece[k];
                k += 1;
                near.around(&keys[i], 0..26, |_, j| {
                    if obstacle_of[j].is_none() && left.binary_search(&j).is_ok() {
                        obstacle_of[j] = Some(into);
                        piece.push(j);
                    }
                });
            }
            members_of[into] = piece;
        }
    }
    if walls.is_empty() {
        return walls;
    }
    // Each wall's front: the side its foot meets the ground on (the building's rooms and
    // corridors); unknown where it meets no ground. The ground is looked for off the wall's
    // plane by more than the wall is thick (`within`) and up to three voxels further, on both
    // sides of each of its voxels: the floor right under a wall lies on both sides of its plane
    // (where passes disagree by centimetres, floor points land behind the wall too), the room's
    // floor goes on in front of it.
    // Judged over all the pieces of a plane together (a door's recess has floor behind the wall's
    // plane).
    let mut side_of_plane: Vec<f64> = vec![0.0; plane_of_wall.iter().max().map_or(0, |p| p + 1)];
    for (w, piece) in walls.iter().enumerate() {
        let (centre, normal, within) = planes[w];
        for &i in piece {
            let Some(m) = stats[i].mean() else { continue };
            let on_plane = m - normal * normal.dot(&(m - centre));
            for side in [-1.0, 1.0] {
                for t in 0..3 {
                    let p = on_plane + normal * (side * (within + (t as f64 + 0.5) * res));
                    if let Some(j) = near.get(&v.acc.key(&p))
                        && matches!(classes[j], VoxelClass::Navigable(_))
                    {
                        side_of_plane[plane_of_wall[w]] += side;
                    }
                }
            }
        }
    }
    let ground_side: Vec<Option<Vector3<f64>>> = (0..walls.len())
        .map(|w| {
            let side = side_of_plane[plane_of_wall[w]];
            (side != 0.0).then(|| planes[w].1 * side.signum())
        })
        .collect();
    // An obstacle within two voxels of a wall that lies on its plane or behind it (where two walls meet,
    // a door's jambs and recess, a wall's end, a pass's sheet a few centimetres off: at most a
    // tenth of its voxels more than w, or two voxels, in front of it) is part of it; what stands
    // in front of a wall by more (furniture against it) stays an obstacle.
    for members in members_of.iter_mut() {
        // The walls within two voxels of it (where the poses disagree, a wall's points can land
        // a few centimetres behind it, apart from it).
        let mut touched: Vec<u32> = vec![];
        for &i in members.iter() {
            let k = keys[i];
            for n in (-2..=2)
                .flat_map(|dx| (-2..=2).flat_map(move |dy| (-2..=2).map(move |dz| [k[0] + dx, k[1] + dy, k[2] + dz])))
            {
                if let Some(j) = near.get(&n)
                    && wall_of[j] != u32::MAX
                {
                    touched.push(wall_of[j]);
                }
            }
        }
        touched.sort_unstable();
        touched.dedup();
        let into = touched.into_iter().find(|&w| {
            let (centre, _, within) = planes[w as usize];
            let beyond = within.max(2.0 * res);
            ground_side[w as usize].is_some_and(|front| {
                let in_front = members
                    .iter()
                    .filter(|&&i| stats[i].mean().is_some_and(|m| front.dot(&(m - centre)) > beyond))
                    .count();
                in_front * 10 <= members.len()
            })
        });
        let Some(w) = into else { continue };
        let (centre, normal, _) = planes[w as usize];
        for i in members.drain(..) {
            obstacle_of[i] = None;
            wall_of[i] = w;
            let mean = stats[i].mean().unwrap_or(centre);
            classes[i] = VoxelClass::Wall(PlaneFit {
                centroid_m: mean,
                normal,
                mse_m2: 0.0,
                spread_m2: 0.0,
                within_scans: false,
            });
            walls[w as usize].push(i);
        }
    }
    walls
}

/// The least-squares plane through `points`: their centroid, the unit normal of least spread,
/// and whether they are thin about it (the least spread under a quarter of the middle one).
/// `None` under 3 points or without a finite fit.
fn plane_with_thinness(points: &[Vector3<f64>]) -> Option<(Vector3<f64>, Vector3<f64>, bool)> {
    if points.len() < 3 {
        return None;
    }
    let centre = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
    let cov = points.iter().map(|p| (p - centre) * (p - centre).transpose()).sum::<Matrix3<f64>>();
    if !cov.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eig = SymmetricEigen::new(cov);
    let i = eig.eigenvalues.imin();
    let normal: Vector3<f64> = eig.eigenvectors.column(i).into_owned();
    let thin = eig.eigenvalues[i] < 0.25 * middle(&eig.eigenvalues);
    (normal.norm() > 0.0).then(|| (centre, normal.normalize(), thin))
}

/// The share of its extent (along it × its height, in voxels) a piece of a plane must fill to be
/// a wall in [`carve_walls`].
const WALL_MIN_FILL: f64 = 0.5;
/// How far off a wall's plane a region must reach to be its top in [`carve_walls`] (more than an
/// interior wall is thick), m.
const WALL_TOP_OFF_M: f64 = 0.2;
/// Bins of a wall's horizontal direction in [`carve_walls`]'s vote, deg.
const WALL_AZIMUTH_BIN_DEG: f64 = 3.0;

/// A voxel left to its neighbours only because its scans disagree ([`discover_with`]'s flags).
const THICK: u8 = 1;
/// A voxel whose own points (fewer than a class needs, or from scans that disagree) fit a plane
/// steeper than `max_slope_deg`.
const STEEP_FIT: u8 = 2;

/// Foot voxels a local ground plane is fitted to ([`discover_with`]: whether an obstacle stands
/// out of the ground).
const LOCAL_FOOT: usize = 16;
/// At most this many shape voxels × foot voxels are searched for the local ground; an obstacle
/// beyond it is not judged (it stands).
const LOCAL_FOOT_WORK: usize = 4_000_000;

/// The ground beside an obstacle: a plane z = z₀ + a·(x − x₀) + b·(y − y₀) through its voxels'
/// means, fitted robustly ([`FootPlane::fit`]; level through their mean when they do not span a
/// plane), and their scatter about it.
#[derive(Debug, Clone, Copy)]
struct FootPlane {
    /// The means' centroid, m.
    centre_m: Vector3<f64>,
    /// Slopes dz/dx, dz/dy.
    slope: [f64; 2],
    /// The means' scatter off the plane, m: the Gaussian σ of their median absolute height.
    sigma_m: f64,
}

impl FootPlane {
    /// The plane through `points` (`None` without any), robust to a few voxels off the ground
    /// (a piece of furniture's top that joined the floor, a second sheet): the least-squares
    /// plane, then again through the points within 3 σ of it, σ = 1.4826 × the median absolute
    /// height off the plane (the MAD's Gaussian σ), which is also the scatter kept.
    fn fit(points: impl Iterator<Item = Vector3<f64>>) -> Option<FootPlane> {
        let points: Vec<Vector3<f64>> = points.collect();
        let first = Self::least_squares(&points)?;
        let sigma = first.mad_sigma(&points);
        let inliers: Vec<Vector3<f64>> =
            points.iter().filter(|p| first.height(p).abs() <= 3.0 * sigma).copied().collect();
        let mut plane = Self::least_squares(&inliers).unwrap_or(first);
        plane.sigma_m = plane.mad_sigma(&points);
        Some(plane)
    }

    /// 1.4826 × the median of |height| over `points` (0 without points).
    fn mad_sigma(&self, points: &[Vector3<f64>]) -> f64 {
        let mut h: Vec<f64> = points.iter().map(|p| self.height(p).abs()).collect();
        1.4826 * median(&mut h)
    }

    /// The least-squares plane (its `sigma_m` left 0).
    fn least_squares(points: &[Vector3<f64>]) -> Option<FootPlane> {
        if points.is_empty() {
            return None;
        }
        let centre_m = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
        let (mut sxx, mut sxy, mut syy, mut sxz, mut syz) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for p in points {
            let d = p - centre_m;
            sxx += d.x * d.x;
            sxy += d.x * d.y;
            syy += d.y * d.y;
            sxz += d.x * d.z;
            syz += d.y * d.z;
        }
        let det = sxx * syy - sxy * sxy;
        // Spanning a plane: both horizontal spreads and not along a line (the determinant against
        // the spreads' product, scale-free).
        let slope = if points.len() >= 3 && det > 1e-6 * (sxx * syy).max(f64::MIN_POSITIVE) {
            [(sxz * syy - syz * sxy) / det, (syz * sxx - sxz * sxy) / det]
        } else {
            [0.0, 0.0]
        };
        Some(FootPlane { centre_m, slope, sigma_m: 0.0 })
    }

    /// How far `p` lies above the plane (vertically), m.
    fn height(&self, p: &Vector3<f64>) -> f64 {
        let d = p - self.centre_m;
        d.z - self.slope[0] * d.x - self.slope[1] * d.y
    }
}

/// What an occupied voxel of the map is, for a viewer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MapVoxelClass {
    /// Occupied, neither navigable nor part of an obstacle (or not classified yet).
    Occupied,
    /// Part of a navigable region.
    Navigable,
    /// Part of an obstacle.
    Obstacle,
    /// Part of a wall ([`Wall`]).
    Wall,
}

/// One occupied leaf of the occupancy map with its class.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapVoxel {
    /// Centre of the leaf's cube, world frame, m.
    pub center_m: [f64; 3],
    /// Edge length of the cube, m (larger than the resolution for a pruned leaf).
    pub size_m: f64,
    /// Occupancy probability.
    pub occupancy: f64,
    /// Its class (by the point-statistics voxel at its centre).
    pub class: MapVoxelClass,
}

/// The occupied leaves of `tree`, each classified by the navigable-space discovery `classes`
/// over `points` (the voxel of `points` at the leaf's centre); without `classes` all are
/// [`MapVoxelClass::Occupied`].
pub fn occupied_voxels(tree: &octree::OcTree, points: &PointAccumulator, classes: Option<&Discovery>) -> Vec<MapVoxel> {
    let obstacle: std::collections::HashSet<VoxelKey> =
        classes.map(|d| d.obstacles.iter().flat_map(|o| o.voxels.iter().copied()).collect()).unwrap_or_default();
    tree.leaves().filter_map(|l| leaf_voxel(tree, points, classes, &obstacle, l)).collect()
}

/// The occupied voxels of one region of the tree (see [`octree::OcTree::leaves_in_region`]:
/// the leaves at least as deep as the region), unclassified ([`MapVoxelClass::Occupied`]): what
/// a follower of [`octree::OcTree::take_changes`] re-reads for a changed region.
pub fn occupied_voxels_in_region(
    tree: &octree::OcTree,
    points: &PointAccumulator,
    region_depth: u8,
    region: [u16; 3],
) -> Vec<MapVoxel> {
    let none = std::collections::HashSet::new();
    tree.leaves_in_region(region_depth, region).filter_map(|l| leaf_voxel(tree, points, None, &none, l)).collect()
}

/// One leaf as a [`MapVoxel`] when it is occupied.
fn leaf_voxel(
    tree: &octree::OcTree,
    points: &PointAccumulator,
    classes: Option<&Discovery>,
    obstacle: &std::collections::HashSet<VoxelKey>,
    l: octree::Leaf,
) -> Option<MapVoxel> {
    if !tree.is_occupied_log_odds(l.log_odds) {
        return None;
    }
    let res = tree.resolution();
    let c = tree.key_to_coord(l.key);
    let size = res * l.edge_voxels() as f64;
    let center_m = if l.depth >= 16 {
        c
    } else {
        // A pruned leaf: the centre of its cube.
        let m = tree.key_to_coord(l.min_key());
        [m[0] - 0.5 * res + 0.5 * size, m[1] - 0.5 * res + 0.5 * size, m[2] - 0.5 * res + 0.5 * size]
    };
    let class = match classes {
        None => MapVoxelClass::Occupied,
        Some(d) => {
            let k = points.key(&Vector3::from(c));
            match d.classes.get(&k) {
                Some(VoxelClass::Navigable(_)) => MapVoxelClass::Navigable,
                Some(VoxelClass::Wall(_)) => MapVoxelClass::Wall,
                _ if obstacle.contains(&k) => MapVoxelClass::Obstacle,
                _ => MapVoxelClass::Occupied,
            }
        }
    };
    Some(MapVoxel { center_m, size_m: size, occupancy: octree::probability(l.log_odds as f64), class })
}

/// An obstacle landmark: a Gaussian over the points of the scans' obstacles associated with it.
#[derive(Debug, Clone, Default)]
pub struct ObstacleLandmark {
    /// Point statistics of every associated scan obstacle.
    pub stats: VoxelStats,
    /// Point statistics of the scan obstacle last associated with it: the part of the object
    /// the last scan saw, which the next scan, from nearly the same pose, sees again.
    pub last: VoxelStats,
    /// Scans it was seen in.
    pub scans: u32,
}

/// What one scan did to the tracked obstacles.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TrackUpdate {
    /// Scan obstacles associated with an existing landmark.
    pub associated: u64,
    /// Scan obstacles that started a new landmark.
    pub new: u64,
    /// Landmarks merged into another (their Gaussians came within the gate).
    pub merged: u64,
}

/// Obstacles tracked across scans ([6D] §VI): the obstacles of each scan ([`discover`] on its
/// points alone) are associated with the landmarks by Bhattacharyya distance
/// ([`associate_obstacles`]); an associated one adds its points to the landmark's Gaussian, the
/// others start new landmarks.
#[derive(Debug, Clone, Default)]
pub struct ObstacleTracker {
    /// The landmarks so far.
    pub landmarks: Vec<ObstacleLandmark>,
}

impl ObstacleTracker {
    /// Takes one scan's points. `max_bhattacharyya` gates the association; `regularise_m2` is
    /// added to the covariances' diagonal (a voxel's extent, for flat obstacles).
    pub fn update(
        &mut self,
        scan: &PointAccumulator,
        cfg: &NsdConfig,
        max_bhattacharyya: f64,
        regularise_m2: f64,
    ) -> Result<TrackUpdate, NavigableError> {
        let found = discover(scan, |_| true, cfg)?;
        let mut update = TrackUpdate::default();
        if found.obstacles.is_empty() {
            return Ok(update);
        }
        // Each scan obstacle against each landmark's Gaussian over all its points and against
        // the part the last scan saw ([6D] §VI matches the obstacles of consecutive scans): a
        // rock seen part by part from a moving vehicle stays one landmark while its parts
        // overlap from one scan to the next.
        let reg = Matrix3::identity() * regularise_m2.max(0.0);
        let gaussian = |s: &VoxelStats| s.mean_cov().map(|(m, c)| (m, c + reg));
        let mut pairs = vec![];
        for (l, landmark) in self.landmarks.iter().enumerate() {
            let views: Vec<_> = [gaussian(&landmark.stats), gaussian(&landmark.last)].into_iter().flatten().collect();
            for (o, obstacle) in found.obstacles.iter().enumerate() {
                let d = views
                    .iter()
                    .filter_map(|(m, c)| {
                        geometry::gaussian::bhattacharyya(m, c, &obstacle.mean_m, &(obstacle.cov_m2 + reg)).ok()
                    })
                    .fold(f64::INFINITY, f64::min);
                if d <= max_bhattacharyya {
                    pairs.push((l, o, d));
                }
            }
        }
        pairs.sort_by(|p, q| p.2.total_cmp(&q.2));
        let (mut used_l, mut used_o) = (vec![false; self.landmarks.len()], vec![false; found.obstacles.len()]);
        pairs.retain(|(l, o, _)| {
            let free = !used_l[*l] && !used_o[*o];
            if free {
                used_l[*l] = true;
                used_o[*o] = true;
            }
            free
        });
        let stats_of = |o: &Obstacle| {
            let mut stats = VoxelStats::default();
            for k in &o.voxels {
                if let Some(v) = scan.cells().get(k) {
                    stats.merge(v);
                }
            }
            stats
        };
        let mut matched = vec![false; found.obstacles.len()];
        for (l, o, _) in &pairs {
            matched[*o] = true;
            let stats = stats_of(&found.obstacles[*o]);
            self.landmarks[*l].stats.merge(&stats);
            self.landmarks[*l].last = stats;
            self.landmarks[*l].scans += 1;
            update.associated += 1;
        }
        let mut touched: Vec<usize> = pairs.iter().map(|(l, _, _)| *l).collect();
        for (o, obstacle) in found.obstacles.iter().enumerate() {
            if !matched[o] {
                touched.push(self.landmarks.len());
                let stats = stats_of(obstacle);
                self.landmarks.push(ObstacleLandmark { stats, last: stats, scans: 1 });
                update.new += 1;
            }
        }
        update.merged = self.merge_overlapping(&touched, max_bhattacharyya, regularise_m2);
        Ok(update)
    }

    /// Merges each landmark in `touched` with every other landmark within `max_bhattacharyya` of
    /// it, nearest first, until none is: one object seen part by part from several poses starts
    /// a landmark per part, and the parts' Gaussians come together as more of it is seen.
    /// Returns the merges.
    fn merge_overlapping(&mut self, touched: &[usize], max_bhattacharyya: f64, regularise_m2: f64) -> u64 {
        let reg = Matrix3::identity() * regularise_m2.max(0.0);
        let gaussian = |l: &ObstacleLandmark| l.stats.mean_cov().map(|(m, c)| (m, c + reg));
        let mut alive = vec![true; self.landmarks.len()];
        let mut work: Vec<usize> = touched.to_vec();
        let mut merges = 0;
        while let Some(a) = work.pop() {
            if !alive[a] {
                continue;
            }
            let Some((ma, ca)) = gaussian(&self.landmarks[a]) else { continue };
            let nearest = (0..self.landmarks.len())
                .filter(|b| *b != a && alive[*b])
                .filter_map(|b| {
                    let (mb, cb) = gaussian(&self.landmarks[b])?;
                    let d = geometry::gaussian::bhattacharyya(&ma, &ca, &mb, &cb).ok()?;
                    (d <= max_bhattacharyya).then_some((b, d))
                })
                .min_by(|x, y| x.1.total_cmp(&y.1));
            if let Some((b, _)) = nearest {
                let other = self.landmarks[b].clone();
                self.landmarks[a].stats.merge(&other.stats);
                self.landmarks[a].scans += other.scans;
                alive[b] = false;
                merges += 1;
                work.push(a);
            }
        }
        let mut i = 0;
        self.landmarks.retain(|_| {
            i += 1;
            alive[i - 1]
        });
        merges
    }
}

/// Associates obstacles of two scans or maps ([6D] §VI): greedy by the Bhattacharyya distance
/// (EQUATIONS §7), each obstacle at most once, pairs at most `max_distance` apart; returns
/// (index in `a`, index in `b`, distance). A covariance that is not positive definite (a flat
/// obstacle) is regularised by `regularise_m2` on the diagonal.
pub fn associate_obstacles(
    a: &[Obstacle],
    b: &[Obstacle],
    max_distance: f64,
    regularise_m2: f64,
) -> Vec<(usize, usize, f64)> {
    let reg = Matrix3::identity() * regularise_m2.max(0.0);
    let mut pairs = vec![];
    for (i, x) in a.iter().enumerate() {
        for (j, y) in b.iter().enumerate() {
            if let Ok(d) = geometry::gaussian::bhattacharyya(&x.mean_m, &(x.cov_m2 + reg), &y.mean_m, &(y.cov_m2 + reg))
                && d <= max_distance
            {
                pairs.push((i, j, d));
            }
        }
    }
    pairs.sort_by(|p, q| p.2.total_cmp(&q.2));
    let (mut used_a, mut used_b) = (vec![false; a.len()], vec![false; b.len()]);
    pairs
        .into_iter()
        .filter(|(i, j, _)| {
            let free = !used_a[*i] && !used_b[*j];
            if free {
                used_a[*i] = true;
                used_b[*j] = true;
            }
            free
        })
        .collect()
}

fn io_err(path: &Path) -> impl Fn(std::io::Error) -> NavigableError + '_ {
    move |source| NavigableError::Io { path: path.display().to_string(), source }
}

/// Binary (little-endian) PLY of the navigable voxels: one vertex per voxel, its centre
/// projected on its plane, with the normal and `region` (index into [`Discovery::regions`]).
/// (ASCII until 2026-12-06: formatting the text took 2.8 s of the main job's end of run.)
pub fn write_navigable_ply(path: &Path, acc: &PointAccumulator, d: &Discovery) -> Result<(), NavigableError> {
    let mut rows = vec![];
    for (r, region) in d.regions.iter().enumerate() {
        for k in &region.voxels {
            if let Some(VoxelClass::Navigable(p)) = d.classes.get(k) {
                rows.push((p.project(&acc.centre(k)), p.normal, r));
            }
        }
    }
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment navigable space: voxel centres on their planes\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nproperty int region\nend_header\n",
        rows.len()
    );
    let mut bytes = header.into_bytes();
    bytes.reserve(rows.len() * 28);
    for (p, n, r) in rows {
        for v in [p.x, p.y, p.z, n.x, n.y, n.z] {
            bytes.extend_from_slice(&(v as f32).to_le_bytes());
        }
        bytes.extend_from_slice(&(r as i32).to_le_bytes());
    }
    std::fs::write(path, bytes).map_err(io_err(path))
}

/// Binary (little-endian) PLY of the obstacles as a mesh: the voxel faces of each obstacle that
/// no other voxel of the same obstacle covers (its outer surface), corners shared within an
/// obstacle; vertices carry `obstacle` (index into [`Discovery::obstacles`]).
pub fn write_obstacles_ply(path: &Path, acc: &PointAccumulator, d: &Discovery) -> Result<(), NavigableError> {
    write_voxel_meshes_ply(path, acc, d.obstacles.iter().map(|o| &o.voxels[..]), "obstacle")
}

/// The walls as meshes, as [`write_obstacles_ply`] writes the obstacles: the outer faces of each
/// wall's voxels, each vertex with its wall's index (`property int wall`).
pub fn write_walls_ply(path: &Path, acc: &PointAccumulator, d: &Discovery) -> Result<(), NavigableError> {
    write_voxel_meshes_ply(path, acc, d.walls.iter().map(|w| &w.voxels[..]), "wall")
}

/// Each set of voxels as the outer faces of its voxels (binary PLY), each vertex with its set's
/// index as `property int <what>`.
fn write_voxel_meshes_ply<'a>(
    path: &Path,
    acc: &PointAccumulator,
    sets: impl Iterator<Item = &'a [VoxelKey]>,
    what: &str,
) -> Result<(), NavigableError> {
    let r = acc.res_m;
    let mut vertices: Vec<([f32; 3], i32)> = vec![];
    let mut faces: Vec<[u32; 4]> = vec![];
    for (o, voxels) in sets.enumerate() {
        let set: std::collections::HashSet<VoxelKey> = voxels.iter().copied().collect();
        let mut corners: HashMap<VoxelKey, u32> = HashMap::new();
        for k in voxels {
            for axis in 0..3 {
                for side in [0i32, 1] {
                    let mut n = *k;
                    n[axis] += if side == 0 { -1 } else { 1 };
                    if set.contains(&n) {
                        continue;
                    }
                    let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                    let mut corner = |du: i32, dv: i32| {
                        let mut c = *k;
                        c[axis] += side;
                        c[u] += du;
                        c[v] += dv;
                        *corners.entry(c).or_insert_with(|| {
                            let p = [c[0] as f64 * r, c[1] as f64 * r, c[2] as f64 * r];
                            vertices.push(([p[0] as f32, p[1] as f32, p[2] as f32], o as i32));
                            (vertices.len() - 1) as u32
                        })
                    };
                    faces.push([corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)]);
                }
            }
        }
    }
    let mut w = std::io::BufWriter::new(std::fs::File::create(path).map_err(io_err(path))?);
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment {what}s: outer voxel faces\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty int {what}\nelement face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        vertices.len(),
        faces.len()
    );
    let mut bytes = header.into_bytes();
    bytes.reserve(vertices.len() * 16 + faces.len() * 17);
    for (p, o) in &vertices {
        for c in p {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
        bytes.extend_from_slice(&o.to_le_bytes());
    }
    for f in &faces {
        bytes.push(4);
        for i in f {
            bytes.extend_from_slice(&i.to_le_bytes());
        }
    }
    w.write_all(&bytes).map_err(io_err(path))?;
    w.flush().map_err(io_err(path))
}

#[cfg(test)]
mod tests {
    use super::*;

    const RES: f64 = 0.1;

    #[test]
    fn scans_merged_give_the_statistics_of_their_points_added_one_by_one() {
        let mut one_by_one = PointAccumulator::new(RES);
        let mut merged = PointAccumulator::new(RES);
        for scan in 0..3 {
            let mut s = PointAccumulator::new(RES);
            for i in 0..500 {
                let t = (scan * 500 + i) as f64 * 0.013;
                let p = Vector3::new(t.sin() * 0.7, (t * 1.3).cos() * 0.4, 0.05 * t);
                one_by_one.add(&p);
                s.add(&p);
            }
            merged.merge(&s).unwrap();
        }
        assert_eq!(merged.cells().len(), one_by_one.cells().len());
        for (k, a) in one_by_one.cells() {
            let b = &merged.cells()[k];
            assert_eq!(a.n, b.n, "{k:?}");
            assert!((a.sum_m - b.sum_m).norm() < 1e-9 && (a.sum_sq_m2() - b.sum_sq_m2()).norm() < 1e-9, "{k:?}");
        }
        let err = merged.merge(&PointAccumulator::new(0.05)).unwrap_err();
        assert!(err.to_string().contains("0.05 m"), "{err}");
    }

    /// Dense points on a surface z = f(x, y) over a rectangle (spacing 1 cm).
    fn surface(acc: &mut PointAccumulator, x: (f64, f64), y: (f64, f64), f: impl Fn(f64, f64) -> f64) {
        let mut xi = x.0 + 0.005;
        while xi < x.1 {
            let mut yi = y.0 + 0.005;
            while yi < y.1 {
                acc.add(&Vector3::new(xi, yi, f(xi, yi)));
                yi += 0.01;
            }
            xi += 0.01;
        }
    }

    /// A vertical face x = x0 over y, z ranges.
    fn wall(acc: &mut PointAccumulator, x0: f64, y: (f64, f64), z: (f64, f64)) {
        let mut yi = y.0 + 0.005;
        while yi < y.1 {
            let mut zi = z.0 + 0.005;
            while zi < z.1 {
                acc.add(&Vector3::new(x0, yi, zi));
                zi += 0.01;
            }
            yi += 0.01;
        }
    }

    fn run(acc: &PointAccumulator) -> Discovery {
        discover(acc, |_| true, &NsdConfig::default()).unwrap()
    }

    #[test]
    fn the_forward_offsets_are_the_neighbours_after_the_voxel() {
        let k = [3, -2, 7];
        let after: Vec<VoxelKey> = neighbours(&k).filter(|n| n > &k).collect();
        assert_eq!(after.len(), 13);
        assert_eq!(FORWARD.map(|o| neighbour(&k, o)).collect::<Vec<_>>(), after);
    }

    #[test]
    fn a_flat_floor_is_one_navigable_region() {
        let mut acc = PointAccumulator::new(RES);
        surface(&mut acc, (0.0, 2.0), (0.0, 1.0), |_, _| 0.033);
        let d = run(&acc);
        assert_eq!(d.regions.len(), 1);
        assert_eq!(d.regions[0].voxels.len(), 200);
        assert!((d.regions[0].area_m2 - 2.0).abs() < 1e-9);
        assert!(d.obstacles.is_empty());
        let plane = fit_plane(&acc.cells()[&[5, 5, 0]]).unwrap();
        assert!(plane.mse_m2 < 1e-12 && plane.slope_deg() < 1e-6);
    }

    #[test]
    fn a_gentle_ramp_is_navigable_and_a_steep_one_is_not() {
        let mut gentle = PointAccumulator::new(RES);
        surface(&mut gentle, (0.0, 2.0), (0.0, 1.0), |x, _| 0.02 + x * 20f64.to_radians().tan());
        let d = run(&gentle);
        assert_eq!(d.regions.len(), 1, "one ramp region");
        assert!(d.regions[0].voxels.len() >= 200);
        let mut steep = PointAccumulator::new(RES);
        surface(&mut steep, (0.0, 1.0), (0.0, 1.0), |x, _| 0.02 + x * 45f64.to_radians().tan());
        let d = run(&steep);
        assert!(d.regions.is_empty());
        let c = d.counts();
        assert_eq!(c.navigable, 0);
        assert!(c.steep > 50);
    }

    #[test]
    fn a_step_splits_the_floor_into_two_regions() {
        let mut acc = PointAccumulator::new(RES);
        surface(&mut acc, (0.0, 1.0), (0.0, 1.0), |_, _| 0.033);
        surface(&mut acc, (1.0, 2.0), (0.0, 1.0), |_, _| 0.233); // 20 cm up
        let d = run(&acc);
        assert_eq!(d.regions.len(), 2, "a 20 cm step is no boundary to walk across");
        assert!(d.regions.iter().all(|r| r.voxels.len() == 100));
    }

    #[test]
    fn a_box_on_the_floor_makes_an_obstacle_and_a_top_region() {
        let mut acc = PointAccumulator::new(RES);
        // Floor around a 0.6 × 0.6 × 0.5 m box at x, y in [0.7, 1.3].
        surface(&mut acc, (0.0, 2.0), (0.0, 2.0), |_, _| 0.033);
        let inside = |p: &Vector3<f64>| (0.7..1.3).contains(&p.x) && (0.7..1.3).contains(&p.y);
        let floor: Vec<VoxelKey> = acc.cells().keys().filter(|k| inside(&acc.centre(k))).copied().collect();
        for k in floor {
            acc.cells.remove(&k);
        }
        surface(&mut acc, (0.7, 1.3), (0.7, 1.3), |_, _| 0.533); // top
        for x0 in [0.703, 1.297] {
            wall(&mut acc, x0, (0.7, 1.3), (0.04, 0.53));
        }
        for y0 in [0.703, 1.297] {
            let mut xi = 0.705;
            while xi < 1.3 {
                let mut zi = 0.045;
                while zi < 0.53 {
                    acc.add(&Vector3::new(xi, y0, zi));
                    zi += 0.01;
                }
                xi += 0.01;
            }
        }
        let d = run(&acc);
        // The floor ring is one region; the box sides (steep planes and the non-planar edges)
        // form one obstacle, and the box's top, which lies on that obstacle, is part of it.
        assert_eq!(d.regions.len(), 1, "{:?}", d.regions.iter().map(|r| r.voxels.len()).collect::<Vec<_>>());
        assert!(d.regions[0].voxels.iter().all(|k| k[2] == 0), "the floor");
        assert_eq!(d.regions[0].voxels.len(), 400 - 36, "the floor ring");
        assert_eq!(d.obstacles.len(), 1, "{:?}", d.obstacles.iter().map(|o| o.voxels.len()).collect::<Vec<_>>());
        let o = &d.obstacles[0];
        let top = o.voxels.iter().filter(|k| k[2] == 5).count();
        assert!(top >= 16, "the box's top is the obstacle's: {top} voxels at its height");
        assert!((o.mean_m.x - 1.0).abs() < 0.05 && (o.mean_m.y - 1.0).abs() < 0.05, "{}", o.mean_m);
        // Written as layers.
        let dir = std::env::temp_dir().join(format!("nsd-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        write_navigable_ply(&dir.join("navigable.ply"), &acc, &d).unwrap();
        let nav = std::fs::read(dir.join("navigable.ply")).unwrap();
        let end = nav.windows(11).position(|w| w == b"end_header\n").expect("a PLY header") + 11;
        let navigable: usize = d.regions.iter().map(|r| r.voxels.len()).sum();
        assert_eq!(nav.len() - end, navigable * 28, "7 four-byte values per navigable voxel");
        let first_z = f32::from_le_bytes(nav[end + 8..end + 12].try_into().unwrap());
        assert!((first_z - 0.033).abs() < 0.01, "the floor's height: {first_z}");
        write_obstacles_ply(&dir.join("obstacles.ply"), &acc, &d).unwrap();
        let bytes = std::fs::read(dir.join("obstacles.ply")).unwrap();
        let text = String::from_utf8_lossy(&bytes);
        assert!(text.contains("format binary_little_endian 1.0") && text.contains("element face"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A floor z = 0.033 over [0, 4] × [0, 4] m with a rock on it: a sphere of radius 1 m centred
    /// 0.3 m below the floor at (2, 2), seen from above by two passes whose poses disagree on the
    /// rock by `dx_m` along x and `dz_m` in height (two scans, merged as the mapper merges them).
    fn rock_on_the_floor(dx_m: f64, dz_m: f64) -> PointAccumulator {
        let (c, r) = (Vector3::new(2.0, 2.0, 0.033 - 0.3), 1.0);
        let mut acc = PointAccumulator::new(RES);
        for pass in 0..2 {
            let mut scan = PointAccumulator::new(RES);
            let (lx, lz) = (pass as f64 * dx_m, pass as f64 * dz_m);
            surface(&mut scan, (0.0, 4.0), (0.0, 4.0), |x, y| {
                let d2 = (x - lx - c.x).powi(2) + (y - c.y).powi(2);
                let on_rock = (r * r - d2).max(0.0).sqrt() + c.z;
                if on_rock > 0.033 { on_rock + lz } else { 0.033 }
            });
            acc.merge(&scan).unwrap();
        }
        acc
    }

    #[test]
    fn a_rocks_top_is_the_rocks_even_where_two_passes_disagree_on_it() {
        // Passes 12-20 cm apart in height put the rock's top in two layers of voxels, with the
        // flank of one pass beside the top of the other: the top of the obstacle voxels around
        // was not enough to tell (before 2026-12-07 the upper sheet stayed a region of its own).
        for (dx_m, dz_m) in [(0.0, 0.0), (0.1, 0.12), (0.0, 0.2)] {
            let acc = rock_on_the_floor(dx_m, dz_m);
            let d = run(&acc);
            // The floor around is one region; the rock (its steep flanks and its gently sloping
            // top, 0.7 m above the floor) is one obstacle.
            let sizes: Vec<usize> = d.regions.iter().map(|r| r.voxels.len()).collect();
            assert_eq!(sizes.len(), 1, "dx {dx_m}, dz {dz_m}: regions {sizes:?}");
            assert!(d.regions[0].voxels.iter().all(|k| k[2] == 0), "dx {dx_m}, dz {dz_m}: the floor");
            let obstacles: Vec<usize> = d.obstacles.iter().map(|o| o.voxels.len()).collect();
            assert_eq!(obstacles.len(), 1, "dx {dx_m}, dz {dz_m}: {obstacles:?}");
            let apex = d.obstacles[0].voxels.iter().filter(|k| k[2] >= 6).count();
            assert!(apex >= 10, "dx {dx_m}, dz {dz_m}: the rock's top is the obstacle's ({apex} voxels at its height)");
        }
    }

    #[test]
    fn the_ground_stays_ground_over_a_sheet_of_obstacle_voxels_below_it() {
        // A floor over [0, 4] × [0, 4] m and, just below most of it, a layer of
        // scattered points (a second pass whose pose put the seabed lower, seen as clutter): the
        // obstacle voxels the floor touches lie below it, as under a rock's top. The floor is
        // still the ground (before 2026-12-07 it joined the obstacle under it, and the map had
        // no ground at all: the main job's test once saw that).
        let mut acc = PointAccumulator::new(RES);
        surface(&mut acc, (0.0, 4.0), (0.0, 4.0), |_, _| 0.05);
        let mut rng = 11u64;
        for i in 0..30 {
            for j in 0..30 {
                for _ in 0..40 {
                    let (x, y) = (
                        0.5 + (i as f64 + 0.5 + uniform(&mut rng)) * RES,
                        0.5 + (j as f64 + 0.5 + uniform(&mut rng)) * 0.1,
                    );
                    acc.add(&Vector3::new(x, y, -0.05 + uniform(&mut rng) * 0.09));
                }
            }
        }
        let d = run(&acc);
        let floor: usize = d.regions.iter().take(1).map(|r| r.voxels.iter().filter(|k| k[2] == 0).count()).sum();
        assert!(
            floor >= 1500,
            "the floor's 1,600 voxels are the largest region: {floor}; regions {:?}, obstacles {:?}",
            d.regions.iter().map(|r| r.voxels.len()).collect::<Vec<_>>(),
            d.obstacles.iter().map(|o| o.voxels.len()).collect::<Vec<_>>()
        );
        assert!(d.obstacles.iter().all(|o| o.voxels.iter().all(|k| k[2] < 0)), "no floor voxel in an obstacle");
    }

    /// A vertical face y = y0 over x, z ranges.
    fn wall_y(acc: &mut PointAccumulator, y0: f64, x: (f64, f64), z: (f64, f64)) {
        let mut xi = x.0 + 0.005;
        while xi < x.1 {
            let mut zi = z.0 + 0.005;
            while zi < z.1 {
                acc.add(&Vector3::new(xi, y0, zi));
                zi += 0.01;
            }
            xi += 0.01;
        }
    }

    /// A 6 × 5 m room's floor with two of its walls (2 m seen, no top) and a cabinet against one.
    fn room_with_a_cabinet(acc: &mut PointAccumulator) {
        surface(acc, (0.0, 6.0), (0.0, 5.0), |_, _| 0.05);
        wall(acc, 0.02, (0.0, 5.0), (0.05, 2.05));
        wall_y(acc, 4.98, (0.0, 6.0), (0.05, 2.05));
        // The cabinet: x 0.02-0.62, y 2-3, 1.2 m high (front, sides, top).
        wall(acc, 0.62, (2.0, 3.0), (0.05, 1.25));
        wall_y(acc, 2.0, (0.02, 0.62), (0.05, 1.25));
        wall_y(acc, 3.0, (0.02, 0.62), (0.05, 1.25));
        surface(acc, (0.02, 0.62), (2.0, 3.0), |_, _| 1.25);
    }

    #[test]
    fn a_rooms_walls_are_walls_and_a_cabinet_against_one_is_an_obstacle_of_its_own() {
        let mut acc = PointAccumulator::new(RES);
        room_with_a_cabinet(&mut acc);
        let d = run(&acc);
        let in_walls: std::collections::HashSet<VoxelKey> =
            d.walls.iter().flat_map(|w| w.voxels.iter().copied()).collect();
        // Both walls' faces away from the cabinet are walls.
        let k = |x: f64, y: f64, z: f64| acc.key(&Vector3::new(x, y, z));
        for p in [k(0.02, 0.5, 1.0), k(0.02, 4.5, 1.5), k(3.0, 4.98, 1.0), k(5.5, 4.98, 0.5)] {
            assert!(
                in_walls.contains(&p),
                "{p:?} in a wall; walls {:?}",
                d.walls.iter().map(|w| w.voxels.len()).collect::<Vec<_>>()
            );
        }
        // The cabinet's front is an obstacle's, and no obstacle holds a wall voxel.
        let front = k(0.62, 2.5, 0.6);
        let cabinet: Vec<&Obstacle> = d.obstacles.iter().filter(|o| o.voxels.contains(&front)).collect();
        assert_eq!(cabinet.len(), 1, "obstacles {:?}", d.obstacles.iter().map(|o| o.voxels.len()).collect::<Vec<_>>());
        assert!(d.obstacles.iter().all(|o| o.voxels.iter().all(|v| !in_walls.contains(v))));
        // Judged with the scene's truth: the cabinet is found, apart from the walls.
        let truth = |p: &Vector3<f64>| {
            if p.x <= 0.72 && (1.9..=3.1).contains(&p.y) && p.z <= 1.35 && p.x > 0.1 {
                truth::TruthClass::Object(0)
            } else if p.x < 0.12 || p.y > 4.88 {
                truth::TruthClass::Wall
            } else if p.z < 0.15 {
                truth::TruthClass::Ground
            } else {
                truth::TruthClass::Nothing
            }
        };
        let score = truth::score(&d, &acc, truth);
        assert_eq!((score.objects_found, score.objects_observed), (1, 1), "{score:?}");
        assert!(score.wall.share().is_some_and(|s| s > 0.9), "{score:?}");
        // Without walls (`min_wall_length_m = 0`) the cabinet is part of the walls' obstacle.
        let without = discover(&acc, |_| true, &NsdConfig { min_wall_length_m: 0.0, ..Default::default() }).unwrap();
        assert!(without.walls.is_empty());
        let with_front: Vec<&Obstacle> = without.obstacles.iter().filter(|o| o.voxels.contains(&front)).collect();
        assert!(with_front.iter().all(|o| o.voxels.contains(&k(0.02, 0.5, 1.0))), "one obstacle with the wall");
    }

    #[test]
    fn a_ceiling_seen_from_below_is_no_region_and_the_walls_under_it_stay_walls() {
        let mut acc = PointAccumulator::new(RES);
        room_with_a_cabinet(&mut acc);
        surface(&mut acc, (0.0, 6.0), (0.0, 5.0), |_, _| 2.05);
        // The map: the points' voxels occupied, the room's inside (but the cabinet) seen free
        // through, the rest (behind the walls, above the ceiling) unknown.
        let cell = |k: &VoxelKey| {
            let c = acc.centre(k);
            let in_cabinet = c.x < 0.62 && (2.0..3.0).contains(&c.y) && c.z < 1.25;
            if acc.cells().contains_key(k) {
                MapCell::Occupied
            } else if c.x > 0.02 && c.y < 4.98 && c.z > 0.05 && c.z < 2.05 && c.y > 0.0 && c.x < 6.0 && !in_cabinet {
                MapCell::Free
            } else {
                MapCell::Unknown
            }
        };
        let k = |x: f64, y: f64, z: f64| acc.key(&Vector3::new(x, y, z));
        let ceiling = k(3.0, 2.5, 2.05);
        let d = discover_in(&acc, cell, &NsdConfig::default(), &PlaneFits::new()).unwrap();
        assert!(matches!(d.classes.get(&ceiling), Some(VoxelClass::Patch(_))), "{:?}", d.classes.get(&ceiling));
        assert!(d.regions.iter().all(|r| !r.voxels.contains(&ceiling)));
        assert!(d.obstacles.iter().all(|o| !o.voxels.contains(&ceiling)));
        assert!(d.regions[0].voxels.contains(&k(3.0, 2.5, 0.05)), "the floor is the largest region");
        let in_walls: std::collections::HashSet<VoxelKey> =
            d.walls.iter().flat_map(|w| w.voxels.iter().copied()).collect();
        for p in [k(0.02, 0.5, 1.0), k(0.02, 4.5, 1.5), k(3.0, 4.98, 1.0), k(5.5, 4.98, 0.5)] {
            assert!(in_walls.contains(&p), "{p:?} in a wall");
        }
        // Without the free space the map says nothing of the side it was seen from: the ceiling
        // is a region of its own.
        let blind = run(&acc);
        assert!(blind.regions.iter().any(|r| r.voxels.contains(&ceiling)));
    }

    #[test]
    fn a_wall_doubled_behind_by_one_pass_with_floor_points_behind_it_is_one_wall() {
        // A room's floor in front of a wall (y = 4.98), none in the row of voxels along the
        // wall's foot (there the floor's voxels hold the wall's points too); one pass, its pose
        // 14 cm off, put a strip of floor and a short sheet of the wall behind the wall's plane.
        // The floor's voxels next to the wall are then all behind it: the wall's front is judged
        // by the floor beyond its thickness (the room), and the sheet behind the wall is the
        // wall's, no obstacle. Judged by the wall's 26 neighbours (the rule before), the front
        // was the strip's side, the sheet stood in front of the wall, and stayed an obstacle.
        let mut acc = PointAccumulator::new(RES);
        surface(&mut acc, (0.0, 6.0), (0.0, 4.8), |_, _| 0.05);
        wall_y(&mut acc, 4.98, (0.0, 6.0), (0.05, 2.05));
        surface(&mut acc, (0.0, 6.0), (5.0, 5.1), |_, _| 0.06);
        wall_y(&mut acc, 5.12, (1.0, 2.5), (0.15, 1.65));
        let d = run(&acc);
        let k = |x: f64, y: f64, z: f64| acc.key(&Vector3::new(x, y, z));
        let sheet = k(1.75, 5.12, 1.0);
        assert!(
            d.walls.iter().any(|w| w.voxels.contains(&sheet)),
            "walls {:?}, obstacles {:?}",
            d.walls.iter().map(|w| (w.voxels.len(), w.normal)).collect::<Vec<_>>(),
            d.obstacles.iter().map(|o| (o.voxels.len(), o.mean_m)).collect::<Vec<_>>()
        );
        assert!(d.obstacles.iter().all(|o| !o.voxels.contains(&sheet)));
    }

    #[test]
    fn a_box_whose_top_was_seen_is_an_obstacle_and_no_wall() {
        // A 4 × 2 m box 1.8 m high on a floor, its top seen (a wreck's hull, a container): its
        // long sides are planes 4 m long and 1.8 m high, but they have a top.
        let mut acc = PointAccumulator::new(RES);
        surface(&mut acc, (0.0, 8.0), (0.0, 6.0), |_, _| 0.05);
        wall(&mut acc, 2.0, (2.0, 4.0), (0.05, 1.85));
        wall(&mut acc, 6.0, (2.0, 4.0), (0.05, 1.85));
        wall_y(&mut acc, 2.0, (2.0, 6.0), (0.05, 1.85));
        wall_y(&mut acc, 4.0, (2.0, 6.0), (0.05, 1.85));
        surface(&mut acc, (2.0, 6.0), (2.0, 4.0), |_, _| 1.85);
        let d = run(&acc);
        assert!(d.walls.is_empty(), "walls {:?}", d.walls.iter().map(|w| w.voxels.len()).collect::<Vec<_>>());
        let side = acc.key(&Vector3::new(4.0, 2.0, 1.0));
        assert!(d.obstacles.iter().any(|o| o.voxels.contains(&side)));
    }

    #[test]
    fn the_foot_plane_is_the_least_squares_plane_and_its_scatter() {
        let mut rng = 7u64;
        let points: Vec<Vector3<f64>> = (0..400)
            .map(|i| {
                let (x, y) = ((i % 20) as f64 * 0.1, (i / 20) as f64 * 0.1);
                Vector3::new(x, y, 1.0 + 0.1 * x - 0.05 * y + 0.02 * uniform(&mut rng))
            })
            .collect();
        let f = FootPlane::fit(points.iter().copied()).unwrap();
        assert!((f.slope[0] - 0.1).abs() < 2e-3 && (f.slope[1] + 0.05).abs() < 2e-3, "{:?}", f.slope);
        // Uniform noise of width 0.02 m: the median absolute height 0.005 m, × 1.4826.
        assert!((f.sigma_m - 1.4826 * 0.005).abs() < 1e-3, "{}", f.sigma_m);
        assert!((f.height(&Vector3::new(1.0, 1.0, 1.55)) - 0.5).abs() < 5e-3);
        // A tenth of the points a metre up (a table's top that joined the floor): the same
        // plane and scatter.
        let mut with_tops = points.clone();
        for p in with_tops.iter_mut().step_by(10) {
            p.z += 1.0;
        }
        let g = FootPlane::fit(with_tops.iter().copied()).unwrap();
        assert!((g.slope[0] - 0.1).abs() < 2e-3 && (g.slope[1] + 0.05).abs() < 2e-3, "{:?}", g.slope);
        assert!(g.sigma_m < 0.012 && (g.height(&Vector3::new(1.0, 1.0, 1.55)) - 0.5).abs() < 5e-3, "{g:?}");
        // Points along a line span no plane: level through their mean.
        let line = FootPlane::fit((0..10).map(|i| Vector3::new(i as f64, 2.0 * i as f64, i as f64))).unwrap();
        assert_eq!(line.slope, [0.0, 0.0]);
        assert!((line.height(&Vector3::new(0.0, 0.0, 4.5))).abs() < 1e-12);
        assert!(FootPlane::fit(std::iter::empty()).is_none());
    }

    /// A reproducible uniform number in [-0.5, 0.5).
    fn uniform(state: &mut u64) -> f64 {
        *state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (*state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    }

    /// `scans` scans of the floor z = `z` over [0, 2] × [0, 1] m, each a jittered 2.5 cm grid
    /// with 2 mm of noise (about 16 points per voxel and scan).
    fn floor_scans(scans: usize, z: f64, rng: &mut u64) -> Vec<Vec<Vector3<f64>>> {
        (0..scans)
            .map(|_| {
                let (ox, oy) = (uniform(rng) * 0.025, uniform(rng) * 0.025);
                let mut points = vec![];
                for i in 0..80 {
                    for j in 0..40 {
                        let x = (i as f64 + 0.5) * 0.025 + ox;
                        let y = (j as f64 + 0.5) * 0.025 + oy;
                        if (0.0..2.0).contains(&x) && (0.0..1.0).contains(&y) {
                            points.push(Vector3::new(x, y, z + uniform(rng) * 0.007));
                        }
                    }
                }
                points
            })
            .collect()
    }

    /// Scan `i` of a vehicle passing over a floor (z = 0.033 m, 2 mm of noise) with a 0.6 m box
    /// on it, across the origin (negative keys, many chunks of [`ChunkIndex`]): the part of the
    /// scene within 1.5 m of x = −4 + 0.5 i, a jittered 2.5 cm grid.
    fn passing_scan(i: usize, rng: &mut u64) -> PointAccumulator {
        let mut scan = PointAccumulator::new(RES);
        let cx = -4.0 + 0.5 * i as f64;
        let (ox, oy) = (uniform(rng) * 0.025, uniform(rng) * 0.025);
        let in_box = |x: f64, y: f64| (0.2..0.8).contains(&x) && (-0.3..0.3).contains(&y);
        for a in 0..120 {
            for b in 0..240 {
                let (x, y) = (cx - 1.5 + a as f64 * 0.025 + ox, -3.0 + b as f64 * 0.025 + oy);
                let z = if in_box(x, y) { 0.633 } else { 0.033 };
                scan.add(&Vector3::new(x, y, z + uniform(rng) * 0.004));
            }
        }
        for a in 0..24 {
            for h in 0..24 {
                let (t, z) = (0.2 + a as f64 * 0.025 + 0.0125, 0.045 + h as f64 * 0.025);
                for p in [[0.203, t - 0.5, z], [0.797, t - 0.5, z], [t, -0.297, z], [t, 0.297, z]] {
                    if (p[0] - cx).abs() < 1.5 {
                        scan.add(&Vector3::new(p[0], p[1], p[2] + uniform(rng) * 0.004));
                    }
                }
            }
        }
        scan
    }

    #[test]
    fn kept_plane_fits_give_the_discovery_of_fresh_ones_to_the_last_bit() {
        let mut rng = 11;
        let mut acc = PointAccumulator::new(RES);
        acc.track_changes();
        let mut fits = PlaneFits::new();
        let cfg = NsdConfig::default();
        let same = |a: &Discovery, b: &Discovery| {
            let differ = a.classes.iter().filter(|(k, c)| b.classes.get(k) != Some(*c)).count();
            assert!(differ == 0 && a.classes.len() == b.classes.len(), "{differ} voxels' classes differ");
            assert_eq!(a.regions, b.regions);
            assert_eq!(a.obstacles, b.obstacles);
            assert_eq!((a.surface_sigma_m, a.step_m), (b.surface_sigma_m, b.step_m));
        };
        for i in 0..16 {
            acc.merge(&passing_scan(i, &mut rng)).unwrap();
            if i % 5 == 4 {
                let changed = acc.take_changed();
                assert!(
                    !changed.is_empty() && (i == 4 || changed.len() < acc.cells().len()),
                    "{} changed",
                    changed.len()
                );
                fits.refresh(&acc, changed);
            }
        }
        // Scan 15 came after the last refresh: its voxels are fitted again, the others are kept.
        let changed_since = acc.take_changed();
        let fresh = discover(&acc, |_| true, &cfg).unwrap();
        let kept = discover_with(&acc, |_| true, &cfg, &fits).unwrap();
        assert!(fresh.classes.len() > PARALLEL_MIN_VOXELS, "{} voxels: the two-thread path", fresh.classes.len());
        assert_eq!(fresh.fitted, fresh.classes.len());
        assert_eq!(kept.fitted, changed_since.len());
        same(&fresh, &kept);
        // What the scene is: the floor one region, the box one obstacle with its top.
        assert_eq!(kept.regions.len(), 1, "{:?}", kept.regions.iter().map(|r| r.voxels.len()).collect::<Vec<_>>());
        assert_eq!(kept.obstacles.len(), 1);
        assert!(kept.obstacles[0].voxels.iter().any(|k| k[2] == 6), "the box's top is the obstacle's");
        fits.refresh(&acc, changed_since);
        let all_kept = discover_with(&acc, |_| true, &cfg, &fits).unwrap();
        assert_eq!(all_kept.fitted, 0);
        same(&fresh, &all_kept);
        // Only the occupied voxels, and the same whichever way.
        let occupied = |k: &VoxelKey| k[0] % 3 != 0;
        same(&discover(&acc, occupied, &cfg).unwrap(), &discover_with(&acc, occupied, &cfg, &fits).unwrap());
    }

    proptest::proptest! {
        #[test]
        fn the_chunk_index_finds_every_voxel_and_no_other(
            keys in proptest::collection::btree_set(
                proptest::strategy::Strategy::prop_map((-20i32..20, -20i32..20, -20i32..20), |(x, y, z)| [x, y, z]), 1..400),
            probes in proptest::collection::vec((-21i32..21, -21i32..21, -21i32..21), 1..400),
        ) {
            let keys: Vec<VoxelKey> = keys.into_iter().collect();
            let index = ChunkIndex::new(&keys);
            let mut near = index.near();
            for (i, k) in keys.iter().enumerate() {
                proptest::prop_assert_eq!(near.get(k), Some(i));
            }
            for (x, y, z) in probes {
                let k = [x, y, z];
                proptest::prop_assert_eq!(near.get(&k), keys.iter().position(|o| *o == k));
                // Its neighbours in the offsets' order, inside a chunk or on its faces.
                let mut found = vec![];
                near.around(&k, 0..26, |o, j| found.push((o, j)));
                let expected: Vec<(usize, usize)> = (0..26)
                    .filter_map(|o| keys.iter().position(|other| *other == neighbour(&k, o)).map(|j| (o, j)))
                    .collect();
                proptest::prop_assert_eq!(found, expected);
            }
        }
    }

    proptest::proptest! {
        #[test]
        fn voxels_sorted_as_packed_keys_come_in_the_keys_order(
            keys in proptest::collection::btree_set(
                proptest::strategy::Strategy::prop_map(
                    (-(1i32 << 20)..(1 << 20), -40i32..40, -40i32..40), |(x, y, z)| [x, y, z]), 1..300),
            far in proptest::option::of(proptest::prelude::any::<i32>()),
            parallel: bool,
        ) {
            let mut acc = PointAccumulator::new(RES);
            for k in &keys {
                acc.cells.insert(*k, VoxelStats::default());
            }
            // A key beyond ±2^20 voxels takes the plain sort.
            if let Some(x) = far {
                acc.cells.insert([x, 0, 0], VoxelStats::default());
            }
            let mut want: Vec<VoxelKey> = acc.cells.keys().copied().collect();
            want.sort_unstable();
            let sorted = sorted_cells(&acc, parallel);
            let got: Vec<VoxelKey> = (0..sorted.len()).map(|i| sorted.get(i).0).collect();
            proptest::prop_assert_eq!(got, want);
        }
    }

    #[test]
    fn two_passes_that_disagree_by_centimetres_are_one_floor_and_not_when_pooled_as_one_scan() {
        let mut rng = 7;
        // Two passes over the same floor whose poses disagree by 4 cm in height.
        let mut all = floor_scans(5, 0.033, &mut rng);
        all.extend(floor_scans(5, 0.073, &mut rng));
        let mut by_scan = PointAccumulator::new(RES);
        let mut pooled = PointAccumulator::new(RES);
        for scan in &all {
            let mut s = PointAccumulator::new(RES);
            for p in scan {
                s.add(p);
                pooled.add(p);
            }
            by_scan.merge(&s).unwrap();
        }
        let cell = &by_scan.cells()[&[5, 5, 0]];
        assert_eq!(cell.scans(), 10);
        assert_eq!(pooled.cells()[&[5, 5, 0]].scans(), 1);
        // Each scan's own points lie on a plane: the floor is one region, and its surfaces are
        // about 2 cm thick (the two passes 4 cm apart).
        let d = run(&by_scan);
        assert_eq!(d.regions.len(), 1, "{:?}", d.regions.iter().map(|r| r.voxels.len()).collect::<Vec<_>>());
        assert_eq!(d.regions[0].voxels.len(), 200);
        assert!(d.obstacles.is_empty());
        assert!((0.015..0.025).contains(&d.surface_sigma_m), "{}", d.surface_sigma_m);
        let plane = fit_plane(cell).unwrap();
        assert!(plane.within_scans && plane.mse_m2 < 1e-5, "{plane:?}");
        // The same points as one scan are two sheets 4 cm apart in every voxel: not planar.
        let d = run(&pooled);
        assert!(d.regions.is_empty(), "{:?}", d.regions.iter().map(|r| r.voxels.len()).collect::<Vec<_>>());
        assert_eq!(d.counts().non_planar, 200);
    }

    #[test]
    fn sparsely_sampled_voxels_on_the_floor_fill_the_region_and_a_line_of_points_is_no_plane() {
        let mut acc = PointAccumulator::new(RES);
        // Dense except a strip x in [0.9, 1.1] with two points per voxel: the strip would cut
        // the floor in two.
        surface(&mut acc, (0.0, 0.9), (0.0, 1.0), |_, _| 0.033);
        surface(&mut acc, (1.1, 2.0), (0.0, 1.0), |_, _| 0.033);
        for i in 0..2 {
            for j in 0..10 {
                for d in [0.02, 0.07] {
                    acc.add(&Vector3::new(0.9 + i as f64 * 0.1 + d, j as f64 * 0.1 + d, 0.033));
                }
            }
        }
        let d = run(&acc);
        assert_eq!(d.regions.len(), 1, "{:?}", d.regions.iter().map(|r| r.voxels.len()).collect::<Vec<_>>());
        assert_eq!(d.regions[0].voxels.len(), 200);
        // Points along one line fit any plane through it: too few to tell.
        let mut line = VoxelStats::default();
        for i in 0..10 {
            line.add(&Vector3::new(0.005 + i as f64 * 0.01, 0.05, 0.05));
        }
        let p = fit_plane(&line).unwrap();
        assert!(p.spread_m2 < 1e-12, "{p:?}");
        let mut one = PointAccumulator::new(RES);
        for i in 0..10 {
            one.add(&Vector3::new(0.005 + i as f64 * 0.01, 0.05, 0.05));
        }
        assert_eq!(run(&one).classes[&[0, 0, 0]], VoxelClass::Sparse);
    }

    #[test]
    fn a_patch_smaller_than_a_vehicle_is_no_region_and_a_rough_spot_is_no_obstacle() {
        let mut acc = PointAccumulator::new(RES);
        surface(&mut acc, (0.0, 2.0), (0.0, 1.0), |_, _| 0.033);
        // A 0.3 m square shelf high above the floor, touching nothing: 0.09 m² < 0.25 m².
        surface(&mut acc, (0.5, 0.8), (0.3, 0.6), |_, _| 1.533);
        // A ridge on the floor, a 45° face 4 cm high whose points lie 2 cm above the floor on
        // average (within the 3 cm step): steep voxels that do not rise out of the floor.
        for k in [[15, 5, 0], [15, 6, 0]] {
            acc.cells.remove(&k);
        }
        surface(&mut acc, (1.5, 1.54), (0.5, 0.7), |x, _| 0.033 + (x - 1.5));
        let ridge = fit_plane(&acc.cells()[&[15, 5, 0]]).unwrap();
        assert!(ridge.slope_deg() > 40.0 && ridge.spread_m2 > 1e-4, "{ridge:?}");
        let d = run(&acc);
        assert!(matches!(d.classes[&[15, 5, 0]], VoxelClass::Navigable(_)), "{:?}", d.classes[&[15, 5, 0]]);
        assert_eq!(d.regions.len(), 1, "{:?}", d.regions.iter().map(|r| r.voxels.len()).collect::<Vec<_>>());
        assert_eq!(d.regions[0].voxels.len(), 200);
        assert_eq!(d.counts().patch, 9);
        assert!(d.obstacles.is_empty(), "{:?}", d.obstacles.iter().map(|o| o.voxels.clone()).collect::<Vec<_>>());
        // With a 0.05 m² footprint the shelf is a region of its own.
        let cfg = NsdConfig { min_region_area_m2: 0.05, ..Default::default() };
        assert_eq!(discover(&acc, |_| true, &cfg).unwrap().regions.len(), 2);
    }

    #[test]
    fn an_obstacle_needs_min_obstacle_voxels_of_its_own_shape() {
        let mut acc = PointAccumulator::new(RES);
        surface(&mut acc, (0.0, 2.0), (0.0, 1.0), |_, _| 0.033);
        // A post 0.1 m square and 0.2 m tall on the floor: two voxels whose points lie on its
        // four faces (not planar).
        acc.cells.remove(&[10, 5, 0]);
        for z in 0..20 {
            for i in 0..10 {
                let (z, t) = (0.005 + z as f64 * 0.01, 1.0 + 0.005 + i as f64 * 0.01);
                for p in [[t, 0.5, z], [t, 0.5999, z], [1.0, t - 0.5, z], [1.0999, t - 0.5, z]] {
                    acc.add(&Vector3::from(p));
                }
            }
        }
        let d = run(&acc);
        assert!(d.obstacles.is_empty(), "{:?}", d.obstacles.iter().map(|o| o.voxels.clone()).collect::<Vec<_>>());
        let cfg = NsdConfig { min_obstacle_voxels: 2, ..Default::default() };
        let d = discover(&acc, |_| true, &cfg).unwrap();
        assert_eq!(d.obstacles.len(), 1);
        assert!(d.obstacles[0].voxels.contains(&[10, 5, 1]), "{:?}", d.obstacles[0].voxels);
    }

    #[test]
    fn a_boulder_seen_part_by_part_from_a_vehicle_going_round_it_is_one_landmark() {
        // A sphere of 0.8 m radius; scan i sees the part of it facing azimuth 15° · i (points
        // every ~2 cm whose outward normal is within 46° of the view), as a vehicle passing it
        // would. Against the Gaussian of all the points so far alone, the twelfth part is too
        // far from the first eleven and starts a second landmark ([11, 1]); against the part
        // the last scan saw it is the same boulder.
        let (r, centre) = (0.8, Vector3::new(2.0, 2.0, 1.0));
        let mut tracker = ObstacleTracker::default();
        let cfg = NsdConfig::default();
        for i in 0..12 {
            let a = (15.0 * i as f64).to_radians();
            let view = Vector3::new(a.cos(), a.sin(), 0.6).normalize();
            let mut scan = PointAccumulator::new(RES);
            for t in 0..126 {
                let theta = t as f64 * std::f64::consts::PI / 125.0;
                for p in 0..252 {
                    let phi = p as f64 * 2.0 * std::f64::consts::PI / 252.0;
                    let n = Vector3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos());
                    if n.dot(&view) > 0.7 {
                        scan.add(&(centre + n * r));
                    }
                }
            }
            tracker.update(&scan, &cfg, 1.0, (RES * 0.5).powi(2)).unwrap();
        }
        let seen: Vec<u32> = tracker.landmarks.iter().map(|l| l.scans).collect();
        assert_eq!(seen, vec![12], "one landmark seen in every scan: {seen:?}");
        let (mean, _) = tracker.landmarks[0].stats.mean_cov().unwrap();
        assert!((mean - centre).norm() < r, "{mean}");
    }

    #[test]
    fn obstacles_associate_by_bhattacharyya_distance() {
        let ob = |x: f64, s: f64| Obstacle {
            voxels: vec![],
            mean_m: Vector3::new(x, 0.0, 0.0),
            cov_m2: Matrix3::identity() * s,
            points: 10,
        };
        let a = vec![ob(0.0, 0.04), ob(5.0, 0.04)];
        let b = vec![ob(5.05, 0.04), ob(0.02, 0.05), ob(20.0, 0.04)];
        let pairs = associate_obstacles(&a, &b, 0.5, 0.0);
        let idx: Vec<(usize, usize)> = pairs.iter().map(|p| (p.0, p.1)).collect();
        assert_eq!(idx.len(), 2);
        assert!(idx.contains(&(0, 1)) && idx.contains(&(1, 0)));
        // Identical Gaussians: distance 0. Same covariance, offset d: d²/(8σ²).
        let d = geometry::gaussian::bhattacharyya(&a[0].mean_m, &a[0].cov_m2, &a[0].mean_m, &a[0].cov_m2).unwrap();
        assert!(d.abs() < 1e-12);
        let p = associate_obstacles(&[ob(0.0, 0.04)], &[ob(0.4, 0.04)], 10.0, 0.0);
        assert!((p[0].2 - 0.16 / (8.0 * 0.04)).abs() < 1e-12, "{}", p[0].2);
    }

    #[test]
    fn invalid_settings_are_named() {
        let acc = PointAccumulator::new(RES);
        let cfg = NsdConfig { min_points: 1, ..Default::default() };
        let e = discover(&acc, |_| true, &cfg).unwrap_err();
        assert!(e.to_string().starts_with("min_points"), "{e}");
    }
}
