//! The occupancy octree: node arena, scan insertion, pruning, queries and leaf iteration.

use std::sync::atomic::{AtomicUsize, Ordering};

use nalgebra::{Point3, Vector3};

use crate::key::{OcTreeKey, TREE_DEPTH, TREE_MAX_VAL, coord_to_key_checked, key_to_coord};
use crate::raycast::{RayScratch, merge_codes};
use crate::{OctreeError, Result};

/// Bit pattern (a NaN) of the log-odds of a slot that holds no node.
const ABSENT_BITS: u32 = 0x7FC0_DEAD;
/// Points handed to a ray-casting thread at a time.
const CHUNK: usize = 2048;
/// Below this many points a scan is cast on the calling thread only.
const PARALLEL_MIN_POINTS: usize = 8192;

/// OctoMap's `logodds(p)`: `(float) log(p / (1 - p))`.
pub fn logodds(probability: f64) -> f32 {
    (probability / (1.0 - probability)).ln() as f32
}

/// OctoMap's `probability(l)`: `1 - 1 / (1 + exp(l))`.
pub fn probability(log_odds: f64) -> f64 {
    1.0 - 1.0 / (1.0 + log_odds.exp())
}

/// Inverse sensor model and clamping (probabilities; OctoMap's defaults via `Default`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorModel {
    /// P(occupied | hit), default 0.7.
    pub prob_hit: f64,
    /// P(occupied | miss), default 0.4.
    pub prob_miss: f64,
    /// Lower clamping probability, default 0.1192.
    pub clamp_min: f64,
    /// Upper clamping probability, default 0.971.
    pub clamp_max: f64,
    /// Nodes with P ≥ this are occupied, default 0.5.
    pub occupancy_threshold: f64,
}

impl Default for SensorModel {
    fn default() -> Self {
        SensorModel { prob_hit: 0.7, prob_miss: 0.4, clamp_min: 0.1192, clamp_max: 0.971, occupancy_threshold: 0.5 }
    }
}

/// A 3-D point accepted by the insertion and query functions.
pub trait Point3Like {
    /// The point in `f32` (OctoMap stores scan points as `float`).
    fn xyz_f32(&self) -> [f32; 3];
    /// The point in `f64` (used by queries; `f32` input converts exactly).
    fn xyz_f64(&self) -> [f64; 3];
}

impl Point3Like for [f32; 3] {
    fn xyz_f32(&self) -> [f32; 3] {
        *self
    }
    fn xyz_f64(&self) -> [f64; 3] {
        self.map(f64::from)
    }
}
impl Point3Like for [f64; 3] {
    fn xyz_f32(&self) -> [f32; 3] {
        self.map(|v| v as f32)
    }
    fn xyz_f64(&self) -> [f64; 3] {
        *self
    }
}
impl Point3Like for Vector3<f32> {
    fn xyz_f32(&self) -> [f32; 3] {
        [self.x, self.y, self.z]
    }
    fn xyz_f64(&self) -> [f64; 3] {
        [self.x as f64, self.y as f64, self.z as f64]
    }
}
impl Point3Like for Vector3<f64> {
    fn xyz_f32(&self) -> [f32; 3] {
        [self.x as f32, self.y as f32, self.z as f32]
    }
    fn xyz_f64(&self) -> [f64; 3] {
        [self.x, self.y, self.z]
    }
}
impl Point3Like for Point3<f32> {
    fn xyz_f32(&self) -> [f32; 3] {
        self.coords.xyz_f32()
    }
    fn xyz_f64(&self) -> [f64; 3] {
        self.coords.xyz_f64()
    }
}
impl Point3Like for Point3<f64> {
    fn xyz_f32(&self) -> [f32; 3] {
        self.coords.xyz_f32()
    }
    fn xyz_f64(&self) -> [f64; 3] {
        self.coords.xyz_f64()
    }
}

/// What one [`OcTree::insert_point_cloud`] call did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct InsertStats {
    /// Points given.
    pub points: usize,
    /// Points ignored: not finite, or (within max range) end point outside the tree.
    pub skipped_points: usize,
    /// Distinct free keys of the scan (after removing occupied ones).
    pub free_cells: usize,
    /// Distinct occupied keys of the scan.
    pub occupied_cells: usize,
    /// Key updates that changed the map (the rest were early-aborted at the clamp).
    pub applied_updates: usize,
}

/// A leaf of the tree, as OctoMap's leaf iterator reports it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Leaf {
    /// OctoMap's `it.getKey()`: the finest-level key of the leaf's centre (for a leaf at depth
    /// 16 the voxel's own key; for a larger leaf `min_key + 2^(15 - depth)`).
    pub key: OcTreeKey,
    /// Depth of the leaf (16 = finest voxel; smaller = pruned leaf covering `8^(16 - depth)` voxels).
    pub depth: u8,
    /// Occupancy log-odds.
    pub log_odds: f32,
}

impl Leaf {
    /// Lowest-corner key of the region the leaf covers (OctoMap's `getIndexKey()`).
    pub fn min_key(&self) -> OcTreeKey {
        let half = if self.depth >= 16 { 0 } else { (TREE_MAX_VAL >> self.depth) as u16 };
        OcTreeKey(self.key.0.map(|k| k.wrapping_sub(half)))
    }

    /// Number of finest voxels along one edge of the leaf (`2^(16 - depth)`).
    pub fn edge_voxels(&self) -> u32 {
        1 << (TREE_DEPTH - self.depth.min(16) as u32)
    }
}

/// One tree node: log-odds and the index of its 8-child block (0 = no children).
#[derive(Debug, Clone, Copy)]
#[repr(C)]
pub(crate) struct Node {
    pub(crate) value: f32,
    pub(crate) children: u32,
}

impl Node {
    pub(crate) const ABSENT: Node = Node { value: f32::from_bits(ABSENT_BITS), children: 0 };

    #[inline]
    pub(crate) fn exists(&self) -> bool {
        !self.value.is_nan()
    }
}

/// Occupancy octree of depth 16 with OctoMap 1.9.7 semantics (see the crate docs).
///
/// Nodes live in an arena of 8-node blocks; block 0 holds the root in slot 0.
#[derive(Debug, Clone)]
pub struct OcTree {
    resolution: f64,
    res_factor: f64,
    model: SensorModel,
    pub(crate) hit_log: f32,
    pub(crate) miss_log: f32,
    pub(crate) clamp_min_log: f32,
    pub(crate) clamp_max_log: f32,
    pub(crate) occ_log: f32,
    pub(crate) nodes: Vec<Node>,
    free_blocks: Vec<u32>,
    pub(crate) num_nodes: usize,
    threads: usize,
    scratch: Vec<RayScratch>,
    codes: Vec<u64>,
    changes: Option<Box<ChangeTracker>>,
}

/// Which parts of the occupied map changed since [`OcTree::take_changes`] was last called (see
/// [`OcTree::track_changes`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MapChanges {
    /// Depth of the regions (their edge is `2^(16 - depth)` finest voxels).
    pub region_depth: u8,
    /// Every region whose occupied leaves may have changed: region index per axis, `key >> (16 -
    /// region_depth)`, each once, in no particular order.
    pub regions: Vec<[u16; 3]>,
    /// The occupied map may have changed anywhere (tracking just started, the tree was cleared
    /// or pruned as a whole, or an occupied leaf larger than a region was split or merged):
    /// compare everything.
    pub all: bool,
}

#[derive(Debug, Clone)]
struct ChangeTracker {
    region_depth: u8,
    regions: std::collections::HashSet<u64>,
    /// The region recorded last (updates come in Morton order: most repeat it).
    last: u64,
    all: bool,
}

impl ChangeTracker {
    #[inline]
    fn record(&mut self, morton: u64) {
        let r = morton >> (3 * (TREE_DEPTH - self.region_depth as u32));
        if r != self.last || self.regions.is_empty() {
            self.last = r;
            self.regions.insert(r);
        }
    }
}

impl OcTree {
    /// Empty tree with OctoMap's default sensor model. `resolution` (m) must be finite and > 0.
    pub fn new(resolution: f64) -> Result<Self> {
        Self::with_model(resolution, SensorModel::default())
    }

    /// Empty tree with a given sensor model.
    pub fn with_model(resolution: f64, model: SensorModel) -> Result<Self> {
        if !(resolution.is_finite() && resolution > 0.0) {
            return Err(OctreeError::InvalidParameter(format!("resolution must be finite and > 0, got {resolution}")));
        }
        let probs = [model.prob_hit, model.prob_miss, model.clamp_min, model.clamp_max, model.occupancy_threshold];
        if probs.iter().any(|p| !(*p > 0.0 && *p < 1.0)) {
            return Err(OctreeError::InvalidParameter(format!(
                "sensor model probabilities must be in (0, 1): {model:?}"
            )));
        }
        if model.prob_hit < 0.5 || model.prob_miss > 0.5 || model.clamp_min >= model.clamp_max {
            return Err(OctreeError::InvalidParameter(format!(
                "need prob_hit >= 0.5, prob_miss <= 0.5, clamp_min < clamp_max: {model:?}"
            )));
        }
        let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1).min(2);
        Ok(OcTree {
            resolution,
            res_factor: 1.0 / resolution,
            model,
            hit_log: logodds(model.prob_hit),
            miss_log: logodds(model.prob_miss),
            clamp_min_log: logodds(model.clamp_min),
            clamp_max_log: logodds(model.clamp_max),
            occ_log: logodds(model.occupancy_threshold),
            nodes: vec![Node::ABSENT; 8],
            free_blocks: Vec::new(),
            num_nodes: 0,
            threads,
            scratch: Vec::new(),
            codes: Vec::new(),
            changes: None,
        })
    }

    /// Voxel edge length (m).
    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// The sensor model.
    pub fn sensor_model(&self) -> SensorModel {
        self.model
    }

    /// Log-odds of (hit, miss, clamp min, clamp max, occupancy threshold), as stored (`f32`).
    pub fn log_odds_params(&self) -> [f32; 5] {
        [self.hit_log, self.miss_log, self.clamp_min_log, self.clamp_max_log, self.occ_log]
    }

    /// Number of ray-casting threads used by [`OcTree::insert_point_cloud`] (default:
    /// min(2, available cores)). The map does not depend on it.
    pub fn ray_threads(&self) -> usize {
        self.threads
    }

    /// Sets the number of ray-casting threads (at least 1).
    pub fn set_ray_threads(&mut self, threads: usize) {
        self.threads = threads.max(1);
    }

    /// Removes all nodes.
    pub fn clear(&mut self) {
        self.nodes.clear();
        self.nodes.resize(8, Node::ABSENT);
        self.free_blocks.clear();
        self.num_nodes = 0;
        self.changed_everywhere();
    }

    // ------------------------------------------------------------------ change tracking

    /// Starts (or restarts) recording which regions of the occupied map change, for a consumer
    /// that follows the map without comparing all of it each time (voxel deltas). Regions are the
    /// cubes of the tree at `region_depth` (1..=16; edge `2^(16 - region_depth)` finest voxels).
    /// A leaf update is recorded when the leaf was or becomes occupied (a free leaf that stays
    /// free changes nothing a consumer of occupied voxels sees); splitting or merging an occupied
    /// leaf larger than a region marks everything. The first [`OcTree::take_changes`] after this
    /// says `all`. Costs one hash insert per occupied update (the updates are in Morton order, so
    /// consecutive ones in one region are recorded once).
    pub fn track_changes(&mut self, region_depth: u8) -> Result<()> {
        if !(1..=TREE_DEPTH as u8).contains(&region_depth) {
            return Err(OctreeError::InvalidParameter(format!("region depth must be 1..=16, got {region_depth}")));
        }
        self.changes = Some(Box::new(ChangeTracker {
            region_depth,
            regions: std::collections::HashSet::new(),
            last: 0,
            all: true,
        }));
        Ok(())
    }

    /// What changed since the last call (or since [`OcTree::track_changes`]); `None` when changes
    /// are not tracked.
    pub fn take_changes(&mut self) -> Option<MapChanges> {
        let c = self.changes.as_mut()?;
        let shift = TREE_DEPTH - c.region_depth as u32;
        let regions =
            c.regions.drain().map(|r| OcTreeKey::from_morton(r << (3 * shift)).0.map(|k| k >> shift)).collect();
        Some(MapChanges { region_depth: c.region_depth, regions, all: std::mem::take(&mut c.all) })
    }

    fn changed_everywhere(&mut self) {
        if let Some(c) = self.changes.as_mut() {
            c.all = true;
            c.regions.clear();
        }
    }

    /// A leaf at `depth` holding `value` is split or merged: a consumer must look beyond one
    /// region when it is occupied and larger than a region.
    #[inline]
    fn leaf_reshaped(&mut self, depth: usize, value: f32) {
        if let Some(c) = self.changes.as_mut()
            && value >= self.occ_log
            && depth < c.region_depth as usize
        {
            c.all = true;
        }
    }

    /// The leaves inside one region (index per axis `key >> (16 - region_depth)`, as
    /// [`MapChanges::regions`] gives it), in leaf-iterator order. Leaves larger than the region
    /// are not reported (none when the region lies inside one; [`MapChanges::all`] covers
    /// changes to those).
    pub fn leaves_in_region(&self, region_depth: u8, region: [u16; 3]) -> Leaves<'_> {
        let mut stack = Vec::with_capacity(64);
        let depth = (region_depth as u32).min(TREE_DEPTH);
        let shift = TREE_DEPTH - depth;
        if self.root_exists() && depth >= 1 {
            let min = OcTreeKey(region.map(|r| ((r as u32) << shift) as u16));
            let m = min.morton();
            let mut node = 0usize;
            let mut found = true;
            for d in 0..depth {
                let b = self.nodes[node].children as usize;
                if b == 0 {
                    found = false; // a leaf above the region's depth
                    break;
                }
                let c = b * 8 + ((m >> (3 * (TREE_DEPTH - 1 - d))) & 7) as usize;
                if !self.nodes[c].exists() {
                    found = false;
                    break;
                }
                node = c;
            }
            if found {
                // The centre key of a node at `depth`, as the leaf iterator computes it.
                let key = if depth >= TREE_DEPTH {
                    min
                } else {
                    OcTreeKey(min.0.map(|k| k.wrapping_add((TREE_MAX_VAL >> depth) as u16)))
                };
                stack.push((node as u32, depth as u8, key));
            }
        }
        Leaves { tree: self, stack }
    }

    // ------------------------------------------------------------------ keys

    /// `coordToKeyChecked` for a point (`floor(c * (1 / res)) + 32768` in `f64`), `None` outside
    /// the tree or for non-finite input.
    pub fn coord_to_key(&self, point: impl Point3Like) -> Option<OcTreeKey> {
        let p = point.xyz_f64();
        Some(OcTreeKey([
            coord_to_key_checked(p[0], self.res_factor)?,
            coord_to_key_checked(p[1], self.res_factor)?,
            coord_to_key_checked(p[2], self.res_factor)?,
        ]))
    }

    /// Centre of a finest-level voxel.
    pub fn key_to_coord(&self, key: OcTreeKey) -> [f64; 3] {
        key.0.map(|k| key_to_coord(k, self.resolution))
    }

    // ------------------------------------------------------------------ arena

    #[inline]
    fn alloc_block(&mut self, fill: Node) -> u32 {
        if let Some(b) = self.free_blocks.pop() {
            let base = b as usize * 8;
            self.nodes[base..base + 8].fill(fill);
            b
        } else {
            let b = (self.nodes.len() / 8) as u32;
            self.nodes.extend_from_slice(&[fill; 8]);
            b
        }
    }

    #[inline]
    fn free_block(&mut self, b: u32) {
        let base = b as usize * 8;
        self.nodes[base..base + 8].fill(Node::ABSENT);
        self.free_blocks.push(b);
    }

    pub(crate) fn root_exists(&self) -> bool {
        self.nodes[0].exists()
    }

    /// Creates an absent child `ci` of `node` (allocating the block if needed); returns its index.
    pub(crate) fn create_child(&mut self, node: usize, ci: usize, value: f32) -> usize {
        let mut b = self.nodes[node].children;
        if b == 0 {
            b = self.alloc_block(Node::ABSENT);
            self.nodes[node].children = b;
        }
        let c = b as usize * 8 + ci;
        self.nodes[c] = Node { value, children: 0 };
        self.num_nodes += 1;
        c
    }

    /// Creates the root (value `value`) if it does not exist.
    pub(crate) fn ensure_root(&mut self, value: f32) -> bool {
        if self.root_exists() {
            return false;
        }
        self.nodes[0] = Node { value, children: 0 };
        self.num_nodes = 1;
        true
    }

    #[inline]
    fn collapsible(&self, node: usize) -> Option<f32> {
        let b = self.nodes[node].children;
        if b == 0 {
            return None;
        }
        let c = &self.nodes[b as usize * 8..b as usize * 8 + 8];
        let v0 = c[0].value;
        // NaN (absent) never compares equal, so absent children make the node non-collapsible.
        if c.iter().all(|n| n.children == 0 && n.value == v0) { Some(v0) } else { None }
    }

    /// OctoMap's `pruneNode`: collapses 8 equal leaf children into `node`.
    fn prune_node(&mut self, node: usize) -> bool {
        match self.collapsible(node) {
            Some(v) => {
                let b = self.nodes[node].children;
                self.nodes[node] = Node { value: v, children: 0 };
                self.free_block(b);
                self.num_nodes -= 8;
                true
            }
            None => false,
        }
    }

    #[inline]
    fn max_child(&self, node: usize) -> f32 {
        let b = self.nodes[node].children as usize * 8;
        let mut m = -f32::MAX;
        for n in &self.nodes[b..b + 8] {
            if n.exists() && n.value > m {
                m = n.value;
            }
        }
        m
    }

    /// Eager bookkeeping of an inner node after an update below it: prune it, or set its
    /// log-odds to the maximum of its children.
    #[inline]
    fn finalize(&mut self, node: usize, depth: usize) {
        if self.nodes[node].children == 0 {
            return;
        }
        if self.prune_node(node) {
            self.leaf_reshaped(depth, self.nodes[node].value);
        } else {
            self.nodes[node].value = self.max_child(node);
        }
    }

    // ------------------------------------------------------------------ insertion

    /// Integrates one scan exactly like OctoMap's `insertPointCloud(scan, origin, max_range,
    /// lazy, discretize = false)`: see the crate docs. `max_range < 0` means unlimited. With
    /// `lazy`, inner nodes are neither updated nor pruned: call
    /// [`OcTree::update_inner_occupancy`] (and [`OcTree::prune`]) before querying inner nodes.
    ///
    /// Non-finite points are skipped (counted in [`InsertStats::skipped_points`]); points in range
    /// whose ray leaves the tree contribute no free space (OctoMap does the same).
    pub fn insert_point_cloud<P: Point3Like + Sync>(
        &mut self,
        points: &[P],
        origin: impl Point3Like,
        max_range: f64,
        lazy: bool,
    ) -> Result<InsertStats> {
        let o = origin.xyz_f32();
        if !o.iter().all(|v| v.is_finite()) {
            return Err(OctreeError::InvalidParameter(format!("sensor origin not finite: {o:?}")));
        }
        if max_range.is_nan() {
            return Err(OctreeError::InvalidParameter("max_range is NaN".into()));
        }
        let skipped = self.cast_scan(points, o, max_range);
        let occupied = self.codes.iter().filter(|c| *c & 1 == 1).count();
        let mut stats = InsertStats {
            points: points.len(),
            skipped_points: skipped,
            free_cells: self.codes.len() - occupied,
            occupied_cells: occupied,
            applied_updates: 0,
        };
        stats.applied_updates = self.apply_codes(lazy);
        Ok(stats)
    }

    /// OctoMap's `computeUpdate`: the scan's distinct free and occupied keys (disjoint; sorted in
    /// Morton order), without changing the map.
    pub fn compute_update<P: Point3Like + Sync>(
        &self,
        points: &[P],
        origin: impl Point3Like,
        max_range: f64,
    ) -> (Vec<OcTreeKey>, Vec<OcTreeKey>) {
        let mut tmp = self.clone_params();
        tmp.cast_scan(points, origin.xyz_f32(), max_range);
        let mut free = Vec::new();
        let mut occ = Vec::new();
        for &c in &tmp.codes {
            let k = OcTreeKey::from_morton(c >> 1);
            if c & 1 == 1 { occ.push(k) } else { free.push(k) }
        }
        (free, occ)
    }

    fn clone_params(&self) -> OcTree {
        OcTree {
            resolution: self.resolution,
            res_factor: self.res_factor,
            model: self.model,
            hit_log: self.hit_log,
            miss_log: self.miss_log,
            clamp_min_log: self.clamp_min_log,
            clamp_max_log: self.clamp_max_log,
            occ_log: self.occ_log,
            nodes: Vec::new(),
            free_blocks: Vec::new(),
            num_nodes: 0,
            threads: self.threads,
            scratch: Vec::new(),
            codes: Vec::new(),
            changes: None,
        }
    }

    /// Casts all rays of a scan into `self.codes` (sorted, one `(morton << 1) | hit` per key).
    /// Returns the number of skipped points.
    fn cast_scan<P: Point3Like + Sync>(&mut self, points: &[P], origin: [f32; 3], max_range: f64) -> usize {
        let n = points.len();
        let threads = if n < PARALLEL_MIN_POINTS { 1 } else { self.threads };
        if self.scratch.len() < threads {
            self.scratch.resize_with(threads, RayScratch::default);
        }
        let (res, rf) = (self.resolution, self.res_factor);
        let next = AtomicUsize::new(0);
        let work = |s: &mut RayScratch| {
            s.clear();
            loop {
                let start = next.fetch_add(CHUNK, Ordering::Relaxed);
                if start >= n {
                    break;
                }
                for p in &points[start..(start + CHUNK).min(n)] {
                    s.cast(origin, p.xyz_f32(), max_range, res, rf);
                }
            }
            s.finish();
        };
        let (first, rest) = self.scratch[..threads].split_first_mut().expect("threads >= 1");
        if rest.is_empty() {
            work(first);
        } else {
            let work = &work;
            let joined = crossbeam::scope(|sc| {
                for s in rest.iter_mut() {
                    sc.spawn(move |_| work(s));
                }
                work(first);
            });
            if let Err(panic) = joined {
                std::panic::resume_unwind(panic);
            }
        }
        let lists: Vec<&[u64]> = self.scratch[..threads].iter().map(|s| s.codes.as_slice()).collect();
        merge_codes(&lists, &mut self.codes);
        self.scratch[..threads].iter().map(|s| s.skipped).sum()
    }

    /// Applies `self.codes` (sorted Morton order, free or hit per key) with OctoMap's `updateNode`
    /// semantics. Keys are visited in depth-first order and the root-to-leaf path is shared
    /// between consecutive keys; in eager mode every inner node on the path is pruned or given the
    /// maximum of its children once all updates below it are done, which yields the same tree as
    /// OctoMap's per-key bottom-up pass (the result of that pass does not depend on the order).
    /// Returns the number of applied (not early-aborted) updates.
    fn apply_codes(&mut self, lazy: bool) -> usize {
        let codes = std::mem::take(&mut self.codes);
        let depth = TREE_DEPTH as usize;
        let mut path = [0usize; 17];
        let mut dirty = [false; 17];
        let mut path_len = 0usize;
        let mut prev = 0u64;
        let mut applied = 0usize;
        for (i, &c) in codes.iter().enumerate() {
            let m = c >> 1;
            let delta = if c & 1 == 1 { self.hit_log } else { self.miss_log };
            let start = if i == 0 {
                0
            } else {
                let x = m ^ prev;
                let top_group = (63 - x.leading_zeros()) as usize / 3;
                (depth - 1 - top_group).min(path_len - 1)
            };
            for d in (start + 1..path_len).rev() {
                if dirty[d] {
                    if !lazy {
                        self.finalize(path[d], d);
                    }
                    dirty[d] = false;
                }
            }
            prev = m;
            let mut created = false;
            if i == 0 {
                created = self.ensure_root(0.0);
                path[0] = 0;
            }
            path_len = start + 1;
            let mut d = start;
            let mut node = path[d];
            loop {
                if d == depth {
                    if created || !self.aborts(node, delta) {
                        let before = self.nodes[node].value;
                        self.update_log_odds(node, delta);
                        applied += 1;
                        dirty[..depth].fill(true);
                        if let Some(c) = self.changes.as_mut()
                            && ((!created && before >= self.occ_log) || self.nodes[node].value >= self.occ_log)
                        {
                            c.record(m);
                        }
                    }
                    break;
                }
                let ci = ((m >> (3 * (depth - 1 - d))) & 7) as usize;
                let b = self.nodes[node].children;
                if b != 0 {
                    let child = b as usize * 8 + ci;
                    if !self.nodes[child].exists() {
                        self.nodes[child] = Node { value: 0.0, children: 0 };
                        self.num_nodes += 1;
                        created = true;
                    }
                    node = child;
                } else if created {
                    node = self.create_child(node, ci, 0.0);
                } else {
                    // A leaf above the finest level: a pruned node (what OctoMap's search finds).
                    if self.aborts(node, delta) {
                        break;
                    }
                    let v = self.nodes[node].value;
                    self.leaf_reshaped(d, v);
                    let nb = self.alloc_block(Node { value: v, children: 0 });
                    self.nodes[node].children = nb;
                    self.num_nodes += 8;
                    node = nb as usize * 8 + ci;
                }
                d += 1;
                path[d] = node;
                path_len = d + 1;
            }
        }
        for d in (0..path_len).rev() {
            if dirty[d] && !lazy {
                self.finalize(path[d], d);
            }
        }
        self.codes = codes;
        applied
    }

    /// Early abort of `updateNode`: the node is already at the clamp in the update direction.
    #[inline]
    fn aborts(&self, node: usize, delta: f32) -> bool {
        let v = self.nodes[node].value;
        (delta >= 0.0 && v >= self.clamp_max_log) || (delta <= 0.0 && v <= self.clamp_min_log)
    }

    #[inline]
    fn update_log_odds(&mut self, node: usize, delta: f32) {
        let mut v = self.nodes[node].value + delta;
        if v < self.clamp_min_log {
            v = self.clamp_min_log;
        } else if v > self.clamp_max_log {
            v = self.clamp_max_log;
        }
        self.nodes[node].value = v;
    }

    /// OctoMap's `updateNode(key, occupied, lazy)` for a single key (one hit or miss).
    pub fn update_key(&mut self, key: OcTreeKey, occupied: bool, lazy: bool) -> bool {
        self.codes.clear();
        self.codes.push(key.morton() << 1 | occupied as u64);
        self.apply_codes(lazy) == 1
    }

    /// Sets every inner node to the maximum log-odds of its children (OctoMap's
    /// `updateInnerOccupancy`, needed after lazy insertion).
    pub fn update_inner_occupancy(&mut self) {
        if self.root_exists() {
            self.update_inner_recurs(0, 0);
        }
    }

    fn update_inner_recurs(&mut self, node: usize, depth: u32) {
        let b = self.nodes[node].children as usize;
        if b == 0 {
            return;
        }
        if depth < TREE_DEPTH {
            for c in b * 8..b * 8 + 8 {
                if self.nodes[c].exists() {
                    self.update_inner_recurs(c, depth + 1);
                }
            }
        }
        self.nodes[node].value = self.max_child(node);
    }

    /// OctoMap's `prune()`: for depth 15, 14, ..., 1 collapse every node at that depth whose 8
    /// children are leaves with identical log-odds, stopping after the first depth where nothing
    /// was collapsed (the root is never collapsed by this function).
    pub fn prune(&mut self) {
        if !self.root_exists() {
            return;
        }
        self.changed_everywhere();
        for max_depth in (1..TREE_DEPTH).rev() {
            if self.prune_recurs(0, 0, max_depth) == 0 {
                break;
            }
        }
    }

    fn prune_recurs(&mut self, node: usize, depth: u32, max_depth: u32) -> usize {
        if depth < max_depth {
            let b = self.nodes[node].children as usize;
            if b == 0 {
                return 0;
            }
            let mut n = 0;
            for c in b * 8..b * 8 + 8 {
                if self.nodes[c].exists() {
                    n += self.prune_recurs(c, depth + 1, max_depth);
                }
            }
            n
        } else {
            self.prune_node(node) as usize
        }
    }

    /// OctoMap's `toMaxLikelihood()`: every node (inner ones too) set to the upper clamp if
    /// occupied, else to the lower clamp. [`OcTree::write_binary`] does not need it (it writes
    /// the max-likelihood tree without changing `self`).
    pub fn to_max_likelihood(&mut self) {
        self.changed_everywhere();
        let (occ, lo, hi) = (self.occ_log, self.clamp_min_log, self.clamp_max_log);
        for n in self.nodes.iter_mut().filter(|n| n.exists()) {
            n.value = if n.value >= occ { hi } else { lo };
        }
    }

    // ------------------------------------------------------------------ queries

    /// Log-odds of the leaf containing `point` (OctoMap's `search(point)`), `None` if unknown or
    /// outside the tree.
    pub fn search(&self, point: impl Point3Like) -> Option<f32> {
        self.search_key(self.coord_to_key(point)?)
    }

    /// Log-odds of the leaf containing the finest-level voxel `key`, `None` if unknown.
    #[inline]
    pub fn search_key(&self, key: OcTreeKey) -> Option<f32> {
        let nodes = &self.nodes;
        let mut n = nodes[0];
        if !n.exists() {
            return None;
        }
        let m = key.morton();
        let mut shift = 45;
        loop {
            if n.children == 0 {
                return Some(n.value);
            }
            let c = n.children as usize * 8 + ((m >> shift) & 7) as usize;
            n = nodes[c];
            if !n.exists() {
                return None;
            }
            if shift == 0 {
                return Some(n.value);
            }
            shift -= 3;
        }
    }

    /// Whether a log-odds value counts as occupied (≥ the occupancy threshold).
    pub fn is_occupied_log_odds(&self, log_odds: f32) -> bool {
        log_odds >= self.occ_log
    }

    /// `Some(true)` occupied, `Some(false)` free, `None` unknown.
    pub fn is_occupied(&self, point: impl Point3Like) -> Option<bool> {
        self.search(point).map(|l| self.is_occupied_log_odds(l))
    }

    /// Iterator over all leaves in OctoMap's leaf-iterator order (depth first, child 0 first).
    pub fn leaves(&self) -> Leaves<'_> {
        let mut stack = Vec::with_capacity(64);
        if self.root_exists() {
            let r = TREE_MAX_VAL as u16;
            stack.push((0u32, 0u8, OcTreeKey([r, r, r])));
        }
        Leaves { tree: self, stack }
    }

    /// Number of nodes (OctoMap's `size()`).
    pub fn num_nodes(&self) -> usize {
        self.num_nodes
    }

    /// Number of leaves (OctoMap's `getNumLeafNodes()`).
    pub fn num_leaves(&self) -> usize {
        self.leaves().count()
    }

    /// (occupied, free) leaves, in one walk of the tree (every leaf is one or the other: their sum
    /// is [`OcTree::num_leaves`]).
    pub fn num_occupied_free_leaves(&self) -> (usize, usize) {
        let (mut occ, mut free) = (0, 0);
        for l in self.leaves() {
            if self.is_occupied_log_odds(l.log_odds) {
                occ += 1;
            } else {
                free += 1;
            }
        }
        (occ, free)
    }

    /// Heap bytes of the tree storage (node arena capacity, 8 bytes per slot, plus the free-block
    /// list). Excludes [`OcTree::scratch_bytes`].
    pub fn memory_usage_bytes(&self) -> usize {
        std::mem::size_of::<Self>() + self.nodes.capacity() * 8 + self.free_blocks.capacity() * 4
    }

    /// Heap bytes of the reusable per-scan buffers (hash sets, code lists).
    pub fn scratch_bytes(&self) -> usize {
        self.codes.capacity() * 8
            + self
                .scratch
                .iter()
                .map(|s| s.free.heap_bytes() + s.occupied.heap_bytes() + s.codes.capacity() * 8)
                .sum::<usize>()
    }

    /// Releases the per-scan buffers and unused arena capacity.
    pub fn shrink_to_fit(&mut self) {
        self.scratch = Vec::new();
        self.codes = Vec::new();
        self.nodes.shrink_to_fit();
        self.free_blocks.shrink_to_fit();
    }

    /// FNV-1a hash over (key, depth as u32, log-odds) of all leaves in iteration order, the
    /// `leaf_hash` of the OctoMap benchmark (equal hashes = identical trees).
    pub fn leaf_hash(&self) -> u64 {
        let mut h = 0xcbf2_9ce4_8422_2325u64;
        let mut feed = |bytes: &[u8]| {
            for &b in bytes {
                h ^= b as u64;
                h = h.wrapping_mul(0x0000_0100_0000_01B3);
            }
        };
        for l in self.leaves() {
            for k in l.key.0 {
                feed(&k.to_le_bytes());
            }
            feed(&(l.depth as u32).to_le_bytes());
            feed(&l.log_odds.to_le_bytes());
        }
        h
    }
}

/// Iterator over the leaves of an [`OcTree`] (see [`OcTree::leaves`]).
#[derive(Debug)]
pub struct Leaves<'a> {
    tree: &'a OcTree,
    stack: Vec<(u32, u8, OcTreeKey)>,
}

impl Iterator for Leaves<'_> {
    type Item = Leaf;

    fn next(&mut self) -> Option<Leaf> {
        while let Some((node, depth, key)) = self.stack.pop() {
            let n = self.tree.nodes[node as usize];
            if n.children == 0 || depth as u32 == TREE_DEPTH {
                return Some(Leaf { key, depth, log_odds: n.value });
            }
            let cd = depth + 1;
            let off = (TREE_MAX_VAL >> cd) as u16;
            let b = n.children as usize * 8;
            for i in (0..8).rev() {
                if self.tree.nodes[b + i].exists() {
                    let mut k = key;
                    for (a, kk) in k.0.iter_mut().enumerate() {
                        *kk = if i & (1 << a) != 0 {
                            kk.wrapping_add(off)
                        } else {
                            kk.wrapping_sub(off).wrapping_sub(if off == 0 { 1 } else { 0 })
                        };
                    }
                    self.stack.push(((b + i) as u32, cd, k));
                }
            }
        }
        None
    }
}
