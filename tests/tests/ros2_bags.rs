//! ROS 2 bags against an implementation no one here wrote: Python `rosbags` (PyPI) writes
//! rosbag2 MCAP bags (tests/python/rosbags_interop.py), the pipeline replays them (ingest's
//! `rosbag2` source), and damaged copies of them are counted and skipped, not fatal.
//!
//! - The Freiburg 079 CARMEN log (../shared/data/carmen) as /scan + /odom: grid SLAM on the bag
//!   scores the benchmark's relations as on the file replay of the same scans (within 10 %).
//! - One message of each type the pipeline reads, with the values rosbags was given, and bad
//!   ones (another type on a route's topic, a truncated message, a NaN field, a cloud without z).
//! - A corrupt chunk and a truncated file: named, counted, the rest replayed.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use crate::summary_schema::part;
use grid_slam_stage::summary::GridSlamPart;
use ingest_stage::summary::IngestPart;
use pipeline_tests::{TestRun, carmen_source, fr079_grid_slam, ingest_after_slam2d};
use ros2_interop::msgs::CameraInfo;
use ros2_interop::route::{Decoded, InRoute, InService, RouteDecoder};
use ros2_interop::{BagReader, BagWarts, Message};

fn script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("python/rosbags_interop.py")
}

fn carmen_log() -> (String, String) {
    let data = format!("{}/../../shared/data/carmen", env!("CARGO_MANIFEST_DIR"));
    let log = format!("{data}/freiburg-079-corrected.log.gz");
    assert!(
        Path::new(&log).is_file(),
        "{log} is missing: the project's shared/ folder (with data/carmen) belongs beside the repository"
    );
    (data, log)
}

/// Runs the rosbags helper; returns its JSON output.
fn rosbags(args: &[&str]) -> serde_json::Value {
    let o = Command::new("python3").arg(script()).args(args).output().expect("python3 runs");
    assert!(
        o.status.success(),
        "rosbags_interop.py {args:?} failed (the test command installs `rosbags` from PyPI):\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).expect("the helper prints JSON")
}

const SCANS: usize = 600;

fn grid_slam_on(run: &mut TestRun, data: &str, source: &str) -> serde_json::Value {
    let processes = format!("{}{}", fr079_grid_slam(data, 8, 1, 30.0), ingest_after_slam2d(source));
    run.run_to_end("end = \"end_of_stream\"\nend_of_stream_from = [\"slam2d\"]", &processes, Duration::from_secs(300))
}

/// A recorder that writes grid SLAM's outputs as a ROS 2 bag (`ros2_bag` in the run's output
/// directory) and nothing else; ingest starts after it and slam2d.
const ROS2_RECORDER: &str = r#"
[processes.rec]
kind = "recorder"
[processes.rec.settings]
services = ["pipeline/grid_slam/pose"]
end_after = ["slam2d"]
send_end_of_stream = true
[processes.rec.settings.ros2]
out = [
  { what = "map" },
  { what = "grid_slam_odometry" },
  { what = "grid_slam_path" },
  { what = "tf", from = "grid_slam", odom = "planar_odometry" },
]
"#;

#[test]
fn a_bag_rosbags_wrote_from_the_fr079_log_maps_as_the_file_replay_does() {
    let (data, log) = carmen_log();
    let mut bag_run = TestRun::new("ros2bag");
    let bag = bag_run.dir.path().join("fr079");
    let written = rosbags(&["carmen", &log, bag.to_str().unwrap(), "--max-scans", &SCANS.to_string()]);
    assert_eq!(written["scans"], SCANS);
    let source = format!(
        r#"source = "rosbag2"
[processes.ingest.settings.rosbag2]
path = "{}"
routes = [{{ topic = "/scan", service = "laser" }}, {{ topic = "/odom", service = "planar_odometry" }}]"#,
        bag.display()
    );
    // The recorder writes what grid SLAM makes of it as a ROS 2 bag, read back below by rosbags.
    let processes = format!(
        "{}{ROS2_RECORDER}{}",
        fr079_grid_slam(&data, 8, 1, 30.0),
        ingest_after_slam2d(&source).replace(r#"after = ["slam2d"]"#, r#"after = ["slam2d", "rec"]"#)
    );
    let from_bag = bag_run.run_to_end(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"slam2d\", \"rec\"]",
        &processes,
        Duration::from_secs(300),
    );
    let ingest = part::<IngestPart>(&from_bag).ingest;
    assert_eq!(ingest.messages.laser, SCANS as u64, "{ingest:?}");
    assert_eq!(ingest.messages.planar_odometry, SCANS as u64, "{ingest:?}");
    let bag = ingest.details.rosbag2.as_ref().expect("the bag's counts");
    assert_eq!(bag.routes["/scan"].published, SCANS as u64, "{ingest:?}");
    assert!(ingest.data_warts.is_empty(), "a clean bag: {ingest:?}");
    let grid = part::<GridSlamPart>(&from_bag).grid_slam;
    assert_eq!(grid.scans, SCANS as u64, "every scan of the bag is mapped: {grid:?}");
    let g = grid.run.as_ref().expect("the filter ran");

    // The recorder's ROS 2 bag, read by rosbags: every message decodes, one per grid SLAM output.
    let recorder = part::<recorder_stage::summary::RecorderPart>(&from_bag).recorder;
    let rec = recorder.ros2_bag.as_ref().expect("the recorder's ROS 2 bag");
    assert_eq!(rec.report.undecodable, 0, "{rec:?}");
    let out = rosbags(&["read", rec.report.dir.to_str().expect("the bag's directory")]);
    let (poses, grids) = (g.poses_published, g.grids_published);
    assert!(poses >= SCANS as u64 / 2 && grids >= 1, "{g:?}");
    assert_eq!(out["/slam/grid/odometry"]["count"], poses, "{out}");
    assert_eq!(out["/slam/grid/odometry"]["type"], "nav_msgs/msg/Odometry");
    assert_eq!(out["/map"]["count"], grids, "{out}");
    let map = &out["/map"]["last"];
    assert_eq!(map["frame_id"], "map");
    let resolution_m = g.grid.as_ref().expect("the final grid").resolution_m;
    assert!((map["resolution"].as_f64().unwrap() - resolution_m).abs() < 1e-6, "{map}");
    assert_eq!(map["cells"].as_u64().unwrap(), map["width"].as_u64().unwrap() * map["height"].as_u64().unwrap());
    assert_eq!(out["/slam/grid/path"]["last"]["poses"], poses, "the last path holds every pose: {out}");
    // /tf: odom → base_link per odometry message and map → odom per pose, but for the poses that
    // came before any odometry at or before their stamp (counted).
    let tf = out["/tf"]["count"].as_u64().unwrap();
    let skipped = rec.report.tf_without_odometry.get("/tf").copied().unwrap_or(0);
    assert!(skipped <= 10, "{skipped} poses before the first odometry: {rec:?}");
    assert_eq!(tf, SCANS as u64 + poses - skipped, "{tf}: {out}\n{rec:?}");
    assert!(out.get("/tf_static").is_none(), "odom comes from odometry: no identity map → odom");

    let mut file_run = TestRun::new("ros2file");
    let from_file = grid_slam_on(&mut file_run, &data, &carmen_source(&log, SCANS));
    assert_eq!(part::<GridSlamPart>(&from_file).grid_slam.scans, SCANS as u64);
    let relations = |s: &serde_json::Value| {
        part::<GridSlamPart>(s).grid_slam.run.and_then(|r| r.relations).expect("scored against the relations")
    };
    let (a, b) = (relations(&from_bag), relations(&from_file));
    eprintln!("relations: bag {a:?}\nfile {b:?}");
    assert_eq!(a.scored, b.scored, "the same relations are scored");
    assert!(a.scored > 100, "{a:?}");
    for (k, x, y) in
        [("trans_mean_m", a.trans_mean_m, b.trans_mean_m), ("rot_mean_deg", a.rot_mean_deg, b.rot_mean_deg)]
    {
        // The issue asks for 10 %. The inputs agree to about 1e-8, not bitwise (sensor_msgs/LaserScan
        // carries the beam angles as float32, the CARMEN line's geometry is f64), and since the
        // matcher ends by Gauss-Newton (continuous, where hill climbing's fixed steps absorbed such
        // differences) the particle set's resampling amplifies them: 0.0314 against 0.0307 m on
        // 2026-12-06, 2.5 % apart.
        assert!((x - y).abs() <= 0.10 * y.max(1e-3), "{k}: bag {x} vs file {y}: not within 10 %");
    }
}

fn samples_bag(dir: &Path) -> (PathBuf, serde_json::Value) {
    let bag = dir.join("samples");
    let expect = rosbags(&["samples", bag.to_str().unwrap()]);
    (bag, expect)
}

fn route(topic: &str, service: InService) -> InRoute {
    let mut r = InRoute::new(topic, service);
    r.range_sigma_m = 1.0;
    r
}

#[test]
fn every_input_type_rosbags_wrote_decodes_to_the_values_it_was_given() {
    let dir = tempfile::tempdir().unwrap();
    let (bag, expect) = samples_bag(dir.path());
    let mut decoders: Vec<RouteDecoder> = [
        ("/scan", InService::Laser),
        ("/odom", InService::PlanarOdometry),
        ("/cloud", InService::Cloud),
        ("/imu", InService::Heading),
        ("/pressure", InService::Depth),
        ("/ranges", InService::BuoyRanges),
        ("/odom_wrong", InService::PlanarOdometry),
        ("/depth", InService::DepthImage),
    ]
    .into_iter()
    .map(|(t, s)| {
        let mut r = route(t, s);
        r.camera_info = "/camera_info".into();
        r.stride = 1;
        RouteDecoder::new(r)
    })
    .collect();
    let mut reader = BagReader::open(&bag).unwrap();
    let mut ok = vec![];
    let mut errors = vec![];
    while let Some(m) = reader.next_message().unwrap() {
        if &*m.topic == "/camera_info" {
            let info = ros2_interop::decode::<CameraInfo>(&m.data, CameraInfo::TYPE_NAME).unwrap();
            decoders.iter_mut().find(|d| d.route.service == InService::DepthImage).unwrap().set_camera_info(info);
            continue;
        }
        let d = decoders.iter_mut().find(|d| *d.route.topic == *m.topic).expect("a route per topic");
        if *m.type_name != *d.route.service.ros_type() {
            errors.push((m.topic.to_string(), "wrong_type".to_string()));
            continue;
        }
        match d.decode(&m.data) {
            Ok(v) => ok.push(v),
            Err(e) => errors.push((m.topic.to_string(), e.to_string())),
        }
    }
    assert_eq!(reader.warts(), &BagWarts::default());
    assert_eq!(ok.len(), 7, "{ok:?}");
    for v in &ok {
        match v {
            Decoded::Laser { stamp_ns, header, ranges } => {
                assert_eq!(*stamp_ns, expect["scan"]["stamp_ns"].as_u64().unwrap());
                assert_eq!(header.beams, 4);
                assert_eq!(ranges[..3], [1.0, 2.0, 30.0], "+Inf is no return (range_max)");
                assert!(ranges[3].is_nan());
            }
            Decoded::PlanarOdometry { odometry, .. } => {
                assert_eq!(odometry.position_m, [1.5, -2.0]);
                assert!((odometry.yaw_rad - 0.5).abs() < 1e-12);
            }
            Decoded::Cloud { points, non_finite, .. } if points.len() == 2 && points[0][2] == 2.0 => {
                // The depth image: (u 0, v 0) at 2 m and (3, 1) at 1 m through K.
                let want = [[-0.04, -0.02, 2.0], [0.01, 0.0, 1.0]];
                for (p, w) in points.iter().zip(want) {
                    assert!(p.iter().zip(w).all(|(a, b)| (a - b).abs() < 1e-6), "{points:?}");
                }
                assert_eq!(*non_finite, 6, "the zero pixels");
            }
            Decoded::Cloud { points, non_finite, .. } => {
                assert_eq!(points, &vec![[1.0, 3.0, 5.0], [2.0, 4.0, 6.0]]);
                assert_eq!(*non_finite, 1);
            }
            Decoded::Heading { reading, .. } => {
                assert!((reading.yaw_rad + 0.25).abs() < 1e-12 && (reading.sigma_rad - 0.02).abs() < 1e-12);
            }
            Decoded::Depth { reading, .. } => assert!((reading.depth_m - 12.0).abs() < 1e-9),
            Decoded::BuoyRange { range, .. } => {
                assert_eq!(range.buoy_id, 2);
                assert!((range.range_m - 42.5).abs() < 1e-6 && (range.sigma_m - 0.3).abs() < 1e-6);
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    let msg = |topic: &str, needle: &str| errors.iter().any(|(t, e)| t == topic && e.contains(needle));
    assert!(msg("/scan", "angle_increment") && msg("/scan", "not finite"), "{errors:?}");
    assert!(msg("/scan", "not a sensor_msgs/msg/LaserScan"), "the truncated scan: {errors:?}");
    assert!(msg("/odom_wrong", "wrong_type"), "{errors:?}");
    assert!(msg("/cloud", "no field `z`"), "{errors:?}");
    assert_eq!(errors.len(), 4, "{errors:?}");
}

#[test]
fn a_bag_of_every_input_type_is_replayed_and_what_is_bad_is_counted_per_route() {
    let mut run = TestRun::new("ros2samples");
    let (bag, _) = samples_bag(run.dir.path());
    let processes = format!(
        r#"
[processes.monitor]
kind = "sensor_monitor"
[processes.monitor.settings]
known_buoy_ids = [2]

[processes.ingest]
kind = "ingest"
after = ["monitor"]
[processes.ingest.settings]
source = "rosbag2"
real_time_factor = 0.0
[processes.ingest.settings.rosbag2]
path = "{}"
routes = [
  {{ topic = "/scan", service = "laser" }},
  {{ topic = "/cloud", service = "cloud" }},
  {{ topic = "/imu", service = "heading" }},
  {{ topic = "/pressure", service = "depth" }},
  {{ topic = "/ranges", service = "buoy_ranges" }},
  {{ topic = "/odom_wrong", service = "planar_odometry" }},
  {{ topic = "/depth", service = "depth_image", camera_info = "/camera_info", stride = 1 }},
]
"#,
        bag.display()
    );
    let s = run.run_to_end(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"monitor\"]",
        &processes,
        Duration::from_secs(60),
    );
    let ingest = part::<IngestPart>(&s).ingest;
    let bag = ingest.details.rosbag2.as_ref().expect("the bag's counts");
    let routes = &bag.routes;
    assert_eq!(routes["/scan"].published, 1, "{ingest:?}");
    assert_eq!(routes["/scan"].invalid, 1, "{ingest:?}");
    assert_eq!(routes["/scan"].undecodable, 1, "{ingest:?}");
    assert_eq!(routes["/cloud"].invalid, 1, "{ingest:?}");
    assert_eq!(routes["/cloud"].non_finite_points, 1, "{ingest:?}");
    assert_eq!(routes["/odom_wrong"].wrong_type, 1, "{ingest:?}");
    assert_eq!(bag.unrouted_messages.get("/odom"), Some(&1), "a topic without a route is counted: {ingest:?}");
    let w = &ingest.data_warts;
    let wart = |k: &str| w.get(k).copied().unwrap_or(0);
    assert_eq!(
        (wart("invalid_messages"), wart("undecodable_messages"), wart("wrong_type_messages")),
        (2, 1, 1),
        "{w:?}"
    );
    let m = part::<sensor_monitor_stage::summary::SensorMonitorPart>(&s).sensor_monitor;
    for (service, n) in [("cloud", 2), ("heading", 1), ("depth", 1), ("buoy_ranges", 1)] {
        let s = &m.streams[&format!("pipeline/sensors/{service}")];
        assert_eq!((s.accepted, s.rejected.is_empty()), (n, true), "{service}: {m:?}");
    }
    assert_eq!(m.cloud_points, 4, "the cloud's two finite points and the depth image's two: {m:?}");
    assert_eq!(routes["/depth"].camera_infos, 1, "{ingest:?}");
    let log = run.log();
    for needle in
        ["`/odom_wrong` is sensor_msgs/msg/FluidPressure in the bag", "no field `z`", "a topic without a route"]
    {
        assert!(log.contains(needle), "`{needle}` is not in the log");
    }
}

/// Offsets of the top-level chunk records of an MCAP file.
fn chunk_offsets(bytes: &[u8]) -> Vec<usize> {
    let mut at = 8;
    let mut out = vec![];
    while at + 9 <= bytes.len() {
        let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap()) as usize;
        if bytes[at] == 0x06 {
            out.push(at);
        }
        if bytes[at] == 0x0f {
            break;
        }
        at += 9 + len;
    }
    out
}

#[test]
fn a_corrupt_chunk_and_a_truncated_file_are_named_counted_and_the_rest_replayed() {
    let (_, log) = carmen_log();
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("fr");
    rosbags(&["carmen", &log, bag.to_str().unwrap(), "--max-scans", &SCANS.to_string()]);
    let file = bag.join("fr.mcap");
    let clean = std::fs::read(&file).unwrap();
    let count = |path: &Path| {
        let mut r = BagReader::open(path).unwrap();
        let mut n = 0;
        while r.next_message().unwrap().is_some() {
            n += 1;
        }
        (n, r.warts().clone(), r.take_problems())
    };
    let (all, warts, _) = count(&bag);
    assert_eq!((all, warts), (2 * SCANS, BagWarts::default()));

    // Overwrite the length of the first record inside the first chunk: its inner framing breaks
    // (the chunk holds the schemas and channels too; the reader has them from the summary).
    let chunks = chunk_offsets(&clean);
    assert!(chunks.len() >= 2, "rosbags wrote {} chunk(s)", chunks.len());
    let mut bad = clean.clone();
    let records = chunks[0] + 9 + 8 + 8 + 8 + 4 + 4 + 8; // past the chunk header: times, size, crc, "", length
    for b in &mut bad[records + 1..records + 9] {
        *b = 0xff;
    }
    std::fs::write(&file, &bad).unwrap();
    let (n, warts, problems) = count(&bag);
    assert_eq!(warts.corrupt_chunks, 1, "{warts:?}");
    assert!(n > 0 && n < all, "the other chunks are read: {n} of {all}");
    assert!(
        problems.iter().any(|p| p.contains(&format!("@{}", chunks[0])) && p.contains("corrupt chunk")),
        "named with its offset: {problems:?}"
    );

    // Cut the file in the middle of its second chunk.
    std::fs::write(&file, &clean[..chunks[1] + 1000]).unwrap();
    let (n, warts, problems) = count(&bag);
    assert_eq!(warts.truncated_files, 1, "{warts:?}");
    assert!(n > 0 && n < all, "{n} of {all}");
    assert!(problems.iter().any(|p| p.contains(&format!("@{}", chunks[1])) && p.contains("truncated")), "{problems:?}");

    // Through the pipeline: the run ends cleanly and says what it lost.
    std::fs::write(&file, &bad).unwrap();
    let mut run = TestRun::new("ros2corrupt");
    let processes = format!(
        r#"
[processes.monitor]
kind = "sensor_monitor"

[processes.ingest]
kind = "ingest"
after = ["monitor"]
[processes.ingest.settings]
source = "rosbag2"
real_time_factor = 0.0
[processes.ingest.settings.rosbag2]
path = "{}"
routes = [{{ topic = "/scan", service = "laser" }}]
"#,
        bag.display()
    );
    let s = run.run_to_end(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"monitor\"]",
        &processes,
        Duration::from_secs(60),
    );
    assert_eq!(part::<IngestPart>(&s).ingest.data_warts.get("corrupt_chunks"), Some(&1), "{}", s["ingest"]);
    assert!(run.log().contains("corrupt chunk"), "warned in the log");
}
