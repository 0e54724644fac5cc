//! Statistics of the KITTI-like stereo drive (`sim::road`): features per frame, depths, motion
//! between frames: `cargo run --release -p sim --example road_stats`.

fn main() {
    let mut sim = sim::road::RoadSim::new(sim::road::RoadConfig::default()).expect("valid defaults");
    let (mut n, mut frames, mut wrong, mut spurious) = (0usize, 0usize, 0usize, 0usize);
    let mut depths = vec![];
    let mut prev: Option<usize> = None;
    let mut steps = vec![];
    let truth: Vec<_> = sim.truth().to_vec();
    for f in sim.by_ref() {
        frames += 1;
        n += f.observations.len();
        wrong += f.observations.iter().filter(|o| o.wrong_match).count();
        spurious += f.observations.iter().filter(|o| o.landmark_id.is_none()).count();
        depths.extend(f.observations.iter().map(|o| o.point_cam_m.z));
        if let Some(p) = prev {
            let d = truth[p].world_from_body.inverse() * truth[f.index].world_from_body;
            steps.push((d.translation.vector.norm(), d.rotation.angle().to_degrees()));
        }
        prev = Some(f.index);
    }
    depths.sort_by(f64::total_cmp);
    let q = |v: &[f64], p: f64| v[((v.len() - 1) as f64 * p) as usize];
    let max_step = steps.iter().fold((0.0f64, 0.0f64), |m, s| (m.0.max(s.0), m.1.max(s.1)));
    println!(
        "{frames} frames ({} dropped), {:.0} features/frame ({wrong} wrong matches, {spurious} spurious), {} landmarks, path {:.0} m",
        sim.dropped(),
        n as f64 / frames as f64,
        sim.landmark_count(),
        sim.path_length_m()
    );
    println!(
        "depth p5 {:.1} m, p50 {:.1} m, p95 {:.1} m, max {:.1} m; largest step between frames {:.2} m, {:.1}°",
        q(&depths, 0.05),
        q(&depths, 0.5),
        q(&depths, 0.95),
        depths.last().unwrap(),
        max_step.0,
        max_step.1
    );
}
