//! Unit tests of the parent module.

use super::*;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

fn truth_at(t: f64) -> Vector3<f64> {
    // A lawnmower-like curve in the world, m.
    Vector3::new(2.0 * t, 10.0 * (t / 8.0).sin(), -5.0 - 0.05 * t)
}

fn world_from_local() -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(30.0, -12.0, -4.0), UnitQuaternion::from_euler_angles(0.0, 0.0, 0.7))
}

fn pair(t: f64, segment: u32, buoy: Vector3<f64>, buoy_sigma: f64) -> PairInput {
    let local = world_from_local().inverse().transform_point(&truth_at(t).into()).coords;
    let mut c = Matrix6::identity() * 1e-4;
    c[(0, 0)] = 0.01;
    c[(1, 1)] = 0.01;
    c[(2, 2)] = 0.01;
    PairInput {
        t_s: t,
        segment,
        local_from_body: Isometry3::from_parts(Translation3::from(local), UnitQuaternion::identity()),
        local_covariance: c,
        buoy_m: buoy,
        buoy_cov_m2: Matrix3::identity() * buoy_sigma * buoy_sigma,
    }
}

#[test]
fn local_alignment_removes_the_drift_of_a_long_local_map() {
    // The local path drifts (a bending error growing to ~1.2 m over 60 s); fixes every second
    // with 0.3 m noise. One transform for the whole segment leaves the bend; transforms
    // fitted over ±10 s around each pose follow it.
    let drift = |t: f64| Vector3::new(0.0003 * t * t, -0.0002 * t * t, 0.0);
    let run = |window: f64| {
        let mut f = Fusion::new(FusionConfig { local_window_s: window, ..Default::default() }).unwrap();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(9);
        let n = Normal::new(0.0, 0.3).unwrap();
        for k in 0..600 {
            let t = k as f64 * 0.1;
            if k % 10 == 0 {
                let noise = Vector3::new(n.sample(&mut rng), n.sample(&mut rng), n.sample(&mut rng));
                f.push_fix(FixInput {
                    t_s: t,
                    position_m: truth_at(t) + noise,
                    covariance_m2: Matrix3::identity() * 0.09,
                })
                .unwrap();
            }
            let mut p = pair(t, 0, truth_at(t), 0.3);
            let local = world_from_local().inverse().transform_point(&(truth_at(t) + drift(t)).into()).coords;
            p.local_from_body = Isometry3::from_parts(Translation3::from(local), UnitQuaternion::identity());
            f.push_pair(p).unwrap();
        }
        let fin = f.finish();
        let se: f64 = fin.slam_world.iter().map(|(t, p)| (p.translation.vector - truth_at(*t)).norm_squared()).sum();
        (se / fin.slam_world.len() as f64).sqrt()
    };
    let (global, local) = (run(0.0), run(10.0));
    assert!(local < 0.6 * global, "local alignment {local:.3} m against one transform {global:.3} m");
}

#[test]
fn a_segment_is_aligned_from_its_fixes_and_the_fused_path_beats_the_buoy_path() {
    let mut f = Fusion::new(FusionConfig::default()).unwrap();
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
    let n = Normal::new(0.0, 0.5).unwrap();
    let noise = |rng: &mut rand_xoshiro::Xoshiro256PlusPlus| Vector3::new(n.sample(rng), n.sample(rng), n.sample(rng));
    let mut outs = vec![];
    for k in 0..600 {
        let t = k as f64 * 0.1;
        if k % 10 == 0 {
            f.push_fix(FixInput {
                t_s: t,
                position_m: truth_at(t) + noise(&mut rng),
                covariance_m2: Matrix3::identity() * 0.25,
            })
            .unwrap();
        }
        let buoy = truth_at(t) + noise(&mut rng) * 0.6;
        outs.push((t, f.push_pair(pair(t, 0, buoy, 0.3)).unwrap(), buoy));
    }
    let seg = f.segment(0).unwrap();
    assert_eq!(seg.status, SegmentStatus::Aligned);
    let a = seg.alignment.as_ref().unwrap();
    assert!((a.global_from_local.translation.vector - world_from_local().translation.vector).norm() < 0.5);
    assert!(a.global_from_local.rotation.angle_to(&world_from_local().rotation) < 0.02);
    let fin = f.finish();
    let rms = |e: &mut dyn Iterator<Item = f64>| {
        let v: Vec<f64> = e.collect();
        (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
    };
    let buoy_err = rms(&mut outs.iter().map(|(t, _, b)| (b - truth_at(*t)).norm()));
    let fused_err = rms(&mut fin.path.iter().map(|o| (o.world_from_body.translation.vector - truth_at(o.t_s)).norm()));
    assert!(fused_err < 0.5 * buoy_err, "fused {fused_err} vs buoy {buoy_err}");
    // A 99 % gate with consistent covariances leaves about 1 % of the poses camera-only.
    let fused = fin.path.iter().filter(|o| o.source == Source::Fused).count();
    assert!(fused >= 580, "{fused} of 600 fused");
    assert_eq!(fin.slam_world.len(), 600);
}

#[test]
fn a_prediction_changes_nothing_and_matches_the_pose_of_an_unchanged_alignment() {
    let run = |predict: bool| {
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        let mut outs = vec![];
        for k in 0..300 {
            let t = k as f64 * 0.1;
            if k % 10 == 0 {
                let position_m = truth_at(t) + Vector3::new(0.1, -0.1, 0.05) * (k as f64 * 0.7).sin();
                f.push_fix(FixInput { t_s: t, position_m, covariance_m2: Matrix3::identity() * 0.25 }).unwrap();
            }
            let p = pair(t, 0, truth_at(t), 0.3);
            let first = predict.then(|| f.predict_pair(&p).unwrap());
            let out = f.push_pair(p).unwrap();
            if let Some(first) = first
                && !out.realigned
            {
                // Same state, same pair: the same pose as the refined one.
                assert_eq!(first.world_from_body, out.world_from_body, "at {t}");
            }
            outs.push(out.world_from_body);
        }
        (outs, f.finish().path.len())
    };
    assert_eq!(run(true), run(false), "predictions leave the state as it was");
}

#[test]
fn before_enough_fixes_the_buoy_alone_is_used() {
    let mut f = Fusion::new(FusionConfig::default()).unwrap();
    let out = f.push_pair(pair(0.0, 0, truth_at(0.0), 0.3)).unwrap();
    assert_eq!(out.source, Source::BuoyOnly);
    assert_eq!(out.world_from_body.translation.vector, truth_at(0.0));
    assert_eq!(f.segment(0).unwrap().status, SegmentStatus::WaitingForFixes { fixes: 0 });
}

#[test]
fn collinear_fixes_leave_the_segment_waiting_and_say_why() {
    let mut f = Fusion::new(FusionConfig::default()).unwrap();
    // A straight line in the world: the rotation about it is unobservable.
    let line = |t: f64| Vector3::new(2.0 * t, 0.0, -5.0);
    for k in 0..100 {
        let t = k as f64 * 0.1;
        if k % 10 == 0 {
            f.push_fix(FixInput { t_s: t, position_m: line(t), covariance_m2: Matrix3::identity() * 0.01 }).unwrap();
        }
        let mut p = pair(t, 0, line(t), 0.1);
        p.local_from_body.translation.vector = Vector3::new(2.0 * t, 0.0, 0.0);
        let out = f.push_pair(p).unwrap();
        assert_eq!(out.source, Source::BuoyOnly);
    }
    assert!(
        matches!(&f.segment(0).unwrap().status, SegmentStatus::Degenerate { reason } if reason.contains("collinear")),
        "{:?}",
        f.segment(0).unwrap().status
    );
}

#[test]
fn a_compass_resolves_a_collinear_segment() {
    let mut f = Fusion::new(FusionConfig::default()).unwrap();
    // The vehicle drives straight along world y (yaw 90°); the local frame is yawed by 30°
    // from the world, so the body moves at 60° in the local frame.
    let yaw_local = 30f64.to_radians();
    let world_from_local = Isometry3::from_parts(
        Translation3::new(5.0, -3.0, -8.0),
        UnitQuaternion::from_euler_angles(0.0, 0.0, yaw_local),
    );
    let world = |t: f64| Vector3::new(0.0, 1.5 * t, -8.0);
    for k in 0..120 {
        let t = k as f64 * 0.1;
        if k % 10 == 0 {
            f.push_fix(FixInput { t_s: t, position_m: world(t), covariance_m2: Matrix3::identity() * 0.01 }).unwrap();
            let yaw = std::f64::consts::FRAC_PI_2 + 0.01 * ((k / 10) as f64 - 5.0) / 5.0;
            f.push_heading(HeadingInput { t_s: t, yaw_rad: yaw, sigma_rad: 0.03 }).unwrap();
        }
        let local_pose = world_from_local.inverse()
            * Isometry3::from_parts(
                Translation3::from(world(t)),
                UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2),
            );
        let p = PairInput {
            t_s: t,
            segment: 0,
            local_from_body: local_pose,
            local_covariance: Matrix6::identity() * 1e-4,
            buoy_m: world(t),
            buoy_cov_m2: Matrix3::identity() * 0.01,
        };
        f.push_pair(p).unwrap();
    }
    let seg = f.segment(0).unwrap();
    assert!(matches!(seg.status, SegmentStatus::AlignedWithHeading { .. }), "{:?}", seg.status);
    let a = seg.alignment.as_ref().unwrap();
    assert!(a.global_from_local.rotation.angle_to(&world_from_local.rotation) < 0.02, "{}", a.global_from_local);
    assert!((a.global_from_local.translation.vector - world_from_local.translation.vector).norm() < 0.2);
    // Without the compass the same segment waits.
    let mut g = Fusion::new(FusionConfig { use_heading: false, ..Default::default() }).unwrap();
    for p in &seg.pairs {
        if (p.t_s * 10.0).round() as i64 % 10 == 0 {
            g.push_fix(FixInput { t_s: p.t_s, position_m: p.buoy_m, covariance_m2: Matrix3::identity() * 0.01 })
                .unwrap();
        }
        g.push_pair(p.clone()).unwrap();
    }
    assert!(matches!(g.segment(0).unwrap().status, SegmentStatus::Degenerate { .. }));
}

#[test]
fn camera_and_buoy_that_stop_overlapping_request_one_new_local_map() {
    // (Without the handover: this test's segment 1 is not in the body frame where it starts.)
    let cfg = FusionConfig { no_overlap_frames: 5, handover_max_gap_s: 0.0, ..Default::default() };
    let mut f = Fusion::new(cfg).unwrap();
    for k in 0..300 {
        let t = k as f64 * 0.1;
        if k % 10 == 0 {
            f.push_fix(FixInput { t_s: t, position_m: truth_at(t), covariance_m2: Matrix3::identity() * 0.01 })
                .unwrap();
        }
        assert!(!f.push_pair(pair(t, 0, truth_at(t), 0.1)).unwrap().request_new_segment);
    }
    // The buoy now reads 20 m away: outside the gate.
    let mut requests = 0;
    for k in 300..320 {
        let t = k as f64 * 0.1;
        let out = f.push_pair(pair(t, 0, truth_at(t) + Vector3::new(20.0, 0.0, 0.0), 0.1)).unwrap();
        assert_eq!(out.source, Source::CameraOnly);
        requests += usize::from(out.request_new_segment);
        if k < 304 {
            assert!(!out.request_new_segment, "only after 5 in a row");
        }
    }
    assert_eq!(requests, 1, "asked once per segment");
    // A new segment starts waiting for its own fixes.
    let out = f.push_pair(pair(32.0, 1, truth_at(32.0), 0.1)).unwrap();
    assert_eq!(out.source, Source::BuoyOnly);
}

/// A body pose on the lawnmower curve, heading along it, with a small roll and pitch.
fn body_at(t: f64) -> Isometry3<f64> {
    let v = truth_at(t + 0.01) - truth_at(t - 0.01);
    Isometry3::from_parts(
        Translation3::from(truth_at(t)),
        UnitQuaternion::from_euler_angles(0.02 * (t / 3.0).sin(), 0.01, v.y.atan2(v.x)),
    )
}

/// Pairs of two local maps: the first in frame `world_from_local()` up to `switch_s`, the second
/// in the body frame at its first stamp (as FastSLAM starts a new local map), fixes every second
/// from `fixes_from_s` on (buoy σ 0.1 m, exact here).
fn two_local_maps(
    cfg: FusionConfig,
    switch_s: f64,
    fixes_from_s: f64,
    fix_offset: Vector3<f64>,
) -> (Fusion, Vec<FusedOutput>) {
    let mut f = Fusion::new(cfg).unwrap();
    let mut outs = vec![];
    let origin2 = body_at(switch_s);
    for k in 0..400 {
        let t = k as f64 * 0.1;
        if k % 10 == 0 && t >= fixes_from_s {
            let offset = if t >= switch_s { fix_offset } else { Vector3::zeros() };
            f.push_fix(FixInput {
                t_s: t,
                position_m: truth_at(t) + offset,
                covariance_m2: Matrix3::identity() * 0.01,
            })
            .unwrap();
        }
        let (segment, frame) = if t < switch_s - 1e-9 { (0, world_from_local()) } else { (1, origin2) };
        let mut p = pair(t, segment, truth_at(t), 0.1);
        p.local_from_body = frame.inverse() * body_at(t);
        outs.push(f.push_pair(p).unwrap());
    }
    (f, outs)
}

#[test]
fn a_new_local_map_starts_from_the_previous_transform_and_the_fixes_refine_it() {
    let (f, outs) = two_local_maps(FusionConfig::default(), 20.0, 0.0, Vector3::zeros());
    let seg = f.segment(1).unwrap();
    let h = seg.handover.as_ref().expect("a handover");
    assert_eq!(h.from, 0);
    // Its first pose is mapped by the carried transform (no buoy-only pose, no wait for fixes):
    // position and attitude as the truth's.
    let first = outs.iter().find(|o| o.segment == 1).unwrap();
    assert_ne!(first.source, Source::BuoyOnly);
    assert!((first.world_from_body.translation.vector - truth_at(20.0)).norm() < 0.05, "{first:?}");
    assert!(first.world_from_body.rotation.angle_to(&body_at(20.0).rotation) < 0.01);
    assert!(outs.iter().filter(|o| o.segment == 1).all(|o| o.source != Source::BuoyOnly));
    assert!(matches!(seg.status, SegmentStatus::AlignedWithPrior { fixes } if fixes > 10), "{:?}", seg.status);
    assert!(seg.alignment.unwrap().global_from_local.rotation.angle_to(&body_at(20.0).rotation) < 0.01);
    // A predicted pose of a map not seen yet is carried over too.
    let (g, _) = two_local_maps(FusionConfig::default(), 40.0, 0.0, Vector3::zeros());
    let mut p = pair(40.0, 1, truth_at(40.0), 0.1);
    p.local_from_body = Isometry3::identity();
    let predicted = g.predict_pair(&p).unwrap();
    assert_ne!(predicted.source, Source::BuoyOnly);
    assert!((predicted.world_from_body.translation.vector - truth_at(40.0)).norm() < 0.05, "{predicted:?}");
    // Off: the new map waits for its own fixes, buoy only meanwhile.
    let (_, outs) =
        two_local_maps(FusionConfig { handover_max_gap_s: 0.0, ..Default::default() }, 20.0, 0.0, Vector3::zeros());
    assert_eq!(outs.iter().find(|o| o.segment == 1).unwrap().source, Source::BuoyOnly);
}

#[test]
fn fixes_that_disagree_with_the_carried_transform_replace_it() {
    // After the switch the fixes read 3 m off (σ 0.1 m): not what the carried transform says.
    let (f, _) = two_local_maps(FusionConfig::default(), 20.0, 0.0, Vector3::new(3.0, 0.0, 0.0));
    let seg = f.segment(1).unwrap();
    assert!(seg.prior_rejected);
    assert_eq!(seg.status, SegmentStatus::Aligned);
    let t = seg.alignment.unwrap().global_from_local.translation.vector;
    assert!((t - (body_at(20.0).translation.vector + Vector3::new(3.0, 0.0, 0.0))).norm() < 0.1, "{t}");
}

#[test]
fn bad_inputs_are_errors() {
    let mut f = Fusion::new(FusionConfig::default()).unwrap();
    let mut p = pair(0.0, 0, truth_at(0.0), 0.3);
    p.buoy_m.x = f64::NAN;
    assert!(f.push_pair(p).is_err());
    let fix = FixInput { t_s: f64::NAN, position_m: Vector3::zeros(), covariance_m2: Matrix3::identity() };
    assert!(f.push_fix(fix).is_err());
    assert!(Fusion::new(FusionConfig { gate_probability: 1.5, ..Default::default() }).is_err());
}

#[test]
fn the_final_and_live_covariances_hold_when_the_fixes_errors_are_correlated_in_time() {
    // Fixes every second whose errors follow an AR(1) process (ρ = 0.8 from one fix to the
    // next, σ 0.3 m per axis, each fix's covariance honest on its own), the buoy positions of the
    // pairs interpolated between them as the synchronizer does. A window's transform averages
    // about a fifth of its fixes' independent errors, and the pose's own buoy position shares
    // most of its error: taken as independent, the final path's position NEES comes out far
    // above 3 (39 on the simulated mission; docs/fusion.md).
    let (sigma, rho) = (0.3f64, 0.8f64);
    let (mut nees, mut live_nees) = (vec![], vec![]);
    for seed in 1..=4u64 {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
        let n = Normal::new(0.0, 1.0).unwrap();
        let mut e = Vector3::new(n.sample(&mut rng), n.sample(&mut rng), n.sample(&mut rng)) * sigma;
        let q = (1.0 - rho * rho).sqrt() * sigma;
        let errors: Vec<Vector3<f64>> = (0..=120)
            .map(|_| {
                let now = e;
                e = e * rho + Vector3::new(n.sample(&mut rng), n.sample(&mut rng), n.sample(&mut rng)) * q;
                now
            })
            .collect();
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        let mut live = vec![];
        for k in 0..1200 {
            let t = k as f64 * 0.1;
            if k % 10 == 0 {
                let cov = Matrix3::identity() * sigma * sigma;
                f.push_fix(FixInput { t_s: t, position_m: truth_at(t) + errors[k / 10], covariance_m2: cov }).unwrap();
            }
            let (i, w) = (k / 10, (k % 10) as f64 / 10.0);
            let buoy = truth_at(t) + errors[i] * (1.0 - w) + errors[i + 1] * w;
            let o = f.push_pair(pair(t, 0, buoy, sigma)).unwrap();
            // The live poses once the local map's transform rests on 20 fixes or more.
            if t >= 20.0 {
                live.push((
                    t,
                    o.world_from_body.translation.vector,
                    o.covariance.fixed_view::<3, 3>(0, 0).into_owned(),
                ));
            }
        }
        let fin = f.finish();
        let r1 = fin.fix_correlation.rho().get(1).copied().unwrap_or(0.0);
        assert!((r1 - rho).abs() < 0.2, "seed {seed}: lag-1 correlation estimated {r1:.2}, true {rho}");
        let est: Vec<_> = fin
            .path
            .iter()
            .map(|o| (o.t_s, o.world_from_body.translation.vector, o.covariance.fixed_view::<3, 3>(0, 0).into_owned()))
            .collect();
        let truth: Vec<_> = (0..1200).map(|k| (k as f64 * 0.1, truth_at(k as f64 * 0.1))).collect();
        nees.push(geometry::trajectory::position_nees(&est, &truth, false, 1.0).unwrap().mean);
        live_nees.push(geometry::trajectory::position_nees(&live, &truth, false, 1.0).unwrap().mean);
    }
    // Four missions of 120 s with errors correlated over seconds: about 50 independent samples
    // of the mean error in all, not 4,800 (a mean of 3 when consistent).
    let mean = nees.iter().sum::<f64>() / nees.len() as f64;
    assert!((1.5..=4.5).contains(&mean), "final path NEES {mean:.2} (by seed {nees:.2?}): not about 3");
    // The live poses too: their local map's transform is fitted to all its fixes as if
    // independent; the correlation estimated from the residuals so far accounts for them.
    let mean = live_nees.iter().sum::<f64>() / live_nees.len() as f64;
    assert!((1.5..=4.5).contains(&mean), "live NEES {mean:.2} (by seed {live_nees:.2?}): not about 3");
}
