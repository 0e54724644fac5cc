//! The global landmark map (EQUATIONS §6.4, \[3D\] eq 38): every segment's landmarks mapped into the global
//! frame, L^g = R·L^l + T with Σ^g = R·Σ^l·Rᵀ plus the transform's own uncertainty
//! ([`Alignment::map_point`]), and landmarks of DIFFERENT segments that are the same point merged.
//!
//! Merge rule. Segments are taken in ascending segment id; each landmark of a segment is compared
//! with the global landmarks built so far that hold no member of its segment. A pair is a candidate
//! when (a) their descriptors are within [`MergeConfig::max_hamming`] bits, if both have one, and
//! (b) the Mahalanobis gate d² = Δᵀ(P₁+P₂)⁻¹Δ ≤ [`MergeConfig::gate_chi2`] holds (or, with
//! [`MergeConfig::use_bhattacharyya`], the Bhattacharyya distance is ≤
//! [`MergeConfig::max_bhattacharyya`]). Candidates are assigned greedily by increasing distance, one
//! landmark per global landmark per segment (a mutual-exclusion matching), and fused covariance-weighted
//! (the product of the Gaussians, as in [`crate::fuse::fuse`]); the others start new global landmarks.
//! So two landmarks of one segment never end up in one global landmark. The estimates of different
//! segments are treated as independent (they are, apart from sharing the buoy system); landmarks of one
//! segment share their transform's error, which the per-landmark covariance includes but the fusion
//! does not model as a correlation.
//!
//! Speed: a uniform hash grid over the global landmarks' means. A pair can only pass the gate γ if
//! ‖Δ‖ ≤ max(ρ₁, ρ₂) with ρ = √(2γ·λ_max(P)) (because λ_max(P₁+P₂) ≤ 2·max λ_max), and the Bhattacharyya
//! gate m implies the Mahalanobis gate 4m. The cell is the median ρ; a query scans the cells within
//! max(ρ, 4 cells) of its mean, plus a list of the few global landmarks whose ρ exceeds 4 cells. That is
//! O(n) for typical maps (50 000 landmarks in well under a second), never a quadratic pass unless the
//! covariances are wildly spread.

use std::collections::{HashMap, HashSet};
use std::io::Write;
use std::path::Path;

use nalgebra::{Cholesky, Matrix3, SymmetricEigen, Vector3};
use serde::{Deserialize, Serialize};

use crate::FusionError;
use crate::align::Alignment;
use crate::fuse::{check_covariance, fuse_unchecked};
use validation::{Issues, Validate};

/// A landmark of one segment's local map, in the segment's local frame.
#[derive(Debug, Clone, PartialEq)]
pub struct MapLandmark {
    /// Id within the segment.
    pub id: u64,
    /// The segment (its id: landmarks with the same segment id are never merged).
    pub segment: u32,
    /// Mean in the local frame, m.
    pub mean_m: Vector3<f64>,
    /// Covariance in the local frame, m² (symmetric PSD).
    pub cov_m2: Matrix3<f64>,
    /// A 256-bit binary descriptor (e.g. ORB), if any.
    pub descriptor: Option<[u8; 32]>,
    /// How many times the segment observed it.
    pub observations: u32,
}

/// A landmark of the global map, possibly merged from several segments.
#[derive(Debug, Clone, PartialEq)]
pub struct GlobalLandmark {
    /// Mean in the global frame, m.
    pub mean_m: Vector3<f64>,
    /// Covariance in the global frame, m² (symmetric).
    pub cov_m2: Matrix3<f64>,
    /// The descriptor of the member with the most observations that has one.
    pub descriptor: Option<[u8; 32]>,
    /// Sum of the members' observations.
    pub observations: u32,
    /// The merged landmarks as (segment, id), in merge order; at most one per segment.
    pub members: Vec<(u32, u64)>,
}

/// Settings of the cross-segment merge (keys relative to the config table).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MergeConfig {
    /// Gate on the squared Mahalanobis distance of the difference, Δᵀ(P₁+P₂)⁻¹Δ (χ²₃; 99 %: 11.345).
    pub gate_chi2: f64,
    /// Gate on the Bhattacharyya distance when `use_bhattacharyya` (default 11.345/4: the same gate
    /// as `gate_chi2` for two equal covariances; unlike it, it also refuses very different covariances).
    pub max_bhattacharyya: f64,
    /// Largest Hamming distance, bits, between the descriptors when both landmarks have one.
    pub max_hamming: u32,
    /// Gate with the Bhattacharyya distance instead of the Mahalanobis distance.
    pub use_bhattacharyya: bool,
}

impl Default for MergeConfig {
    fn default() -> Self {
        Self { gate_chi2: 11.345, max_bhattacharyya: 11.345 / 4.0, max_hamming: 50, use_bhattacharyya: false }
    }
}

impl Validate for MergeConfig {
    fn validate(&self, issues: &mut Issues) {
        if !(self.gate_chi2.is_finite() && self.gate_chi2 > 0.0) {
            issues.push("gate_chi2", "must be finite and > 0");
        }
        if !(self.max_bhattacharyya.is_finite() && self.max_bhattacharyya > 0.0) {
            issues.push("max_bhattacharyya", "must be finite and > 0");
        }
        if self.max_hamming > 256 {
            issues.push("max_hamming", "must be <= 256 (bits of a descriptor)");
        }
    }
}

/// Counts of one [`build_global_map_with_stats`] run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MergeStats {
    /// Landmarks given.
    pub input: usize,
    /// Landmarks dropped: a non-finite value or a covariance that is not symmetric PSD (also after
    /// mapping through the segment's alignment).
    pub dropped: usize,
    /// Landmarks merged into a global landmark of another segment.
    pub merged: usize,
    /// Global landmarks produced.
    pub output: usize,
}

/// Eq 38 for every segment, then the cross-segment merge (module docs). Landmarks with non-finite
/// values or non-PSD covariances are dropped; an invalid `cfg` merges nothing. Use
/// [`build_global_map_with_stats`] for the counts and the config error.
pub fn build_global_map(segments: &[(Alignment, Vec<MapLandmark>)], cfg: &MergeConfig) -> Vec<GlobalLandmark> {
    match build_global_map_with_stats(segments, cfg) {
        Ok((map, _)) => map,
        Err(_) => build(segments, &MergeConfig::default(), false).0,
    }
}

/// A landmark mapped to the global frame.
struct Entry {
    segment: u32,
    id: u64,
    mean: Vector3<f64>,
    cov: Matrix3<f64>,
    descriptor: Option<[u8; 32]>,
    observations: u32,
}

/// A global landmark under construction.
struct Cluster {
    mean: Vector3<f64>,
    cov: Matrix3<f64>,
    descriptor: Option<[u8; 32]>,
    descriptor_observations: u32,
    observations: u32,
    members: Vec<(u32, u64)>,
    /// Search radius ρ = √(2γ·λ_max), m.
    radius: f64,
    /// Where it is indexed.
    slot: Slot,
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Slot {
    Cell((i64, i64, i64)),
    Big,
}

/// The hash grid over the clusters' means.
struct Grid {
    cell_m: f64,
    big_radius_m: f64,
    /// Largest radius of a cluster ever indexed in a cell (≤ `big_radius_m`).
    max_cell_radius_m: f64,
    cells: HashMap<(i64, i64, i64), Vec<usize>>,
    big: Vec<usize>,
}

impl Grid {
    fn key(&self, p: &Vector3<f64>) -> (i64, i64, i64) {
        let k = |v: f64| (v / self.cell_m).floor() as i64; // saturating cast
        (k(p.x), k(p.y), k(p.z))
    }
    fn slot_for(&self, mean: &Vector3<f64>, radius: f64) -> Slot {
        if radius > self.big_radius_m { Slot::Big } else { Slot::Cell(self.key(mean)) }
    }
    fn insert(&mut self, idx: usize, slot: Slot, radius: f64) {
        match slot {
            Slot::Cell(k) => {
                self.max_cell_radius_m = self.max_cell_radius_m.max(radius);
                self.cells.entry(k).or_default().push(idx)
            }
            Slot::Big => self.big.push(idx),
        }
    }
    fn remove(&mut self, idx: usize, slot: Slot) {
        let list = match slot {
            Slot::Cell(k) => self.cells.get_mut(&k),
            Slot::Big => Some(&mut self.big),
        };
        if let Some(list) = list
            && let Some(pos) = list.iter().position(|&i| i == idx)
        {
            list.swap_remove(pos);
        }
    }
    /// Every cluster index that may pass a gate with a query at `p` of radius `radius`: the cells
    /// within max(radius, the largest indexed cluster radius) and every big cluster.
    fn candidates(&self, p: &Vector3<f64>, radius: f64, out: &mut Vec<usize>) {
        out.clear();
        let r = radius.max(self.max_cell_radius_m);
        let lo = self.key(&(p - Vector3::repeat(r)));
        let hi = self.key(&(p + Vector3::repeat(r)));
        let span = |a: i64, b: i64| (b.saturating_sub(a) as u128).saturating_add(1);
        let cells = span(lo.0, hi.0).saturating_mul(span(lo.1, hi.1)).saturating_mul(span(lo.2, hi.2));
        if cells > (self.cells.len() as u128).max(1) {
            // Cheaper to look at every occupied cell.
            for list in self.cells.values() {
                out.extend_from_slice(list);
            }
        } else {
            for x in lo.0..=hi.0 {
                for y in lo.1..=hi.1 {
                    for z in lo.2..=hi.2 {
                        if let Some(list) = self.cells.get(&(x, y, z)) {
                            out.extend_from_slice(list);
                        }
                    }
                }
            }
        }
        out.extend_from_slice(&self.big);
    }
}

fn hamming(a: &[u8; 32], b: &[u8; 32]) -> u32 {
    a.iter().zip(b).map(|(x, y)| (x ^ y).count_ones()).sum()
}

fn max_eigenvalue(p: &Matrix3<f64>) -> f64 {
    SymmetricEigen::new(*p).eigenvalues.max().max(0.0)
}

/// [`build_global_map`] with the counts; error only for an invalid `cfg`
/// ([`FusionError::InvalidArgument`]).
pub fn build_global_map_with_stats(
    segments: &[(Alignment, Vec<MapLandmark>)],
    cfg: &MergeConfig,
) -> Result<(Vec<GlobalLandmark>, MergeStats), FusionError> {
    if !cfg.issues().is_empty() {
        return Err(FusionError::InvalidArgument("merge config (see MergeConfig::validate)"));
    }
    Ok(build(segments, cfg, true))
}

/// Eq 38 and, when `merge`, the merge, for a valid `cfg`.
fn build(
    segments: &[(Alignment, Vec<MapLandmark>)],
    cfg: &MergeConfig,
    merge: bool,
) -> (Vec<GlobalLandmark>, MergeStats) {
    let mut stats = MergeStats::default();
    // Eq 38 (with the transform's uncertainty).
    let mut entries: Vec<Entry> = Vec::new();
    for (alignment, landmarks) in segments {
        for lm in landmarks {
            stats.input += 1;
            if !lm.mean_m.iter().all(|v| v.is_finite()) {
                stats.dropped += 1;
                continue;
            }
            let Ok(cov_local) = check_covariance("landmark covariance", &lm.cov_m2) else {
                stats.dropped += 1;
                continue;
            };
            let (mean, cov) = alignment.map_point(&lm.mean_m, &cov_local);
            let Ok(cov) = check_covariance("global landmark covariance", &cov) else {
                stats.dropped += 1;
                continue;
            };
            if !mean.iter().all(|v| v.is_finite()) {
                stats.dropped += 1;
                continue;
            }
            entries.push(Entry {
                segment: lm.segment,
                id: lm.id,
                mean,
                cov,
                descriptor: lm.descriptor,
                observations: lm.observations,
            });
        }
    }
    entries.sort_by_key(|e| e.segment); // stable: keeps the given order within a segment
    let gamma = if cfg.use_bhattacharyya { 4.0 * cfg.max_bhattacharyya } else { cfg.gate_chi2 };
    let radius_of = |cov: &Matrix3<f64>| (2.0 * gamma * max_eigenvalue(cov)).sqrt();
    let radii: Vec<f64> = entries.iter().map(|e| radius_of(&e.cov)).collect();
    let mut sorted = radii.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted.get(sorted.len() / 2).copied().unwrap_or(1.0);
    let cell_m = if median.is_finite() && median > 1e-6 { median } else { 1e-6 };
    let mut grid =
        Grid { cell_m, big_radius_m: 4.0 * cell_m, max_cell_radius_m: 0.0, cells: HashMap::new(), big: Vec::new() };
    let mut clusters: Vec<Cluster> = Vec::with_capacity(entries.len());
    let mut found = Vec::new();
    let mut start = 0;
    while start < entries.len() {
        let segment = entries[start].segment;
        let end = start + entries[start..].iter().take_while(|e| e.segment == segment).count();
        // Candidate pairs (distance, entry, cluster) against the clusters of earlier segments.
        let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
        for ei in (start..end).filter(|_| merge) {
            let e = &entries[ei];
            grid.candidates(&e.mean, radii[ei], &mut found);
            for &ci in &found {
                let c = &clusters[ci];
                let reach = radii[ei].max(c.radius);
                if (c.mean - e.mean).norm_squared() > reach * reach {
                    continue;
                }
                if let (Some(a), Some(b)) = (&e.descriptor, &c.descriptor)
                    && hamming(a, b) > cfg.max_hamming
                {
                    continue;
                }
                if c.members.iter().any(|m| m.0 == segment) {
                    continue; // cannot happen (clusters of this segment are added after), kept as a guard
                }
                let distance = if cfg.use_bhattacharyya {
                    match bhattacharyya(&e.mean, &e.cov, &c.mean, &c.cov) {
                        Ok(d) if d <= cfg.max_bhattacharyya => d,
                        _ => continue,
                    }
                } else {
                    let Some(chol) = Cholesky::new(e.cov + c.cov) else { continue };
                    let diff = e.mean - c.mean;
                    let d2 = diff.dot(&chol.solve(&diff));
                    if d2 > cfg.gate_chi2 {
                        continue;
                    }
                    d2
                };
                pairs.push((distance, ei, ci));
            }
        }
        pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut entry_used = vec![false; end - start];
        let mut cluster_used: HashSet<usize> = HashSet::new();
        for (_, ei, ci) in pairs {
            if entry_used[ei - start] || cluster_used.contains(&ci) {
                continue;
            }
            let e = &entries[ei];
            let c = &mut clusters[ci];
            let Ok((mean, cov, _)) = fuse_unchecked(&e.mean, &e.cov, &c.mean, &c.cov) else { continue };
            entry_used[ei - start] = true;
            cluster_used.insert(ci);
            stats.merged += 1;
            c.mean = mean;
            c.cov = cov;
            c.observations = c.observations.saturating_add(e.observations);
            c.members.push((e.segment, e.id));
            if e.descriptor.is_some() && (c.descriptor.is_none() || e.observations > c.descriptor_observations) {
                c.descriptor = e.descriptor;
                c.descriptor_observations = e.observations;
            }
            c.radius = radius_of(&c.cov);
            let old = c.slot;
            let new = grid.slot_for(&c.mean, c.radius);
            if new != old {
                clusters[ci].slot = new;
                grid.remove(ci, old);
                grid.insert(ci, new, clusters[ci].radius);
            }
        }
        for ei in start..end {
            if entry_used[ei - start] {
                continue;
            }
            let e = &entries[ei];
            let slot = grid.slot_for(&e.mean, radii[ei]);
            let idx = clusters.len();
            clusters.push(Cluster {
                mean: e.mean,
                cov: e.cov,
                descriptor: e.descriptor,
                descriptor_observations: if e.descriptor.is_some() { e.observations } else { 0 },
                observations: e.observations,
                members: vec![(e.segment, e.id)],
                radius: radii[ei],
                slot,
            });
            grid.insert(idx, slot, radii[ei]);
        }
        start = end;
    }
    stats.output = clusters.len();
    let map = clusters
        .into_iter()
        .map(|c| GlobalLandmark {
            mean_m: c.mean,
            cov_m2: c.cov,
            descriptor: c.descriptor,
            observations: c.observations,
            members: c.members,
        })
        .collect();
    (map, stats)
}

/// Bhattacharyya distance of two Gaussians ([`geometry::gaussian::bhattacharyya`]), with the
/// fusion crate's error type.
pub fn bhattacharyya(
    m1: &Vector3<f64>,
    p1: &Matrix3<f64>,
    m2: &Vector3<f64>,
    p2: &Matrix3<f64>,
) -> Result<f64, FusionError> {
    Ok(geometry::gaussian::bhattacharyya(m1, p1, m2, p2)?)
}

/// ASCII PLY of the global landmarks: one vertex each with `x y z` (m), `cov_trace_m2` (trace of the
/// covariance), `observations` and `members` (number of merged segment landmarks).
pub fn write_ply(path: &Path, landmarks: &[GlobalLandmark]) -> Result<(), FusionError> {
    let io = |e: std::io::Error| FusionError::Io { path: path.display().to_string(), message: e.to_string() };
    let file = std::fs::File::create(path).map_err(io)?;
    let mut w = std::io::BufWriter::new(file);
    write!(
        w,
        "ply\nformat ascii 1.0\ncomment global landmark map (fusion crate); units m, m^2\nelement vertex {}\n\
         property double x\nproperty double y\nproperty double z\nproperty double cov_trace_m2\n\
         property uint observations\nproperty uint members\nend_header\n",
        landmarks.len()
    )
    .map_err(io)?;
    for l in landmarks {
        writeln!(
            w,
            "{} {} {} {} {} {}",
            l.mean_m.x,
            l.mean_m.y,
            l.mean_m.z,
            l.cov_m2.trace(),
            l.observations,
            u32::try_from(l.members.len()).unwrap_or(u32::MAX)
        )
        .map_err(io)?;
    }
    w.flush().map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Matrix6, Translation3, UnitQuaternion};
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal, Uniform};
    use rand_xoshiro::Xoshiro256PlusPlus;

    type Segments = Vec<(Alignment, Vec<MapLandmark>)>;

    fn iso(x: f64, y: f64, z: f64, roll: f64, pitch: f64, yaw: f64) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(roll, pitch, yaw))
    }

    fn exact(t: Isometry3<f64>) -> Alignment {
        Alignment::from_transform(t, Matrix6::zeros())
    }

    fn lm(segment: u32, id: u64, mean: Vector3<f64>, var: f64) -> MapLandmark {
        MapLandmark { id, segment, mean_m: mean, cov_m2: Matrix3::identity() * var, descriptor: None, observations: 3 }
    }

    /// `count` landmarks ≥ ~2 m apart, seen by `segments` segments with different local frames, with
    /// noise σ = 1 cm and a declared σ of 2 cm (so that no true pair misses the 99 % gate: a pair
    /// fails only beyond d² = 4·11.3, probability ~1e-9).
    fn scene(count: usize, segments: u32, seed: u64) -> (Vec<Vector3<f64>>, Segments) {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        let side = (count as f64).cbrt().ceil() as usize;
        let jitter = Uniform::new(-0.5, 0.5).unwrap();
        let truth: Vec<Vector3<f64>> = (0..count)
            .map(|i| {
                let (x, y, z) = (i % side, (i / side) % side, i / (side * side));
                Vector3::new(x as f64 * 3.0, y as f64 * 3.0, z as f64 * 3.0)
                    + Vector3::from_fn(|_, _| jitter.sample(&mut rng))
            })
            .collect();
        let noise = Normal::new(0.0, 0.01).unwrap();
        let segs = (0..segments)
            .map(|s| {
                let t = iso(10.0 * s as f64, -4.0 * s as f64, 1.0, 0.1 * s as f64, -0.05 * s as f64, 0.8 * s as f64);
                let lms = truth
                    .iter()
                    .enumerate()
                    .map(|(i, g)| {
                        let local = t.inverse_transform_point(&(*g).into()).coords
                            + Vector3::from_fn(|_, _| noise.sample(&mut rng));
                        lm(s, i as u64, local, 0.02 * 0.02)
                    })
                    .collect();
                (exact(t), lms)
            })
            .collect();
        (truth, segs)
    }

    #[test]
    fn eq_38_maps_a_landmark_into_the_global_frame() {
        let t = iso(5.0, -3.0, 2.0, 0.2, -0.1, 1.3);
        let cov = Matrix3::new(0.04, 0.01, 0.0, 0.01, 0.02, 0.005, 0.0, 0.005, 0.09);
        let l = MapLandmark { cov_m2: cov, ..lm(0, 7, Vector3::new(1.0, 2.0, 3.0), 0.0) };
        let map = build_global_map(&[(exact(t), vec![l])], &MergeConfig::default());
        assert_eq!(map.len(), 1);
        let r = t.rotation.to_rotation_matrix();
        let expected = r * Vector3::new(1.0, 2.0, 3.0) + Vector3::new(5.0, -3.0, 2.0);
        assert!((map[0].mean_m - expected).norm() < 1e-12);
        assert!((map[0].cov_m2 - r * cov * r.transpose()).amax() < 1e-15);
        assert_eq!(map[0].members, vec![(0, 7)]);
        assert_eq!(map[0].observations, 3);
        // The transform's own uncertainty adds to the covariance.
        let a = Alignment::from_transform(t, Matrix6::identity() * 1e-4);
        let map = build_global_map(
            &[(a, vec![MapLandmark { cov_m2: cov, ..lm(0, 7, Vector3::zeros(), 0.0) }])],
            &MergeConfig::default(),
        );
        assert!(map[0].cov_m2.trace() > cov.trace() + 2.9e-4);
    }

    #[test]
    fn two_segments_seeing_the_same_landmarks_merge_into_one_each_with_reduced_covariance() {
        let (truth, segs) = scene(300, 2, 1);
        let (map, stats) = build_global_map_with_stats(&segs, &MergeConfig::default()).unwrap();
        assert_eq!(stats, MergeStats { input: 600, dropped: 0, merged: 300, output: 300 });
        for g in &map {
            assert_eq!(g.members.len(), 2);
            assert_eq!(g.members[0].1, g.members[1].1, "different landmarks merged: {:?}", g.members);
            assert_ne!(g.members[0].0, g.members[1].0);
            assert!((g.cov_m2 - Matrix3::identity() * 0.0002).amax() < 1e-12, "{}", g.cov_m2);
            assert!((g.mean_m - truth[g.members[0].1 as usize]).norm() < 0.1);
            assert_eq!(g.observations, 6);
        }
        // Three segments: one global landmark each, three members.
        let (_, segs) = scene(100, 3, 2);
        let map = build_global_map(&segs, &MergeConfig::default());
        assert_eq!(map.len(), 100);
        assert!(map.iter().all(|g| g.members.len() == 3));
    }

    #[test]
    fn landmarks_of_one_segment_never_merge() {
        let p = Vector3::new(1.0, 1.0, 1.0);
        let one = vec![lm(0, 1, p, 0.01), lm(0, 2, p, 0.01), lm(0, 3, p + Vector3::new(0.01, 0.0, 0.0), 0.01)];
        let map = build_global_map(&[(exact(Isometry3::identity()), one.clone())], &MergeConfig::default());
        assert_eq!(map.len(), 3);
        // A second segment's landmark at the same place takes exactly one of them (the closest).
        let other = vec![lm(1, 9, p + Vector3::new(0.011, 0.0, 0.0), 0.01)];
        let segs = [(exact(Isometry3::identity()), one), (exact(Isometry3::identity()), other)];
        let map = build_global_map(&segs, &MergeConfig::default());
        assert_eq!(map.len(), 3);
        let merged: Vec<&GlobalLandmark> = map.iter().filter(|g| g.members.len() == 2).collect();
        assert_eq!(merged.len(), 1);
        assert_eq!(merged[0].members, vec![(0, 3), (1, 9)]);
        // Two entries of the same segment id in different tuples do not merge either.
        let split = [
            (exact(Isometry3::identity()), vec![lm(4, 1, p, 0.01)]),
            (exact(Isometry3::identity()), vec![lm(4, 2, p, 0.01)]),
        ];
        assert_eq!(build_global_map(&split, &MergeConfig::default()).len(), 2);
    }

    #[test]
    fn descriptors_decide_when_both_landmarks_have_one() {
        let p = Vector3::new(3.0, 0.0, -1.0);
        let with = |seg, d: Option<[u8; 32]>| MapLandmark { descriptor: d, ..lm(seg, 1, p, 0.01) };
        let a = [0u8; 32];
        let mut far = [0u8; 32];
        far[..8].copy_from_slice(&[0xff; 8]); // 64 bits apart
        let mut near = [0u8; 32];
        near[0] = 0x0f; // 4 bits apart
        let id = exact(Isometry3::identity());
        let cfg = MergeConfig::default();
        let run = |x, y| build_global_map(&[(id, vec![with(0, x)]), (id, vec![with(1, y)])], &cfg).len();
        assert_eq!(run(Some(a), Some(far)), 2);
        assert_eq!(run(Some(a), Some(near)), 1);
        assert_eq!(run(Some(a), None), 1);
        assert_eq!(run(None, None), 1);
        let map = build_global_map(&[(id, vec![with(0, None)]), (id, vec![with(1, Some(near))])], &cfg);
        assert_eq!(map[0].descriptor, Some(near));
    }

    #[test]
    fn the_gate_keeps_distinct_landmarks_apart() {
        let id = exact(Isometry3::identity());
        // σ = 0.1 m each: d² = 1² / 0.02 = 50 > 11.345.
        let segs =
            [(id, vec![lm(0, 1, Vector3::zeros(), 0.01)]), (id, vec![lm(1, 1, Vector3::new(1.0, 0.0, 0.0), 0.01)])];
        assert_eq!(build_global_map(&segs, &MergeConfig::default()).len(), 2);
        let wide = MergeConfig { gate_chi2: 60.0, ..MergeConfig::default() };
        assert_eq!(build_global_map(&segs, &wide).len(), 1);
    }

    #[test]
    fn bhattacharyya_matches_hand_computed_values() {
        let z = Vector3::zeros();
        let p = Matrix3::new(0.5, 0.1, 0.0, 0.1, 0.3, 0.05, 0.0, 0.05, 0.2);
        assert!(bhattacharyya(&z, &p, &z, &p).unwrap().abs() < 1e-15);
        // 1-D-like: covariances diag(σ₁², 1, 1) and diag(σ₂², 1, 1), means μ apart along x:
        // D_B = μ²/(4(σ₁²+σ₂²)) + ½·ln((σ₁²+σ₂²)/(2σ₁σ₂)).
        let d = |s1: f64, s2: f64| {
            (Matrix3::from_diagonal(&Vector3::new(s1, 1.0, 1.0)), Matrix3::from_diagonal(&Vector3::new(s2, 1.0, 1.0)))
        };
        // σ² = 1 and 1, μ = 2: 4/8 = 0.5.
        let (a, b) = d(1.0, 1.0);
        assert!((bhattacharyya(&z, &a, &Vector3::new(2.0, 0.0, 0.0), &b).unwrap() - 0.5).abs() < 1e-14);
        // σ² = 1 and 4, μ = 0: ½·ln(5/4) = 0.111572; μ = 3: 9/20 + 0.111572 = 0.561572.
        let (a, b) = d(1.0, 4.0);
        assert!((bhattacharyya(&z, &a, &z, &b).unwrap() - 0.5 * 1.25f64.ln()).abs() < 1e-14);
        assert!((bhattacharyya(&z, &a, &Vector3::new(3.0, 0.0, 0.0), &b).unwrap() - 0.561_571_775).abs() < 1e-8);
        assert!(matches!(bhattacharyya(&z, &Matrix3::zeros(), &z, &a), Err(FusionError::NotPositiveDefinite(_))));
        assert!(matches!(bhattacharyya(&Vector3::new(f64::NAN, 0.0, 0.0), &a, &z, &a), Err(FusionError::NonFinite(_))));
    }

    #[test]
    fn the_bhattacharyya_gate_also_refuses_very_different_covariances() {
        let id = exact(Isometry3::identity());
        // Same place, σ² 1e-4 vs 1: Mahalanobis d² = 0 merges; D_B = 1.5·ln(1.0001/0.02) ≈ 5.87 > 2.84 does not.
        let segs = [(id, vec![lm(0, 1, Vector3::zeros(), 1e-4)]), (id, vec![lm(1, 1, Vector3::zeros(), 1.0)])];
        assert_eq!(build_global_map(&segs, &MergeConfig::default()).len(), 1);
        let bhat = MergeConfig { use_bhattacharyya: true, ..MergeConfig::default() };
        assert_eq!(build_global_map(&segs, &bhat).len(), 2);
        let (_, segs) = scene(200, 2, 5);
        assert_eq!(build_global_map(&segs, &bhat).len(), 200);
    }

    #[test]
    fn invalid_landmarks_are_dropped_and_an_invalid_config_merges_nothing() {
        let id = exact(Isometry3::identity());
        let mut bad_cov = lm(0, 2, Vector3::zeros(), 0.01);
        bad_cov.cov_m2[(0, 0)] = -1.0;
        let segs = [
            (id, vec![lm(0, 1, Vector3::new(f64::NAN, 0.0, 0.0), 0.01), bad_cov, lm(0, 3, Vector3::zeros(), 0.01)]),
            (id, vec![lm(1, 1, Vector3::zeros(), 0.01)]),
        ];
        let (map, stats) = build_global_map_with_stats(&segs, &MergeConfig::default()).unwrap();
        assert_eq!(stats, MergeStats { input: 4, dropped: 2, merged: 1, output: 1 });
        assert_eq!(map.len(), 1);
        let bad =
            MergeConfig { gate_chi2: f64::NAN, max_bhattacharyya: 0.0, max_hamming: 300, use_bhattacharyya: false };
        let keys: Vec<String> = bad.issues().into_iter().map(|i| i.key).collect();
        assert_eq!(keys, ["gate_chi2", "max_bhattacharyya", "max_hamming"]);
        assert!(matches!(build_global_map_with_stats(&segs, &bad), Err(FusionError::InvalidArgument(_))));
        assert_eq!(build_global_map(&segs, &bad).len(), 2);
        let nan_transform = Alignment::from_transform(Isometry3::identity(), Matrix6::identity() * f64::NAN);
        let (_, stats) = build_global_map_with_stats(
            &[(nan_transform, vec![lm(0, 1, Vector3::zeros(), 0.01)])],
            &MergeConfig::default(),
        )
        .unwrap();
        assert_eq!(stats.dropped, 1);
        assert!(MergeConfig::default().issues().is_empty());
    }

    #[test]
    fn fifty_thousand_landmarks_merge_quickly() {
        let (_, segs) = scene(25_000, 2, 3);
        let start = std::time::Instant::now();
        let (map, stats) = build_global_map_with_stats(&segs, &MergeConfig::default()).unwrap();
        println!("50 000 landmarks → {} global in {:?} ({stats:?})", map.len(), start.elapsed());
        assert_eq!(map.len(), 25_000);
        assert_eq!(stats.merged, 25_000);
    }

    #[test]
    fn the_ply_file_is_written_and_parseable() {
        let (_, segs) = scene(50, 2, 4);
        let map = build_global_map(&segs, &MergeConfig::default());
        let dir = std::env::temp_dir().join(format!("fusion_ply_test_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("map.ply");
        write_ply(&path, &map).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let (header, body) = text.split_once("end_header\n").unwrap();
        assert!(header.starts_with("ply\nformat ascii 1.0\n"));
        assert!(header.contains(&format!("element vertex {}\n", map.len())));
        let properties = header.lines().filter(|l| l.starts_with("property")).count();
        let rows: Vec<Vec<f64>> =
            body.lines().map(|l| l.split(' ').map(|v| v.parse::<f64>().unwrap()).collect()).collect();
        assert_eq!(rows.len(), map.len());
        for (row, g) in rows.iter().zip(&map) {
            assert_eq!(row.len(), properties);
            assert_eq!(row[0], g.mean_m.x);
            assert_eq!(row[3], g.cov_m2.trace());
            assert_eq!(row[5], 2.0);
        }
        let missing = dir.join("no_such_dir").join("map.ply");
        assert!(matches!(write_ply(&missing, &map), Err(FusionError::Io { .. })));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
