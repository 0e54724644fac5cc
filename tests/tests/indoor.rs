//! The simulated indoor mission of the omni-directional robot end to end under the supervisor
//! (config/indoor.toml's processes, 10 particles): grid SLAM on the laser and the wheel encoders,
//! the 3-D map built from the depth camera at the 2-D SLAM poses and rebuilt along the final path.
//! Checks the trajectory against the ground truth, the 2-D map against the true walls, and the 3-D
//! map against the scene's true occupancy (scene.json), including the furniture that differs
//! between the laser's plane and the 3-D scene (a table top, a crate below the laser). A live view
//! (`kind = "viewer"`) runs along: a Foxglove WebSocket client (tests/python/foxglove_ws_client.py)
//! receives the 2-D map (`/grid`) and the grid SLAM path (`/grid_slam/path`) while the run goes on.

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::Duration;

use pipeline_tests::TestRun;

/// Distance from a point to an axis-aligned box (0 inside).
fn box_distance(p: [f64; 3], min: [f64; 3], max: [f64; 3]) -> f64 {
    (0..3).map(|i| (min[i] - p[i]).max(p[i] - max[i]).max(0.0).powi(2)).sum::<f64>().sqrt()
}

#[test]
fn the_indoor_mission_maps_in_2d_and_3d_at_the_grid_slam_poses() {
    let _heavy = pipeline_tests::heavy();
    let mut run = TestRun::new("indoor");
    let processes = r#"
[processes.slam2d]
kind = "grid_slam"
[processes.slam2d.settings]
grid_every_s = 5.0
[processes.slam2d.settings.filter]
particles = 10
resolution_m = 0.05
usable_range_m = 12.0
threads = 2
linear_update_m = 0.25
angular_update_rad = 0.125

[processes.map]
kind = "octree_mapper"
[processes.map.settings]
resolution_m = 0.05
pose_source = "grid_slam"
max_range_m = 6.0
end_after = ["ingest", "slam2d"]
rebuild_from = "grid_slam.tum"
traversability_interval_s = 5.0
truth_scene = "scene.json"
[processes.map.settings.mount]
offset_m = [0.1, 0.0, 0.6]
pitch_down_deg = 10.0

[processes.ingest]
kind = "ingest"
after = ["slam2d", "map", "view"]
[processes.ingest.settings]
source = "indoor"
real_time_factor = 0.0

[processes.view]
kind = "viewer"
[processes.view.settings]
port = PORT
"#;
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let processes = processes.replace("PORT", &port.to_string());
    let cfg = run.write_config("end = \"end_of_stream\"\nend_of_stream_from = [\"slam2d\", \"map\"]", &processes);
    run.start_supervisor(&cfg, &[]);
    // The client connects (retrying until the viewer listens) while the mission runs, and stops
    // once it has had two of each (or reports what came when the run ends first).
    let client = Command::new("python3")
        .arg(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python/foxglove_ws_client.py"))
        .args(["--url", &format!("ws://127.0.0.1:{port}"), "--timeout-s", "400", "--min-messages", "2"])
        .args(["--want", "/grid", "--want", "/grid_slam/path", "--at-least", "/grid_slam/path", "poses", "2"])
        .args(["--want", "/traversability"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("python3 runs the Foxglove client");
    let status = run.wait_supervisor(Duration::from_secs(600)).expect("the run ends");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    assert_eq!(run.leftovers(), Vec::<PathBuf>::new(), "iceoryx2 files left behind");
    let summary = run.summary();
    // Every key is declared in docs/summary.schema.json (ingest, grid_slam, octree_mapper, viewer).
    crate::summary_schema::assert_declared(&summary);
    crate::summary_schema::assert_valid_by_jsonschema(&run.out_dir().join("summary.json"));
    let seen = client.wait_with_output().expect("the client ends");
    let stdout = String::from_utf8_lossy(&seen.stdout);
    assert!(seen.status.success(), "client: {}\n{stdout}", String::from_utf8_lossy(&seen.stderr));
    let seen: serde_json::Value = serde_json::from_str(stdout.trim()).expect("the client's JSON");
    let (grid, path) = (&seen["topics"]["/grid"], &seen["topics"]["/grid_slam/path"]);
    assert_eq!(grid["schema"], "foxglove.Grid", "{seen:#}");
    assert_eq!(grid["last"]["frame_id"], "world", "{seen:#}");
    // The building is 16 x 12 m: a map of at least a room at 0.05 m cells, one byte each.
    let columns = grid["last"]["columns"].as_u64().unwrap_or(0);
    assert!(columns >= 40 && grid["last"]["cells"].as_u64().unwrap_or(0) >= 40 * columns, "{seen:#}");
    assert!((grid["last"]["cell_size"].as_f64().unwrap_or(0.0) - 0.05).abs() < 1e-9, "{seen:#}");
    // The mapper's 2.5-D traversability grid of the map so far (`traversability_interval_s`):
    // the floor navigable, the furniture and walls obstacles, at the map's 0.05 m, every cell's
    // height finite (0 where unknown: the class says what is defined).
    let trav = &seen["topics"]["/traversability"];
    assert_eq!(trav["schema"], "foxglove.Grid", "{seen:#}");
    assert_eq!(trav["last"]["fields"], serde_json::json!(["height", "slope", "class"]), "{seen:#}");
    assert!((trav["last"]["cell_size"].as_f64().unwrap_or(0.0) - 0.05).abs() < 1e-9, "{seen:#}");
    assert_eq!(trav["last"]["heights_finite"], true, "{seen:#}");
    eprintln!("traversability grid: {}", trav["last"]);
    let class = |c: &str| trav["last"]["class_counts"][c].as_u64().unwrap_or(0);
    assert!(class("1") >= 400 && class("2") >= 40, "a floor of 1 m² and obstacles: {seen:#}");
    assert_eq!(path["schema"], "foxglove.PosesInFrame", "{seen:#}");
    assert!(path["last"]["poses"].as_u64().unwrap_or(0) >= 2, "{seen:#}");
    assert_eq!(path["last"]["finite"], true, "{seen:#}");
    assert_eq!(path["last"]["frame_id"], "world", "{seen:#}");
    use crate::summary_schema::part;
    let grid: grid_slam_stage::summary::GridSlamPart = part(&summary);
    let mapper: octree_mapper_stage::summary::OctreeMapperPart = part(&summary);
    let ingest: ingest_stage::summary::IngestPart = part(&summary);
    let ate = grid.ate_m.as_ref().and_then(|a| a.grid_slam).expect("ATE");
    let g = grid.grid_slam.run.as_ref().expect("the filter ran");
    let m = &mapper.octree_mapper;
    let rebuild = m.end_of_stream.as_ref().and_then(|e| e.rebuild.as_ref()).expect("the map was rebuilt");
    eprintln!(
        "ATE {ate:.3} m; grid_slam {}; mapper counters {:?} rebuild {rebuild:?}",
        summary["grid_slam"], m.counters
    );
    assert!(ate <= 0.05, "ATE {ate}");
    // The pose graph ran behind the filter (the default) and closed the laps' loops.
    let be = &g.back_end;
    assert_eq!(be.kind, grid_slam_stage::BackEndKind::PoseGraph, "{be:?}");
    assert!(be.error.is_none(), "{be:?}");
    let report = be.report.as_ref().expect("the back end's report");
    assert!(report.loop_constraints > 20, "{report:?}");
    assert!(report.max_correction_m < 0.5, "{report:?}");
    assert_eq!(grid.grid_slam.scans, ingest.ingest.messages.laser, "every scan mapped");
    let clouds = ingest.ingest.messages.cloud;
    assert_eq!(m.counters.clouds_inserted, clouds, "every cloud in the live map: {m:?}");
    assert_eq!(rebuild.clouds as u64, clouds, "every cloud in the rebuilt map: {rebuild:?}");
    assert_eq!(rebuild.clouds_without_pose, 0);
    // The navigable space and obstacles scored against the scene's boxes (issue 39,
    // docs/octree_mapper.md): every classified voxel judged, the floor and the furniture seen;
    // the floor one region. Since 2026-12-07 the walls are a class of their own (EQUATIONS §7
    // "Walls"), in the map and in the truth: the furniture against them is found (8 of 8 pieces
    // of furniture, where 6 of 8 were before, two merged with the walls), and the components
    // left on walls count against the precision: 0.833 at these grid SLAM poses until a wall's
    // front was judged by the floor beyond its thickness (the floor right under a wall the
    // poses' error doubled lies on both sides of it) and what stands out of a wall by under two
    // voxels was taken as the wall's (a pass's sheet a few centimetres off): 0.909 since
    // (2026-12-07), 1.000 at the true poses (`nsd_eval --indoor`; `--indoor --poses
    // <grid_slam.tum>` gives this run's numbers offline). The issue's 0.9.
    let end = m.end_of_stream.as_ref().expect("the end of stream's navigable space");
    let truth = end.truth.as_ref().expect("the layers scored against scene.json");
    let v = &end.voxels;
    eprintln!("against the truth: {truth:?}");
    let by_origin = end.truth_by_origin.as_ref().expect("the clouds carry the simulator's true poses");
    eprintln!("judged by origin: {by_origin:?}");
    assert_eq!(truth.voxels, v.navigable + v.steep + v.non_planar + v.sparse + v.patch + v.wall, "{truth:?}");
    assert!(truth.ground.voxels > 0 && truth.objects_observed >= 3, "{truth:?}");
    assert!(truth.largest_region_ground_share.is_some_and(|s| s >= 0.9), "{truth:?}");
    assert!(truth.regions <= 50, "{truth:?}");
    assert!(truth.precision.is_some_and(|p| p >= 0.9), "{truth:?}");
    assert!(truth.recall.is_some_and(|r| r >= 0.9), "{truth:?}");
    assert!(truth.wall.share().is_some_and(|s| s >= 0.9), "{truth:?}");
    assert!(truth.agreement.is_some_and(|a| a >= 0.8), "{truth:?}");
    // Judged where each voxel's points truly came from (the classification without the poses'
    // error): issue 39's 95 %. Since a column of steep surface is filled from its top down
    // (EQUATIONS §7, 2026-12-07) the floor region no longer climbs the walls seen a line per
    // scan: 0.928 before, 0.966 at the true poses (`nsd_eval --poses truth --indoor`).
    assert!(by_origin.agreement.is_some_and(|a| a >= 0.95), "{by_origin:?}");
    assert!(by_origin.regions <= 50 && by_origin.precision.is_some_and(|p| p >= 0.9), "{by_origin:?}");
    assert!(by_origin.recall.is_some_and(|r| r >= 0.9), "{by_origin:?}");

    let out = run.out_dir();
    let scene: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("scene.json")).unwrap()).unwrap();
    let boxes: Vec<(String, [f64; 3], [f64; 3])> = scene["boxes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| {
            let v = |k: &str| -> [f64; 3] {
                let a = b[k].as_array().unwrap();
                [a[0].as_f64().unwrap(), a[1].as_f64().unwrap(), a[2].as_f64().unwrap()]
            };
            (b["what"].as_str().unwrap().to_string(), v("min"), v("max"))
        })
        .collect();

    // 2-D: the walls' inner faces at the laser's height, occupied within one cell in grid.pgm.
    let yaml = std::fs::read_to_string(out.join("grid.yaml")).unwrap();
    let origin: Vec<f64> = yaml
        .lines()
        .find_map(|l| l.strip_prefix("origin: ["))
        .unwrap()
        .trim_end_matches(']')
        .split(',')
        .map(|x| x.trim().parse().unwrap())
        .collect();
    let pgm = std::fs::read(out.join("grid.pgm")).unwrap();
    let text = String::from_utf8_lossy(&pgm[..64]).to_string();
    let dims: Vec<usize> = text.lines().nth(2).unwrap().split_whitespace().map(|x| x.parse().unwrap()).collect();
    let (w, h) = (dims[0], dims[1]);
    let data = &pgm[pgm.len() - w * h..];
    let occupied_2d = |x: f64, y: f64| -> bool {
        let (i, j) = (((x - origin[0]) / 0.05).floor() as i64, ((y - origin[1]) / 0.05).floor() as i64);
        (-1..=1).any(|di| {
            (-1..=1).any(|dj| {
                let (a, b) = (i + di, j + dj);
                a >= 0
                    && b >= 0
                    && (a as usize) < w
                    && (b as usize) < h
                    && data[(h - 1 - b as usize) * w + a as usize] == 0
            })
        })
    };
    // Every vertical face of every wall longer than 0.2 m, sampled 2 cm off it inside the
    // building, except where furniture stands in front of it (a shelf, the radiator).
    let inside = |x: f64, y: f64| x > -8.0 && x < 8.0 && y > -5.0 && y < 7.0;
    let blocked = |x: f64, y: f64| {
        boxes.iter().filter(|(w, _, _)| w != "wall").any(|(_, min, max)| {
            min[2] <= 0.25
                && max[2] >= 0.25
                && x >= min[0] - 0.1
                && x <= max[0] + 0.1
                && y >= min[1] - 0.1
                && y <= max[1] + 0.1
        })
    };
    let (mut on, mut all) = (0usize, 0usize);
    for (what, min, max) in &boxes {
        if what != "wall" {
            continue;
        }
        let mut faces: Vec<(f64, f64)> = vec![];
        let (nx, ny) = (((max[0] - min[0]) / 0.05) as usize, ((max[1] - min[1]) / 0.05) as usize);
        if nx > 4 {
            for k in 1..nx {
                let x = min[0] + k as f64 * 0.05;
                faces.push((x, min[1] - 0.02));
                faces.push((x, max[1] + 0.02));
            }
        }
        if ny > 4 {
            for k in 1..ny {
                let y = min[1] + k as f64 * 0.05;
                faces.push((min[0] - 0.02, y));
                faces.push((max[0] + 0.02, y));
            }
        }
        for (x, y) in faces {
            if !inside(x, y) || blocked(x, y) {
                continue;
            }
            all += 1;
            on += usize::from(occupied_2d(x, y));
        }
    }
    let wall_share = on as f64 / all as f64;
    // Below the laser's plane: the crate is not in the 2-D map.
    let crate_in_2d = occupied_2d(-3.5, -4.3);

    // 3-D: occupied voxels on true surfaces (precision), and the furniture seen.
    let tree = octree::OcTree::read_binary_file(out.join("map.bt")).unwrap();
    let res = tree.resolution();
    let (mut near, mut occ) = (0usize, 0usize);
    for l in tree.leaves().filter(|l| tree.is_occupied_log_odds(l.log_odds) && l.depth >= 16) {
        let c = tree.key_to_coord(l.key);
        occ += 1;
        if boxes.iter().any(|(_, min, max)| box_distance(c, *min, *max) <= res) {
            near += 1;
        }
    }
    let precision = near as f64 / occ as f64;
    // Occupied voxels on each table top (above its legs' height), and on the crate.
    let on_box = |what: &str| -> Vec<usize> {
        boxes
            .iter()
            .filter(|(w, _, _)| w == what)
            .map(|(_, min, max)| {
                tree.leaves()
                    .filter(|l| tree.is_occupied_log_odds(l.log_odds) && l.depth >= 16)
                    .filter(|l| box_distance(tree.key_to_coord(l.key), *min, *max) <= 0.5 * res)
                    .count()
            })
            .collect()
    };
    let tops = on_box("table_top");
    let table_tops = tops.iter().filter(|n| **n >= 5).count();
    let crate_3d = on_box("crate").iter().all(|n| *n >= 5);
    let live = octree::OcTree::read_binary_file(out.join("map_live.bt")).unwrap();
    let (live_occ, _) = live.num_occupied_free_leaves();

    // Agreement with the reference map: the same clouds (the simulator is deterministic) inserted
    // at the camera's true poses, same resolution, range and sensor model; per leaf of the
    // reference, whether our map says the same at its centre (as octree_bench compares with OctoMap).
    let mut sim = sim::indoor::IndoorSim::new(sim::indoor::IndoorConfig::default()).unwrap();
    let mut reference = octree::OcTree::with_model(res, octree::SensorModel::default()).unwrap();
    reference.set_ray_threads(2);
    while let Some(events) = sim.next_events() {
        for e in events {
            if let sim::indoor::IndoorEvent::Cloud { world_from_camera, points, .. } = e {
                let world: Vec<[f32; 3]> = points
                    .iter()
                    .map(|p| {
                        let w = world_from_camera.transform_point(&nalgebra::Point3::new(
                            p[0] as f64,
                            p[1] as f64,
                            p[2] as f64,
                        ));
                        [w.x as f32, w.y as f32, w.z as f32]
                    })
                    .collect();
                let o = world_from_camera.translation.vector;
                reference.insert_point_cloud(&world, [o.x, o.y, o.z], 6.0, false).unwrap();
            }
        }
    }
    let agree = |map: &octree::OcTree| -> (f64, f64) {
        let (mut occ_n, mut occ_ok, mut free_n, mut free_ok) = (0usize, 0usize, 0usize, 0usize);
        for l in reference.leaves() {
            let c = reference.key_to_coord(l.key);
            let theirs = map.is_occupied(c);
            if reference.is_occupied_log_odds(l.log_odds) {
                occ_n += 1;
                occ_ok += usize::from(theirs == Some(true));
            } else {
                free_n += 1;
                free_ok += usize::from(theirs == Some(false));
            }
        }
        (occ_ok as f64 / occ_n as f64, free_ok as f64 / free_n as f64)
    };
    let (occ_agree, free_agree) = agree(&tree);
    let (live_occ_agree, live_free_agree) = agree(&live);
    eprintln!(
        "2-D walls occupied within one cell: {:.1}% of {all}; crate in the 2-D map: {crate_in_2d}; \
         3-D occupied voxels on true surfaces (within {res} m): {:.1}% of {occ} (live map {live_occ} occupied leaves); \
         table-top voxels {tops:?}, crate seen {crate_3d}; agreement with the map at the true poses: \
         occupied {:.1}%, free {:.1}% (live map: {:.1}%, {:.1}%)",
        100.0 * wall_share,
        100.0 * precision,
        100.0 * occ_agree,
        100.0 * free_agree,
        100.0 * live_occ_agree,
        100.0 * live_free_agree
    );
    assert!(wall_share >= 0.95, "{wall_share}");
    assert!(!crate_in_2d, "the crate is below the laser's plane");
    assert!(precision >= 0.95, "{precision}");
    assert!(table_tops == 2 && crate_3d, "the 3-D map holds what the laser cannot see");
    assert!(occ_agree >= 0.85 && free_agree >= 0.93, "agreement with the true-pose map: {occ_agree} {free_agree}");
}
