//! Unit tests of the parent module.

#![allow(non_snake_case)]

use super::*;
use geometry::{StereoPixels, StereoRig};
use rand_distr::{Distribution, Normal};

fn kitti() -> StereoRig {
    StereoRig { f_px: 718.0, cx_px: 607.0, cy_px: 185.0, baseline_m: 0.54, width_px: 1242, height_px: 375 }
}

/// A KITTI-like frame of `world` points seen from `world_from_cam`: noisy pixels (σ 0.5 px),
/// triangulated with first-order covariance; `outliers` random wrong matches added.
fn frame(
    world: &[(u64, Vector3<f64>)],
    world_from_cam: &Isometry3<f64>,
    keep: f64,
    outliers: f64,
    ids: bool,
    rng: &mut Xoshiro256PlusPlus,
) -> Vec<Observation> {
    let rig = kitti();
    let n = Normal::new(0.0, 0.5).unwrap();
    let mut out = vec![];
    for (id, w) in world {
        let p = world_from_cam.inverse_transform_point(&(*w).into()).coords;
        let Some(px) = rig.project(&p) else { continue };
        if rng.random::<f64>() > keep || px.u_left_px - px.u_right_px < 1.0 {
            continue;
        }
        let noisy = StereoPixels {
            u_left_px: px.u_left_px + n.sample(rng),
            u_right_px: px.u_right_px + n.sample(rng),
            v_px: px.v_px + n.sample(rng),
        };
        let (Ok(p), Ok(c)) = (rig.triangulate(&noisy), rig.triangulation_covariance(&noisy, 0.5)) else { continue };
        let mut o = Observation::from_camera(&p, &c, None, &Isometry3::identity()).unwrap();
        o.track_id = ids.then_some(*id);
        out.push(o);
    }
    let k = (out.len() as f64 * outliers) as usize;
    for _ in 0..k {
        let d = rng.random_range(1.0..60.0);
        let u = rng.random_range(d..1242.0);
        let px = StereoPixels { u_left_px: u, u_right_px: u - d, v_px: rng.random_range(0.0..375.0) };
        let (p, c) = (rig.triangulate(&px).unwrap(), rig.triangulation_covariance(&px, 0.5).unwrap());
        let mut o = Observation::from_camera(&p, &c, None, &Isometry3::identity()).unwrap();
        o.track_id = ids.then_some(1_000_000 + rng.random_range(0..1000u64));
        out.push(o);
    }
    // Shuffle: order carries no information.
    for i in (1..out.len()).rev() {
        out.swap(i, rng.random_range(0..=i));
    }
    out
}

/// A street: points on two facades, the ground and some far ones, camera frame of the start.
fn street(rng: &mut Xoshiro256PlusPlus, n: usize) -> Vec<(u64, Vector3<f64>)> {
    (0..n as u64)
        .map(|id| {
            let z = 2.0 + 90.0 * rng.random::<f64>().powi(2);
            let p = match rng.random_range(0..4) {
                0 => Vector3::new(-7.0 + rng.random_range(-0.3..0.3), rng.random_range(-6.0..1.5), z),
                1 => Vector3::new(8.0 + rng.random_range(-0.3..0.3), rng.random_range(-6.0..1.5), z),
                2 => Vector3::new(rng.random_range(-7.0..8.0), 1.6 + rng.random_range(-0.05..0.05), z),
                _ => Vector3::new(rng.random_range(-40.0..40.0), rng.random_range(-15.0..1.5), z + 30.0),
            };
            (id, p)
        })
        .collect()
}

fn motion(tx: f64, ty: f64, tz: f64, yaw_deg: f64, pitch_deg: f64, roll_deg: f64) -> Isometry3<f64> {
    // Camera frame: y down, so a yaw of the vehicle is a rotation about camera −y.
    Isometry3::from_parts(
        Translation3::new(tx, ty, tz),
        UnitQuaternion::from_euler_angles(pitch_deg.to_radians(), -yaw_deg.to_radians(), roll_deg.to_radians()),
    )
}

fn check(reg: &Registration, truth: &Isometry3<f64>) -> f64 {
    let err = truth.inverse() * reg.prev_from_cur;
    let e = Vector6::new(
        err.translation.vector.x,
        err.translation.vector.y,
        err.translation.vector.z,
        err.rotation.scaled_axis().x,
        err.rotation.scaled_axis().y,
        err.rotation.scaled_axis().z,
    );
    let nees = e.dot(&(reg.covariance.try_inverse().unwrap() * e));
    assert!(err.translation.vector.norm() < 0.1, "translation error {} ({reg:?})", err.translation.vector);
    assert!(err.rotation.angle().to_degrees() < 0.3, "rotation error {}°", err.rotation.angle().to_degrees());
    nees
}

#[test]
fn a_large_motion_is_found_without_track_ids_or_prior_among_outliers() {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(1);
    let world = street(&mut rng, 1200);
    let truth = motion(0.2, -0.05, 1.5, 10.0, 1.0, 0.5);
    let a = frame(&world, &Isometry3::identity(), 0.8, 0.1, false, &mut rng);
    let b = frame(&world, &truth, 0.8, 0.1, false, &mut rng);
    let mut fe = FrontEnd::new(FrontEndConfig::default());
    assert_eq!(
        fe.register(Frame::from_observations(&a, &Isometry3::identity()), 0.1),
        Err(RegistrationError::FirstFrame)
    );
    let r = fe.register(Frame::from_observations(&b, &Isometry3::identity()), 0.1).unwrap();
    assert_eq!(r.method, Method::Search, "{r:?}");
    check(&r, &truth);
    assert!(r.inliers > 100, "{r:?}");
}

#[test]
fn track_ids_give_the_motion_and_wrong_ids_are_outliers() {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(2);
    let world = street(&mut rng, 1000);
    let truth = motion(-0.1, 0.0, 1.2, -6.0, 0.0, 0.0);
    let a = frame(&world, &Isometry3::identity(), 0.8, 0.1, true, &mut rng);
    let mut b = frame(&world, &truth, 0.8, 0.1, true, &mut rng);
    // 5 % of the tracks jump to another feature.
    for o in b.iter_mut().step_by(20) {
        o.track_id = o.track_id.map(|t| (t + 17) % 1000);
    }
    let mut fe = FrontEnd::new(FrontEndConfig::default());
    let _ = fe.register(Frame::from_observations(&a, &Isometry3::identity()), 0.1);
    let r = fe.register(Frame::from_observations(&b, &Isometry3::identity()), 0.1).unwrap();
    assert_eq!(r.method, Method::TrackIds);
    assert!((r.candidates_per_point - 1.0).abs() < 0.5, "{r:?}");
    check(&r, &truth);
}

#[test]
fn steady_motion_uses_the_prior_and_the_covariance_is_consistent() {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(3);
    let world = street(&mut rng, 1500);
    let mut fe = FrontEnd::new(FrontEndConfig::default());
    let step = motion(0.0, 0.0, 1.0, 1.0, 0.0, 0.0);
    let mut pose = Isometry3::identity();
    let mut nees = vec![];
    let mut guided = 0;
    for k in 0..12 {
        let obs = frame(&world, &pose, 0.8, 0.1, false, &mut rng);
        match fe.register(Frame::from_observations(&obs, &Isometry3::identity()), 0.1) {
            Ok(r) => {
                guided += (r.method == Method::Guided) as usize;
                nees.push(check(&r, &step));
            }
            Err(e) => assert!(k == 0, "frame {k}: {e}"),
        }
        pose *= step;
    }
    assert!(guided >= 9, "the constant-velocity prior is used once the motion is known ({guided} of 11)");
    let mean = nees.iter().sum::<f64>() / nees.len() as f64;
    // 6 degrees of freedom: a consistent covariance gives a mean NEES near 6.
    assert!(mean > 1.0 && mean < 18.0, "mean NEES {mean} ({nees:?})");
}

#[test]
fn unrelated_frames_are_refused_not_registered() {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(4);
    let w1 = street(&mut rng, 800);
    let w2 = street(&mut rng, 800);
    let a = frame(&w1, &Isometry3::identity(), 0.8, 0.0, false, &mut rng);
    let b = frame(&w2, &Isometry3::identity(), 0.8, 0.0, false, &mut rng);
    let mut fe = FrontEnd::new(FrontEndConfig::default());
    let _ = fe.register(Frame::from_observations(&a, &Isometry3::identity()), 0.1);
    let e = fe.register(Frame::from_observations(&b, &Isometry3::identity()), 0.1).unwrap_err();
    assert!(matches!(e, RegistrationError::NoConsensus { .. }), "{e}");
}

#[test]
fn the_body_frame_motion_is_the_camera_motion_conjugated_by_the_extrinsic() {
    let b = geometry::body_from_camera(&Vector3::new(0.5, 0.1, -0.2), 0.4);
    let cam_motion = motion(0.1, 0.2, 1.0, 5.0, 1.0, -2.0);
    let mut cov = Matrix6::identity() * 1e-4;
    cov[(3, 3)] = 1e-6;
    let r = Registration {
        prev_from_cur: cam_motion,
        covariance: cov,
        inliers: 10,
        points: (10, 10),
        candidates_per_point: 1.0,
        method: Method::Guided,
        hypotheses: 1,
        chi2_per_dof: 1.0,
        matches: vec![],
    };
    let (m, c) = motion_in_body(&r, &b);
    // The body motion moves the camera by the camera motion.
    let cam_prev = b;
    let cam_cur = m * b;
    assert!(((cam_prev.inverse() * cam_cur).to_homogeneous() - cam_motion.to_homogeneous()).norm() < 1e-12);
    // Perturbations: the body-frame covariance maps back through the adjoint.
    let A = adjoint(&b);
    let back = A.try_inverse().unwrap() * c * A.try_inverse().unwrap().transpose();
    assert!((back - cov).norm() < 1e-12);
    // And the adjoint is right to first order.
    let eps = Vector6::new(1e-6, -2e-6, 3e-6, 2e-6, 1e-6, -1e-6);
    let exp = |e: &Vector6<f64>| {
        Isometry3::from_parts(
            Translation3::from(e.fixed_rows::<3>(0).into_owned()),
            UnitQuaternion::from_scaled_axis(e.fixed_rows::<3>(3).into_owned()),
        )
    };
    let lhs = b * exp(&eps) * b.inverse();
    let rhs = exp(&(A * eps));
    assert!((lhs.to_homogeneous() - rhs.to_homogeneous()).norm() < 1e-10);
}
