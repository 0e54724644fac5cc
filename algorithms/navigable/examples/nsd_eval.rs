//! Navigable space and obstacles of the simulated main mission, scored against the scene's truth,
//! without the pipeline: the simulator's depth clouds (`sim::SimConfig::default()`, the main
//! job's mission) inserted into an occupancy map and the point statistics as the octree mapper
//! does, at the true poses or at the poses of a trajectory the main job wrote, then
//! [`navigable::discover`] and [`navigable::truth::score`].
//!
//! ```sh
//! cargo run --release -p navigable --example nsd_eval -- [--poses truth|out/default/fused_live.tum]
//!     [--settings nsd.toml] [--res 0.1] [--clouds N] [--tolerance M] [--landmarks] [--indoor]
//!     [--refresh-every 85] [--repeat N] [--seed S] [--regions] [--ring] [--bench-scene DIR]
//! ```
//!
//! `--bench-scene DIR`: the OctoMap reference benchmark's scene instead (`../shared/bench/octomap`:
//! a 10 × 6 × 3 m room with a table, a box on it, a cabinet, a crate, a shelf, a sideboard, a
//! pillar, a barrel, a bin and a lamp pole; 20 depth frames, 1 mm quantisation, no other noise),
//! `DIR/scans.bin` and `DIR/scene.txt` as `python3 gen_scene.py --out DIR` writes them, at 0.05 m
//! (`--res` after it for another) and 6 m range. Its truth: within the tolerance of a box or a
//! cylinder, an object (touching ones one object: the table and the box on it); of a wall, a
//! wall; of the floor, the ground; the ceiling and the rest, nothing.
//!
//! `--repeat N`: the discovery at the end run N times on the same map (its time as the minimum
//! and the median of the N: one run's time on a shared machine varies by a third).
//!
//! `--seed S`: the simulator's seed (`[processes.ingest.settings.sim] seed`; 1 by default).
//! `--regions`: prints every obstacle and every region but the largest, with the truth of their
//! voxels' points and what lies around them (why a region did not join the ground).
//!
//! `--refresh-every N`: the plane fits refreshed every N clouds, as the mapper does every
//! `fits_refresh_interval_s` (5 s: about 85 of the main job's clouds), so that the discovery
//! at the end, whose time is printed, fits only what changed after the last refresh (0: no
//! refreshes, every voxel fitted at the end).
//!
//! `--ring`: `--indoor` in the 148 m ring building (`config/indoor_ring.toml`'s).
//! `--indoor`: the indoor mission's depth clouds instead (`sim::indoor`, its default building,
//! 0.05 m voxels, 6 m range) against its boxes; with `--poses` a grid SLAM path of the indoor
//! mission (`grid_slam.tum` of `config/indoor.toml`'s run: the body's poses, the depth camera's
//! mounting from the indoor simulator's settings).
//!
//! `--poses FILE`: TUM `world_from_body` poses (interpolated at each cloud's stamp; the depth
//! camera's mounting from the simulator's settings). `--settings`: a TOML file with the keys of
//! `[processes.map.settings.nsd]` (keys it does not give take the crate's defaults; without it,
//! the main job's settings: the defaults with `max_plane_mse_m2 = 0.0004`). Prints the score twice: each voxel judged where the map puts
//! it (the mean of its points, as summary.json `octree_mapper.truth`) and judged by where its
//! points truly came from (each cloud's points at the true pose: the classification alone,
//! without the poses' error). `--landmarks`: also tracks the obstacles of each scan as the mapper
//! does (Bhattacharyya distance 1.0) and judges the landmarks against the objects.

use std::path::PathBuf;
use std::time::Instant;

use nalgebra::{Isometry3, Point3, Vector3};
use navigable::truth::TruthClass;
use navigable::{NsdConfig, PointAccumulator};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut poses: Option<PathBuf> = None;
    let mut settings: Option<PathBuf> = None;
    let mut res = 0.1;
    let mut max_clouds = usize::MAX;
    let mut tolerance = 0.0;
    let mut track = false;
    let mut indoor = false;
    let mut refresh_every = 85usize;
    let mut repeat = 1usize;
    let mut regions_report = false;
    let mut seed: Option<u64> = None;
    let mut ring = false;
    let mut bench_scene: Option<PathBuf> = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = || args.next().ok_or_else(|| format!("{a} needs a value"));
        match a.as_str() {
            "--poses" => {
                let v = value()?;
                poses = (v != "truth").then(|| PathBuf::from(v));
            }
            "--settings" => settings = Some(PathBuf::from(value()?)),
            "--res" => res = value()?.parse()?,
            "--clouds" => max_clouds = value()?.parse()?,
            "--tolerance" => tolerance = value()?.parse()?,
            "--landmarks" => track = true,
            "--indoor" => indoor = true,
            "--ring" => {
                indoor = true;
                ring = true;
            }
            "--refresh-every" => refresh_every = value()?.parse()?,
            "--repeat" => repeat = value()?.parse::<usize>()?.max(1),
            "--regions" => regions_report = true,
            "--seed" => seed = Some(value()?.parse()?),
            "--bench-scene" => {
                bench_scene = Some(PathBuf::from(value()?));
                res = 0.05;
            }
            other => return Err(format!("unknown argument {other}").into()),
        }
    }
    let cfg: NsdConfig = match &settings {
        Some(p) => toml::from_str(&std::fs::read_to_string(p)?)?,
        None => NsdConfig { max_plane_mse_m2: 0.0004, ..Default::default() },
    };
    if indoor {
        res = 0.05;
    }
    let max_range = if indoor || bench_scene.is_some() { 6.0 } else { 14.0 };
    let tolerance = if tolerance > 0.0 { tolerance } else { res };
    let mut sim_cfg = sim::SimConfig::default();
    if let Some(seed) = seed {
        sim_cfg.seed = seed;
    }
    let pitch = sim_cfg.sensors.depth_camera.pitch_down_deg.to_radians();
    let mut body_from_sensor = geometry::body_from_camera(&Vector3::new(0.6, 0.0, -0.3), pitch);
    let trajectory = match &poses {
        Some(p) => Some(geometry::tum::read_tum(p)?),
        None => None,
    };
    // The clouds (stamp, true world_from_sensor, points) and the truth: the underwater mission,
    // or with --indoor the indoor one (its default building, 0.05 m voxels, 6 m range).
    type Cloud = (f64, Isometry3<f64>, Vec<[f32; 3]>);
    type Judge = Box<dyn Fn(&Vector3<f64>) -> TruthClass + Sync>;
    let (clouds_in, judge): (Box<dyn Iterator<Item = Cloud>>, Judge) = if let Some(dir) = &bench_scene {
        use datasets::octomap_bench::{BenchTruth, read_bench_scans, read_bench_scene};
        let scene = read_bench_scene(dir.join("scene.txt"))?;
        // Each frame as a sensor at its origin with the world's axes, a second apart.
        let frames = read_bench_scans(dir.join("scans.bin"))?.into_iter().enumerate().map(|(i, f)| {
            let o = f.origin_m;
            let pose = Isometry3::translation(o[0] as f64, o[1] as f64, o[2] as f64);
            (i as f64, pose, f.points_m.iter().map(|p| [p[0] - o[0], p[1] - o[1], p[2] - o[2]]).collect())
        });
        (
            Box::new(frames),
            Box::new(move |p: &Vector3<f64>| match scene.at([p.x, p.y, p.z], tolerance) {
                BenchTruth::Object(i) => TruthClass::Object(i),
                BenchTruth::Wall => TruthClass::Wall,
                BenchTruth::Floor => TruthClass::Ground,
                BenchTruth::Ceiling | BenchTruth::Nothing => TruthClass::Nothing,
            }),
        )
    } else if indoor {
        let mut indoor_cfg = sim::indoor::IndoorConfig::default();
        if ring {
            indoor_cfg.building = sim::indoor::Building::Ring;
        }
        let mut sim = sim::indoor::IndoorSim::new(indoor_cfg)?;
        body_from_sensor = sim.body_from_camera();
        let truth = sim::indoor::IndoorTruth::new(sim.scene().boxes.iter().map(|b| (b.min, b.max, b.what)));
        let clouds = std::iter::from_fn(move || sim.next_events()).flatten().filter_map(|e| match e {
            sim::indoor::IndoorEvent::Cloud { t_s, world_from_camera, points } => {
                Some((t_s, world_from_camera, points))
            }
            _ => None,
        });
        (
            Box::new(clouds),
            Box::new(move |p: &Vector3<f64>| match truth.at(p, tolerance) {
                sim::indoor::IndoorTruthAt::Floor => TruthClass::Ground,
                sim::indoor::IndoorTruthAt::Object(i) => TruthClass::Object(i),
                sim::indoor::IndoorTruthAt::Wall => TruthClass::Wall,
                sim::indoor::IndoorTruthAt::Nothing => TruthClass::Nothing,
            }),
        )
    } else {
        let simulator = sim::Simulator::new(sim_cfg)?;
        let scene = simulator.scene().clone();
        let rocks = scene.rocks.len() as u32;
        let clouds = simulator.filter_map(|e| match e {
            sim::SimEvent::Cloud(c) => Some((c.t_s, c.world_from_sensor, c.points_sensor_m)),
            _ => None,
        });
        (
            Box::new(clouds),
            Box::new(move |p: &Vector3<f64>| match scene.truth_at(p, tolerance) {
                sim::scene::SceneTruth::Seabed => TruthClass::Ground,
                sim::scene::SceneTruth::Rock(i) => TruthClass::Object(i as u32),
                sim::scene::SceneTruth::Wreck => TruthClass::Object(rocks),
                sim::scene::SceneTruth::Nothing => TruthClass::Nothing,
            }),
        )
    };
    let judge = &*judge;
    let mut tree = octree::OcTree::new(res)?;
    tree.set_ray_threads(2);
    let mut acc = PointAccumulator::new(res);
    acc.track_changes();
    let mut fits = navigable::PlaneFits::new();
    let mut origins = navigable::truth::TrueOrigins::new(res);
    let mut tracker = navigable::ObstacleTracker::default();
    let (mut clouds, mut without_pose, mut moved) = (0usize, 0usize, 0.0);
    let t0 = Instant::now();
    let mut next = 0usize;
    let mut buf = geometry::trajectory::PoseBuffer::default();
    for (t_s, true_pose, points) in clouds_in {
        if clouds >= max_clouds {
            break;
        }
        let world_from_sensor: Isometry3<f64> = match &trajectory {
            None => true_pose,
            Some(tr) => {
                while next < tr.len() && tr[next].0 <= t_s + 1.0 {
                    buf.push(tr[next].0, tr[next].1);
                    next += 1;
                }
                match buf.at(t_s, 1.0) {
                    geometry::trajectory::PoseLookup::Ready(body) => body * body_from_sensor,
                    _ => {
                        without_pose += 1;
                        continue;
                    }
                }
            }
        };
        moved += (world_from_sensor.translation.vector - true_pose.translation.vector).norm();
        let origin = world_from_sensor.translation.vector;
        let world: Vec<[f32; 3]> = points
            .iter()
            .map(|p| {
                let w = world_from_sensor.transform_point(&Point3::new(p[0] as f64, p[1] as f64, p[2] as f64));
                [w.x as f32, w.y as f32, w.z as f32]
            })
            .collect();
        tree.insert_point_cloud(&world, [origin.x, origin.y, origin.z], max_range, false)?;
        let mut scan = PointAccumulator::new(res);
        for (p, s) in world.iter().zip(&points) {
            let v = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            if (v - origin).norm() <= max_range {
                scan.add(&v);
                let t = true_pose.transform_point(&Point3::new(s[0] as f64, s[1] as f64, s[2] as f64));
                origins.add(acc.key(&v), &t.coords);
            }
        }
        acc.merge(&scan)?;
        if track {
            tracker.update(&scan, &cfg, 1.0, (res * 0.5).powi(2))?;
        }
        clouds += 1;
        if refresh_every > 0 && clouds % refresh_every == 0 {
            let changed = acc.take_changed();
            fits.refresh(&acc, changed);
        }
    }
    let inserted_s = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let occupied = |k: &navigable::VoxelKey| {
        let c = [(k[0] as f64 + 0.5) * res, (k[1] as f64 + 0.5) * res, (k[2] as f64 + 0.5) * res];
        match tree.search(c) {
            Some(l) if tree.is_occupied_log_odds(l) => navigable::MapCell::Occupied,
            Some(_) => navigable::MapCell::Free,
            None => navigable::MapCell::Unknown,
        }
    };
    let mut d = navigable::discover_in(&acc, occupied, &cfg, &fits)?;
    let mut times = vec![t1.elapsed().as_secs_f64()];
    for _ in 1..repeat {
        let t = Instant::now();
        d = navigable::discover_in(&acc, occupied, &cfg, &fits)?;
        times.push(t.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    let discover_s = times[0];
    if repeat > 1 {
        println!("discovery over {repeat} runs: min {:.3} s, median {:.3} s", times[0], times[repeat / 2]);
    }
    let c = d.counts();
    println!(
        "{clouds} clouds ({without_pose} without a pose; mean offset from the true sensor position {:.3} m) in {inserted_s:.1} s (plane fits refreshed: {}); discovery {discover_s:.2} s ({} of {} voxels fitted at the end)",
        moved / clouds.max(1) as f64,
        fits.fitted(),
        d.fitted,
        d.classes.len()
    );
    println!(
        "surface sigma {:.4} m, step {:.3} m; voxels: navigable {}, steep {}, non-planar {}, sparse {}, patches {}; obstacles {}",
        d.surface_sigma_m,
        d.step_m,
        c.navigable,
        c.steep,
        c.non_planar,
        c.sparse,
        c.patch,
        d.obstacles.len()
    );
    let mut at_map = navigable::truth::score(&d, &acc, judge);
    if track {
        let means: Vec<(Vector3<f64>, u32)> =
            tracker.landmarks.iter().filter_map(|l| Some((l.stats.mean_cov()?.0, l.scans))).collect();
        let l = navigable::truth::score_landmarks(&means, 2, judge);
        println!(
            "obstacle landmarks: {} in all, {} seen in 2 or more scans, {} of them on objects; {} objects with one, {} with several (at most {})",
            tracker.landmarks.len(),
            l.landmarks,
            l.on_objects,
            l.objects_with_one,
            l.objects_with_several,
            l.most_on_one_object
        );
        // By the truth's object index: the rocks first, the wreck last (the main mission's scene).
        println!("obstacle landmarks per object: {:?}", l.per_object);
        at_map.landmarks = Some(l);
    }
    if regions_report {
        report_regions(&d, &acc, &origins, judge);
    }
    let by_points = origins.score(&d, judge);
    for (name, s) in [("judged where the map puts it", at_map), ("judged by its points' true origin", by_points)] {
        println!(
            "{name}: agreement {:.3}; ground navigable {:.3} ({} voxels); object in obstacles {:.3} ({}); wall in walls {:.3} ({}, walls {}); nothing in none {:.3} ({}); objects {} / {} (split {}), components {} (precision {:.3}); regions {}, largest {:.3} of the ground",
            s.agreement.unwrap_or(f64::NAN),
            s.ground.share().unwrap_or(f64::NAN),
            s.ground.voxels,
            s.object.share().unwrap_or(f64::NAN),
            s.object.voxels,
            s.wall.share().unwrap_or(f64::NAN),
            s.wall.voxels,
            d.walls.len(),
            s.nothing.share().unwrap_or(f64::NAN),
            s.nothing.voxels,
            s.objects_found,
            s.objects_observed,
            s.objects_split,
            s.components,
            s.precision.unwrap_or(f64::NAN),
            s.regions,
            s.largest_region_ground_share.unwrap_or(f64::NAN),
        );
    }
    Ok(())
}

/// `--regions`: every region but the largest, with what its voxels' true origins are and what
/// lies around it (why it did not join its neighbours).
fn report_regions(
    d: &navigable::Discovery,
    acc: &PointAccumulator,
    origins: &navigable::truth::TrueOrigins,
    judge: &(dyn Fn(&Vector3<f64>) -> TruthClass + Sync),
) {
    use navigable::VoxelClass;
    use std::collections::HashMap;
    let mut region_of: HashMap<navigable::VoxelKey, usize> = HashMap::new();
    for (r, reg) in d.regions.iter().enumerate() {
        for k in &reg.voxels {
            region_of.insert(*k, r);
        }
    }
    let mut obstacle_of: HashMap<navigable::VoxelKey, usize> = HashMap::new();
    for (o, ob) in d.obstacles.iter().enumerate() {
        for k in &ob.voxels {
            obstacle_of.insert(*k, o);
        }
    }
    let max_cos = 20f64.to_radians().cos();
    for (w, wall) in d.walls.iter().enumerate() {
        let mut truth = std::collections::BTreeMap::new();
        for k in &wall.voxels {
            *truth.entry(format!("{:?}", origins.mean(k).map(|m| judge(&m)))).or_insert(0) += 1;
        }
        let n = wall.voxels.len().max(1) as f64;
        let c = wall.voxels.iter().fold(Vector3::zeros(), |a, k| a + acc.centre(k)) / n;
        println!(
            "wall {w}: {} voxels at ({:.1}, {:.1}, {:.2}), normal ({:.2}, {:.2}, {:.2}); origins {truth:?}",
            wall.voxels.len(),
            c.x,
            c.y,
            c.z,
            wall.normal.x,
            wall.normal.y,
            wall.normal.z
        );
    }
    for (o, ob) in d.obstacles.iter().enumerate() {
        let (mut ground, mut object, mut wall, mut other) = (0, 0, 0, 0);
        let mut objects = std::collections::BTreeMap::new();
        let (mut steep, mut nonplanar, mut nav, mut sparse) = (0, 0, 0, 0);
        let mut zs = vec![];
        for k in &ob.voxels {
            zs.push(acc.centre(k).z);
            match origins.mean(k).map(|m| judge(&m)) {
                Some(TruthClass::Ground) => ground += 1,
                Some(TruthClass::Object(i)) => {
                    object += 1;
                    *objects.entry(i).or_insert(0) += 1;
                }
                Some(TruthClass::Wall) => wall += 1,
                _ => other += 1,
            }
            match d.classes.get(k) {
                Some(VoxelClass::Steep(_)) => steep += 1,
                Some(VoxelClass::NonPlanar) => nonplanar += 1,
                Some(VoxelClass::Navigable(_)) => nav += 1,
                _ => sparse += 1,
            }
        }
        // Around: the largest region's voxels beside it, their z.
        let mut foot = vec![];
        for k in &ob.voxels {
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        let n = [k[0] + dx, k[1] + dy, k[2] + dz];
                        if region_of.get(&n) == Some(&0) {
                            foot.push(acc.centre(&n).z);
                        }
                    }
                }
            }
        }
        foot.sort_by(f64::total_cmp);
        zs.sort_by(f64::total_cmp);
        let f = foot.get(foot.len() / 2).copied().unwrap_or(f64::NAN);
        println!(
            "obstacle {o}: {} voxels at ({:.1}, {:.1}, {:.2}); origins ground {ground} object {object} {:?} wall {wall} other {other}; steep {steep} non-planar {nonplanar} navigable {nav} sparse {sparse}; foot {} voxels, top {:.2} m above it, median {:.2}",
            ob.voxels.len(),
            ob.mean_m.x,
            ob.mean_m.y,
            ob.mean_m.z,
            objects,
            foot.len(),
            zs.last().unwrap() - f,
            zs[zs.len() / 2] - f
        );
    }
    for (r, reg) in d.regions.iter().enumerate() {
        let (mut ground, mut object, mut nothing) = (0, 0, 0);
        let mut centre = Vector3::zeros();
        for k in &reg.voxels {
            centre += acc.centre(k);
            match origins.mean(k).map(|m| judge(&m)) {
                Some(TruthClass::Ground) => ground += 1,
                Some(TruthClass::Object(_)) => object += 1,
                _ => nothing += 1,
            }
        }
        centre /= reg.voxels.len() as f64;
        let mut zs: Vec<f64> = reg.voxels.iter().map(|k| acc.centre(k).z).collect();
        zs.sort_by(f64::total_cmp);
        let q = |x: f64| zs[((zs.len() as f64 - 1.0) * x) as usize];
        println!(
            "  region {r} z: q01 {:.2} q10 {:.2} q50 {:.2} q90 {:.2} q99 {:.2}",
            q(0.01),
            q(0.1),
            q(0.5),
            q(0.9),
            q(0.99)
        );
        // Around: (other region: normal fails, step fails, joinable), obstacle, sparse, patch, absent.
        let (mut normal_fail, mut step_fail, mut other_ok, mut obst, mut sparse, mut patch, mut absent) =
            (0, 0, 0, 0, 0, 0, 0);
        let mut step_gaps = vec![];
        let mut other_regions = std::collections::BTreeSet::new();
        for k in &reg.voxels {
            let Some(VoxelClass::Navigable(a)) = d.classes.get(k) else { continue };
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        if (dx, dy, dz) == (0, 0, 0) {
                            continue;
                        }
                        let n = [k[0] + dx, k[1] + dy, k[2] + dz];
                        match d.classes.get(&n) {
                            None => absent += 1,
                            Some(VoxelClass::Navigable(b)) => {
                                let Some(&o) = region_of.get(&n) else { continue };
                                if o == r {
                                    continue;
                                }
                                other_regions.insert(o);
                                let touch = (acc.centre(k) + acc.centre(&n)) * 0.5;
                                let gap = (a.project(&touch) - b.project(&touch)).norm();
                                if a.normal.dot(&b.normal) < max_cos {
                                    normal_fail += 1;
                                } else if gap > d.step_m {
                                    step_fail += 1;
                                    step_gaps.push(gap);
                                } else {
                                    other_ok += 1;
                                }
                            }
                            Some(VoxelClass::Sparse) => sparse += 1,
                            Some(VoxelClass::Patch(_)) => patch += 1,
                            Some(_) => {
                                if obstacle_of.contains_key(&n) {
                                    obst += 1
                                } else {
                                    sparse += 1
                                }
                            }
                        }
                    }
                }
            }
        }
        // Height above the foot of each obstacle touched: the largest region's voxels beside it.
        let mut heights = vec![];
        {
            let mut touched = std::collections::BTreeSet::new();
            for k in &reg.voxels {
                for dx in -1..=1 {
                    for dy in -1..=1 {
                        for dz in -1..=1 {
                            if let Some(&o) = obstacle_of.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) {
                                touched.insert(o);
                            }
                        }
                    }
                }
            }
            for o in touched {
                let mut foot = vec![];
                let mut top: f64 = f64::NEG_INFINITY;
                for k in &d.obstacles[o].voxels {
                    top = top.max(acc.centre(k).z);
                    for dx in -1..=1 {
                        for dy in -1..=1 {
                            for dz in -1..=1 {
                                let n = [k[0] + dx, k[1] + dy, k[2] + dz];
                                if region_of.get(&n) == Some(&0) {
                                    foot.push(acc.centre(&n).z);
                                }
                            }
                        }
                    }
                }
                if foot.is_empty() {
                    heights.push((o, f64::NAN, f64::NAN));
                    continue;
                }
                foot.sort_by(f64::total_cmp);
                let f = foot[foot.len() / 2];
                let mut zs: Vec<f64> = reg.voxels.iter().map(|k| acc.centre(k).z - f).collect();
                zs.sort_by(f64::total_cmp);
                heights.push((o, zs[zs.len() / 2], top - f));
            }
        }
        let heights: Vec<String> = heights.iter().map(|(o, h, t)| format!("o{o}: {h:.2}/{t:.2}")).collect();
        println!("  heights above foot (region/obstacle top): {}", heights.join(", "));
        step_gaps.sort_by(f64::total_cmp);
        let med = step_gaps.get(step_gaps.len() / 2).copied().unwrap_or(0.0);
        println!(
            "region {r}: {} voxels at ({:.1}, {:.1}, {:.2}), slope {:.1} deg; origins ground {ground} object {object} none {nothing}; around: other regions {:?} (normal {normal_fail}, step {step_fail} median {med:.3} m, joinable {other_ok}), obstacle {obst}, sparse/unjoined {sparse}, patch {patch}, absent {absent}",
            reg.voxels.len(),
            centre.x,
            centre.y,
            centre.z,
            reg.normal.z.clamp(-1.0, 1.0).acos().to_degrees(),
            other_regions.iter().take(5).collect::<Vec<_>>()
        );
    }
}
