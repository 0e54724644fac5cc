//! The ingest process with real sources, feeding the sensor monitor through iceoryx2.

use std::time::Duration;

use crate::summary_schema::part;
use ingest_stage::summary::IngestPart;
use pipeline_tests::TestRun;
use sensor_monitor_stage::summary::SensorMonitorSummary;
use supervisor::outcome::EndReason;
use supervisor::report::SupervisorPart;

const LONG: Duration = Duration::from_secs(60);

fn repo(path: &str) -> String {
    format!("{}/../{path}", env!("CARGO_MANIFEST_DIR"))
}

const MONITOR: &str = "[processes.monitor]\nkind = \"sensor_monitor\"\n";

const SHORT_SIM: &str = r#"
[processes.ingest]
kind = "ingest"
after = ["monitor"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 30.0
[processes.ingest.settings.sim.sensors.depth_camera]
width_px = 48
height_px = 36
"#;

const RUN_EOS: &str = "end = \"end_of_stream\"\nend_of_stream_from = [\"monitor\"]\nduration_s = 120";

fn run_to_end(run: &mut TestRun, processes: &str) -> serde_json::Value {
    let s = run.run_to_end(RUN_EOS, processes, LONG);
    assert_eq!(part::<SupervisorPart>(&s).run.end_reason, EndReason::EndOfStream, "{s:#}");
    s
}

/// The sensor monitor's part.
fn monitor_part(s: &serde_json::Value) -> SensorMonitorSummary {
    part::<sensor_monitor_stage::summary::SensorMonitorPart>(s).sensor_monitor
}

/// (accepted, rejected, missed) of `service` at the sensor monitor.
fn monitor(s: &serde_json::Value, service: &str) -> (u64, u64, u64) {
    let m = monitor_part(s).streams.remove(service).unwrap_or_else(|| panic!("{service} not monitored: {s:#}"));
    (m.accepted, m.rejected.values().sum(), m.missed)
}

#[test]
fn the_simulated_mission_reaches_the_monitor_complete_with_ground_truth() {
    let mut run = TestRun::new("simmission");
    let s = run_to_end(&mut run, &format!("{MONITOR}{SHORT_SIM}"));
    let sent = part::<IngestPart>(&s).ingest.messages;
    for (svc, published) in [
        ("pipeline/sensors/odometry", sent.odometry),
        ("pipeline/sensors/stereo", sent.stereo),
        ("pipeline/sensors/buoy_ranges", sent.buoy_ranges),
        ("pipeline/sensors/depth", sent.depth),
        ("pipeline/sensors/cloud", sent.cloud),
    ] {
        let (accepted, rejected, missed) = monitor(&s, svc);
        assert!(accepted > 0, "{svc}: nothing arrived: {s:#}");
        assert_eq!(accepted, published, "{svc}: sent vs accepted");
        assert_eq!((rejected, missed), (0, 0), "{svc}");
    }
    assert_eq!(part::<SupervisorPart>(&s).processes["ingest"].undelivered, 0);
    let gt = std::fs::read_to_string(run.out_dir().join("ground_truth.tum")).unwrap();
    let odometry = sent.odometry as usize;
    assert_eq!(gt.lines().count(), odometry + 1, "one true pose per odometry step plus the start");
    let fields: Vec<f64> = gt.lines().nth(10).unwrap().split(' ').map(|f| f.parse().unwrap()).collect();
    assert_eq!(fields.len(), 8, "TUM: t tx ty tz qx qy qz qw");
    let qn: f64 = fields[4..].iter().map(|q| q * q).sum();
    assert!((qn - 1.0).abs() < 1e-6);
    let scene: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.out_dir().join("scene.json")).unwrap()).unwrap();
    assert_eq!(scene["scene"]["buoys_m"].as_array().unwrap().len(), 5);
}

#[test]
fn the_same_seed_publishes_identical_messages_and_another_seed_does_not() {
    let digests = |seed: u64| {
        let mut run = TestRun::new("simseed");
        // A dotted key defines sim.seed; the [..sim.mission] tables below stay valid TOML.
        let procs = format!("{MONITOR}{SHORT_SIM}")
            .replace("source = \"sim\"", &format!("source = \"sim\"\nsim.seed = {seed}"));
        let s = run_to_end(&mut run, &procs);
        monitor_part(&s).digests
    };
    let a = digests(7);
    let b = digests(7);
    let c = digests(8);
    assert_eq!(a, b, "same seed, same messages");
    for svc in [
        "pipeline/sensors/odometry",
        "pipeline/sensors/stereo",
        "pipeline/sensors/buoy_ranges",
        "pipeline/sensors/cloud",
    ] {
        assert_ne!(a[svc], c[svc], "{svc}: another seed must change the data");
    }
}

#[test]
fn plaza2_as_fast_as_possible_delivers_every_row() {
    let mut run = TestRun::new("plaza2");
    let procs = format!(
        "{MONITOR}[processes.monitor.settings]\nknown_buoy_ids = [0, 1, 5, 6]\n\n[processes.ingest]\nkind = \"ingest\"\nafter = [\"monitor\"]\n\
         restart = \"never\"\n[processes.ingest.settings]\nsource = \"plaza2\"\nreal_time_factor = 0.0\n\
         [processes.ingest.settings.plaza2]\ndir = \"{}\"\n",
        repo("algorithms/datasets/data/plaza2")
    );
    let s = run_to_end(&mut run, &procs);
    assert_eq!(monitor(&s, "pipeline/sensors/odometry"), (4090, 0, 0), "{s:#}");
    assert_eq!(monitor(&s, "pipeline/sensors/buoy_ranges"), (1816, 0, 0), "{s:#}");
    let gt = std::fs::read_to_string(run.out_dir().join("ground_truth.tum")).unwrap();
    assert_eq!(gt.lines().count(), 4091);
}

#[test]
fn a_real_time_factor_paces_the_data_clock() {
    let mut run = TestRun::new("rtf");
    let procs = format!("{MONITOR}{}", SHORT_SIM.replace("real_time_factor = 0.0", "real_time_factor = 25.0"));
    let s = run_to_end(&mut run, &procs);
    let ingest = part::<IngestPart>(&s).ingest;
    let (data, wall) = (ingest.data_duration_s, ingest.wall_duration_s);
    assert!(data > 20.0, "{data}");
    // Never faster than 25× (slower is allowed on a loaded machine).
    assert!(wall >= data / 25.0 * 0.95, "{data} s of data in {wall} s");
}

#[test]
fn the_octomap_scan_file_is_replayed_as_one_cloud() {
    let mut run = TestRun::new("scanfile");
    let procs = format!(
        "{MONITOR}\n[processes.ingest]\nkind = \"ingest\"\nafter = [\"monitor\"]\nrestart = \"never\"\n[processes.ingest.settings]\n\
         source = \"clouds\"\nreal_time_factor = 0.0\n[processes.ingest.settings.clouds]\nfiles = [\"{}\"]\nrepeat = 2\n",
        repo("algorithms/datasets/data/octomap/scan.dat.bz2")
    );
    let s = run_to_end(&mut run, &procs);
    assert_eq!(monitor(&s, "pipeline/sensors/cloud"), (2, 0, 0));
    assert_eq!(monitor_part(&s).cloud_points, 2 * 88_206);
}

#[test]
fn depth_images_are_back_projected_into_clouds() {
    let mut run = TestRun::new("depthimg");
    let mut files = vec![];
    for k in 0..3u16 {
        // A fronto-parallel wall at 1.5 m (mm units), with a hole of zeros that must be skipped.
        let data: Vec<u16> = (0..64 * 48).map(|i| if i % 64 < 8 { 0 } else { 1500 + k }).collect();
        let img = datasets::DepthImage::new(64, 48, data).unwrap();
        let path = run.dir.path().join(format!("depth{k}.png"));
        datasets::depth::write_depth_png(&path, &img).unwrap();
        files.push(format!("\"{}\"", path.display()));
    }
    let procs = format!(
        "{MONITOR}\n[processes.ingest]\nkind = \"ingest\"\nafter = [\"monitor\"]\nrestart = \"never\"\n[processes.ingest.settings]\n\
         source = \"depth_images\"\nreal_time_factor = 0.0\n[processes.ingest.settings.depth_images]\nfiles = [{}]\n\
         fx_px = 60.0\nfy_px = 60.0\ncx_px = 31.5\ncy_px = 23.5\n",
        files.join(", ")
    );
    let s = run_to_end(&mut run, &procs);
    assert_eq!(monitor(&s, "pipeline/sensors/cloud"), (3, 0, 0), "{s:#}");
    assert_eq!(monitor_part(&s).cloud_points, 3 * 56 * 48);
}

#[test]
fn the_kitti_stereo_features_are_replayed_when_the_data_set_is_present() {
    let dir = repo("../shared/data/stereo_vo_large");
    let factors = std::path::Path::new(&dir).join("VO_stereo_factors_large.txt");
    if !datasets::shared_data_present(factors, "the_kitti_stereo_features_are_replayed_when_the_data_set_is_present") {
        return;
    }
    let mut run = TestRun::new("stereovo");
    let procs = format!(
        "{MONITOR}\n[processes.ingest]\nkind = \"ingest\"\nafter = [\"monitor\"]\nrestart = \"never\"\n[processes.ingest.settings]\n\
         source = \"stereo_vo\"\nreal_time_factor = 0.0\n[processes.ingest.settings.stereo_vo]\ndir = \"{dir}\"\n"
    );
    let s = run_to_end(&mut run, &procs);
    assert_eq!(monitor(&s, "pipeline/sensors/stereo"), (26, 0, 0));
    assert_eq!(monitor_part(&s).stereo_observations, 8189);
    assert!(run.out_dir().join("vo_camera_poses.tum").exists());
}

#[test]
fn a_malformed_data_file_fails_ingest_with_its_file_and_line() {
    let mut run = TestRun::new("badfile");
    let dir = run.dir.path().join("plaza2");
    std::fs::create_dir_all(&dir).unwrap();
    for f in ["Plaza2_DR.txt", "Plaza2_GT.txt", "Plaza2_TL.txt", "Plaza2_TD.txt"] {
        std::fs::copy(repo(&format!("algorithms/datasets/data/plaza2/{f}")), dir.join(f)).unwrap();
    }
    let td = std::fs::read_to_string(dir.join("Plaza2_TD.txt")).unwrap();
    let mut lines: Vec<&str> = td.lines().collect();
    lines[16] = "3.1566e+003 2.0 1.0";
    std::fs::write(dir.join("Plaza2_TD.txt"), lines.join("\n")).unwrap();
    let procs = format!(
        "{MONITOR}\n[processes.ingest]\nkind = \"ingest\"\nafter = [\"monitor\"]\nrestart = \"never\"\n[processes.ingest.settings]\n\
         source = \"plaza2\"\n[processes.ingest.settings.plaza2]\ndir = \"{}\"\n",
        dir.display()
    );
    let cfg = run.write_config("end = \"signal\"", &procs);
    run.start_supervisor(&cfg, &[]);
    run.wait_for_log("Plaza2_TD.txt:17", 1, LONG);
    run.wait_for_log("not restarted", 1, LONG);
    run.signal_supervisor(nix::sys::signal::Signal::SIGTERM);
    run.wait_supervisor(LONG).expect("stops");
    assert_eq!(run.summary()["processes"]["ingest"]["state"], "FAILED");
    assert_eq!(run.summary()["processes"]["monitor"]["state"], "done", "the rest of the pipeline keeps running");
}

#[test]
fn invalid_ingest_settings_name_their_keys() {
    for (settings, key) in [
        ("source = \"teleport\"", "processes.ingest.settings.source"),
        ("real_time_factor = -1.0", "processes.ingest.settings.real_time_factor"),
        (
            "[processes.ingest.settings.sim.sensors.depth_camera]\nwidth_px = 1000",
            "processes.ingest.settings.sim.sensors.depth_camera",
        ),
        (
            "[processes.ingest.settings.sim.sensors.stereo]\npixel_sigma = 1.0",
            "processes.ingest.settings.sim.sensors.stereo.pixel_sigma",
        ),
    ] {
        let mut run = TestRun::new("badingest");
        let procs =
            format!("{MONITOR}\n[processes.ingest]\nkind = \"ingest\"\n[processes.ingest.settings]\n{settings}\n");
        let cfg = run.write_config("end = \"signal\"", &procs);
        run.start_supervisor(&cfg, &[]);
        let status = run.wait_supervisor(Duration::from_secs(20)).expect("exits");
        assert_eq!(status.code(), Some(2), "{}", run.log());
        assert!(run.log().contains(&format!("`{key}`")), "must name `{key}`:\n{}", run.log());
    }
}
