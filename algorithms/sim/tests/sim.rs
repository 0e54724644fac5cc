//! The simulator: determinism, the mission's shape, and each sensor model against its equations.

use nalgebra::{Point3, Vector3};
use sim::{SimConfig, SimEvent, Simulator};

fn short() -> SimConfig {
    let mut c = SimConfig::default();
    c.mission.legs = 2;
    c.mission.leg_length_m = 40.0;
    c.sensors.depth_camera.width_px = 40;
    c.sensors.depth_camera.height_px = 30;
    c
}

fn run(c: SimConfig) -> (Vec<SimEvent>, Simulator) {
    let mut s = Simulator::new(c).expect("valid config");
    let events: Vec<_> = s.by_ref().collect();
    (events, s)
}

#[test]
fn the_same_seed_gives_identical_events_and_another_seed_does_not() {
    let (a, _) = run(short());
    let (b, _) = run(short());
    assert!(a.len() > 1000);
    assert_eq!(a, b);
    let mut other = short();
    other.seed = 2;
    let (c, _) = run(other);
    assert_ne!(a, c);
}

#[test]
fn changing_one_sensor_does_not_change_another_sensors_noise() {
    let (a, _) = run(short());
    let mut c = short();
    c.sensors.depth_camera.width_px = 20;
    let (b, _) = run(c);
    let odo = |v: &[SimEvent]| {
        v.iter().filter(|e| matches!(e, SimEvent::Odometry(_) | SimEvent::Buoys(_))).cloned().collect::<Vec<_>>()
    };
    assert_eq!(odo(&a), odo(&b));
}

#[test]
fn events_come_in_time_order_at_their_rates() {
    let (events, s) = run(short());
    let mut last = 0.0;
    let (mut odo, mut stereo, mut buoys) = (0usize, 0usize, 0usize);
    for e in &events {
        assert!(e.t_s() >= last);
        last = e.t_s();
        match e {
            SimEvent::Odometry(_) => odo += 1,
            SimEvent::Stereo(_) => stereo += 1,
            SimEvent::Buoys(_) => buoys += 1,
            _ => {}
        }
    }
    let t = s.time_s();
    assert!((odo as f64 - 50.0 * t).abs() < 2.0, "odometry {odo} in {t} s");
    assert!((stereo as f64 - 15.0 * t).abs() < 2.0, "stereo {stereo} in {t} s");
    assert!((buoys as f64 - t).abs() < 2.0, "buoys {buoys} in {t} s");
}

#[test]
fn the_mission_exercises_all_three_angles_and_depths() {
    let mut c = SimConfig::default();
    c.sensors.depth_camera.rate_hz = 0.0; // only the path matters here
    let (_, s) = run(c);
    let (mut roll, mut pitch) = (0f64, 0f64);
    let mut yaws = vec![];
    let (mut zmin, mut zmax) = (f64::MAX, f64::MIN);
    for t in s.truth() {
        let (r, p, y) = t.world_from_body.rotation.euler_angles();
        roll = roll.max(r.abs());
        pitch = pitch.max(p.abs());
        yaws.push(y);
        zmin = zmin.min(t.world_from_body.translation.z);
        zmax = zmax.max(t.world_from_body.translation.z);
    }
    assert!(roll.to_degrees() > 2.0, "roll {roll}");
    assert!(pitch.to_degrees() > 10.0, "pitch {pitch}");
    assert!(
        yaws.iter().any(|y| y.abs() < 0.3) && yaws.iter().any(|y| (y.abs() - std::f64::consts::PI).abs() < 0.3),
        "legs in both directions"
    );
    assert!(zmax > -8.0 && zmin < -20.0, "depth range {zmin}..{zmax}");
}

#[test]
fn odometry_noise_matches_its_configured_sigma_against_the_true_motion() {
    let (events, s) = run(short());
    let truth = s.truth();
    let sigma = SimConfig::default().sensors.odometry.speed_sigma_mps;
    let mut residuals = vec![];
    for (k, e) in events.iter().filter_map(|e| if let SimEvent::Odometry(o) = e { Some(o) } else { None }).enumerate() {
        // True speed from consecutive true poses: the process model moves along body x.
        let (a, b) = (truth[k].world_from_body, truth[k + 1].world_from_body);
        let v_true = (b.translation.vector - a.translation.vector).dot(&(a.rotation * Vector3::x())) / e.input.dt_s;
        residuals.push(e.input.v_mps - v_true);
    }
    let n = residuals.len() as f64;
    let mean = residuals.iter().sum::<f64>() / n;
    let sd = (residuals.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    assert!(mean.abs() < 4.0 * sigma / n.sqrt(), "mean {mean}");
    assert!((sd / sigma - 1.0).abs() < 0.1, "sd {sd} vs sigma {sigma}");
}

#[test]
fn stereo_observations_are_consistent_with_the_true_landmarks_and_their_covariance() {
    let (events, s) = run(short());
    let truth = s.truth();
    let dt = 1.0 / SimConfig::default().sensors.odometry.rate_hz;
    let mut nees = vec![];
    let mut spurious = 0;
    let mut real = 0;
    for e in &events {
        let SimEvent::Stereo(f) = e else { continue };
        let k = (f.t_s / dt).round() as usize;
        let world_from_cam = truth[k].world_from_body * s.body_from_stereo();
        for o in &f.observations {
            let Some(id) = o.landmark_id else {
                spurious += 1;
                continue;
            };
            real += 1;
            let l = s.scene().landmarks()[id as usize];
            let predicted = world_from_cam.inverse() * Point3::from(l.position_m);
            let d = o.point_cam_m - predicted.coords;
            let cov = o.covariance_cam_m2;
            assert!(cov.symmetric_eigenvalues().min() > 0.0);
            nees.push(d.dot(&(cov.try_inverse().unwrap() * d)));
        }
    }
    assert!(real > 1000, "{real} observations");
    let frac = spurious as f64 / real as f64;
    assert!((frac - 0.05).abs() < 0.02, "spurious fraction {frac}");
    // Normalised error of a 3-D Gaussian: mean 3 (first-order covariance; triangulation is
    // slightly non-linear, so allow a margin), and the bulk under the χ²₃(0.99) gate.
    let mean = nees.iter().sum::<f64>() / nees.len() as f64;
    assert!((2.4..3.8).contains(&mean), "mean NEES {mean}");
    let inside = nees.iter().filter(|e| **e < 11.34).count() as f64 / nees.len() as f64;
    assert!(inside > 0.97, "{inside} inside the 99% gate");
}

#[test]
fn buoy_ranges_carry_the_configured_bias_noise_outliers_and_dropouts() {
    let mut c = SimConfig::default();
    c.mission.legs = 2;
    c.sensors.depth_camera.rate_hz = 0.0;
    let (events, s) = run(c.clone());
    let truth = s.truth();
    let dt = 1.0 / c.sensors.odometry.rate_hz;
    let b = &c.sensors.buoys;
    let (mut residuals, mut outliers, mut got, mut cycles) = (vec![], 0usize, 0usize, 0usize);
    for e in &events {
        let SimEvent::Buoys(r) = e else { continue };
        cycles += 1;
        let p = truth[(r.t_s / dt).round() as usize].world_from_body.translation.vector;
        for x in &r.ranges {
            got += 1;
            let err = x.range_m - (p - Vector3::from(s.scene().buoys_m[x.buoy_id as usize])).norm();
            if err - b.bias_m > 5.0 * b.sigma_m {
                outliers += 1;
            } else {
                residuals.push(err);
            }
        }
    }
    let expected = cycles * s.scene().buoys_m.len();
    let dropout = 1.0 - got as f64 / expected as f64;
    assert!((dropout - b.dropout_probability).abs() < 0.04, "dropout {dropout}");
    let of = outliers as f64 / got as f64;
    assert!((of - b.outlier_probability).abs() < 0.03, "outlier fraction {of}");
    let mut sorted = residuals.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    assert!((median - b.bias_m).abs() < 0.08, "median error {median} vs bias {}", b.bias_m);
}

#[test]
fn outliers_removed_leaves_the_other_ranges_exactly_as_they_were() {
    let mut c = SimConfig::default();
    c.mission.legs = 2;
    c.sensors.depth_camera.rate_hz = 0.0;
    c.sensors.stereo.rate_hz = 0.0;
    c.sensors.buoys.outlier_probability = 0.2;
    c.sensors.buoys.outlier_min_m = 3.0;
    c.sensors.buoys.outliers_both_signs = true;
    let ranges = |c: SimConfig| {
        let (events, _) = run(c);
        events.into_iter().filter_map(|e| if let SimEvent::Buoys(r) = e { Some(r) } else { None }).collect::<Vec<_>>()
    };
    let with = ranges(c.clone());
    c.sensors.buoys.outliers_removed = true;
    let removed = ranges(c.clone());
    c.sensors.buoys.outlier_probability = 0.0;
    let clean = ranges(c);
    assert_eq!(with.len(), removed.len());
    let (mut kept, mut left_out) = (0, 0);
    for ((w, r), k) in with.iter().zip(&removed).zip(&clean) {
        assert_eq!(w.t_s, r.t_s);
        // Every range of the clean run is either an outlier (3 m or more off) in the run with
        // them, and missing from the run with them removed, or the same range in all three.
        let mut rs = r.ranges.iter();
        for (x, y) in w.ranges.iter().zip(&k.ranges) {
            assert_eq!(x.buoy_id, y.buoy_id);
            if (x.range_m - y.range_m).abs() >= 3.0 - 1e-9 {
                left_out += 1;
            } else {
                assert_eq!(x.range_m, y.range_m);
                assert_eq!(rs.next().map(|z| (z.buoy_id, z.range_m)), Some((x.buoy_id, x.range_m)));
                kept += 1;
            }
        }
        assert!(rs.next().is_none(), "a range in the removed run that is not in the clean run");
    }
    let share = left_out as f64 / (kept + left_out) as f64;
    assert!((share - 0.2).abs() < 0.04, "{left_out} left out of {}", kept + left_out);
}

#[test]
fn depth_clouds_lie_on_the_scene_surfaces() {
    let (events, s) = run(short());
    let mut checked = 0;
    for e in &events {
        let SimEvent::Cloud(c) = e else { continue };
        let origin = Point3::from(c.world_from_sensor.translation.vector);
        for p in c.points_sensor_m.iter().step_by(17) {
            let local = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            let dir = c.world_from_sensor.rotation * local.normalize();
            let hit = s.scene().ray_cast(&origin, &dir, 50.0).expect("a surface along the ray");
            assert!((hit - local.norm()).abs() < 0.06, "range {} vs surface at {hit}", local.norm());
            checked += 1;
        }
    }
    assert!(checked > 500, "{checked}");
}

#[test]
fn invalid_configs_are_refused_with_their_keys() {
    let mut c = SimConfig::default();
    c.sensors.depth_camera.width_px = 1000;
    c.scene.buoys_m.truncate(2);
    let Err(sim::SimError::Config(problems)) = Simulator::new(c) else { panic!("accepted") };
    let keys: Vec<_> = problems.iter().map(|i| i.key.as_str()).collect();
    assert!(keys.contains(&"sensors.depth_camera") && keys.contains(&"scene.buoys_m"), "{keys:?}");
}
