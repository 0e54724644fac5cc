//! The filter on synthetic frames and on a short simulated run.

use std::collections::BTreeMap;

use fastslam::eval::{TrajectorySample, evaluate};
use fastslam::{FastSlam, FastSlamConfig, Observation, Proposal};
use nalgebra::{Isometry3, Matrix3, Vector3};
use sim::{SimConfig, SimEvent, Simulator};

fn obs(p: [f64; 3], sigma: f64, desc: Option<u8>) -> Observation {
    Observation {
        z_m: Vector3::from(p),
        Rz: Matrix3::identity() * sigma * sigma,
        descriptor: desc.map(|d| [d; 32]),
        track_id: None,
        stereo: None,
    }
}

fn quiet(particles: usize) -> FastSlamConfig {
    FastSlamConfig { particles, process_position_sigma: 0.0, process_rotation_sigma: 0.0, ..Default::default() }
}

#[test]
fn association_picks_the_right_landmark_and_rejects_gated_outliers() {
    let mut f = FastSlam::new(quiet(1)).unwrap();
    let frame = [obs([5.0, 0.0, 0.0], 0.05, None), obs([5.0, 2.0, 0.0], 0.05, None), obs([6.0, -2.0, 1.0], 0.05, None)];
    let r = f.update(&frame);
    assert_eq!((r.new, r.matched), (3, 0));
    let r = f.update(&frame);
    assert_eq!(r.matched, 3, "the same landmarks again: {r:?}");
    let ids = r.associations.clone();
    assert_eq!(ids.iter().flatten().count(), 3);
    // Shuffled order: association follows position, not index.
    let shuffled = [frame[2].clone(), frame[0].clone(), frame[1].clone()];
    let r2 = f.update(&shuffled);
    assert_eq!(r2.associations, vec![ids[2], ids[0], ids[1]]);
    // An outlier 1 m off with 5 cm noise is outside every gate: a new landmark, not a match.
    let r3 = f.update(&[obs([5.0, 1.0, 0.0], 0.05, None)]);
    assert_eq!((r3.matched, r3.new), (0, 1), "{r3:?}");
}

#[test]
fn descriptors_decide_between_landmarks_inside_the_gate() {
    let mut f = FastSlam::new(quiet(1)).unwrap();
    let a = obs([5.0, 0.0, 0.0], 0.3, Some(0x00));
    let b = obs([5.0, 0.4, 0.0], 0.3, Some(0xff));
    f.update(&[a.clone(), b.clone()]);
    f.update(&[a, b]);
    // Between the two but closer to A, with B's descriptor: B.
    let r = f.update(&[obs([5.0, 0.15, 0.0], 0.3, Some(0xff))]);
    let map = f.best_map();
    let id_b = map.iter().find(|(_, l)| l.descriptor == Some([0xff; 32])).unwrap().0;
    assert_eq!(r.associations, vec![Some(id_b)]);
}

#[test]
fn invalid_observations_are_errors_not_panics() {
    let body_from_camera = Isometry3::identity();
    assert!(
        Observation::from_camera(&Vector3::new(f64::NAN, 0.0, 1.0), &Matrix3::identity(), None, &body_from_camera)
            .is_err()
    );
    assert!(
        Observation::from_camera(&Vector3::new(0.0, 0.0, 1.0), &-Matrix3::identity(), None, &body_from_camera).is_err()
    );
    let mut f = FastSlam::new(quiet(3)).unwrap();
    let bad = geometry::ProcessInput { v_mps: f64::NAN, delta_theta_rad: Vector3::zeros(), dt_s: 0.1 };
    assert!(f.predict(&bad, [0.0; 4]).is_err());
    assert!(FastSlam::new(FastSlamConfig { particles: 0, ..Default::default() }).is_err());
}

fn short_run(proposal: Proposal, threads: usize) -> (Vec<fastslam::eval::SegmentScore>, usize) {
    let mut sc = SimConfig::default();
    sc.mission.legs = 1;
    sc.mission.leg_length_m = 40.0;
    sc.sensors.depth_camera.rate_hz = 0.0;
    let mut sim = Simulator::new(sc).unwrap();
    let body_from_cam = sim.body_from_stereo();
    let mut f = FastSlam::new(FastSlamConfig { particles: 50, proposal, threads, ..Default::default() }).unwrap();
    let mut traj = vec![];
    let mut origins = BTreeMap::from([(0u32, 0.0)]);
    let mut matched = 0;
    for e in sim.by_ref() {
        match e {
            SimEvent::Odometry(o) => f.predict(&o.input, o.variances).unwrap(),
            SimEvent::Stereo(fr) => {
                let o: Vec<_> = fr
                    .observations
                    .iter()
                    .map(|o| {
                        Observation::from_camera(
                            &o.point_cam_m,
                            &o.covariance_cam_m2,
                            Some(o.descriptor),
                            &body_from_cam,
                        )
                        .unwrap()
                    })
                    .collect();
                let r = f.update(&o);
                matched += r.matched;
                if r.new_segment.is_some() {
                    origins.insert(f.segment(), fr.t_s);
                }
                let e = f.estimate();
                traj.push(TrajectorySample {
                    t_s: fr.t_s,
                    segment: f.segment(),
                    map_from_body: e.map_from_body,
                    covariance: e.covariance,
                });
            }
            _ => {}
        }
    }
    let truth: Vec<_> = sim.truth().iter().map(|t| (t.t_s, t.world_from_body)).collect();
    (evaluate(&traj, &truth, &origins), matched)
}

#[test]
fn a_short_simulated_run_stays_within_bounds() {
    for proposal in [Proposal::Motion, Proposal::Optimal] {
        let (scores, matched) = short_run(proposal, 2);
        // The particles' work split over threads or not gives the same filter (each particle
        // has its own noise stream; results are gathered in particle order).
        let (one_thread, matched_one) = short_run(proposal, 1);
        assert_eq!(matched, matched_one, "{proposal:?}");
        assert_eq!(format!("{scores:?}"), format!("{one_thread:?}"), "{proposal:?}");
        assert!(matched > 1000, "{proposal:?}: associations happen ({matched})");
        let longest = scores.iter().max_by_key(|s| s.samples).unwrap();
        assert!(longest.samples > 100, "{scores:?}");
        assert!(longest.ate_m < 0.5, "{proposal:?}: ATE {} m on the longest local map: {scores:?}", longest.ate_m);
    }
}

#[test]
fn new_landmarks_get_consecutive_ids_in_observation_order() {
    let mut f = FastSlam::new(quiet(4)).unwrap();
    // Three new landmarks: ids from the first free one, in observation order.
    let frame = [obs([5.0, 0.0, 0.0], 0.05, None), obs([5.0, 2.0, 0.0], 0.05, None), obs([6.0, -2.0, 1.0], 0.05, None)];
    let r = f.update(&frame);
    let first = r.first_new_id;
    assert_eq!(r.new_ids, vec![Some(first), Some(first + 1), Some(first + 2)], "{r:?}");
    // The same three again (matched: no ids) and one new between two matched ones: the next id.
    let mut again = frame.to_vec();
    again.insert(1, obs([8.0, 4.0, 0.0], 0.05, None));
    let r = f.update(&again);
    assert_eq!(r.new_ids, vec![None, Some(first + 3), None, None], "{r:?}");
    assert_eq!(r.first_new_id, first + 3);
    assert_eq!(r.associations[0], Some(first));
    assert_eq!(r.associations[3], Some(first + 2));
    // A frame with nothing new reserves no id.
    let r = f.update(&frame);
    assert!(r.new_ids.iter().all(Option::is_none));
    let r = f.update(&[obs([3.0, -4.0, 0.0], 0.05, None)]);
    assert_eq!(r.new_ids, vec![Some(first + 4)]);
}
