//! Prints statistics of the default simulated mission (event counts, observations per frame,
//! attitude range, time to simulate): `cargo run --release -p sim --example sim_stats`.
use sim::{SimConfig, SimEvent, Simulator};

fn main() {
    let t0 = std::time::Instant::now();
    let mut sim = Simulator::new(SimConfig::default()).expect("default config is valid");
    println!("landmarks {}, expected duration {:.0} s", sim.scene().landmark_count, sim.expected_duration_s());
    let (mut odo, mut stereo, mut buoys, mut clouds, mut press) = (0, 0, 0, 0, 0);
    let mut obs_hist = [0usize; 6];
    let mut points = 0usize;
    for e in sim.by_ref() {
        match e {
            SimEvent::Odometry(_) => odo += 1,
            SimEvent::Stereo(f) => {
                stereo += 1;
                let n = f.observations.iter().filter(|o| o.landmark_id.is_some()).count();
                obs_hist[match n {
                    0 => 0,
                    1..=4 => 1,
                    5..=19 => 2,
                    20..=49 => 3,
                    50..=99 => 4,
                    _ => 5,
                }] += 1;
            }
            SimEvent::Buoys(_) => buoys += 1,
            SimEvent::Cloud(c) => {
                clouds += 1;
                points += c.points_sensor_m.len()
            }
            SimEvent::Pressure(_) => press += 1,
            SimEvent::Compass(_) => {}
        }
    }
    let (mut rmax, mut pmax) = (0f64, 0f64);
    for t in sim.truth() {
        let (r, p, _) = t.world_from_body.rotation.euler_angles();
        rmax = rmax.max(r.abs());
        pmax = pmax.max(p.abs());
    }
    println!(
        "t_end {:.1} s: odometry {odo}, stereo {stereo}, buoys {buoys}, clouds {clouds} ({:.0} pts avg), pressure {press}",
        sim.time_s(),
        points as f64 / clouds.max(1) as f64
    );
    println!(
        "real obs per frame: 0:{} 1-4:{} 5-19:{} 20-49:{} 50-99:{} 100+:{}",
        obs_hist[0], obs_hist[1], obs_hist[2], obs_hist[3], obs_hist[4], obs_hist[5]
    );
    println!(
        "max |roll| {:.1} deg, max |pitch| {:.1} deg; simulated in {:.2} s",
        rmax.to_degrees(),
        pmax.to_degrees(),
        t0.elapsed().as_secs_f64()
    );
}
