//! A base station under attack, as issue "let no one in" tried it, inside a network namespace of
//! the test's own (nothing leaves it): the base station's pipeline (a bridge receiving robot
//! `auv1`'s odometry over mutual TLS, a recorder) with certificates made by `supervisor certs`; a
//! rogue peer written with Eclipse Zenoh's own Python API (`tests/python/zenoh_rogue.py`) puts
//! messages with the public wire signature under `auv1`'s key: without a certificate, with a
//! valid certificate of the same CA for `auv2`, and over plain TCP; then the real `auv1` sends
//! its stream. The base station's pipeline holds exactly `auv1`'s messages (the digest of the
//! bytes equal to what `auv1` sent; nothing refused for a wrong signature or length: the rogue's
//! never reached the bridge), and a capture of the link (tcpdump in the namespace) holds no
//! plaintext of it.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use pipeline_tests::{NetNs, TestRun};

const LONG: Duration = Duration::from_secs(240);
const ODOMETRY: &str = "pipeline/sensors/odometry";
const PORT: u16 = 7447;

fn tls(dir: &Path, name: &str) -> String {
    format!(
        "tls = {{ ca_certificate = {:?}, certificate = {:?}, private_key = {:?} }}",
        dir.join("ca.pem"),
        dir.join(format!("{name}.pem")),
        dir.join(format!("{name}.key"))
    )
}

/// Runs the rogue peer in the namespace; returns (peers it was linked to, messages it put).
fn rogue(ns: &NetNs, endpoint: &str, certs: Option<(&Path, Option<&str>)>) -> (u64, u64) {
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python/zenoh_rogue.py");
    let signature = bridge_stage::signature(pipeline_runtime::topics::topic(ODOMETRY).expect("topic"));
    let mut cmd = ns.command("python3");
    cmd.arg(&script).args(["--endpoint", endpoint, "--key", &format!("slam/auv1/{ODOMETRY}")]);
    cmd.args(["--attachment", &signature, "--count", "100", "--seconds", "2"]);
    if let Some((dir, name)) = certs {
        cmd.arg("--ca").arg(dir.join("ca.pem"));
        if let Some(n) = name {
            cmd.arg("--cert").arg(dir.join(format!("{n}.pem"))).arg("--key-file").arg(dir.join(format!("{n}.key")));
        }
    }
    let out = cmd.output().expect("python3 runs the rogue peer");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "the rogue peer (PyPI eclipse-zenoh; scripts/test.sh installs it): {}\n{stdout}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).expect("the rogue's JSON line");
    (v["peers"].as_u64().expect("peers"), v["put"].as_u64().expect("put"))
}

/// Kills tcpdump on drop (it writes each packet as it comes: `-U`).
struct Capture(std::process::Child);

impl Drop for Capture {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn a_rogue_peer_puts_nothing_into_the_base_stations_pipeline_and_the_link_shows_no_plaintext() {
    let ns = NetNs::required("sec");
    let dir = tempfile::tempdir().expect("tmp");
    let certs = dir.path();
    let made = Command::new(pipeline_tests::bin("supervisor"))
        .args(["certs", "--days", "1", "--name", "base", "--name", "auv1", "--name", "auv2", "--dir"])
        .arg(certs)
        .output()
        .expect("supervisor certs runs");
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));

    let pcap = certs.join("link.pcap");
    let capture = Capture(
        ns.command("tcpdump")
            .args(["-i", "lo", "-U", "-s", "0", "-w"])
            .arg(&pcap)
            .args(["tcp", "port", &PORT.to_string()])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("tcpdump runs (Debian package tcpdump; scripts/test.sh installs it)"),
    );

    let mut base = TestRun::new("secbase");
    let base_cfg = base.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"rec\", \"link\"]\nduration_s = 200",
        &format!(
            r#"
[processes.rec]
kind = "recorder"
[processes.rec.settings]
services = ["{ODOMETRY}"]
end_after = ["link"]
send_end_of_stream = true

[processes.link]
kind = "bridge"
after = ["rec"]
[processes.link.settings]
zenoh = {{ listen = ["tls/127.0.0.1:{PORT}"], {} }}
in = [{{ from = "auv1", service = "{ODOMETRY}" }}]
"#,
            tls(certs, "base")
        ),
    );
    base.start_supervisor_in(&ns.wrapper(), &base_cfg, &[]);
    base.wait_for_log("zenoh session open", 1, Duration::from_secs(60));

    let endpoint = format!("tls/127.0.0.1:{PORT}");
    let no_cert = rogue(&ns, &endpoint, Some((certs, None)));
    let auv2 = rogue(&ns, &endpoint, Some((certs, Some("auv2"))));
    let plain = rogue(&ns, &format!("tcp/127.0.0.1:{PORT}"), None);
    assert_eq!(no_cert.0, 0, "a peer without a certificate got in");
    assert_eq!(plain.0, 0, "a plain TCP peer got in");
    assert_eq!(auv2.0, 1, "auv2's certificate is valid: it connects (and may publish only under auv2)");

    let mut robot = TestRun::new("secrobot");
    let robot_cfg = robot.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"link\"]\nduration_s = 200",
        &format!(
            r#"
[processes.link]
kind = "bridge"
[processes.link.settings]
robot = "auv1"
end_after = ["ingest"]
zenoh = {{ connect = ["tls/127.0.0.1:{PORT}"], {} }}
out = [{{ service = "{ODOMETRY}" }}]

[processes.ingest]
kind = "ingest"
after = ["link"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 40.0
[processes.ingest.settings.sim.sensors.depth_camera]
rate_hz = 0.0
"#,
            tls(certs, "auv1")
        ),
    );
    robot.start_supervisor_in(&ns.wrapper(), &robot_cfg, &[]);
    let rs = robot.wait_supervisor(LONG).expect("the robot's run ends");
    let bs = base.wait_supervisor(LONG).expect("the base station's run ends (the robot's end of stream)");
    assert_eq!(rs.code(), Some(0), "robot:\n{}", robot.log());
    assert_eq!(bs.code(), Some(0), "base:\n{}", base.log());
    drop(capture);

    let (r, b) = (robot.summary(), base.summary());
    let out = &r["bridge"]["out"][ODOMETRY]["counts"];
    let inn = &b["bridge"]["in"][ODOMETRY]["counts"];
    eprintln!("rogue (peers, put): no certificate {no_cert:?}, auv2 {auv2:?}, plain {plain:?}\nout {out}\nin {inn}");
    let sent = out["sent"].as_u64().expect("sent");
    assert!(sent > 10, "{out}");
    // Everything that reached the base's bridge under auv1 is auv1's: the count and the digest
    // of the bytes are the robot's, and nothing came with a wrong signature or length.
    assert_eq!(inn["received"].as_u64(), Some(sent), "{inn} against {out}");
    assert_eq!(inn["published"].as_u64(), Some(sent), "{inn}");
    assert_eq!(inn["digest"], out["digest"], "the same bytes, in order");
    assert_eq!(inn["wrong_type"].as_u64(), Some(0), "{inn}");
    assert_eq!(inn["bad_length"].as_u64(), Some(0), "{inn}");
    assert_eq!(b["recorder"]["messages"][ODOMETRY].as_u64(), Some(sent), "{:#}", b["recorder"]);
    assert_eq!(b["bridge"]["security"]["mode"], "mutual_tls");
    // The rogue without a certificate and the plain-TCP one: each attempt refused and counted.
    let refused = b["bridge"]["security"]["refused_handshakes"].as_u64().expect("refused_handshakes");
    eprintln!("refused handshakes: {refused}");
    assert!(refused >= 2, "refused_handshakes {refused}: {}", b["bridge"]["security"]);
    assert_eq!(b["run"]["end_reason"], "end_of_stream", "{}", b["run"]);

    // The capture holds the run's traffic, none of it readable: the wire signature travels with
    // every message (the Zenoh attachment), and over plain TCP it would be in the clear.
    let bytes = std::fs::read(&pcap).expect("the capture");
    assert!(bytes.len() > 20_000, "tcpdump captured only {} bytes", bytes.len());
    let signature = bridge_stage::signature(pipeline_runtime::topics::topic(ODOMETRY).expect("topic"));
    for needle in [signature.as_str(), "slam-wire", "pipeline/sensors/odometry"] {
        assert!(!bytes.windows(needle.len()).any(|w| w == needle.as_bytes()), "`{needle}` in the clear on the link");
    }
    for run in [&robot, &base] {
        assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new(), "iceoryx2 files left behind");
    }
}
