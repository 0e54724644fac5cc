//! Navigable space and obstacles of the simulated main mission, scored against the scene's truth,
//! without the pipeline: the simulator's depth clouds (`sim::SimConfig::default()`, the main
//! job's mission) inserted into an occupancy map and the point statistics as the octree mapper
//! does, at the true poses or at the poses of a trajectory the main job wrote, then
//! [`navigable::discover`] and [`navigable::truth::score`].
//!
//! ```sh
//! cargo run --release -p navigable --example nsd_eval -- [--poses truth|out/default/fused_live.tum]
//!     [--settings nsd.toml] [--res 0.1] [--clouds N] [--tolerance M]
//! ```
//!
//! `--poses FILE`: TUM `world_from_body` poses (interpolated at each cloud's stamp; the depth
//! camera's mounting from the simulator's settings). `--settings`: a TOML file with the keys of
//! `[processes.map.settings.nsd]`. Prints the score twice: each voxel judged where the map puts
//! it (the mean of its points, as summary.json `octree_mapper.truth`) and judged by where its
//! points truly came from (each cloud's points at the true pose: the classification alone,
//! without the poses' error).

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
            other => return Err(format!("unknown argument {other}").into()),
        }
    }
    let cfg: NsdConfig = match &settings {
        Some(p) => toml::from_str(&std::fs::read_to_string(p)?)?,
        None => NsdConfig { max_plane_mse_m2: 0.0004, ..Default::default() },
    };
    let tolerance = if tolerance > 0.0 { tolerance } else { res };
    let sim_cfg = sim::SimConfig::default();
    let pitch = sim_cfg.sensors.depth_camera.pitch_down_deg.to_radians();
    let body_from_sensor = geometry::body_from_camera(&Vector3::new(0.6, 0.0, -0.3), pitch);
    let trajectory = match &poses {
        Some(p) => Some(geometry::tum::read_tum(p)?),
        None => None,
    };
    let simulator = sim::Simulator::new(sim_cfg)?;
    let scene = simulator.scene().clone();
    let rocks = scene.rocks.len() as u32;
    let judge = |p: &Vector3<f64>| match scene.truth_at(p, tolerance) {
        sim::scene::SceneTruth::Seabed => TruthClass::Ground,
        sim::scene::SceneTruth::Rock(i) => TruthClass::Object(i as u32),
        sim::scene::SceneTruth::Wreck => TruthClass::Object(rocks),
        sim::scene::SceneTruth::Nothing => TruthClass::Nothing,
    };
    let mut tree = octree::OcTree::new(res)?;
    tree.set_ray_threads(2);
    let mut acc = PointAccumulator::new(res);
    let mut origins = navigable::truth::TrueOrigins::new(res);
    let (mut clouds, mut without_pose, mut moved) = (0usize, 0usize, 0.0);
    let t0 = Instant::now();
    let mut next = 0usize;
    let mut buf = geometry::trajectory::PoseBuffer::default();
    for event in simulator {
        let sim::SimEvent::Cloud(c) = event else { continue };
        if clouds >= max_clouds {
            break;
        }
        let world_from_sensor: Isometry3<f64> = match &trajectory {
            None => c.world_from_sensor,
            Some(tr) => {
                while next < tr.len() && tr[next].0 <= c.t_s + 1.0 {
                    buf.push(tr[next].0, tr[next].1);
                    next += 1;
                }
                match buf.at(c.t_s, 1.0) {
                    geometry::trajectory::PoseLookup::Ready(body) => body * body_from_sensor,
                    _ => {
                        without_pose += 1;
                        continue;
                    }
                }
            }
        };
        moved += (world_from_sensor.translation.vector - c.world_from_sensor.translation.vector).norm();
        let origin = world_from_sensor.translation.vector;
        let world: Vec<[f32; 3]> = c
            .points_sensor_m
            .iter()
            .map(|p| {
                let w = world_from_sensor.transform_point(&Point3::new(p[0] as f64, p[1] as f64, p[2] as f64));
                [w.x as f32, w.y as f32, w.z as f32]
            })
            .collect();
        tree.insert_point_cloud(&world, [origin.x, origin.y, origin.z], 14.0, false)?;
        let mut scan = PointAccumulator::new(res);
        for (p, s) in world.iter().zip(&c.points_sensor_m) {
            let v = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            if (v - origin).norm() <= 14.0 {
                scan.add(&v);
                let t = c.world_from_sensor.transform_point(&Point3::new(s[0] as f64, s[1] as f64, s[2] as f64));
                origins.add(acc.key(&v), &t.coords);
            }
        }
        acc.merge(&scan)?;
        clouds += 1;
    }
    let inserted_s = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let occupied = |k: &navigable::VoxelKey| {
        let c = [(k[0] as f64 + 0.5) * res, (k[1] as f64 + 0.5) * res, (k[2] as f64 + 0.5) * res];
        tree.is_occupied(c).unwrap_or(false)
    };
    let d = navigable::discover(&acc, occupied, &cfg)?;
    let discover_s = t1.elapsed().as_secs_f64();
    let c = d.counts();
    println!(
        "{clouds} clouds ({without_pose} without a pose; mean offset from the true sensor position {:.3} m) in {inserted_s:.1} s; discovery {discover_s:.2} s",
        moved / clouds.max(1) as f64
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
    let at_map = navigable::truth::score(&d, &acc, judge);
    let by_points = origins.score(&d, judge);
    for (name, s) in [("judged where the map puts it", at_map), ("judged by its points' true origin", by_points)] {
        println!(
            "{name}: agreement {:.3}; ground navigable {:.3} ({} voxels); object in obstacles {:.3} ({}); nothing in neither {:.3} ({}); objects {} / {} (split {}), components {} (precision {:.3}); regions {}, largest {:.3} of the ground",
            s.agreement.unwrap_or(f64::NAN),
            s.ground.share().unwrap_or(f64::NAN),
            s.ground.voxels,
            s.object.share().unwrap_or(f64::NAN),
            s.object.voxels,
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
