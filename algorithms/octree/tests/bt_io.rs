//! `.bt` I/O: OctoMap's geb079.bt round trip byte for byte, and write/read of our own trees.

use octree::{OcTree, OctreeError};
use proptest::prelude::*;

const GEB079: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/geb079.bt");

#[test]
fn geb079_round_trip_is_byte_identical() {
    let bytes = std::fs::read(GEB079).unwrap();
    let t = OcTree::read_binary(&bytes[..]).unwrap();
    assert_eq!(t.resolution(), 0.08);
    // Numbers from the file's ATTRIBUTION.md.
    assert_eq!(t.num_nodes(), 532_566);
    let (occ, free) = t.num_occupied_free_leaves();
    assert_eq!((occ, free), (143_729, 284_415));
    assert_eq!(t.num_nodes() - t.num_leaves(), 104_422);
    let mut out = Vec::new();
    t.write_binary(&mut out).unwrap();
    assert_eq!(out.len(), bytes.len());
    assert!(out == bytes, "written .bt differs from the original");
}

#[test]
fn malformed_bt_is_an_error() {
    let bytes = std::fs::read(GEB079).unwrap();
    let bad_first = [b"# Octomap OcTree file\n".as_slice(), &bytes[29..]].concat();
    assert!(matches!(OcTree::read_binary(&bad_first[..]), Err(OctreeError::BadHeader(_))));
    let cut = &bytes[..bytes.len() - 10];
    assert!(matches!(OcTree::read_binary(cut), Err(OctreeError::BadData(_))));
    let no_data = b"# Octomap OcTree binary file\nid OcTree\nsize 1\nres 0.1\n";
    assert!(matches!(OcTree::read_binary(&no_data[..]), Err(OctreeError::BadHeader(_))));
    let wrong_type = b"# Octomap OcTree binary file\nid ColorOcTree\nsize 1\nres 0.1\ndata\n\0\0";
    assert!(matches!(OcTree::read_binary(&wrong_type[..]), Err(OctreeError::BadHeader(_))));
    let bad_res = b"# Octomap OcTree binary file\nid OcTree\nsize 1\nres -1\ndata\n\0\0";
    assert!(matches!(OcTree::read_binary(&bad_res[..]), Err(OctreeError::BadHeader(_))));
    let size_mismatch = b"# Octomap OcTree binary file\nid OcTree\nsize 5\nres 0.1\ndata\n\x02\0";
    assert!(matches!(OcTree::read_binary(&size_mismatch[..]), Err(OctreeError::BadData(_))));
    // A chain of inner nodes deeper than 16 levels.
    let mut deep = b"# Octomap OcTree binary file\nid OcTree\nsize 18\nres 0.1\ndata\n".to_vec();
    for _ in 0..17 {
        deep.extend([0x03, 0x00]);
    }
    deep.extend([0x00, 0x00]);
    assert!(matches!(OcTree::read_binary(&deep[..]), Err(OctreeError::BadData(_))));
    // An empty tree round-trips.
    let empty = OcTree::new(0.1).unwrap();
    let mut out = Vec::new();
    empty.write_binary(&mut out).unwrap();
    assert!(out.ends_with(b"size 0\nres 0.1\ndata\n"));
    assert_eq!(OcTree::read_binary(&out[..]).unwrap().num_nodes(), 0);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// write -> read gives the max-likelihood tree: every query answers the ML class, and
    /// writing the read tree again gives the same bytes; `self` is not modified by writing.
    #[test]
    fn write_read_gives_the_max_likelihood_tree(
        scans in prop::collection::vec(
            (prop::array::uniform3(-0.3f32..0.3), prop::collection::vec(prop::array::uniform3(-0.9f32..0.9), 1..60)),
            1..8,
        ),
        lazy in any::<bool>(),
        queries in prop::collection::vec(prop::array::uniform3(-1.2f32..1.2), 300),
    ) {
        let mut t = OcTree::new(0.1).unwrap();
        for (o, pts) in &scans {
            t.insert_point_cloud(pts, *o, -1.0, lazy).unwrap();
        }
        if lazy {
            t.update_inner_occupancy();
        }
        let hash = t.leaf_hash();
        let mut a = Vec::new();
        t.write_binary(&mut a).unwrap();
        prop_assert_eq!(t.leaf_hash(), hash);
        let r = OcTree::read_binary(&a[..]).unwrap();
        let [_, _, lo, hi, _] = t.log_odds_params();
        for q in &queries {
            let want = t.search(*q).map(|l| if t.is_occupied_log_odds(l) { hi } else { lo });
            prop_assert_eq!(r.search(*q), want);
        }
        // Same as OctoMap's in-place route: toMaxLikelihood + prune on a copy.
        let mut ml = t.clone();
        ml.to_max_likelihood();
        ml.prune();
        prop_assert_eq!(r.num_nodes(), ml.num_nodes());
        let mut b = Vec::new();
        r.write_binary(&mut b).unwrap();
        prop_assert_eq!(&a, &b);
        let mut c = Vec::new();
        ml.write_binary(&mut c).unwrap();
        prop_assert_eq!(&a, &c);
    }
}
