//! Navigable space and obstacles scored against a scene's truth (issue 39): what a planner given
//! the [`Discovery`] would get right, voxel by voxel and object by object.
//!
//! Each voxel the discovery classified is judged at the mean of its points (nearer the surface
//! than the voxel's centre) by a `truth` function that says what the scene holds there
//! ([`TruthClass`]: the seabed or floor, object `i`, a building's wall, or nothing: noise, far
//! points). Then:
//! - **per true class**, the share of its observed voxels the map puts in the matching class:
//!   ground (the seabed, a floor) → navigable (in a region), object → obstacle, wall → wall,
//!   nothing → none of them;
//! - **objects**: the obstacles are joined into components where their voxels touch
//!   (26-neighbourhood); a component is matched to the object most of its voxels belong to
//!   (none when most belong to no object). Recall: objects with a matched component over the
//!   objects observed (with at least one voxel judged theirs); precision: matched components over
//!   all components; and how many objects got more than one component;
//! - **regions**: how many, and the share of the observed ground voxels in the largest.

use std::collections::{BTreeMap, HashMap, HashSet};

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::{Discovery, PointAccumulator, VoxelKey, VoxelMap, neighbours};

/// What the scene holds at a point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum TruthClass {
    /// The seabed (or a floor): where a vehicle may go.
    Ground,
    /// Object `i` (a rock, a wreck, a piece of furniture): an obstacle.
    Object(u32),
    /// A building's wall: a [`crate::Wall`].
    Wall,
    /// Nothing the scene knows: noise, points beyond the scene.
    Nothing,
}

/// Agreement of one true class.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct ClassAgreement {
    /// Observed voxels of this true class.
    pub voxels: usize,
    /// Of them, those the map puts in the matching class.
    pub agreeing: usize,
}

impl ClassAgreement {
    /// `agreeing / voxels` (`None` without voxels).
    pub fn share(&self) -> Option<f64> {
        (self.voxels > 0).then(|| self.agreeing as f64 / self.voxels as f64)
    }
}

/// The discovery against the truth.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct TruthScore {
    /// Voxels judged (every voxel the discovery classified).
    pub voxels: usize,
    /// Ground voxels (the seabed, a floor) put in a navigable region.
    pub ground: ClassAgreement,
    /// Object voxels put in an obstacle.
    pub object: ClassAgreement,
    /// Voxels of nothing put in neither.
    pub nothing: ClassAgreement,
    /// A building's wall voxels put in a wall (none in a scene without walls).
    #[serde(default)]
    pub wall: ClassAgreement,
    /// All voxels in agreement over all voxels judged (`null` without voxels).
    pub agreement: Option<f64>,
    /// Objects with at least one voxel judged theirs.
    pub objects_observed: usize,
    /// Obstacle components (obstacles joined where their voxels touch).
    pub components: usize,
    /// Components matched to an object.
    pub components_matched: usize,
    /// Observed objects with a matched component.
    pub objects_found: usize,
    /// Observed objects with more than one matched component.
    pub objects_split: usize,
    /// `objects_found / objects_observed` (`null` when no object was observed).
    pub recall: Option<f64>,
    /// `components_matched / components` (`null` without components).
    pub precision: Option<f64>,
    /// Navigable regions.
    pub regions: usize,
    /// Share of the observed ground voxels in the largest region (`null` without ground voxels).
    pub largest_region_ground_share: Option<f64>,
    /// The obstacle landmarks tracked across scans against the objects ([`score_landmarks`];
    /// `null` when not scored).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub landmarks: Option<LandmarkScore>,
}

/// Obstacle landmarks against the scene's objects: each landmark is judged at its mean.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct LandmarkScore {
    /// Landmarks judged (those seen in at least `min_scans` scans).
    pub landmarks: usize,
    /// The scans a landmark needs to be judged.
    pub min_scans: u32,
    /// Landmarks whose mean lies on an object.
    pub on_objects: usize,
    /// Objects with exactly one landmark.
    pub objects_with_one: usize,
    /// Objects with more than one.
    pub objects_with_several: usize,
    /// The most landmarks one object has.
    pub most_on_one_object: usize,
    /// The landmarks on each object that has one, in the truth's object order (a large object,
    /// a wreck or a wall, may rightly hold several where a small one, a rock, should hold one).
    #[serde(default)]
    pub per_object: Vec<ObjectLandmarks>,
}

/// The landmarks on one object ([`LandmarkScore::per_object`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct ObjectLandmarks {
    /// The object's index in the truth ([`TruthClass::Object`]).
    pub object: u32,
    /// Landmarks whose mean lies on it.
    pub landmarks: usize,
}

/// Judges landmark means (with the scans each was seen in) by `truth`: how many lie on objects,
/// and how many objects got one landmark or several. Landmarks seen in fewer than `min_scans`
/// scans are left out.
pub fn score_landmarks(
    landmarks: &[(Vector3<f64>, u32)],
    min_scans: u32,
    truth: impl Fn(&Vector3<f64>) -> TruthClass,
) -> LandmarkScore {
    let mut per_object: BTreeMap<u32, usize> = BTreeMap::new();
    let mut s = LandmarkScore { min_scans, ..Default::default() };
    for (mean, scans) in landmarks {
        if *scans < min_scans {
            continue;
        }
        s.landmarks += 1;
        if let TruthClass::Object(i) = truth(mean) {
            s.on_objects += 1;
            *per_object.entry(i).or_default() += 1;
        }
    }
    s.objects_with_one = per_object.values().filter(|n| **n == 1).count();
    s.objects_with_several = per_object.values().filter(|n| **n > 1).count();
    s.most_on_one_object = per_object.values().copied().max().unwrap_or(0);
    s.per_object = per_object.into_iter().map(|(object, landmarks)| ObjectLandmarks { object, landmarks }).collect();
    s
}

/// Scores `d` (computed over `acc`) against `truth` (see the module's documentation), each voxel
/// judged at the mean of its points: where the map puts it.
pub fn score(d: &Discovery, acc: &PointAccumulator, truth: impl Fn(&Vector3<f64>) -> TruthClass) -> TruthScore {
    score_with(d, |k| {
        let at = acc.cells().get(k).and_then(|s| s.mean()).unwrap_or_else(|| acc.centre(k));
        truth(&at)
    })
}

/// Where the points in each voxel truly came from: per voxel of the map (where the map put the
/// points), the mean of their true positions (e.g. at the simulator's true poses). Judging each
/// voxel there ([`score_with`] and [`TrueOrigins::mean`]) scores the classification alone,
/// without the poses' error. Kept compactly: the sum of the offsets from the voxel's centre in
/// `f32` and a count, 16 bytes a voxel.
#[derive(Debug, Clone)]
pub struct TrueOrigins {
    res_m: f64,
    sums: VoxelMap<([f32; 3], u32)>,
}

impl TrueOrigins {
    /// Empty, for voxels of `res_m`.
    pub fn new(res_m: f64) -> Self {
        Self { res_m, sums: VoxelMap::default() }
    }

    fn centre(&self, k: &VoxelKey) -> Vector3<f64> {
        Vector3::new(k[0] as f64 + 0.5, k[1] as f64 + 0.5, k[2] as f64 + 0.5) * self.res_m
    }

    /// A point the map put in voxel `k` truly came from `true_m` (non-finite points are skipped).
    pub fn add(&mut self, k: VoxelKey, true_m: &Vector3<f64>) {
        if !true_m.iter().all(|v| v.is_finite()) {
            return;
        }
        let d = true_m - self.centre(&k);
        let e = self.sums.entry(k).or_insert(([0.0; 3], 0));
        for (s, v) in e.0.iter_mut().zip(d.iter()) {
            *s += *v as f32;
        }
        e.1 += 1;
    }

    /// The mean true position of voxel `k`'s points (`None` without any).
    pub fn mean(&self, k: &VoxelKey) -> Option<Vector3<f64>> {
        let (sum, n) = self.sums.get(k)?;
        (*n > 0).then(|| self.centre(k) + Vector3::new(sum[0] as f64, sum[1] as f64, sum[2] as f64) / *n as f64)
    }

    /// Voxels with points.
    pub fn len(&self) -> usize {
        self.sums.len()
    }

    /// No voxel has points.
    pub fn is_empty(&self) -> bool {
        self.sums.is_empty()
    }

    /// Scores `d` against `truth`, each voxel judged at its points' mean true position (at the
    /// voxel's centre when none of its points has one).
    pub fn score(&self, d: &Discovery, truth: impl Fn(&Vector3<f64>) -> TruthClass) -> TruthScore {
        score_with(d, |k| truth(&self.mean(k).unwrap_or_else(|| self.centre(k))))
    }
}

/// Scores `d` against the truth, each classified voxel judged by `judge` (see the module's
/// documentation).
pub fn score_with(d: &Discovery, judge: impl Fn(&VoxelKey) -> TruthClass) -> TruthScore {
    let judged: VoxelMap<TruthClass> = d.classes.keys().map(|k| (*k, judge(k))).collect();
    // Fx-hashed (SipHash over a million keys was most of the score's time).
    let navigable: rustc_hash::FxHashSet<VoxelKey> = d.regions.iter().flat_map(|r| r.voxels.iter().copied()).collect();
    let obstacle: rustc_hash::FxHashSet<VoxelKey> = d.obstacles.iter().flat_map(|o| o.voxels.iter().copied()).collect();
    let wall: rustc_hash::FxHashSet<VoxelKey> = d.walls.iter().flat_map(|w| w.voxels.iter().copied()).collect();
    let mut s = TruthScore { voxels: judged.len(), regions: d.regions.len(), ..Default::default() };
    for (k, t) in &judged {
        let (class, agrees) = match t {
            TruthClass::Ground => (&mut s.ground, navigable.contains(k)),
            TruthClass::Object(_) => (&mut s.object, obstacle.contains(k)),
            TruthClass::Nothing => {
                (&mut s.nothing, !navigable.contains(k) && !obstacle.contains(k) && !wall.contains(k))
            }
            TruthClass::Wall => (&mut s.wall, wall.contains(k)),
        };
        class.voxels += 1;
        class.agreeing += usize::from(agrees);
    }
    let agreeing = s.ground.agreeing + s.object.agreeing + s.nothing.agreeing + s.wall.agreeing;
    s.agreement = (s.voxels > 0).then(|| agreeing as f64 / s.voxels as f64);
    if let Some(largest) = d.regions.first() {
        let on_ground = largest.voxels.iter().filter(|k| judged.get(*k) == Some(&TruthClass::Ground)).count();
        s.largest_region_ground_share = (s.ground.voxels > 0).then(|| on_ground as f64 / s.ground.voxels as f64);
    } else if s.ground.voxels > 0 {
        s.largest_region_ground_share = Some(0.0);
    }
    let observed: HashSet<u32> =
        judged.values().filter_map(|t| if let TruthClass::Object(i) = t { Some(*i) } else { None }).collect();
    s.objects_observed = observed.len();
    let components = obstacle_components(d);
    s.components = components.len();
    let mut found: BTreeMap<u32, usize> = BTreeMap::new();
    for voxels in &components {
        if let Some(object) = majority_object(voxels, &judged) {
            s.components_matched += 1;
            *found.entry(object).or_default() += 1;
        }
    }
    s.objects_found = found.len();
    s.objects_split = found.values().filter(|n| **n > 1).count();
    s.recall = (s.objects_observed > 0).then(|| s.objects_found as f64 / s.objects_observed as f64);
    s.precision = (s.components > 0).then(|| s.components_matched as f64 / s.components as f64);
    s
}

/// The object most of `voxels` belong to, when that is more than half of them.
fn majority_object(voxels: &[VoxelKey], judged: &VoxelMap<TruthClass>) -> Option<u32> {
    let mut votes: BTreeMap<u32, usize> = BTreeMap::new();
    for k in voxels {
        if let Some(TruthClass::Object(i)) = judged.get(k) {
            *votes.entry(*i).or_default() += 1;
        }
    }
    let (object, n) = votes.into_iter().max_by_key(|(i, n)| (*n, std::cmp::Reverse(*i)))?;
    (2 * n > voxels.len()).then_some(object)
}

/// The obstacles joined into components where a voxel of one touches a voxel of another.
fn obstacle_components(d: &Discovery) -> Vec<Vec<VoxelKey>> {
    let owner: HashMap<VoxelKey, usize> =
        d.obstacles.iter().enumerate().flat_map(|(i, o)| o.voxels.iter().map(move |k| (*k, i))).collect();
    let mut parent: Vec<usize> = (0..d.obstacles.len()).collect();
    for (i, o) in d.obstacles.iter().enumerate() {
        for k in &o.voxels {
            for n in neighbours(k) {
                if let Some(&j) = owner.get(&n)
                    && j != i
                {
                    let (a, b) = (crate::find(&mut parent, i), crate::find(&mut parent, j));
                    parent[a.max(b)] = a.min(b);
                }
            }
        }
    }
    let mut groups: BTreeMap<usize, Vec<VoxelKey>> = BTreeMap::new();
    for (i, o) in d.obstacles.iter().enumerate() {
        let root = crate::find(&mut parent, i);
        groups.entry(root).or_default().extend(o.voxels.iter().copied());
    }
    groups.into_values().collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{NsdConfig, discover};

    /// A flat floor at z = 0.05 (10 × 10 voxels of 0.1 m) with two boxes standing on it and a
    /// stray point cloud far above: the truth knows the floor and the two boxes.
    fn scene() -> (PointAccumulator, impl Fn(&Vector3<f64>) -> TruthClass) {
        let mut acc = PointAccumulator::new(0.1);
        let mut rng = 1u64;
        let mut noise = move || {
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((rng >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 0.002
        };
        for i in 0..100 {
            for j in 0..100 {
                let (x, y) = (i as f64 * 0.01 + 0.0005, j as f64 * 0.01 + 0.0005);
                let in_box = |cx: f64, cy: f64| (x - cx).abs() < 0.1 && (y - cy).abs() < 0.1;
                if !in_box(0.25, 0.25) && !in_box(0.75, 0.75) {
                    acc.add(&Vector3::new(x, y, 0.05 + noise()));
                }
            }
        }
        // The boxes: 0.2 m cubes, points on all their faces above the floor.
        for (cx, cy) in [(0.25, 0.25), (0.75, 0.75)] {
            for a in 0..40 {
                for b in 0..40 {
                    let (u, v) = (a as f64 / 40.0 * 0.2 - 0.1, b as f64 / 40.0 * 0.2 + 0.05);
                    for p in [
                        Vector3::new(cx + u, cy - 0.1, v),
                        Vector3::new(cx + u, cy + 0.0999, v),
                        Vector3::new(cx - 0.1, cy + u, v),
                        Vector3::new(cx + 0.0999, cy + u, v),
                        Vector3::new(cx + u, cy + (v - 0.05) - 0.1, 0.2499),
                    ] {
                        acc.add(&p);
                    }
                }
            }
        }
        let truth = |p: &Vector3<f64>| {
            for (i, (cx, cy)) in [(0.25, 0.25), (0.75, 0.75)].into_iter().enumerate() {
                if (p.x - cx).abs() <= 0.11 && (p.y - cy).abs() <= 0.11 && p.z <= 0.26 && p.z > 0.06 {
                    return TruthClass::Object(i as u32);
                }
            }
            if (p.z - 0.05).abs() < 0.01 { TruthClass::Ground } else { TruthClass::Nothing }
        };
        (acc, truth)
    }

    #[test]
    fn a_floor_with_two_boxes_scores_both_boxes_and_the_floor() {
        let (acc, truth) = scene();
        let d = discover(&acc, |_| true, &NsdConfig::default()).expect("discovery");
        let s = score(&d, &acc, &truth);
        assert_eq!(s.voxels, d.classes.len());
        assert_eq!(s.objects_observed, 2, "{s:?}");
        assert_eq!((s.objects_found, s.objects_split), (2, 0), "{s:?}");
        assert_eq!(s.recall, Some(1.0), "{s:?}");
        assert!(s.precision.is_some_and(|p| p > 0.99), "{s:?}");
        assert!(s.ground.share().is_some_and(|g| g > 0.9), "{s:?}");
        assert!(s.largest_region_ground_share.is_some_and(|g| g > 0.9), "{s:?}");
        assert!(s.agreement.is_some_and(|a| a > 0.8), "{s:?}");
    }

    #[test]
    fn a_split_object_and_a_phantom_obstacle_are_counted() {
        let (acc, truth) = scene();
        let mut d = discover(&acc, |_| true, &NsdConfig::default()).expect("discovery");
        // Cut the first box's obstacle in two obstacles.
        let first = d.obstacles.iter().position(|o| truth(&o.mean_m) == TruthClass::Object(0)).expect("box 0");
        let mut o = d.obstacles[first].clone();
        let (keep, moved): (Vec<VoxelKey>, Vec<VoxelKey>) = o.voxels.iter().partition(|k| k[0] <= 2);
        assert!(!keep.is_empty() && !moved.is_empty(), "{:?}", o.voxels);
        d.obstacles[first].voxels = keep;
        o.voxels = moved;
        d.obstacles.push(o);
        // The moved half still touches the kept half (adjacent x): joined again, one component.
        let s = score(&d, &acc, &truth);
        assert_eq!((s.objects_found, s.objects_split), (2, 0), "touching halves are one component: {s:?}");
        // Without the voxels where they touch, the halves are two components of one object.
        let mut apart = d.clone();
        let last = apart.obstacles.len() - 1;
        apart.obstacles[first].voxels.retain(|k| k[0] <= 1);
        apart.obstacles[last].voxels.retain(|k| k[0] >= 3);
        let s = score(&apart, &acc, &truth);
        assert_eq!((s.components, s.objects_found, s.objects_split), (3, 2, 1), "{s:?}");
        assert_eq!(s.recall, Some(1.0), "{s:?}");
        // A phantom obstacle of voxels of nothing (high above the floor) lowers the precision.
        let mut phantom = d.obstacles[0].clone();
        phantom.voxels = vec![[40, 40, 40], [40, 40, 41]];
        d.obstacles.push(phantom);
        let s = score(&d, &acc, &truth);
        assert_eq!(s.components, 3, "{s:?}");
        assert_eq!(s.components_matched, 2, "{s:?}");
        assert!(s.precision.is_some_and(|p| (p - 2.0 / 3.0).abs() < 1e-9), "{s:?}");
    }
}
