//! Camera-only FastSLAM: the stereo front end as the motion input, on the KITTI-like simulated
//! drive (ground truth) and on the real KITTI features of `../shared/data/stereo_vo_large` when
//! they are present (read in place; they may not be committed).

use std::collections::BTreeMap;

use fastslam::eval::{CHI2_3_95, TrajectorySample, evaluate, weighted_mean};
use fastslam::frontend::{Frame, FrontEnd, FrontEndConfig, RegistrationError};
use fastslam::{CameraOnly, FastSlam, FastSlamConfig, Observation};
use nalgebra::{Isometry3, Vector3};

/// RMSE of positions after the best rigid alignment.
fn aligned_rmse(est: &[(f64, Isometry3<f64>)], truth: &[(f64, Isometry3<f64>)]) -> f64 {
    let pairs: Vec<_> = est
        .iter()
        .filter_map(|(t, p)| fastslam::eval::nearest(truth, *t).map(|r| (p.translation.vector, r.translation.vector)))
        .collect();
    let src: Vec<_> = pairs.iter().map(|p| p.0).collect();
    let dst: Vec<_> = pairs.iter().map(|p| p.1).collect();
    let a = geometry::align_rigid(&src, &dst, &vec![1.0; src.len()]).expect("non-degenerate path");
    (src.iter().zip(&dst).map(|(s, d)| (a.transform_point(&(*s).into()).coords - d).norm_squared()).sum::<f64>()
        / src.len() as f64)
        .sqrt()
}

struct Outcome {
    frontend_rmse: f64,
    slam_rmse: f64,
    nees_position: f64,
    failures: usize,
}

fn run(
    frames: &[(f64, Vec<Observation>)],
    b: &Isometry3<f64>,
    truth: &[(f64, Isometry3<f64>)],
    particles: usize,
    assign_tracks: bool,
) -> Outcome {
    // The front end alone, its motions chained.
    let mut fe = FrontEnd::new(FrontEndConfig::default());
    let mut pose = Isometry3::identity();
    let mut fe_traj = vec![];
    let mut failures = 0;
    let mut last: Option<f64> = None;
    for (t, obs) in frames {
        match fe.register(Frame::from_observations(obs, b), last.map_or(0.0, |l| t - l)) {
            Ok(r) => pose *= b * r.prev_from_cur * b.inverse(),
            Err(RegistrationError::FirstFrame) => {}
            Err(_) => failures += 1,
        }
        last = Some(*t);
        fe_traj.push((*t, pose));
    }
    // FastSLAM with it.
    let mut f = FastSlam::new(FastSlamConfig { particles, threads: 2, ..Default::default() }).unwrap();
    let mut cam = CameraOnly::new(FrontEndConfig { assign_tracks, ..Default::default() }, *b);
    let mut traj = vec![];
    let mut samples = vec![];
    let mut last: Option<f64> = None;
    for (t, obs) in frames {
        let mut obs = obs.clone();
        cam.predict(&mut f, &mut obs, last.map_or(0.0, |l| t - l));
        let obs = &obs;
        last = Some(*t);
        let r = f.update(obs);
        assert!(r.new_segment.is_none(), "one local map");
        let e = f.estimate();
        traj.push((*t, e.map_from_body));
        samples.push(TrajectorySample {
            t_s: *t,
            segment: 0,
            map_from_body: e.map_from_body,
            covariance: e.covariance,
        });
    }
    let scores = evaluate(&samples, truth, &BTreeMap::from([(0, frames[0].0)]));
    Outcome {
        frontend_rmse: aligned_rmse(&fe_traj, truth),
        slam_rmse: aligned_rmse(&traj, truth),
        nees_position: weighted_mean(&scores, |s| s.nees_position),
        failures,
    }
}

/// Frames of observations (stamp s, body frame), the camera extrinsic, the true path.
type Drive = (Vec<(f64, Vec<Observation>)>, Isometry3<f64>, Vec<(f64, Isometry3<f64>)>);

fn drive(ids: bool, frames: usize) -> Drive {
    let mut sim = sim::road::RoadSim::new(sim::road::RoadConfig { frames, ..Default::default() }).unwrap();
    let b = sim.body_from_camera();
    let mut out = vec![];
    for f in sim.by_ref() {
        let obs = f
            .observations
            .iter()
            .filter_map(|o| {
                let mut ob = Observation::from_camera(&o.point_cam_m, &o.covariance_cam_m2, None, &b).ok()?;
                ob.track_id = ids.then_some(o.track_id);
                Some(ob)
            })
            .collect();
        out.push((f.t_s, obs));
    }
    let truth = sim.truth().iter().map(|t| (t.t_s, t.world_from_body)).collect();
    (out, b, truth)
}

#[test]
fn on_the_simulated_drive_the_filter_beats_its_own_front_end_and_its_covariance_is_honest() {
    // 300 frames (~280 m: curves, the intersection, dropped frames, wrong stereo matches, wrong
    // tracks), without source ids (the front end's own feature tracks, and maximum likelihood
    // alone) and with them; deterministic (seeded simulator, filter and front end).
    for (ids, assign, must_beat) in [(false, true, true), (true, true, true), (false, false, false)] {
        let (frames, b, truth) = drive(ids, 300);
        let o = run(&frames, &b, &truth, 100, assign);
        let mode = format!("source ids {ids}, front-end tracks {assign}");
        assert_eq!(o.failures, 0, "{mode}: the front end registered every frame");
        assert!(o.frontend_rmse < 0.2, "{mode}: front end RMSE {} m", o.frontend_rmse);
        assert!(o.slam_rmse < 0.2, "{mode}: FastSLAM RMSE {} m", o.slam_rmse);
        if must_beat {
            assert!(
                o.slam_rmse < o.frontend_rmse,
                "{mode}: FastSLAM {} m against its front end's {} m",
                o.slam_rmse,
                o.frontend_rmse
            );
        }
        assert!(
            (CHI2_3_95.0..=CHI2_3_95.1).contains(&o.nees_position),
            "{mode}: mean position NEES {} outside χ²₃'s 95 % interval",
            o.nees_position
        );
    }
}

#[test]
fn on_the_real_kitti_features_the_track_agrees_with_the_data_sets_visual_odometry() {
    let dir = format!("{}/../../../shared/data/stereo_vo_large", env!("CARGO_MANIFEST_DIR"));
    if !datasets::shared_data_present(
        &dir,
        "on_the_real_kitti_features_the_track_agrees_with_the_data_sets_visual_odometry",
    ) {
        return;
    }
    let vo = datasets::StereoVo::load(&dir).expect("the KITTI stereo features load");
    let c = vo.calibration;
    let rig = geometry::StereoRig {
        f_px: c.fx_px,
        cx_px: c.cx_px,
        cy_px: c.cy_px,
        baseline_m: c.baseline_m,
        width_px: 1242,
        height_px: 375,
    };
    let reference: Vec<(f64, Isometry3<f64>)> = vo
        .poses
        .iter()
        .map(|p| {
            let m = p.world_from_camera;
            let r = nalgebra::Rotation3::from_matrix(&m.fixed_view::<3, 3>(0, 0).into_owned());
            (
                p.frame_id as f64 / 10.0,
                Isometry3::from_parts(
                    nalgebra::Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
                    nalgebra::UnitQuaternion::from_rotation_matrix(&r),
                ),
            )
        })
        .collect();
    let path: f64 = reference.windows(2).map(|w| (w[1].1.translation.vector - w[0].1.translation.vector).norm()).sum();
    for ids in [false, true] {
        let frames: Vec<(f64, Vec<Observation>)> = datasets::group_by_frame(&vo.factors)
            .iter()
            .map(|fr| {
                let obs = fr
                    .observations
                    .iter()
                    .filter_map(|o| {
                        let px =
                            geometry::StereoPixels { u_left_px: o.u_left_px, u_right_px: o.u_right_px, v_px: o.v_px };
                        let cov = rig.triangulation_covariance(&px, 0.5).ok()?;
                        let mut ob =
                            Observation::from_camera(&Vector3::from(o.point_cam_m), &cov, None, &Isometry3::identity())
                                .ok()?;
                        ob.track_id = ids.then_some(o.landmark_id);
                        Some(ob)
                    })
                    .collect();
                (fr.frame_id as f64 / 10.0, obs)
            })
            .collect();
        let o = run(&frames, &Isometry3::identity(), &reference, 50, true);
        assert_eq!(o.failures, 0, "ids {ids}");
        // Within 2 % of the path (the goal; measured: < 0.1 %).
        assert!(o.slam_rmse < 0.02 * path, "ids {ids}: RMSE {} m over a {path:.1} m path", o.slam_rmse);
        assert!(o.frontend_rmse < 0.02 * path, "ids {ids}: front end RMSE {} m", o.frontend_rmse);
    }
}

/// A feature the detector misses for a frame keeps its track when it is seen again (and with
/// `bridge_gap_frames = 0` it gets a new one); a feature seen for the first time gets a new
/// track either way.
#[test]
fn a_feature_missed_for_a_frame_keeps_its_track() {
    // The camera looks along the body's x axis (optical z forward, x right, y down).
    let b = Isometry3::from_parts(
        nalgebra::Translation3::new(0.0, 0.0, 0.0),
        nalgebra::UnitQuaternion::from_matrix(&nalgebra::Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0)),
    );
    // 80 points in the world (camera frame at the start), 6-20 m ahead; the camera moves 0.5 m
    // forward a frame. Point 7 is missed in the second frame; point 79 appears in the third.
    let world: Vec<Vector3<f64>> = (0..80)
        .map(|i| {
            let f = i as f64;
            Vector3::new((f * 0.37).sin() * 4.0, (f * 0.23).cos() * 2.0, 6.0 + (f * 0.61).sin().abs() * 14.0)
        })
        .collect();
    let cov = nalgebra::Matrix3::from_diagonal(&Vector3::new(1e-4, 1e-4, 4e-3));
    let frame = |k: usize, skip: &[usize]| -> Vec<Observation> {
        (0..world.len())
            .filter(|i| !skip.contains(i))
            .map(|i| {
                let p = world[i] - Vector3::new(0.0, 0.0, 0.5 * k as f64);
                Observation::from_camera(&p, &cov, None, &b).unwrap()
            })
            .collect()
    };
    let tracks_of = |gap: u32| {
        let mut f = FastSlam::new(FastSlamConfig { particles: 10, ..Default::default() }).unwrap();
        let mut cam = CameraOnly::new(FrontEndConfig { bridge_gap_frames: gap, ..Default::default() }, b);
        let mut out = vec![];
        for (k, skip) in [(0, vec![79]), (1, vec![7, 79]), (2, vec![])] {
            let mut obs = frame(k, &skip);
            cam.predict(&mut f, &mut obs, 0.1);
            f.update(&obs);
            // Observation index → point index.
            let ids: Vec<usize> = (0..world.len()).filter(|i| !skip.contains(i)).collect();
            out.push(ids.into_iter().zip(obs.iter().map(|o| o.track_id.unwrap())).collect::<BTreeMap<_, _>>());
        }
        (out, cam.stats().bridged)
    };
    let (t, bridged) = tracks_of(2);
    assert_eq!(t[2][&7], t[0][&7], "point 7 keeps its track over the frame that missed it");
    assert_eq!(t[2][&3], t[0][&3], "a point seen throughout keeps its track");
    assert!(t.iter().take(2).all(|f| f.values().all(|id| *id != t[2][&79])), "a new point gets a new track");
    assert_eq!(bridged, 1);
    let (t, bridged) = tracks_of(0);
    assert_ne!(t[2][&7], t[0][&7], "without bridging the track ends");
    assert_eq!(bridged, 0);
}
