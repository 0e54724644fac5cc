//! One particle represents no distribution: it takes the improved proposal's mean instead of a
//! draw from it (Grisetti et al. 2007 draw x ~ N(μ, Σ) for a set of particles; with one, the draw
//! only adds Σ as noise at every update, docs/EQUATIONS.md §8). So one particle's path does not
//! depend on the filter's seed, while two particles' paths do.

use grid_slam::{GridSlam, GridSlamConfig, Pose2, ScanGeometry};
use sim::indoor::{IndoorConfig, IndoorEvent, IndoorSim};

/// The best particle's path over the first `scans` laser scans of the simulated indoor mission.
fn path(particles: usize, seed: u64, scans: usize) -> Vec<(f64, Pose2)> {
    let mut sc = IndoorConfig { seed: 1, ..Default::default() };
    sc.depth.rate_hz = 0.0;
    let mut sim = IndoorSim::new(sc.clone()).expect("simulator");
    let l = &sc.laser;
    let geom = ScanGeometry {
        angle_min_rad: -std::f64::consts::PI,
        angle_increment_rad: std::f64::consts::TAU / l.beams as f64,
        beams: l.beams,
        range_min_m: 0.05,
        range_max_m: l.max_range_m,
        body_from_laser: Pose2 { x_m: l.offset_m[0], y_m: l.offset_m[1], theta_rad: 0.0 },
    };
    let cfg = GridSlamConfig { particles, threads: 1, seed, usable_range_m: 12.0, ..Default::default() };
    let mut f = GridSlam::new(cfg, geom).expect("filter");
    let (mut odom, mut seen) = (Pose2::default(), 0);
    while let Some(events) = sim.next_events() {
        for e in events {
            match e {
                IndoorEvent::Odometry { pose, .. } => odom = pose,
                IndoorEvent::Laser { t_s, ranges } => {
                    f.process(t_s, odom, &ranges).expect("scan");
                    seen += 1;
                }
                IndoorEvent::Cloud { .. } => {}
            }
        }
        if seen >= scans {
            break;
        }
    }
    assert!(f.stats().updates >= 10, "the robot moved: {:?}", f.stats());
    f.trajectory()
}

#[test]
fn one_particle_takes_the_proposals_mean_and_two_draw_from_it() {
    let n = 250;
    let (a, b) = (path(1, 1, n), path(1, 2, n));
    assert_eq!(a.len(), b.len());
    assert!(a.iter().zip(&b).all(|(p, q)| p == q), "one particle's path depends on the seed: it drew its poses");
    let (c, d) = (path(2, 1, n), path(2, 2, n));
    let moved = c.iter().zip(&d).map(|(p, q)| (p.1.x_m - q.1.x_m).hypot(p.1.y_m - q.1.y_m)).fold(0.0, f64::max);
    assert!(moved > 1e-4, "two particles' paths should differ with the seed (drawn poses): {moved}");
}
