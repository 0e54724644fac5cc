//! Voxel agreement with OctoMap on the benchmark data set, and insertion speed.
//!
//! ```sh
//! cargo run --release -p octree --example agreement -- \
//!     [--scans /tmp/ob/data/scans.bin] [--maps /work/shared/bench/octomap/results/maps] \
//!     [--threads N] [--res 0.05,0.10] [--lazy] [--write DIR]
//! ```
//!
//! For each resolution: inserts the 20 scans (max range 6.0), prints time, points/s, node counts,
//! memory and the leaf hash (OctoMap's `leaf_hash` of the same data: 0.10 m 26a7811c8069136f,
//! 0.05 m 23da93c3d38d4aaf), then reads OctoMap's max-likelihood map `octomap_res<R>.bt` and
//! compares finest-level voxels (occupied / free / unknown confusion table) and the `.bt` bytes.

use std::collections::HashMap;
use std::time::Instant;

use octree::{OcTree, OcTreeKey, bench_data};

#[derive(Clone, Copy, PartialEq, Eq)]
enum Class {
    Occ = 0,
    Free = 1,
    Unknown = 2,
}

/// Finest-level voxels of a tree, classified (pruned leaves expanded).
fn voxels(t: &OcTree) -> HashMap<u64, Class> {
    let mut m = HashMap::new();
    for l in t.leaves() {
        let c = if t.is_occupied_log_odds(l.log_odds) { Class::Occ } else { Class::Free };
        let k0 = l.min_key();
        let n = l.edge_voxels();
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    let key = OcTreeKey([k0.0[0] + i as u16, k0.0[1] + j as u16, k0.0[2] + k as u16]);
                    m.insert(key.pack(), c);
                }
            }
        }
    }
    m
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut scans = "/tmp/ob/data/scans.bin".to_string();
    let mut maps = "/work/shared/bench/octomap/results/maps".to_string();
    let mut threads = None;
    let mut resolutions = vec![0.10, 0.05];
    let mut lazy = false;
    let mut write_dir = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--scans" => scans = args.next().ok_or("--scans needs a path")?,
            "--maps" => maps = args.next().ok_or("--maps needs a dir")?,
            "--threads" => threads = Some(args.next().ok_or("--threads needs N")?.parse()?),
            "--res" => {
                resolutions =
                    args.next().ok_or("--res needs values")?.split(',').map(|s| s.parse()).collect::<Result<_, _>>()?
            }
            "--lazy" => lazy = true,
            "--write" => write_dir = Some(args.next().ok_or("--write needs a dir")?),
            _ => return Err(format!("unknown argument {a}").into()),
        }
    }
    let data = bench_data::read_scans(&scans)?;
    let max_range = 6.0;
    println!("{}: {} frames, {} points, max range {max_range}", scans, data.frames.len(), data.num_points());

    for &res in &resolutions {
        let mut tree = OcTree::new(res)?;
        if let Some(t) = threads {
            tree.set_ray_threads(t);
        }
        let t0 = Instant::now();
        let mut free_updates = 0;
        let mut occ_updates = 0;
        for f in &data.frames {
            let s = tree.insert_point_cloud(&f.points, f.origin, max_range, lazy)?;
            free_updates += s.free_cells;
            occ_updates += s.occupied_cells;
        }
        let t_insert = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        tree.update_inner_occupancy();
        tree.prune();
        let t_post = t1.elapsed().as_secs_f64();
        let (occ_leaves, free_leaves) = tree.num_occupied_free_leaves();
        println!("\n== res {res} m ({} ray thread(s), {})", tree.ray_threads(), if lazy { "lazy" } else { "eager" });
        println!(
            "insert {:.3} s ({:.0} k points/s); update_inner+prune {:.1} ms; free/occupied cell updates {free_updates} / {occ_updates}",
            t_insert,
            data.num_points() as f64 / t_insert / 1e3,
            t_post * 1e3
        );
        println!(
            "nodes {} leaves {} (occupied {occ_leaves}, free {free_leaves}); memory {} B (+ scratch {} B)",
            tree.num_nodes(),
            tree.num_leaves(),
            tree.memory_usage_bytes(),
            tree.scratch_bytes()
        );
        println!("leaf hash {:016x}", tree.leaf_hash());

        // Point queries (same generator as bench_octomap.cpp).
        let mut s = 20240601u64;
        let mut u01 = || {
            s = s.wrapping_add(0x9E3779B97F4A7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D049BB133111EB);
            ((z ^ (z >> 31)) >> 11) as f64 * (1.0 / 9007199254740992.0)
        };
        let (lo, hi) = ([-0.479, -0.487, -0.483], [10.521, 6.513, 3.517]);
        let queries: Vec<[f32; 3]> = (0..1_000_000)
            .map(|_| {
                let mut p = [0f32; 3];
                for a in 0..3 {
                    p[a] = (lo[a] + (hi[a] - lo[a]) * u01()) as f32;
                }
                p
            })
            .collect();
        let mut best = f64::MAX;
        let (mut found, mut occ) = (0, 0);
        for _ in 0..6 {
            let t = Instant::now();
            found = 0;
            occ = 0;
            for q in &queries {
                if let Some(l) = tree.search(*q) {
                    found += 1;
                    occ += tree.is_occupied_log_odds(l) as usize;
                }
            }
            best = best.min(t.elapsed().as_secs_f64());
        }
        println!(
            "1M search(point): best of 6 passes {:.1} ns/query; found {found} occupied {occ}",
            best * 1e9 / queries.len() as f64
        );

        let path = format!("{maps}/octomap_res{res:.2}.bt");
        let theirs = match OcTree::read_binary_file(&path) {
            Ok(t) => t,
            Err(e) => {
                println!("cannot read {path}: {e}");
                continue;
            }
        };
        let mut ours_bt = Vec::new();
        tree.write_binary(&mut ours_bt)?;
        let their_bytes = std::fs::read(&path)?;
        println!(
            ".bt: ours {} bytes, OctoMap's {} bytes, identical: {}",
            ours_bt.len(),
            their_bytes.len(),
            ours_bt == their_bytes
        );
        if let Some(dir) = &write_dir {
            std::fs::write(format!("{dir}/ours_res{res:.2}.bt"), &ours_bt)?;
        }
        let a = voxels(&tree);
        let b = voxels(&theirs);
        let mut table = [[0u64; 3]; 3];
        for (k, &ca) in &a {
            let cb = b.get(k).copied().unwrap_or(Class::Unknown);
            table[ca as usize][cb as usize] += 1;
        }
        for (k, &cb) in &b {
            if !a.contains_key(k) {
                table[Class::Unknown as usize][cb as usize] += 1;
            }
        }
        println!("finest voxels, rows = ours, columns = OctoMap's .bt");
        println!("{:>10} {:>10} {:>10} {:>10}", "", "occupied", "free", "unknown");
        for (i, name) in ["occupied", "free", "unknown"].iter().enumerate() {
            let r = table[i];
            println!("{name:>10} {:>10} {:>10} {:>10}", r[0], r[1], if i == 2 { "-".into() } else { r[2].to_string() });
        }
        let occ_theirs: u64 = (0..3).map(|i| table[i][0]).sum();
        let free_theirs: u64 = (0..3).map(|i| table[i][1]).sum();
        println!(
            "agreement: occupied {:.4} % ({} / {occ_theirs}), free {:.4} % ({} / {free_theirs})",
            100.0 * table[0][0] as f64 / occ_theirs.max(1) as f64,
            table[0][0],
            100.0 * table[1][1] as f64 / free_theirs.max(1) as f64,
            table[1][1]
        );
    }
    Ok(())
}
