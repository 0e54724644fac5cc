//! The `ros2` gateway against a DDS implementation no one here wrote: Eclipse Cyclone DDS
//! (Python `cyclonedds`, tests/python/cyclonedds_peer.py) declaring the ROS 2 types with their DDS
//! names, as rmw_cyclonedds does. Everything runs inside a network namespace the test makes (only
//! loopback), so DDS discovery never sends a packet on the machine's interfaces.
//!
//! - A robot on ROS 2: Cyclone publishes the Freiburg 079 log's LaserScan + Odometry; grid SLAM
//!   maps them through the gateway (the relations score as the file replay of the same scans),
//!   and Cyclone receives `/map` (transient local: it subscribed first, the map is latched
//!   anyway), the grid-SLAM pose, path and `/tf`.
//! - The main job's outputs on ROS 2 (config/ros2.toml, a 40 s mission): poses near the ground
//!   truth, the voxel cloud's fields, markers, `/tf` and `/tf_static`.
//! - What the gateway must refuse (a NaN field, a zero quaternion, a cloud without z) is counted
//!   per route.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use crate::summary_schema::part;
use grid_slam_stage::summary::GridSlamPart;
use pipeline_tests::{NetNs, TestRun, carmen_source, fr079_grid_slam, ingest_after_slam2d};
use ros2_stage::summary::Ros2Part;

/// Cyclone on the namespace's loopback, multicast on (its default skips loopback).
const CYCLONE: &str = "<CycloneDDS><Domain><General><Interfaces><NetworkInterface name=\"lo\" multicast=\"true\"/>\
                       </Interfaces></General></Domain></CycloneDDS>";

fn peer() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("python/cyclonedds_peer.py")
}

fn cyclone(ns: &NetNs, args: &[&str]) -> Command {
    let mut c = ns.command("python3");
    c.arg(peer()).args(args).env("CYCLONEDDS_URI", CYCLONE).stdin(Stdio::null());
    c
}

/// Waits for a listener to end and returns its JSON.
fn listener_output(child: &mut Child) -> serde_json::Value {
    let mut s = String::new();
    child.stdout.take().expect("piped").read_to_string(&mut s).unwrap();
    let status = child.wait().unwrap();
    assert!(status.success(), "the Cyclone listener failed (the test command installs `cyclonedds` from PyPI)");
    serde_json::from_str(&s).unwrap_or_else(|e| panic!("listener output is not JSON ({e}): {s}"))
}

/// Stops a listener once the run has ended (the gateway lingered after its last messages, so
/// the listener has all of them) and returns what it heard.
fn stop_listener(run: &mut TestRun, pid: u32) -> serde_json::Value {
    std::thread::sleep(Duration::from_millis(500));
    let _ = nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid as i32), nix::sys::signal::Signal::SIGINT);
    listener_output(run.others_mut(pid))
}

fn carmen_data() -> (String, String) {
    let data = format!("{}/../../shared/data/carmen", env!("CARGO_MANIFEST_DIR"));
    let log = format!("{data}/freiburg-079-corrected.log.gz");
    assert!(Path::new(&log).is_file(), "{log} is missing: the project's shared/ folder belongs beside the repository");
    (data, log)
}

const SCANS: u64 = 300;

const RELIABLE_IN: &str =
    r#"when_full = "wait", qos = { reliability = "reliable", durability = "volatile", depth = 1000 }"#;

#[test]
fn a_cyclone_dds_robot_feeds_grid_slam_through_the_gateway_and_gets_the_map_and_tf_back() {
    let ns = NetNs::required("r2g");
    let (data, log) = carmen_data();
    let mut run = TestRun::new("ros2gw");
    let cfg = run.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"slam2d\", \"ros_out\"]",
        &format!(
            r#"{}
[processes.ros_out]
kind = "ros2"
[processes.ros_out.settings]
insecure = true
node_name = "slam_out"
end_after = ["slam2d"]
out = [
  {{ what = "map" }},
  {{ what = "grid_slam_odometry", topic = "/slam/grid/odometry" }},
  {{ what = "grid_slam_path" }},
  {{ what = "tf", from = "grid_slam", odom = "planar_odometry" }},
  {{ what = "grid_slam_pose", topic = "/pose" }},
]
static_transforms = [{{ parent = "base_link", child = "laser", xyz_m = [0.1, 0.0, 0.3] }}]

[processes.ros_in]
kind = "ros2"
after = ["slam2d", "ros_out"]
[processes.ros_in.settings]
insecure = true
node_name = "slam_in"
end_when_idle_s = 3.0
in = [
  {{ topic = "/scan", service = "laser", {RELIABLE_IN} }},
  {{ topic = "/odom", service = "planar_odometry", {RELIABLE_IN} }},
]
"#,
            fr079_grid_slam(&data, 8, 1, 10.0)
        ),
    );
    run.start_supervisor_in(&ns.wrapper(), &cfg, &[]);
    let listen = cyclone(
        &ns,
        &[
            "listen",
            "120",
            "/map:map",
            "/slam/grid/odometry:odometry",
            "/slam/grid/path:path",
            "/tf:tf",
            "/tf_static:tf",
            "ros_discovery_info:nodes",
        ],
    );
    let pid = run.spawn(&mut { listen }).id();
    let o = cyclone(&ns, &["carmen", &log, "--max-scans", &SCANS.to_string(), "--rate-x", "20"]).output().unwrap();
    assert!(o.status.success(), "Cyclone publisher: {}", String::from_utf8_lossy(&o.stderr));
    let status = run.wait_supervisor(Duration::from_secs(180)).expect("the run ends");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    assert!(run.leftovers().is_empty(), "iceoryx2 files left behind");
    let heard = stop_listener(&mut run, pid);
    let s = run.summary();
    crate::summary_schema::assert_declared(&s);

    let gateways = part::<Ros2Part>(&s).ros2;
    let gw_in = &gateways["ros_in"].inbound;
    for topic in ["/scan", "/odom"] {
        let c = &gw_in[topic].counts;
        assert_eq!(c.published, SCANS, "{topic}: {c:?}");
        assert_eq!((c.undecodable, c.invalid, c.lost_in_dds, c.port_failed), (0, 0, 0, 0), "{topic}: {c:?}");
        eprintln!("{topic} latency: {:?}", gw_in[topic].latency_ms);
    }
    assert_eq!(part::<GridSlamPart>(&s).grid_slam.scans, SCANS, "every scan reached grid SLAM");
    let out = &gateways["ros_out"].out;
    assert_eq!(out["/slam/grid/odometry"].counts.published, SCANS, "{out:?}");
    assert_eq!(out["/tf"].counts.published, 2 * SCANS, "odom -> base_link and map -> odom per scan: {out:?}");
    assert_eq!(gateways["ros_out"].not_carried, 0);
    // Nobody subscribes to /pose: nothing is published on it, every pose is counted.
    let pose = &out["/pose"].counts;
    assert_eq!((pose.published, pose.no_subscriber), (0, SCANS), "{out:?}");

    // What Cyclone received.
    assert_eq!(heard["/slam/grid/odometry"]["count"], SCANS, "{heard}");
    let last = &heard["/slam/grid/odometry"]["last"];
    assert_eq!((&last["frame_id"], &last["child_frame_id"]), (&"map".into(), &"base_link".into()));
    assert!(last["position"].as_array().unwrap().iter().all(|v| v.as_f64().unwrap().is_finite()));
    let map = &heard["/map"]["last"];
    assert!(heard["/map"]["count"].as_u64().unwrap() >= 1, "{heard}");
    assert!((map["resolution"].as_f64().unwrap() - 0.05).abs() < 1e-6, "{map}");
    let (w, h) = (map["width"].as_u64().unwrap(), map["height"].as_u64().unwrap());
    assert_eq!(map["cells"], w * h, "{map}");
    assert!(map["occupied"].as_u64().unwrap() > 500 && map["known"].as_u64().unwrap() > 10_000, "{map}");
    assert!(heard["/slam/grid/path"]["last"]["poses"].as_u64().unwrap() >= SCANS - 5, "{heard}");
    let tf = heard["/tf"]["count"].as_u64().unwrap();
    assert_eq!(tf, 2 * SCANS, "{heard}");
    let statics = &heard["/tf_static"]["last"]["transforms"][0];
    assert_eq!((&statics[0], &statics[1]), (&"base_link".into(), &"laser".into()), "{heard}");
    // Both gateways are ROS nodes as `ros2 node list` finds them (rmw's ros_discovery_info), with
    // their DDS endpoints: slam_out's 4 routes and /tf_static, slam_in's 2 readers.
    let nodes = &heard["ros_discovery_info"]["nodes"];
    assert!(nodes["/slam_out"][1].as_u64().unwrap_or(0) >= 5, "{nodes}");
    assert!(nodes["/slam_in"][0].as_u64().unwrap_or(0) >= 2, "{nodes}");

    // The same scans from the file: the same relations score (the issue allows 10 %).
    let mut file_run = TestRun::new("ros2gwfile");
    let from_file = file_run.run_to_end(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"slam2d\"]",
        &format!("{}{}", fr079_grid_slam(&data, 8, 1, 10.0), ingest_after_slam2d(&carmen_source(&log, SCANS as usize))),
        Duration::from_secs(120),
    );
    let relations = |s: &serde_json::Value| {
        part::<GridSlamPart>(s).grid_slam.run.and_then(|r| r.relations).expect("scored against the relations")
    };
    let (a, b) = (relations(&s), relations(&from_file));
    eprintln!("relations through ROS 2: {a:?}\nfrom the file: {b:?}");
    assert_eq!(a.scored, b.scored);
    let (x, y) = (a.trans_mean_m, b.trans_mean_m);
    assert!((x - y).abs() <= 0.1 * y, "trans_mean_m {x} through ROS 2 vs {y} from the file");
}

#[test]
fn what_the_gateway_must_refuse_is_counted_per_route_and_the_rest_goes_through() {
    let ns = NetNs::required("r2b");
    let mut run = TestRun::new("ros2bad");
    let cfg = run.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"monitor\"]",
        r#"
[processes.monitor]
kind = "sensor_monitor"

[processes.ros_in]
kind = "ros2"
after = ["monitor"]
[processes.ros_in.settings]
insecure = true
end_when_idle_s = 2.0
in = [
  { topic = "/scan", service = "laser", qos = { reliability = "reliable", durability = "volatile", depth = 100 } },
  { topic = "/odom", service = "planar_odometry", qos = { reliability = "reliable", durability = "volatile", depth = 100 } },
  { topic = "/cloud", service = "cloud", qos = { reliability = "reliable", durability = "volatile", depth = 100 } },
  { topic = "/scan_be", service = "laser", qos = { reliability = "reliable", durability = "volatile", depth = 10 } },
  { topic = "/scan_typed", service = "laser", qos = { reliability = "reliable", durability = "volatile", depth = 10 } },
  { topic = "/depth", service = "depth_image", camera_info = "/camera_info", stride = 1, qos = { reliability = "reliable", durability = "volatile", depth = 10 } },
]
"#,
    );
    run.start_supervisor_in(&ns.wrapper(), &cfg, &[]);
    let o = cyclone(&ns, &["bad", "3"]).output().unwrap();
    assert!(o.status.success(), "Cyclone publisher: {}", String::from_utf8_lossy(&o.stderr));
    let status = run.wait_supervisor(Duration::from_secs(60)).expect("the run ends");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    let s = run.summary();
    let gateway = part::<Ros2Part>(&s).ros2.remove("ros_in").expect("the gateway's part");
    let r = &gateway.inbound;
    let c = |t: &str| &r[t].counts;
    assert_eq!((c("/scan").invalid, c("/scan").published), (1, 1), "{r:?}");
    assert_eq!(c("/odom").invalid, 1, "{r:?}");
    assert_eq!(c("/cloud").invalid, 1, "{r:?}");
    assert_eq!(gateway.not_carried, 3);
    assert_eq!(c("/scan_be").qos_incompatible, 1, "a best-effort publisher, a reliable route: {r:?}");
    assert_eq!(c("/scan_typed").type_mismatch, 1, "an Odometry publisher on a LaserScan route: {r:?}");
    assert_eq!((c("/scan_be").received, c("/scan_typed").received), (0, 0));
    assert_eq!(gateway.endpoints_unmatched, 2);
    let d = c("/depth");
    assert_eq!((d.camera_infos, d.published, d.invalid), (1, 1, 0), "{d:?}");
    let monitor = part::<sensor_monitor_stage::summary::SensorMonitorPart>(&s).sensor_monitor;
    assert_eq!(monitor.cloud_points, 2, "the depth image's two points: {}", s["sensor_monitor"]);
    let log = run.log();
    for needle in [
        "angle_increment",
        "not a rotation",
        "no field `z`",
        "cannot match the route's",
        "nav_msgs::msg::dds_::Odometry_",
    ] {
        assert!(log.contains(needle), "`{needle}` is not warned about");
    }
}

#[test]
fn the_main_jobs_outputs_reach_a_cyclone_subscriber_near_the_ground_truth() {
    let _heavy = pipeline_tests::heavy();
    let ns = NetNs::required("r2m");
    let mut run = TestRun::new("ros2main");
    let ros2 = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/ros2.toml");
    // config/ros2.toml on a 40 s mission; the run table is this test's. The gateway stays up
    // 3 s at the end (`linger_s`, 1 by default): under the test command's load the Python
    // reader acknowledges the last messages later.
    let cfg = run.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"monitor\", \"slam\", \"buoy\", \"sync\", \"fusion\", \"map\", \"ros\"]",
        &format!(
            "extends = \"{}\"\n[processes.ingest.settings.sim.mission]\nmax_duration_s = 40.0\n\
             [processes.ros.settings]\nrecord_bag = \"ros2_bag\"\nrecord_bag_compression = \"lz4\"\nlinger_s = 3.0\n",
            ros2.canonicalize().unwrap().display()
        ),
    );
    // `extends` must come before any table: move it to the top.
    let text = std::fs::read_to_string(&cfg).unwrap();
    let (ext, rest): (Vec<&str>, Vec<&str>) = text.lines().partition(|l| l.starts_with("extends"));
    std::fs::write(&cfg, format!("{}\n{}\n", ext.join("\n"), rest.join("\n"))).unwrap();
    run.start_supervisor_in(&ns.wrapper(), &cfg, &[]);
    let listen = cyclone(
        &ns,
        &[
            "listen",
            "240",
            "/slam/fused/odometry:odometry",
            "/slam/fused/pose:pose",
            "/slam/fused/path:path",
            "/slam/local/odometry:odometry",
            "/octomap_point_cloud_centers:cloud",
            "/slam/landmarks:markers",
            "/slam/obstacles:markers",
            "/slam/traversability:map",
            "/slam/traversability/cloud:cloud",
            "/tf:tf",
            "/tf_static:tf",
        ],
    );
    let pid = run.spawn(&mut { listen }).id();
    let status = run.wait_supervisor(Duration::from_secs(300)).expect("the run ends");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    assert!(run.leftovers().is_empty());
    let s = run.summary();
    let heard = stop_listener(&mut run, pid);
    let gw = part::<Ros2Part>(&s).ros2.remove("ros").expect("the gateway's part");
    assert_eq!(gw.not_carried, 0, "{gw:?}");
    let fused = gw.out["/slam/fused/odometry"].counts.published;
    assert!(fused > 20, "{gw:?}");
    assert_eq!(heard["/slam/fused/odometry"]["count"], fused, "every fused pose reached Cyclone: {heard}");
    assert_eq!(heard["/tf"]["count"], gw.out["/tf"].counts.published, "{heard}");
    // Near the ground truth (the same ATE the run reports, here per pose).
    let truth = std::fs::read_to_string(run.out_dir().join("ground_truth.tum")).unwrap();
    let truth: Vec<[f64; 4]> = truth
        .lines()
        .filter_map(|l| {
            let v: Vec<f64> = l.split_whitespace().filter_map(|x| x.parse().ok()).collect();
            (v.len() == 8).then(|| [v[0], v[1], v[2], v[3]])
        })
        .collect();
    let last = &heard["/slam/fused/odometry"]["last"];
    let t = last["stamp_ns"].as_f64().unwrap() * 1e-9;
    let near = truth.iter().min_by(|a, b| (a[0] - t).abs().total_cmp(&(b[0] - t).abs())).unwrap();
    let p: Vec<f64> = last["position"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    let err = ((p[0] - near[1]).powi(2) + (p[1] - near[2]).powi(2) + (p[2] - near[3]).powi(2)).sqrt();
    assert!((near[0] - t).abs() < 0.2 && err < 2.0, "last fused pose {p:?} at {t} s vs truth {near:?}: {err} m");
    assert!(last["cov_diag"].as_array().unwrap()[..3].iter().all(|v| v.as_f64().unwrap() > 0.0), "{last}");
    let cloud = &heard["/octomap_point_cloud_centers"]["last"];
    assert_eq!(cloud["point_step"], 16, "{cloud}");
    assert_eq!(
        cloud["fields"],
        serde_json::json!([["x", 0, 7], ["y", 4, 7], ["z", 8, 7], ["occupancy", 12, 7]]),
        "{cloud}"
    );
    assert!(cloud["width"].as_u64().unwrap() > 100, "{cloud}");
    assert_eq!(cloud["bytes"], cloud["width"].as_u64().unwrap() * 16);
    assert!(heard["/slam/landmarks"]["count"].as_u64().unwrap() >= 1, "{heard}");
    // The mapper's traversability grid at the end of its run, as Nav2 takes a map (navigable 0,
    // obstacle 100, unknown -1) at the map's 0.1 m, and its known cells as an elevation cloud.
    let trav = &heard["/slam/traversability"]["last"];
    assert!(heard["/slam/traversability"]["count"].as_u64().unwrap_or(0) >= 1, "{heard}");
    assert!((trav["resolution"].as_f64().unwrap() - 0.1).abs() < 1e-6, "{trav}");
    let (w, h) = (trav["width"].as_u64().unwrap(), trav["height"].as_u64().unwrap());
    assert_eq!(trav["cells"], w * h, "{trav}");
    let known = trav["known"].as_u64().unwrap();
    eprintln!("traversability through ROS 2: {trav}");
    assert!(known > 1000, "the seabed seen in 40 s: {trav}");
    let elevation = &heard["/slam/traversability/cloud"]["last"];
    assert_eq!(
        elevation["fields"],
        serde_json::json!([["x", 0, 7], ["y", 4, 7], ["z", 8, 7], ["slope", 12, 7], ["class", 16, 7]]),
        "{elevation}"
    );
    assert_eq!(elevation["width"], known, "one point per known cell: {elevation}");
    assert_eq!(elevation["bytes"], known * 20, "{elevation}");
    let statics = heard["/tf_static"]["last"]["transforms"].as_array().unwrap().len();
    assert_eq!(statics, 5, "four mounts and map -> odom: {heard}");
    assert_eq!(heard["/tf"]["last"]["transforms"][0][0], "odom");

    // The gateway's ROS 2 bag (`record_bag`, LZ4 chunks), read by Python `rosbags`: every
    // message it published, each decoded.
    let bag = run.out_dir().join("ros2_bag");
    let o = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("python/rosbags_interop.py"))
        .arg("read")
        .arg(&bag)
        .output()
        .unwrap();
    assert!(o.status.success(), "rosbags cannot read {}: {}", bag.display(), String::from_utf8_lossy(&o.stderr));
    let read: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    for (topic, r) in &gw.out {
        // Published, or (nobody subscribed yet, or at all: /slam/local/path) only written.
        let routed = r.counts.published + r.counts.no_subscriber;
        assert_eq!(read[topic]["count"], routed, "{topic}: {read}");
        assert_eq!(read[topic]["type"], r.ros_type, "{topic}");
    }
    assert_eq!(read["/tf_static"]["first"]["transforms"].as_array().unwrap().len(), 5, "{read}");
    assert_eq!(read["/slam/fused/odometry"]["last"]["frame_id"], "map");
}
