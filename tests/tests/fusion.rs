//! The fusion and octree-mapping stages end to end: the default config (config/default.toml, the processes exactly as
//! the main job runs them) must end with a fused global path at most 0.8 of the buoy-only path's
//! error and better than the SLAM path, with an honest SLAM covariance, and write every output the
//! docs/fusion.md lists.

use std::time::Duration;

use pipeline_tests::TestRun;

#[test]
fn the_default_config_ends_with_a_fused_path_better_than_buoy_and_slam() {
    let _heavy = pipeline_tests::heavy();
    let path = format!("{}/../config/default.toml", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).expect("config/default.toml");
    let config: toml::Table = text.parse().expect("valid TOML");
    let run = config["run"].as_table().expect("[run]");
    let processes = toml::to_string(&toml::Table::from_iter([("processes".to_string(), config["processes"].clone())]))
        .expect("processes as TOML");
    let run_extra =
        format!("end = {}\nend_of_stream_from = {}\nduration_s = 600", run["end"], run["end_of_stream_from"]);
    let mut t = TestRun::new("fusiondefault");
    let s = t.run_to_end(&run_extra, &processes, Duration::from_secs(600));
    // Every key of the main job's summary is declared in docs/summary.schema.json, with its type,
    // and the whole file reads as its parts' structs.
    let all = crate::summary_schema::assert_declared(&s);
    assert_eq!(
        all.kinds(),
        ["sensor_monitor", "ingest", "fastslam", "buoy_ekf", "synchronizer", "fusion", "octree_mapper"],
        "the main job's stage kinds"
    );
    assert_eq!(all.supervisor.run.exit_code, 0, "{:#}", s["run"]);
    // The keys are those the main job wrote before its summary was typed (issue 38), plus the two
    // added on purpose (run.elapsed_s, processes.<name>.ready_rss_mib): nothing renamed or lost.
    let listed = std::fs::read_to_string(format!("{}/main_job_summary_keys.txt", env!("CARGO_MANIFEST_DIR"))).unwrap();
    let listed: std::collections::BTreeSet<String> =
        listed.lines().filter(|l| !l.starts_with('#') && !l.is_empty()).map(String::from).collect();
    let keys = crate::summary_schema::key_paths(&s);
    let (gone, new): (Vec<_>, Vec<_>) = (listed.difference(&keys).collect(), keys.difference(&listed).collect());
    assert!(gone.is_empty() && new.is_empty(), "summary keys gone: {gone:?}; new: {new:?}");
    // ... and the file validates against it by an implementation of JSON Schema we did not write.
    crate::summary_schema::assert_valid_by_jsonschema(&t.out_dir().join("summary.json"));
    // The tests read the parts as the structs the stages write.
    let (fusion_part, slam_part, buoy_part) = (all.fusion.unwrap(), all.fastslam.unwrap(), all.buoy_ekf.unwrap());
    let ate = &s["ate_m"];
    let fused_ate = fusion_part.ate_m.as_ref().expect("fused ATE");
    let (fused, buoy, slam) = (
        fused_ate.fused.unwrap(),
        fused_ate.buoy.unwrap(),
        slam_part.ate_m.as_ref().and_then(|a| a.slam).expect("SLAM ATE"),
    );
    // Fusion gains from SLAM: at most 0.8 of the buoy-only path's error (the goal), better than
    // the SLAM path per local map (ATE after an alignment to the truth), and no worse than the
    // SLAM path placed in the world by the same local alignments (the fused path leans on it).
    assert!(fused <= 0.8 * buoy, "fused {fused} m must be <= 0.8 x the buoy-only path {buoy} m: {ate:#}");
    // The buoy EKF alone within what docs/buoy_ekf.md claims for the main job (0.223 m).
    let buoy_ekf = buoy_part.ate_m.as_ref().and_then(|a| a.buoy_ekf).expect("buoy EKF ATE");
    assert!(buoy_ekf <= 0.25, "buoy EKF {buoy_ekf} m over 0.25 m: {ate:#}");
    assert!(fused < slam, "fused {fused} m must beat the SLAM path {slam} m: {ate:#}");
    assert!(fused <= 1.02 * fused_ate.slam_global.unwrap(), "{ate:#}");
    let nees = slam_part.nees.as_ref().and_then(|n| n.slam_position);
    assert!(nees.is_some_and(|n| (0.2158..=9.3484).contains(&n)), "honest SLAM covariance: {:#}", s["nees"]);
    // The final path's covariance no more optimistic than the buoy EKF's that it rests on: the
    // fixes' correlation in time accounted for (docs/EQUATIONS.md §5.3; 39 without, 5.1 with,
    // against the buoy EKF's 5.7 on 2026-12-07). Neither is consistent yet (3 when it is).
    let fused_nees = fusion_part.nees.as_ref().and_then(|n| n.fused.as_ref()).and_then(|n| n.position);
    let buoy_nees = buoy_part.nees.as_ref().and_then(|n| n.buoy_ekf.position).expect("buoy EKF NEES");
    assert!(
        fused_nees.is_some_and(|n| n <= 1.2 * buoy_nees),
        "final path NEES against the buoy EKF's: {:#}",
        s["nees"]
    );
    // The buoy positions interpolated to the SLAM poses' stamps as honest as the fixes they come
    // from: the fixes' cross-covariances taken into the interpolation (docs/EQUATIONS.md §5.1a;
    // 2.89 against the EKF's 2.93 on 2026-12-07, 3.49 by eq 30 as if the fixes were independent).
    let synced_nees = fusion_part.nees.as_ref().and_then(|n| n.buoy.as_ref()).and_then(|n| n.position);
    assert!(
        synced_nees.is_some_and(|n| n <= 1.1 * buoy_nees),
        "synchronised buoy positions' NEES against the buoy EKF's: {:#}",
        s["nees"]
    );
    // The live poses too: their local map's transform inflated for the fixes' correlation
    // estimated during the run (docs/EQUATIONS.md §5.3; 3.03 on 2026-12-07, 3.44 without).
    let live_nees = fusion_part.nees.as_ref().and_then(|n| n.fused_live.as_ref()).and_then(|n| n.position);
    assert!(
        live_nees.is_some_and(|n| n <= 1.2 * buoy_nees),
        "live fused poses' NEES against the buoy EKF's: {:#}",
        s["nees"]
    );
    let poses = &s["synchronizer"]["poses"];
    let (correlated, interpolated) = (poses["correlated"].as_u64(), poses["interpolated"].as_u64());
    assert!(
        correlated.zip(interpolated).is_some_and(|(c, i)| c as f64 >= 0.8 * i as f64),
        "most interpolations with the fixes' cross-covariances: {poses:#}"
    );
    // The ranges' innovations consistent with their covariance (mean NIS 0.97 in [0.94, 1.07] on
    // 2026-12-07; 1.10 before the odometry's attitude fix, docs/buoy_ekf.md).
    let nis = buoy_part.buoy_ekf.range_nis.as_ref().expect("the ranges' NIS");
    assert!(nis.consistent, "range NIS: {nis:?}");
    let f = &fusion_part.fusion;
    assert_eq!(f.poses, slam_part.slam.frames, "one global pose per SLAM pose: {f:#?}");
    assert!(f.segments_aligned >= 1, "{f:#?}");
    assert!(f.global_landmarks > 100, "{f:#?}");
    let out = t.out_dir();
    for file in [
        "fused_global.tum",
        "fused_live.tum",
        "slam_global.tum",
        "slam_local.tum",
        "buoy.tum",
        "ground_truth.tum",
        "global_map.ply",
        "segment_transforms.json",
    ] {
        let meta = std::fs::metadata(out.join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert!(meta.len() > 100, "{file} is nearly empty");
    }
    let png = std::fs::read(out.join("trajectories.png")).expect("trajectories.png");
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    // The octree mapper on the fused poses. The replay waits for it (back-pressure, `when_behind
    // = "wait"`), so every cloud arrives; it drops only a cloud whose pose does not come within
    // pose_wait_s (possible on a loaded machine), and every drop is in summary.json's `dropped`.
    let mapper: octree_mapper_stage::summary::OctreeMapperPart = crate::summary_schema::part(&s);
    let ingest: ingest_stage::summary::IngestPart = crate::summary_schema::part(&s);
    let sup: supervisor::report::SupervisorPart = crate::summary_schema::part(&s);
    let m = &mapper.octree_mapper;
    let c = &m.counters;
    let inserted = c.clouds_inserted;
    let dropped = c.clouds_dropped_behind + c.clouds_dropped_no_pose;
    let sent = ingest.ingest.messages.cloud;
    // On failure: the mapper's process record (restarts, last exit) and what the log says of it.
    let why = || {
        let log: Vec<String> =
            t.log().lines().filter(|l| l.contains("[map]") || l.contains("process=map")).map(String::from).collect();
        format!(
            "{:#}\nprocess: {:#}\nlog (map, last 40 lines):\n{}",
            s["octree_mapper"],
            s["processes"]["map"],
            log[log.len().saturating_sub(40)..].join("\n")
        )
    };
    assert_eq!(c.clouds_missed, 0, "{}", why());
    assert_eq!(inserted + dropped, sent, "every cloud inserted or counted as dropped: {}", why());
    assert!(inserted * 100 >= sent * 98, "{inserted} of {sent} clouds inserted: {m:?}");
    let listed: u64 = sup.dropped.iter().filter(|d| d.process == "map").map(|d| d.messages).sum();
    assert_eq!(listed, dropped, "the mapper's drops are listed in summary.json: {:#}", s["dropped"]);
    assert_eq!(sup.processes["map"].dropped, dropped);
    assert!(sup.undelivered.is_empty(), "nothing undelivered in a replay: {:?}", sup.undelivered);
    assert!(m.occupied_leaves > 10_000, "{m:?}");
    let end = m.end_of_stream.as_ref().expect("the end of stream's navigable space");
    assert!(end.navigable_regions > 0 && end.obstacles > 0, "{m:?}");
    // Scored against the simulated scene (`truth_scene`): every classified voxel judged, the
    // seabed and most of the 31 objects seen (docs/octree_mapper.md, "Navigable space and
    // obstacles against the truth").
    let truth = end.truth.as_ref().expect("the navigable space scored against scene.json");
    let v = &end.voxels;
    assert_eq!(truth.voxels, v.navigable + v.steep + v.non_planar + v.sparse + v.patch + v.wall, "{truth:?}");
    assert!(truth.ground.voxels > truth.voxels / 10 && truth.objects_observed >= 10, "{truth:?}");
    assert_eq!(truth.regions, end.navigable_regions, "{truth:?}");
    // Judged where each voxel's points truly came from (the classification without the fused
    // poses' error): issue 39's targets. 2026-12-07, since regions and obstacles are judged
    // against the ground beside each obstacle (EQUATIONS §7): agreement 0.958, the largest region
    // 0.960 of the seabed, 15 regions (58 before), every observed object found, precision 1.0
    // (0.68 before); drift seeds 2 and 3 of the simulator (docs/octree_mapper.md) score lower.
    let by_origin = end.truth_by_origin.as_ref().expect("the clouds carry the simulator's true poses");
    let at_least = |v: Option<f64>, min: f64, what: &str| {
        assert!(v.is_some_and(|v| v >= min), "{what} {v:?} under {min}: {by_origin:?}")
    };
    at_least(by_origin.agreement, 0.95, "voxel agreement");
    at_least(by_origin.largest_region_ground_share, 0.9, "the largest region's share of the seabed");
    at_least(by_origin.recall, 0.9, "objects found");
    at_least(by_origin.precision, 0.9, "obstacle precision");
    assert!(by_origin.regions <= 50, "{by_origin:?}");
    // Obstacles as landmarks ([6D] §VI): each rock at most 2 (issue 39's target; the wreck, 24 m
    // long, may hold more; 2026-12-06: at most 2 on a rock, 3 on the wreck, at the true and the
    // fused poses).
    let landmarks = truth.landmarks.as_ref().expect("the obstacle landmarks scored");
    let scene: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("scene.json")).expect("scene.json"))
        .expect("scene.json as JSON");
    let rocks = scene["scene"]["rocks"].as_array().expect("the scene's rocks").len() as u32;
    assert!(landmarks.on_objects >= 10, "{landmarks:?}");
    assert!(landmarks.per_object.iter().all(|o| o.object >= rocks || o.landmarks <= 2), "{rocks} rocks: {landmarks:?}");
    // End-to-end latency of the whole pipeline, as measured by its last stages.
    let fused_lat = &fusion_part.pipeline_latency_ms.stereo_to_fused_pose;
    let cloud_lat =
        mapper.pipeline_latency_ms.as_ref().and_then(|l| l.cloud_to_octree.as_ref()).expect("the mapper's latency");
    for (k, lat) in [("stereo_to_fused_pose", fused_lat), ("cloud_to_octree", cloud_lat)] {
        assert!(lat.count > 0 && lat.p50.is_some_and(|p| p > 0.0), "{k}: {lat:?}");
    }
    let bt = std::fs::read(out.join("map.bt")).expect("map.bt");
    assert!(bt.starts_with(b"# Octomap OcTree binary file"));
    for file in ["navigable.ply", "obstacles.ply"] {
        assert!(std::fs::read(out.join(file)).unwrap_or_default().starts_with(b"ply\n"), "{file}");
    }
    // The 2.5-D traversability grid: map_server files whose image is mostly navigable seabed
    // with the rocks and the wreck blocked, and a height for every known cell.
    let yaml = std::fs::read_to_string(out.join("traversability.yaml")).expect("traversability.yaml");
    assert!(yaml.contains("image: traversability.pgm") && yaml.contains("resolution: 0.1"), "{yaml}");
    let pgm = std::fs::read(out.join("traversability.pgm")).expect("traversability.pgm");
    let header: Vec<&[u8]> = pgm.splitn(5, |b| *b == b'\n').collect();
    assert_eq!(header[0], b"P5");
    let size = String::from_utf8_lossy(header[2]).to_string();
    let (w, h) = size.split_once(' ').map(|(w, h)| (w.parse::<usize>().unwrap(), h.parse::<usize>().unwrap())).unwrap();
    let image = header[4];
    assert_eq!(image.len(), w * h, "{size}");
    let count = |v: u8| image.iter().filter(|b| **b == v).count();
    let (free, blocked) = (count(254), count(0));
    assert!(free > 100_000 && blocked > 100 && free > 10 * blocked, "{free} navigable, {blocked} obstacle cells");
    let pfm = std::fs::read(out.join("traversability_height.pfm")).expect("traversability_height.pfm");
    let head = format!("Pf\n{w} {h}\n-1.0\n");
    assert!(pfm.starts_with(head.as_bytes()) && pfm.len() == head.len() + 4 * w * h);
    let known =
        pfm[head.len()..].chunks(4).filter(|c| f32::from_le_bytes((*c).try_into().unwrap()).is_finite()).count();
    assert_eq!(known, free + blocked, "a height for every known cell");
}

#[test]
fn invalid_octree_mapper_settings_name_their_keys() {
    for (settings, key) in [
        ("[processes.p.settings]\nresolution_m = 0.0", "processes.p.settings.resolution_m"),
        ("[processes.p.settings.sensor]\nprob_hit = 0.3", "processes.p.settings.sensor"),
        ("[processes.p.settings]\npose_source = \"gps\"", "processes.p.settings.pose_source"),
        ("[processes.p.settings.nsd]\nmin_points = 1", "processes.p.settings.nsd.min_points"),
        ("[processes.p.settings]\ntruth_tolerance_m = -1.0", "processes.p.settings.truth_tolerance_m"),
        ("[processes.p.settings.nsd]\nmin_region_area_m2 = -1.0", "processes.p.settings.nsd.min_region_area_m2"),
    ] {
        let mut run = TestRun::new("badmapper");
        let procs = format!("[processes.p]\nkind = \"octree_mapper\"\n{settings}\n");
        let cfg = run.write_config("end = \"signal\"", &procs);
        run.start_supervisor(&cfg, &[]);
        let status = run.wait_supervisor(Duration::from_secs(20)).expect("exits");
        assert_eq!(status.code(), Some(2), "{}", run.log());
        assert!(run.log().contains(&format!("`{key}`")), "must name `{key}`:\n{}", run.log());
    }
}

#[test]
fn invalid_fusion_settings_name_their_keys() {
    for (settings, key) in [
        ("[processes.p.settings.fusion]\ngate_probability = 1.5", "processes.p.settings.fusion.gate_probability"),
        ("[processes.p.settings.fusion.align]\nmin_pairs = 1", "processes.p.settings.fusion.align.min_pairs"),
        ("[processes.p.settings]\nslam_process = \"\"", "processes.p.settings.slam_process"),
        ("[processes.p.settings]\nplott = true", "processes.p.settings.plott"),
    ] {
        let mut run = TestRun::new("badfusion");
        let procs = format!("[processes.p]\nkind = \"fusion\"\n{settings}\n");
        let cfg = run.write_config("end = \"signal\"", &procs);
        run.start_supervisor(&cfg, &[]);
        let status = run.wait_supervisor(Duration::from_secs(20)).expect("exits");
        assert_eq!(status.code(), Some(2), "{}", run.log());
        assert!(run.log().contains(&format!("`{key}`")), "must name `{key}`:\n{}", run.log());
    }
}
