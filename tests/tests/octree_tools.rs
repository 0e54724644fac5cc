//! OctoMap's own tools (Debian package octomap-tools, OctoMap 1.9.7) read the `.bt` files the
//! `octree` crate writes, and our reader reads OctoMap's: a small map built from synthetic scans is
//! written with `write_binary_file`, then
//!
//! * `convert_octree ours.bt ours.ot` parses it and writes OctoMap's full `.ot` tree: its node
//!   count and every leaf (order, depth, log-odds) equal what our own reader makes of the file;
//! * `convert_octree ours.bt back.bt` (OctoMap's `readBinary` + `writeBinary`) reproduces our file
//!   byte for byte;
//! * `compare_octrees` expands the tree to the same number of finest-level voxels as ours.
//!
//! And OctoMap's map of the benchmark scene (shared/bench/octomap/results/maps/octomap_res0.10.bt)
//! is read by our reader with the counts of OctoMap's summary and of `convert_octree`.
//! Needs octomap-tools (scripts/test.sh installs it); without it these tests fail.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use octree::OcTree;

const TOOLS_PACKAGE: &str = "octomap-tools";

/// The path of an octomap-tools program; panics naming the package when it is not installed.
fn tool(name: &str) -> PathBuf {
    let found = std::env::var_os("PATH")
        .iter()
        .flat_map(std::env::split_paths)
        .chain([PathBuf::from("/usr/bin")])
        .map(|dir| dir.join(name))
        .find(|p| p.is_file());
    found.unwrap_or_else(|| {
        panic!(
            "`{name}` not found: the Debian package {TOOLS_PACKAGE} (OctoMap's tools) is not installed; run \
             `apt-get install -y --no-install-recommends {TOOLS_PACKAGE}` or use ./scripts/test.sh, which installs it"
        )
    })
}

fn run_tool(name: &str, args: &[&Path]) -> Output {
    let out = Command::new(tool(name)).args(args).output().unwrap_or_else(|e| panic!("cannot run {name}: {e}"));
    assert!(
        out.status.success(),
        "{name} {args:?} failed ({}):\nstdout:\n{}\nstderr:\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// A leaf of OctoMap's `.ot` stream: depth and log-odds bits.
type OtLeaf = (u8, u32);

/// Parses an OctoMap `.ot` file (`AbstractOcTree::write` of an `OcTree`): header lines up to
/// `data`, then per node (depth first, child 0 first) its `f32` log-odds and a child bit mask.
/// Returns (resolution, size from the header, nodes in the stream, leaves).
fn parse_ot(bytes: &[u8]) -> (f64, usize, usize, Vec<OtLeaf>) {
    let mut pos = 0;
    let (mut id, mut size, mut res) = (None, None, None);
    loop {
        let end = bytes[pos..].iter().position(|&b| b == b'\n').expect(".ot header ends before `data`") + pos;
        let line = std::str::from_utf8(&bytes[pos..end]).expect(".ot header is text").trim();
        pos = end + 1;
        if line == "data" {
            break;
        }
        match line.split_once(' ') {
            Some(("id", v)) => id = Some(v.to_string()),
            Some(("size", v)) => size = Some(v.parse::<usize>().expect("size")),
            Some(("res", v)) => res = Some(v.parse::<f64>().expect("res")),
            _ => {}
        }
    }
    assert_eq!(id.as_deref(), Some("OcTree"), ".ot id");
    let (size, res) = (size.expect(".ot size"), res.expect(".ot res"));
    let mut leaves = Vec::new();
    let mut nodes = 0;
    if size > 0 {
        let mut stack = vec![0u8];
        while let Some(depth) = stack.pop() {
            let rec = bytes.get(pos..pos + 5).expect(".ot node stream truncated");
            let value = u32::from_le_bytes([rec[0], rec[1], rec[2], rec[3]]);
            let children = rec[4];
            pos += 5;
            nodes += 1;
            if children == 0 {
                leaves.push((depth, value));
            }
            for i in (0..8).rev() {
                if children & (1 << i) != 0 {
                    stack.push(depth + 1);
                }
            }
        }
    }
    assert_eq!(pos, bytes.len(), ".ot has trailing bytes");
    (res, size, nodes, leaves)
}

/// Finest-level voxels of the leaves (occupied, free).
fn expanded_voxels(t: &OcTree) -> (u64, u64) {
    let (mut occ, mut free) = (0, 0);
    for l in t.leaves() {
        let n = (l.edge_voxels() as u64).pow(3);
        if t.is_occupied_log_odds(l.log_odds) {
            occ += n;
        } else {
            free += n;
        }
    }
    (occ, free)
}

/// `compare_octrees A.ot A.ot`'s "Expanded num. leafs: N".
fn expanded_by_compare_octrees(ot: &Path) -> u64 {
    let out = run_tool("compare_octrees", &[ot, ot]);
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    text.lines()
        .find_map(|l| l.trim().strip_prefix("Expanded num. leafs:"))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("compare_octrees printed no leaf count:\n{text}"))
}

/// A few synthetic depth scans of a 4 x 3 x 2.5 m box room with a pillar, from 3 poses.
fn synthetic_map() -> OcTree {
    let mut tree = OcTree::new(0.1).expect("tree");
    let origins = [[1.03f32, 1.02, 1.21], [2.55, 1.48, 1.04], [3.11, 2.07, 1.52]];
    let (room_lo, room_hi) = ([0.0f64, 0.0, 0.0], [4.0f64, 3.0, 2.5]);
    let (pillar_c, pillar_r) = ([2.0f64, 2.2], 0.2);
    for (s, o) in origins.iter().enumerate() {
        let of = o.map(f64::from);
        let mut points = Vec::new();
        for i in 0..120 {
            for j in 0..60 {
                // Directions on a sphere (azimuth, elevation), rotated a little per scan.
                let az = (i as f64 + 0.37 * s as f64) / 120.0 * std::f64::consts::TAU;
                let el = (j as f64 + 0.5) / 60.0 * std::f64::consts::PI - std::f64::consts::FRAC_PI_2;
                let d = [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()];
                // Distance to the room walls.
                let mut t = f64::INFINITY;
                for a in 0..3 {
                    if d[a] > 1e-9 {
                        t = t.min((room_hi[a] - of[a]) / d[a]);
                    } else if d[a] < -1e-9 {
                        t = t.min((room_lo[a] - of[a]) / d[a]);
                    }
                }
                // Distance to the vertical pillar (infinite cylinder).
                let (px, py) = (of[0] - pillar_c[0], of[1] - pillar_c[1]);
                let qa = d[0] * d[0] + d[1] * d[1];
                let qb = 2.0 * (px * d[0] + py * d[1]);
                let qc = px * px + py * py - pillar_r * pillar_r;
                let disc = qb * qb - 4.0 * qa * qc;
                if qa > 1e-12 && disc >= 0.0 {
                    let tc = (-qb - disc.sqrt()) / (2.0 * qa);
                    if tc > 0.0 {
                        t = t.min(tc);
                    }
                }
                points.push([(of[0] + t * d[0]) as f32, (of[1] + t * d[1]) as f32, (of[2] + t * d[2]) as f32]);
            }
        }
        tree.insert_point_cloud(&points, *o, 5.0, false).expect("insert");
    }
    tree
}

#[test]
fn octomap_tools_read_our_bt_files() {
    let dir = tempfile::tempdir().expect("temp dir");
    let ours_bt = dir.path().join("ours.bt");
    let ours_ot = dir.path().join("ours.ot");
    let back_bt = dir.path().join("back.bt");
    let tree = synthetic_map();
    let (occ_leaves, free_leaves) = tree.num_occupied_free_leaves();
    assert!(occ_leaves > 100 && free_leaves > 100, "map too small: {occ_leaves} occupied, {free_leaves} free leaves");
    tree.write_binary_file(&ours_bt).expect("write .bt");
    // What the file holds (max-likelihood, pruned), as our reader sees it.
    let ml = OcTree::read_binary_file(&ours_bt).expect("our reader reads our .bt");

    let out = run_tool("convert_octree", &[&ours_bt, &ours_ot]);
    let log = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    let (res, size, nodes, leaves) = parse_ot(&std::fs::read(&ours_ot).expect("convert_octree wrote the .ot"));
    assert_eq!(res, 0.1, "resolution in OctoMap's .ot");
    assert_eq!(size, ml.num_nodes(), "node count OctoMap read from our .bt (its log: {log})");
    assert_eq!(nodes, size, ".ot node stream vs its header");
    let ours: Vec<OtLeaf> = ml.leaves().map(|l| (l.depth, l.log_odds.to_bits())).collect();
    assert_eq!(leaves.len(), ours.len(), "leaf count: OctoMap's .ot vs our reader");
    assert_eq!(leaves, ours, "leaves (order, depth, log-odds) of OctoMap's .ot vs our reader");

    run_tool("convert_octree", &[&ours_bt, &back_bt]);
    let a = std::fs::read(&ours_bt).expect("ours.bt");
    let b = std::fs::read(&back_bt).expect("back.bt");
    assert!(a == b, "OctoMap's readBinary + writeBinary changed our .bt ({} -> {} bytes)", a.len(), b.len());

    let (occ_vox, free_vox) = expanded_voxels(&tree);
    assert_eq!(expanded_voxels(&ml), (occ_vox, free_vox), "max-likelihood conversion changed the voxel classes");
    assert_eq!(expanded_by_compare_octrees(&ours_ot), occ_vox + free_vox, "finest-level voxels per compare_octrees");
}

#[test]
fn our_reader_reads_octomaps_benchmark_map() {
    let bt = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/bench/octomap/results/maps/octomap_res0.10.bt");
    assert!(bt.is_file(), "{} is missing (the project's shared/ folder belongs beside the repository)", bt.display());
    let theirs = OcTree::read_binary_file(&bt).expect("our reader reads OctoMap's .bt");
    // results/summary.md (0.10 m): 102143 nodes / 86914 leaves (15580 occupied, 71334 free) in the
    // log-odds tree, 15580 / 125703 occupied / free finest-level voxels. The .bt holds the
    // max-likelihood tree after writeBinary's prune(): same voxels and classes, fewer nodes.
    assert_eq!(theirs.resolution(), 0.1);
    assert_eq!(theirs.num_nodes(), 49359, "nodes (the .bt header says size 49359)");
    assert_eq!(expanded_voxels(&theirs), (15580, 125703), "occupied / free finest-level voxels");
    let leaves = theirs.num_leaves();
    let (occ_leaves, free_leaves) = theirs.num_occupied_free_leaves();
    assert_eq!(occ_leaves, 15580, "occupied leaves (occupied voxels are never pruned together here)");
    assert!(leaves < 86914, "the max-likelihood .bt has fewer leaves than the log-odds tree: {leaves}");
    assert_eq!((leaves, free_leaves), (40728, 25148), "leaves / free leaves of the .bt");

    // OctoMap's own reading of the same file agrees.
    let dir = tempfile::tempdir().expect("temp dir");
    let ot = dir.path().join("theirs.ot");
    run_tool("convert_octree", &[&bt, &ot]);
    let (_, size, nodes, ot_leaves) = parse_ot(&std::fs::read(&ot).expect("convert_octree wrote the .ot"));
    assert_eq!((size, nodes), (theirs.num_nodes(), theirs.num_nodes()), "node count per OctoMap");
    let ours: Vec<OtLeaf> = theirs.leaves().map(|l| (l.depth, l.log_odds.to_bits())).collect();
    assert_eq!(ot_leaves, ours, "leaves (order, depth, log-odds) per OctoMap vs our reader");
    assert_eq!(expanded_by_compare_octrees(&ot), 15580 + 125703, "finest-level voxels per compare_octrees");

    // And our writer reproduces the file.
    let mut bytes = Vec::new();
    theirs.write_binary(&mut bytes).expect("write");
    assert!(bytes == std::fs::read(&bt).expect("read .bt"), "re-writing OctoMap's .bt changed it");
}
