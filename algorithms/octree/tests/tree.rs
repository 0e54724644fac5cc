//! Update rules, pruning, eager/lazy equivalence and a voxel-map reference model.

use std::collections::{BTreeMap, HashMap};

use octree::{OcTree, OcTreeKey, compute_ray_keys, logodds};
use proptest::prelude::*;

const RES: f64 = 0.1;

fn tree() -> OcTree {
    OcTree::new(RES).unwrap()
}

/// Reference model: a plain voxel map with OctoMap's per-scan rules, written independently of
/// the tree (sets, then one clamped update per key).
#[derive(Default)]
struct Model {
    voxels: HashMap<OcTreeKey, f32>,
}

impl Model {
    fn insert(&mut self, t: &OcTree, points: &[[f32; 3]], origin: [f32; 3], max_range: f64) {
        let [hit, miss, lo, hi, _] = t.log_odds_params();
        let mut free = std::collections::HashSet::new();
        let mut occ = std::collections::HashSet::new();
        for p in points {
            let d = [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
            let len = ((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) as f64).sqrt();
            if max_range < 0.0 || len <= max_range {
                compute_ray_keys(origin, *p, RES, |k| {
                    free.insert(k);
                });
                if let Some(k) = t.coord_to_key(*p) {
                    occ.insert(k);
                }
            } else {
                let l = len as f32;
                let r = max_range as f32;
                let end = [0, 1, 2].map(|a| origin[a] + d[a] / l * r);
                compute_ray_keys(origin, end, RES, |k| {
                    free.insert(k);
                });
            }
        }
        for k in free.difference(&occ).chain(occ.iter()) {
            let delta = if occ.contains(k) { hit } else { miss };
            let v = self.voxels.entry(*k).or_insert(0.0);
            *v = (*v + delta).clamp(lo, hi);
        }
    }
}

fn keys_near(t: &OcTree, c: [f32; 3]) -> OcTreeKey {
    t.coord_to_key(c).unwrap()
}

#[test]
fn single_hit_and_miss_values() {
    let mut t = tree();
    let s = t.insert_point_cloud(&[[0.55f32, 0.05, 0.05]], [0.05f32, 0.05, 0.05], -1.0, false).unwrap();
    assert_eq!((s.free_cells, s.occupied_cells, s.applied_updates), (5, 1, 6));
    assert_eq!(t.search([0.55f32, 0.05, 0.05]), Some(logodds(0.7)));
    assert_eq!(t.search([0.25f32, 0.05, 0.05]), Some(logodds(0.4)));
    assert_eq!(t.search([0.05f32, 0.05, 0.05]), Some(logodds(0.4)), "origin voxel is free");
    assert_eq!(t.search([0.65f32, 0.05, 0.05]), None, "beyond the end point: unknown");
    assert_eq!(t.is_occupied([0.55f32, 0.05, 0.05]), Some(true));
    assert_eq!(t.is_occupied([0.35f32, 0.05, 0.05]), Some(false));
    // A second scan accumulates.
    t.insert_point_cloud(&[[0.55f32, 0.05, 0.05]], [0.05f32, 0.05, 0.05], -1.0, false).unwrap();
    assert_eq!(t.search([0.55f32, 0.05, 0.05]), Some(logodds(0.7) + logodds(0.7)));
    assert_eq!(t.search([0.25f32, 0.05, 0.05]), Some(logodds(0.4) + logodds(0.4)));
}

#[test]
fn clamping_both_ways() {
    let mut t = tree();
    let [_, _, lo, hi, _] = t.log_odds_params();
    assert_eq!(hi, logodds(0.971));
    assert_eq!(lo, logodds(0.1192));
    for _ in 0..10 {
        t.insert_point_cloud(&[[0.55f32, 0.05, 0.05]], [0.05f32, 0.05, 0.05], -1.0, false).unwrap();
    }
    assert_eq!(t.search([0.55f32, 0.05, 0.05]), Some(hi));
    assert_eq!(t.search([0.25f32, 0.05, 0.05]), Some(lo));
    // One miss on a clamped-occupied voxel moves it down from the clamp.
    t.insert_point_cloud(&[[0.95f32, 0.05, 0.05]], [0.05f32, 0.05, 0.05], -1.0, false).unwrap();
    assert_eq!(t.search([0.55f32, 0.05, 0.05]), Some(hi + logodds(0.4)));
}

#[test]
fn duplicate_hits_in_one_scan_count_once() {
    let mut t = tree();
    let pts = [[0.51f32, 0.52, 0.53], [0.52, 0.51, 0.55], [0.58, 0.58, 0.58]];
    let s = t.insert_point_cloud(&pts, [0.05f32, 0.05, 0.05], -1.0, false).unwrap();
    assert_eq!(s.occupied_cells, 1);
    assert_eq!(t.search([0.55f32, 0.55, 0.55]), Some(logodds(0.7)));
}

#[test]
fn hit_wins_over_miss_in_the_same_scan() {
    let mut t = tree();
    // The first ray passes through voxel x=0.55 and ends further; the second ends in it.
    let pts = [[0.95f32, 0.05, 0.05], [0.55, 0.05, 0.05]];
    t.insert_point_cloud(&pts, [0.05f32, 0.05, 0.05], -1.0, false).unwrap();
    assert_eq!(t.search([0.55f32, 0.05, 0.05]), Some(logodds(0.7)));
    assert_eq!(t.search([0.45f32, 0.05, 0.05]), Some(logodds(0.4)));
    assert_eq!(t.search([0.95f32, 0.05, 0.05]), Some(logodds(0.7)));
}

#[test]
fn max_range_truncates_to_free_space() {
    let mut t = tree();
    let s = t.insert_point_cloud(&[[2.05f32, 0.05, 0.05]], [0.05f32, 0.05, 0.05], 1.0, false).unwrap();
    assert_eq!(s.occupied_cells, 0);
    // Ray truncated at 1.0 m: end point (1.05) voxel excluded, voxels up to 0.95 free.
    assert_eq!(t.search([0.95f32, 0.05, 0.05]), Some(logodds(0.4)));
    assert_eq!(t.search([1.05f32, 0.05, 0.05]), None);
    assert_eq!(t.search([2.05f32, 0.05, 0.05]), None);
}

#[test]
fn bad_input_is_an_error_or_skipped() {
    assert!(OcTree::new(0.0).is_err());
    assert!(OcTree::new(f64::NAN).is_err());
    let mut t = tree();
    assert!(t.insert_point_cloud(&[[1.0f32, 0.0, 0.0]], [f32::NAN, 0.0, 0.0], -1.0, false).is_err());
    assert!(t.insert_point_cloud(&[[1.0f32, 0.0, 0.0]], [0.0f32; 3], f64::NAN, false).is_err());
    let s = t.insert_point_cloud(&[[f32::INFINITY, 0.0, 0.0], [1e9, 0.0, 0.0]], [0.0f32; 3], -1.0, false).unwrap();
    assert_eq!(s.skipped_points, 2);
    assert_eq!(t.num_nodes(), 0);
    assert_eq!(t.search([1e30f64, 0.0, 0.0]), None);
}

#[test]
fn early_abort_keeps_a_clamped_pruned_region_pruned_in_lazy_mode() {
    let mut t = tree();
    // Fill a 2x2x2 block (one depth-15 node) with hits until clamped, then prune it.
    let pts: Vec<[f32; 3]> = (0..8)
        .map(|i| [0.05 + 0.1 * (i & 1) as f32, 0.05 + 0.1 * (i >> 1 & 1) as f32, 10.05 + 0.1 * (i >> 2) as f32])
        .collect();
    for _ in 0..8 {
        for p in &pts {
            t.update_key(keys_near(&t, *p), true, true);
        }
    }
    t.update_inner_occupancy();
    t.prune();
    let before = t.num_nodes();
    let [_, _, _, hi, _] = t.log_odds_params();
    assert_eq!(t.search(pts[0]), Some(hi));
    let leaf = t.leaves().find(|l| l.log_odds == hi).unwrap();
    assert_eq!(leaf.depth, 15, "the clamped block is one pruned leaf");
    // Another lazy hit inside the pruned, clamped leaf is skipped: no expansion.
    assert!(!t.update_key(keys_near(&t, pts[3]), true, true), "early abort");
    assert_eq!(t.num_nodes(), before);
    // Same through a scan whose ray reaches the block from +x (only its end voxel is in it).
    let s = t.insert_point_cloud(&[pts[3]], [5.15f32, 0.15, 10.05], -1.0, true).unwrap();
    assert_eq!(s.occupied_cells, 1);
    assert_eq!(s.applied_updates, s.free_cells, "the hit is early-aborted");
    assert_eq!(t.search(pts[3]), Some(hi));
    let before = t.num_nodes();
    // A miss is applied: the pruned leaf is expanded (8 new nodes) in lazy mode.
    t.update_key(keys_near(&t, pts[3]), false, true);
    assert_eq!(t.num_nodes(), before + 8);
    assert_eq!(t.search(pts[3]), Some(hi + logodds(0.4)));
    assert_eq!(t.search(pts[2]), Some(hi));
}

#[test]
fn eager_insertion_prunes_on_the_fly() {
    let mut t = tree();
    let pts: Vec<[f32; 3]> = (0..8)
        .map(|i| [0.05 + 0.1 * (i & 1) as f32, 0.05 + 0.1 * (i >> 1 & 1) as f32, 10.05 + 0.1 * (i >> 2) as f32])
        .collect();
    for (i, p) in pts.iter().enumerate() {
        t.update_key(keys_near(&t, *p), true, false);
        let depth = t.leaves().map(|l| l.depth).min().unwrap();
        assert_eq!(depth, if i == 7 { 15 } else { 16 });
    }
    // The 8 voxels got one hit each; before the last one they differ, after it they are equal.
    let n = t.num_nodes();
    let leaf = t.leaves().find(|l| l.log_odds == logodds(0.7)).unwrap();
    assert_eq!(leaf.depth, 15);
    t.prune();
    assert_eq!(t.num_nodes(), n, "eager trees are already pruned");
}

fn cloud_strategy() -> impl Strategy<Value = Vec<([f32; 3], Vec<[f32; 3]>)>> {
    let scan = (prop::array::uniform3(-0.4f32..0.4), prop::collection::vec(prop::array::uniform3(-0.8f32..0.8), 1..40));
    prop::collection::vec(scan, 1..12)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Every voxel equals the reference model, for eager and lazy insertion.
    #[test]
    fn matches_reference_model(scans in cloud_strategy(), max_range in prop_oneof![Just(-1.0f64), 0.3f64..1.2]) {
        let mut eager = tree();
        let mut lazy = tree();
        let mut model = Model::default();
        for (o, pts) in &scans {
            eager.insert_point_cloud(pts, *o, max_range, false).unwrap();
            lazy.insert_point_cloud(pts, *o, max_range, true).unwrap();
            model.insert(&eager, pts, *o, max_range);
        }
        lazy.update_inner_occupancy();
        for x in -12i32..12 {
            for y in -12i32..12 {
                for z in -12i32..12 {
                    let k = OcTreeKey([(32768 + x) as u16, (32768 + y) as u16, (32768 + z) as u16]);
                    let want = model.voxels.get(&k).copied();
                    prop_assert_eq!(eager.search_key(k), want, "eager key {:?}", k);
                    prop_assert_eq!(lazy.search_key(k), want, "lazy key {:?}", k);
                }
            }
        }
        // Eager == lazy + update_inner_occupancy + prune, leaf for leaf.
        lazy.prune();
        prop_assert_eq!(eager.leaf_hash(), lazy.leaf_hash());
        prop_assert_eq!(eager.num_nodes(), lazy.num_nodes());
        prop_assert_eq!(eager.leaves().collect::<Vec<_>>(), lazy.leaves().collect::<Vec<_>>());
    }

    /// Pruning changes no query answer.
    #[test]
    fn prune_preserves_queries(scans in cloud_strategy(), queries in prop::collection::vec(prop::array::uniform3(-1.5f32..1.5), 400)) {
        let mut t = tree();
        for (o, pts) in &scans {
            t.insert_point_cloud(pts, *o, -1.0, true).unwrap();
        }
        t.update_inner_occupancy();
        let before: Vec<_> = queries.iter().map(|q| t.search(*q)).collect();
        let n = t.num_nodes();
        t.prune();
        prop_assert!(t.num_nodes() <= n);
        let after: Vec<_> = queries.iter().map(|q| t.search(*q)).collect();
        prop_assert_eq!(before, after);
    }

    /// A consumer that re-reads only the regions [`OcTree::take_changes`] names (everything when
    /// it says `all`) holds every occupied leaf, value included, after every scan: eager
    /// insertion with pruning, for regions of 1, 4 and 16 finest voxels' edge and the root's.
    #[test]
    fn following_the_changed_regions_keeps_every_occupied_leaf(
        scans in cloud_strategy(),
        max_range in prop_oneof![Just(-1.0f64), 0.3f64..1.2],
        region_depth in prop_oneof![Just(16u8), Just(14u8), Just(12u8), Just(1u8)],
        repeat in 1usize..4,
    ) {
        let mut t = tree();
        t.track_changes(region_depth).unwrap();
        let mut held = BTreeMap::new();
        for (o, pts) in &scans {
            for _ in 0..repeat {
                t.insert_point_cloud(pts, *o, max_range, false).unwrap();
                follow(&mut t, &mut held);
                prop_assert_eq!(&held, &occupied_leaves(&t));
            }
        }
    }

    /// The map does not depend on the number of ray-casting threads.
    #[test]
    fn thread_count_does_not_matter(seed in 0u64..1000) {
        let mut s = seed.wrapping_mul(0x9E3779B97F4A7C15) | 1;
        let mut rnd = || { s ^= s << 13; s ^= s >> 7; s ^= s << 17; (s >> 40) as f32 / (1u64 << 24) as f32 };
        let pts: Vec<[f32; 3]> = (0..20000).map(|_| [rnd() * 4.0 - 2.0, rnd() * 4.0 - 2.0, rnd() * 2.0]).collect();
        let mut a = tree();
        let mut b = tree();
        a.set_ray_threads(1);
        b.set_ray_threads(3);
        for t in [&mut a, &mut b] {
            t.insert_point_cloud(&pts[..12000], [0.1f32, 0.2, 0.3], 2.5, false).unwrap();
            t.insert_point_cloud(&pts[8000..], [-0.3f32, 0.1, 0.5], 2.5, false).unwrap();
        }
        prop_assert_eq!(a.leaf_hash(), b.leaf_hash());
        prop_assert_eq!(a.num_nodes(), b.num_nodes());
    }
}

#[test]
fn leaf_iteration_counts_and_keys() {
    let mut t = tree();
    t.insert_point_cloud(&[[0.55f32, 0.05, 0.05], [0.05, 0.45, 0.05]], [0.05f32, 0.05, 0.05], -1.0, false).unwrap();
    let leaves: Vec<_> = t.leaves().collect();
    assert_eq!(leaves.len(), t.num_leaves());
    let (occ, free) = t.num_occupied_free_leaves();
    assert_eq!(occ, 2);
    assert_eq!(occ + free, leaves.len());
    for l in &leaves {
        assert_eq!(l.depth, 16);
        assert_eq!(t.search_key(l.key), Some(l.log_odds));
        assert_eq!(l.min_key(), l.key);
    }
    // Every leaf voxel is distinct and the node count is consistent.
    let mut keys: Vec<_> = leaves.iter().map(|l| l.key).collect();
    keys.sort();
    keys.dedup();
    assert_eq!(keys.len(), leaves.len());
    assert!(t.num_nodes() > leaves.len());
    assert!(t.memory_usage_bytes() >= t.num_nodes() * 8);
}

/// Every occupied leaf: (lowest key, depth) -> log-odds bits.
fn occupied_leaves(t: &OcTree) -> BTreeMap<([u16; 3], u8), u32> {
    t.leaves()
        .filter(|l| t.is_occupied_log_odds(l.log_odds))
        .map(|l| ((l.min_key().0, l.depth), l.log_odds.to_bits()))
        .collect()
}

/// What a consumer of the changes does: re-reads the named regions, or everything.
fn follow(t: &mut OcTree, held: &mut BTreeMap<([u16; 3], u8), u32>) {
    let c = t.take_changes().expect("tracking");
    if c.all {
        *held = occupied_leaves(t);
        return;
    }
    let shift = 16 - c.region_depth as u32;
    for r in &c.regions {
        held.retain(|(k, d), _| !(*d >= c.region_depth && k.map(|x| x >> shift) == *r));
        for l in t.leaves_in_region(c.region_depth, *r) {
            assert!(l.depth >= c.region_depth);
            assert_eq!(l.min_key().0.map(|x| x >> shift), *r, "a leaf of the region");
            if t.is_occupied_log_odds(l.log_odds) {
                held.insert((l.min_key().0, l.depth), l.log_odds.to_bits());
            }
        }
    }
}

/// Blocks hit until they are pruned into leaves larger than a region, then carved by rays
/// through them (split again), then cleared: the consumer follows every step, and a region
/// inside a larger leaf lists no leaves.
#[test]
fn change_tracking_through_pruning_splitting_and_clearing() {
    let mut t = tree();
    assert_eq!(t.take_changes(), None, "not tracking");
    assert!(t.track_changes(0).is_err() && t.track_changes(17).is_err());
    t.track_changes(15).unwrap();
    let mut held = BTreeMap::new();
    // A 0.8 m cube of points (8^3 voxels), hit from above until clamped: pruned to one leaf
    // of depth 13.
    let cube: Vec<[f32; 3]> = (0..512)
        .map(|i| [0.05 + 0.1 * (i % 8) as f32, 0.05 + 0.1 * (i / 8 % 8) as f32, 0.05 + 0.1 * (i / 64) as f32])
        .collect();
    let mut saw_all_after_start = false;
    for step in 0..12 {
        t.insert_point_cloud(&cube, [0.35f32, 0.35, 5.0], -1.0, false).unwrap();
        let c = t.clone().take_changes().unwrap();
        if step > 0 && c.all {
            saw_all_after_start = true;
        }
        follow(&mut t, &mut held);
        assert_eq!(held, occupied_leaves(&t), "step {step}");
    }
    assert!(held.keys().any(|(_, d)| *d < 15), "pruned into a leaf larger than a region: {held:?}");
    assert!(saw_all_after_start, "merging an occupied leaf larger than a region says all");
    let big = *held.keys().find(|(_, d)| *d < 15).unwrap();
    assert_eq!(t.leaves_in_region(15, big.0.map(|x| x >> 1)).count(), 0, "inside a larger leaf");
    // Rays through the cube from the side: the big leaf splits, inner voxels turn free.
    let far: Vec<[f32; 3]> = (0..64).map(|i| [3.0, 0.05 + 0.1 * (i % 8) as f32, 0.05 + 0.1 * (i / 8) as f32]).collect();
    for step in 0..6 {
        t.insert_point_cloud(&far, [-2.0f32, 0.35, 0.35], -1.0, false).unwrap();
        follow(&mut t, &mut held);
        assert_eq!(held, occupied_leaves(&t), "carving {step}");
    }
    t.clear();
    follow(&mut t, &mut held);
    assert!(held.is_empty());
}
