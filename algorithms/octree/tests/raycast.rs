//! Ray traversal against an independent reference: exact segment/box intersection (slab test in
//! f64) over all voxels of the ray's bounding box.

use std::collections::BTreeSet;

use octree::{OcTreeKey, compute_ray_keys};
use proptest::prelude::*;

const RES: f64 = 0.1;
/// Rays passing closer than this (m) to a voxel's boundary are ambiguous: OctoMap's float DDA
/// may or may not enter the voxel.
const EPS: f64 = 1e-5;

fn key_of(c: f64) -> i64 {
    (c * (1.0 / RES)).floor() as i64 + 32768
}

/// Length of the part of segment o->e (parameter in [0, 1]) inside the voxel box shrunk
/// (`margin` > 0) or grown (`margin` < 0) by `margin`; negative if it misses.
fn inside_len(o: [f64; 3], e: [f64; 3], key: [i64; 3], margin: f64) -> f64 {
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for a in 0..3 {
        let lo = (key[a] - 32768) as f64 * RES + margin;
        let hi = (key[a] - 32767) as f64 * RES - margin;
        let d = e[a] - o[a];
        if d.abs() < 1e-300 {
            if o[a] < lo || o[a] > hi {
                return -1.0;
            }
        } else {
            let (mut a0, mut a1) = ((lo - o[a]) / d, (hi - o[a]) / d);
            if a0 > a1 {
                std::mem::swap(&mut a0, &mut a1);
            }
            t0 = t0.max(a0);
            t1 = t1.min(a1);
        }
    }
    t1 - t0
}

/// Checks the DDA's voxel set against the reference; returns an error message on mismatch.
fn check_ray(o: [f32; 3], e: [f32; 3]) -> Result<(), String> {
    let mut got = Vec::new();
    assert!(compute_ray_keys(o, e, RES, |k| got.push(k)));
    check_keys(o, e, &got)
}

fn check_keys(o: [f32; 3], e: [f32; 3], got: &[OcTreeKey]) -> Result<(), String> {
    let got_set: BTreeSet<OcTreeKey> = got.iter().copied().collect();
    if got_set.len() != got.len() {
        return Err(format!("duplicate voxels in {got:?}"));
    }
    let od = o.map(f64::from);
    let ed = e.map(f64::from);
    let ko = od.map(key_of);
    let ke = ed.map(key_of);
    let to_key = |k: [i64; 3]| OcTreeKey(k.map(|v| v as u16));
    let end_key = to_key(ke);
    if got_set.contains(&end_key) {
        return Err("end voxel visited".into());
    }
    if ko == ke {
        return if got.is_empty() { Ok(()) } else { Err("same voxel but keys visited".into()) };
    }
    if got.first() != Some(&to_key(ko)) {
        return Err(format!("first voxel {:?} is not the origin voxel {:?}", got.first(), to_key(ko)));
    }
    let len = ((ed[0] - od[0]).powi(2) + (ed[1] - od[1]).powi(2) + (ed[2] - od[2]).powi(2)).sqrt();
    let margin = EPS;
    let tol = EPS / len.max(1e-9);
    for x in ko[0].min(ke[0]) - 1..=ko[0].max(ke[0]) + 1 {
        for y in ko[1].min(ke[1]) - 1..=ko[1].max(ke[1]) + 1 {
            for z in ko[2].min(ke[2]) - 1..=ko[2].max(ke[2]) + 1 {
                let k = [x, y, z];
                if k == ke {
                    continue;
                }
                let surely_in = inside_len(od, ed, k, margin) > tol;
                let surely_out = inside_len(od, ed, k, -margin) < -tol;
                let visited = got_set.contains(&to_key(k));
                if surely_in && !visited {
                    return Err(format!("voxel {k:?} crossed by the segment but not visited"));
                }
                if surely_out && visited {
                    return Err(format!("voxel {k:?} visited but not crossed"));
                }
            }
        }
    }
    // Consecutive voxels are face neighbours (a 6-connected walk).
    for w in got.windows(2) {
        let d: i32 = (0..3).map(|a| (w[0].0[a] as i32 - w[1].0[a] as i32).abs()).sum();
        if d != 1 {
            return Err(format!("non-adjacent step {:?} -> {:?}", w[0], w[1]));
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(3000))]

    #[test]
    fn dda_matches_exact_traversal(
        o in prop::array::uniform3(-2.0f32..2.0),
        e in prop::array::uniform3(-2.0f32..2.0),
    ) {
        prop_assert!(check_ray(o, e).is_ok(), "{:?}", check_ray(o, e));
    }

    #[test]
    fn dda_axis_aligned_and_short_rays(
        o in prop::array::uniform3(-1.0f32..1.0),
        d in prop::array::uniform3(-0.35f32..0.35),
        mask in 0usize..8,
    ) {
        let e = [0, 1, 2].map(|a| if mask & (1 << a) != 0 { o[a] } else { o[a] + d[a] });
        prop_assert!(check_ray(o, e).is_ok(), "{:?}", check_ray(o, e));
    }
}

#[test]
fn readme_rules_origin_included_end_excluded() {
    // Along +x from the centre of voxel 32768 to the centre of voxel 32773.
    let mut got = Vec::new();
    assert!(compute_ray_keys([0.05, 0.05, 0.05], [0.55, 0.05, 0.05], RES, |k| got.push(k.0[0])));
    assert_eq!(got, vec![32768, 32769, 32770, 32771, 32772]);
    // Same voxel: nothing.
    got.clear();
    assert!(compute_ray_keys([0.01, 0.01, 0.01], [0.09, 0.02, 0.03], RES, |k| got.push(k.0[0])));
    assert!(got.is_empty());
    // Backwards along -x.
    got.clear();
    assert!(compute_ray_keys([0.05, 0.05, 0.05], [-0.25, 0.05, 0.05], RES, |k| got.push(k.0[0])));
    assert_eq!(got, vec![32768, 32767, 32766]);
    // Outside the tree: false, nothing visited.
    assert!(!compute_ray_keys([0.0; 3], [1e6, 0.0, 0.0], RES, |_| panic!("visited")));
}

#[test]
fn the_reference_rejects_wrong_walks() {
    let o = [0.05f32, 0.12, 0.03];
    let e = [0.73f32, -0.31, 0.44];
    let mut good = Vec::new();
    compute_ray_keys(o, e, RES, |k| good.push(k));
    assert!(good.len() > 5);
    assert!(check_keys(o, e, &good).is_ok());
    // Missing a crossed voxel.
    let mut bad = good.clone();
    bad.remove(3);
    assert!(check_keys(o, e, &bad).is_err());
    // Missing the origin voxel.
    assert!(check_keys(o, e, &good[1..]).is_err());
    // Including the end voxel.
    let mut bad = good.clone();
    bad.push(OcTreeKey([0.73f64, -0.31, 0.44].map(|c| key_of(c as f32 as f64) as u16)));
    assert!(check_keys(o, e, &bad).is_err());
    // A voxel the segment does not cross.
    let mut bad = good.clone();
    let far = OcTreeKey([good[2].0[0], good[2].0[1], good[2].0[2].wrapping_add(3)]);
    bad.insert(3, far);
    assert!(check_keys(o, e, &bad).is_err());
}
