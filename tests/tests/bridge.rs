//! The Zenoh bridge between two pipelines on loopback: a robot (a short simulated mission through
//! `ingest`, a recorder, a bridge sending odometry, depth and buoy ranges) and a base station (a
//! bridge receiving them, a recorder), two supervisors with their own iceoryx2 prefixes, roots
//! and output directories, joined over TCP on 127.0.0.1. The base station's recording holds every
//! message the robot's holds, payload for payload with the same `origin_ns` (publish_ns stamped
//! anew); the robot's end of stream ends the base station's pipeline; messages with another wire
//! signature or a wrong length, put on the robot's keys by a stranger, are counted and not
//! published. (Network namespaces, link faults and the full mission come with the rest of issue
//! #16.)

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use pipeline_tests::TestRun;
use zenoh::Wait;

const LONG: Duration = Duration::from_secs(240);
const SERVICES: [&str; 3] = ["pipeline/sensors/odometry", "pipeline/sensors/depth", "pipeline/sensors/buoy_ranges"];

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").expect("bind").local_addr().expect("addr").port()
}

/// Messages of `topic` in an MCAP file: (origin_ns, publish_ns, user header after `MsgHeader` +
/// payload).
fn messages(path: &Path, topic: &str) -> Vec<(u64, u64, Vec<u8>)> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    mcap::MessageStream::new(&bytes)
        .expect("MCAP")
        .map(|m| m.expect("message"))
        .filter(|m| m.channel.topic == topic)
        .map(|m| {
            let u = |i: usize| u64::from_le_bytes(m.data[i..i + 8].try_into().unwrap());
            (u(16), u(24), m.data[32..].to_vec())
        })
        .collect()
}

#[test]
fn a_robots_streams_reach_a_base_station_byte_for_byte_and_its_end_of_stream_ends_the_base() {
    let port = free_port();
    let services = SERVICES.iter().map(|s| format!("\"{s}\"")).collect::<Vec<_>>().join(", ");
    let ins = SERVICES.iter().map(|s| format!("{{ from = \"r1\", service = \"{s}\" }}")).collect::<Vec<_>>().join(", ");
    let outs = SERVICES.iter().map(|s| format!("{{ service = \"{s}\" }}")).collect::<Vec<_>>().join(", ");

    let mut base = TestRun::new("brbase");
    let base_cfg = base.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"rec\"]\nduration_s = 200",
        &format!(
            r#"
[processes.rec]
kind = "recorder"
[processes.rec.settings]
services = [{services}]
end_after = ["link"]
send_end_of_stream = true

[processes.link]
kind = "bridge"
after = ["rec"]
[processes.link.settings]
zenoh = {{ listen = ["tcp/127.0.0.1:{port}"] }}
in = [{ins}]
"#
        ),
    );
    base.start_supervisor(&base_cfg, &[]);
    base.wait_for_log("zenoh session open", 1, Duration::from_secs(60));

    // A stranger puts a message with another wire signature and one of a wrong length on the
    // robot's odometry key: counted, not published.
    {
        let mut c = zenoh::Config::default();
        c.insert_json5("mode", "\"peer\"").unwrap();
        c.insert_json5("connect/endpoints", &format!("[\"tcp/127.0.0.1:{port}\"]")).unwrap();
        c.insert_json5("scouting/multicast/enabled", "false").unwrap();
        let s = zenoh::open(c).wait().expect("a stranger's session");
        let k = "slam/r1/pipeline/sensors/odometry";
        let p = s.declare_publisher(k).wait().expect("publisher");
        let t0 = std::time::Instant::now();
        while !p.matching_status().wait().unwrap().matching() {
            assert!(t0.elapsed() < Duration::from_secs(30), "the base station's bridge never subscribed");
            std::thread::sleep(Duration::from_millis(20));
        }
        let right = bridge_stage::signature(pipeline_runtime::topics::topic(SERVICES[0]).unwrap());
        p.put(vec![0u8; 32 + 168]).attachment("slam-wire;v=0;h=Old;p=Old;slice=false").wait().unwrap();
        p.put(vec![0u8; 32 + 7]).attachment(right.as_str()).wait().unwrap();
        s.close().wait().unwrap();
    }

    let mut robot = TestRun::new("brrobot");
    let robot_cfg = robot.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"rec\", \"link\"]\nduration_s = 200",
        &format!(
            r#"
[processes.rec]
kind = "recorder"
[processes.rec.settings]
services = [{services}]
end_after = ["ingest"]
send_end_of_stream = true

[processes.link]
kind = "bridge"
[processes.link.settings]
robot = "r1"
end_after = ["ingest"]
zenoh = {{ connect = ["tcp/127.0.0.1:{port}"] }}
out = [{outs}]

[processes.ingest]
kind = "ingest"
after = ["rec", "link"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 40.0
[processes.ingest.settings.sim.sensors.depth_camera]
rate_hz = 0.0
"#
        ),
    );
    robot.start_supervisor(&robot_cfg, &[]);
    let rs = robot.wait_supervisor(LONG).expect("the robot's run ends");
    let bs = base.wait_supervisor(LONG).expect("the base station's run ends (the robot's end of stream)");
    assert_eq!(rs.code(), Some(0), "robot:\n{}", robot.log());
    assert_eq!(bs.code(), Some(0), "base:\n{}", base.log());
    for run in [&robot, &base] {
        assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new(), "iceoryx2 files left behind");
    }
    let (r, b) = (robot.summary(), base.summary());
    let (rb, bb) = (&r["bridge"], &b["bridge"]);
    eprintln!("robot bridge {rb:#}\nbase bridge {bb:#}");
    assert_eq!(rb["end_acknowledged"], true, "{rb:#}");
    assert_eq!(bb["ends_received"], serde_json::json!(["r1"]), "{bb:#}");
    for s in SERVICES {
        let out = &rb["out"][s]["counts"];
        let inn = &bb["in"][s]["counts"];
        let sent = out["sent"].as_u64().unwrap();
        assert!(sent > 5, "{s}: {out}");
        assert_eq!(out["received"].as_u64(), Some(sent), "{s}: {out}");
        let extra = if s == SERVICES[0] { 2 } else { 0 }; // the stranger's two
        assert_eq!(inn["received"].as_u64(), Some(sent + extra), "{s}: {inn}");
        assert_eq!(inn["published"].as_u64(), Some(sent), "{s}: {inn}");
        assert_eq!(bb["in"][s]["lost_on_the_way"].as_u64(), Some(0), "{s}: {bb:#}");
        assert_eq!(inn["undelivered"].as_u64(), Some(0), "{s}: {inn}");
        assert_eq!(b["recorder"]["messages"][s].as_u64(), Some(sent), "{s}: {:#}", b["recorder"]);
    }
    let odo = &bb["in"][SERVICES[0]]["counts"];
    assert_eq!((odo["wrong_type"].as_u64(), odo["bad_length"].as_u64()), (Some(1), Some(1)), "{odo}");
    assert!(base.log().contains("refused a message with another wire signature"), "warned");

    // Payload for payload, with the same origin; published anew (later) on the base station.
    let ingest = &r["ingest"]["messages"];
    let mut compared = BTreeMap::new();
    for (s, key) in SERVICES.iter().zip(["odometry", "depth", "buoy_ranges"]) {
        let here = messages(&robot.out_dir().join("recording.mcap"), s);
        let there = messages(&base.out_dir().join("recording.mcap"), s);
        assert_eq!(here.len() as u64, ingest[key].as_u64().unwrap(), "{s}: the robot's recorder got everything");
        assert_eq!(here.len(), there.len(), "{s}");
        for (a, b) in here.iter().zip(&there) {
            assert_eq!(a.2, b.2, "{s}: payload");
            assert_eq!(a.0, b.0, "{s}: origin_ns kept");
            assert!(b.1 >= a.1, "{s}: published anew on the base station, after the robot");
        }
        compared.insert(*s, here.len());
    }
    eprintln!("compared {compared:?}");
}
