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

use bridge_stage::summary::BridgePart;
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
/// With a certificate, it uses the Zenoh id of the certificate's name (`zid`: true) or a random
/// one.
fn rogue(ns: &NetNs, endpoint: &str, certs: Option<(&Path, Option<&str>)>, zid: bool) -> (u64, u64) {
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python/zenoh_rogue.py");
    let signature = bridge_stage::signature(wire_topics::topic(ODOMETRY).expect("topic"));
    let mut cmd = ns.command("python3");
    cmd.arg(&script).args(["--endpoint", endpoint, "--key", &format!("slam/auv1/{ODOMETRY}")]);
    cmd.args(["--attachment", &signature, "--count", "100", "--seconds", "2"]);
    if let Some((dir, name)) = certs {
        cmd.arg("--ca").arg(dir.join("ca.pem"));
        if let Some(n) = name {
            cmd.arg("--cert").arg(dir.join(format!("{n}.pem"))).arg("--key-file").arg(dir.join(format!("{n}.key")));
            if zid {
                // The id by docs/security.md's recipe, computed by the script itself.
                cmd.args(["--id-of", n]);
            }
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

/// The base station's config: a bridge receiving `auv1`'s odometry over TLS (`extra` added to
/// its settings), and a recorder of it.
fn base_config(run: &mut TestRun, certs: &Path, extra: &str) -> PathBuf {
    run.write_config(
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
{extra}
zenoh = {{ listen = ["tls/127.0.0.1:{PORT}"], {} }}
in = [{{ from = "auv1", service = "{ODOMETRY}" }}]
"#,
            tls(certs, "base")
        ),
    )
}

/// Makes a CA and certificates for `names` in `dir` with `supervisor certs`.
fn make_certs(dir: &Path, names: &[&str]) {
    let mut cmd = Command::new(pipeline_tests::bin("supervisor"));
    cmd.args(["certs", "--days", "1", "--dir"]).arg(dir);
    for n in names {
        cmd.args(["--name", n]);
    }
    let made = cmd.output().expect("supervisor certs runs");
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
}

/// Defence in depth: a robot whose certificate is valid (here a script holding `auv1`'s, as a
/// hijacked robot would) still gets nothing unsound into the base station's pipeline: messages
/// with NaN, repeated sequence numbers, `origin_ns` 10 s ahead or 1000 s old are refused and
/// counted by reason; a flood of 3000 messages back to back is cut to the route's rate (1000 a
/// second) and the rest counted; every message is accounted for.
#[test]
fn a_compromised_robot_gets_only_sound_messages_in_at_a_bounded_rate() {
    let ns = NetNs::required("seccomp");
    let dir = tempfile::tempdir().expect("tmp");
    let certs = dir.path();
    make_certs(certs, &["base", "auv1"]);
    let mut base = TestRun::new("seccomp");
    // `clock = "keep"`: the script answers no clock ask; it runs on this machine's clock.
    let cfg = base_config(&mut base, certs, "clock = \"keep\"");
    base.start_supervisor_in(&ns.wrapper(), &cfg, &[]);
    base.wait_for_log("zenoh session open", 1, Duration::from_secs(60));

    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python/zenoh_compromised.py");
    let signature = bridge_stage::signature(wire_topics::topic(ODOMETRY).expect("topic"));
    let out = ns
        .command("python3")
        .arg(&script)
        .args(["--endpoint", &format!("tls/127.0.0.1:{PORT}"), "--attachment", &signature])
        .arg("--ca")
        .arg(certs.join("ca.pem"))
        .arg("--cert")
        .arg(certs.join("auv1.pem"))
        .arg("--key-file")
        .arg(certs.join("auv1.key"))
        .args(["--id", &bridge_stage::relay::zid_hex("auv1")])
        .output()
        .expect("python3 runs the compromised robot");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}\n{stdout}", String::from_utf8_lossy(&out.stderr));
    let sent: serde_json::Value = serde_json::from_str(stdout.trim()).expect("the script's JSON line");
    let bs = base.wait_supervisor(LONG).expect("the base station's run ends (the end marker)");
    assert_eq!(bs.code(), Some(0), "base:\n{}", base.log());

    let b = base.summary();
    crate::summary_schema::assert_declared(&b);
    use crate::summary_schema::part;
    let bp: bridge_stage::summary::BridgePart = part(&b);
    let recorder: recorder_stage::summary::RecorderPart = part(&b);
    let c = &bp.bridge.inbound[ODOMETRY].counts;
    eprintln!("sent {sent}\nin {c:?}");
    // What the compromised robot's script says it sent (its own JSON line).
    let n = |v: &serde_json::Value, k: &str| v[k].as_u64().unwrap_or_else(|| panic!("{k} in {v}"));
    let s = &sent["sent"];
    assert_eq!(c.refused_non_finite, n(s, "nan"), "{c:?}");
    assert_eq!(c.refused_going_back, n(s, "repeated"), "{c:?}");
    assert_eq!(c.refused_time, n(s, "future") + n(s, "past"), "{c:?}");
    assert_eq!(c.wrong_type + c.bad_length + c.queue_dropped, 0, "{c:?}");
    let flood = n(s, "flood");
    let (rate_dropped, published) = (c.rate_dropped, c.published);
    // The bucket holds one second's worth (1000) and refills at 1000/s while the flood lasts.
    assert!(rate_dropped > 0 && rate_dropped < flood, "{c:?}");
    assert_eq!(c.seq_gaps, 0, "dropped here is not lost on the way: {c:?}");
    assert!(published >= n(s, "good") + 900, "{c:?}");
    // Every message accounted for: taken in (published or refused) or dropped over the rate.
    assert_eq!(c.received + rate_dropped, n(&sent, "total"), "{c:?}");
    assert_eq!(c.received, published + n(s, "nan") + n(s, "repeated") + n(s, "future") + n(s, "past"));
    assert_eq!(recorder.recorder.messages.get(ODOMETRY), Some(&published), "{:?}", recorder.recorder);
    let log = base.log();
    for reason in ["reason=non_finite", "reason=going_back", "reason=time", "over the route's rate limit"] {
        assert!(log.contains(reason), "no warning with `{reason}`:\n{log}");
    }
    assert_eq!(base.leftovers(), Vec::<std::path::PathBuf>::new(), "iceoryx2 files left behind");
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").expect("bind").local_addr().expect("addr").port()
}

/// A robot's config: its bridge sends its odometry to `port` with its own certificate, its sim
/// drives one leg of `leg_m` at `rtf` times real time.
fn robot_config(run: &mut TestRun, certs: &Path, name: &str, port: u16, leg_m: f64, rtf: f64) -> PathBuf {
    run.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"link\"]\nduration_s = 200",
        &format!(
            r#"
[processes.link]
kind = "bridge"
[processes.link.settings]
robot = "{name}"
end_after = ["ingest"]
end_ack_timeout_s = 3.0
zenoh = {{ connect = ["tls/127.0.0.1:{port}"], {} }}
out = [{{ service = "{ODOMETRY}" }}]

[processes.ingest]
kind = "ingest"
after = ["link"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = {rtf}
progress_interval_s = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = {leg_m}
[processes.ingest.settings.sim.sensors.depth_camera]
rate_hz = 0.0
"#,
            tls(certs, name)
        ),
    )
}

/// A certificate revoked mid-run (`supervisor certs --revoke auv2`): the base station's bridge
/// sees the list change, restarts to apply it, and from then on auv2's links are refused (counted
/// with its name) while auv1 goes on; what auv1 sent during the restart is counted as
/// lost, nothing silently.
#[test]
fn a_certificate_revoked_mid_run_is_refused_from_then_on() {
    let dir = tempfile::tempdir().expect("tmp");
    let certs = dir.path();
    make_certs(certs, &["base", "auv1", "auv2"]);
    let port = free_port();
    let mut base = TestRun::new("secrev");
    let cfg = base.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"link\"]\nduration_s = 200",
        &format!(
            r#"
[processes.link]
kind = "bridge"
backoff_initial_s = 0.1
[processes.link.settings]
zenoh = {{ listen = ["tls/127.0.0.1:{port}"], {} }}
in = [
    {{ from = "auv1", service = "{ODOMETRY}" }},
    {{ from = "auv2", service = "{ODOMETRY}", local = "auv2/{ODOMETRY}" }},
]
"#,
            tls(certs, "base")
        ),
    );
    base.start_supervisor(&cfg, &[]);
    base.wait_for_log("zenoh session open", 1, Duration::from_secs(60));
    let (mut r1, mut r2) = (TestRun::new("secrev1"), TestRun::new("secrev2"));
    let c1 = robot_config(&mut r1, certs, "auv1", port, 6.0, 4.0);
    let c2 = robot_config(&mut r2, certs, "auv2", port, 9.0, 4.0);
    r1.start_supervisor(&c1, &[]);
    r2.start_supervisor(&c2, &[]);
    r2.wait_for_log("process=ingest", 1, Duration::from_secs(60));
    std::thread::sleep(Duration::from_secs(2));
    let revoked = Command::new(pipeline_tests::bin("supervisor"))
        .args(["certs", "--revoke", "auv2", "--dir"])
        .arg(certs)
        .output()
        .expect("supervisor certs --revoke runs");
    assert!(revoked.status.success(), "{}", String::from_utf8_lossy(&revoked.stderr));
    let (s1, s2) = (r1.wait_supervisor(LONG).expect("auv1 ends"), r2.wait_supervisor(LONG).expect("auv2 ends"));
    let bs = base.wait_supervisor(LONG).expect("the base station ends with auv1's end of stream");
    assert_eq!(s1.code(), Some(0), "auv1:\n{}", r1.log());
    assert_eq!(s2.code(), Some(0), "auv2:\n{}", r2.log());
    assert_eq!(bs.code(), Some(0), "base:\n{}", base.log());
    assert!(base.started_pids("link").len() >= 2, "the base's bridge restarted:\n{}", base.log());
    assert!(base.log().contains("the revocation list changed"), "{}", base.log());

    let (a1, a2, b) = (r1.summary(), r2.summary(), base.summary());
    for s in [&a1, &a2, &b] {
        crate::summary_schema::assert_declared(s);
    }
    use crate::summary_schema::part;
    let (p1, p2, bp): (BridgePart, BridgePart, BridgePart) = (part(&a1), part(&a2), part(&b));
    let bb = &bp.bridge;
    eprintln!("base bridge {:#}", b["bridge"]);
    let tls = bb.security.tls.as_ref().expect("mutual TLS");
    assert_eq!(tls.revoked.iter().collect::<Vec<_>>(), ["auv2"], "{bb:?}");
    assert_eq!(bb.ends_received, ["auv1"], "{bb:?}");
    // auv1: everything it sent arrived, or is counted as lost (the restart).
    let sent1 = p1.bridge.out[ODOMETRY].counts.sent;
    let in1 = &bb.inbound[ODOMETRY];
    let got1 = in1.counts.received;
    let lost1 = in1.lost_on_the_way.expect("lost");
    assert!(got1 > sent1 / 2, "{in1:?}");
    assert_eq!(got1 + lost1, sent1, "{in1:?}");
    // auv2: what it sent before the revocation got in; after it, its links are refused at the
    // TLS relay (counted with its certificate's name), so nothing more of it gets in.
    let sent2 = p2.bridge.out[ODOMETRY].counts.sent;
    let in2 = &bb.inbound[&format!("auv2/{ODOMETRY}")];
    let got2 = in2.counts.received;
    eprintln!("auv2 sent {sent2}, received {got2}");
    assert!(got2 > 0 && got2 < sent2, "{in2:?}");
    let links = tls.links.as_ref().expect("the relays' counts");
    let revoked_links: u64 =
        links.refused.iter().filter(|r| r.reason == "certificate of `auv2` revoked").map(|r| r.links).sum();
    assert!(revoked_links > 0, "{links:?}");
    assert_eq!(tls.refused_unauthenticated, Some(revoked_links), "{links:?}");
    assert!(base.log().contains("TLS link refused: certificate of `auv2` revoked"), "warned");
    for run in [&r1, &r2, &base] {
        assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new(), "iceoryx2 files left behind");
    }
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
    make_certs(certs, &["base", "auv1", "auv2"]);

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
    // The robot replays as fast as it can: no rate limit on the way in.
    let base_cfg = base_config(&mut base, certs, "accept = { max_rate_hz = 0 }");
    base.start_supervisor_in(&ns.wrapper(), &base_cfg, &[]);
    base.wait_for_log("zenoh session open", 1, Duration::from_secs(60));

    let endpoint = format!("tls/127.0.0.1:{PORT}");
    let no_cert = rogue(&ns, &endpoint, Some((certs, None)), false);
    let auv2 = rogue(&ns, &endpoint, Some((certs, Some("auv2"))), true);
    let plain = rogue(&ns, &format!("tcp/127.0.0.1:{PORT}"), None, false);
    let other_id = rogue(&ns, &endpoint, Some((certs, Some("auv2"))), false);
    assert_eq!(no_cert.0, 0, "a peer without a certificate got in");
    assert_eq!(plain.0, 0, "a plain TCP peer got in");
    assert_eq!(other_id.0, 0, "a peer with auv2's certificate but another Zenoh id got in");
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
    crate::summary_schema::assert_declared(&r);
    crate::summary_schema::assert_declared(&b);
    use crate::summary_schema::part;
    let (rp, bp): (BridgePart, BridgePart) = (part(&r), part(&b));
    let recorder: recorder_stage::summary::RecorderPart = part(&b);
    let sup: supervisor::report::SupervisorPart = part(&b);
    let out = &rp.bridge.out[ODOMETRY].counts;
    let inn = &bp.bridge.inbound[ODOMETRY].counts;
    eprintln!(
        "rogue (peers, put): no certificate {no_cert:?}, auv2 {auv2:?}, plain {plain:?}\nout {out:?}\nin {inn:?}"
    );
    let sent = out.sent;
    assert!(sent > 10, "{out:?}");
    // Everything that reached the base's bridge under auv1 is auv1's: the count and the digest
    // of the bytes are the robot's, and nothing came with a wrong signature or length.
    assert_eq!(inn.received, sent, "{inn:?} against {out:?}");
    assert_eq!(inn.published, sent, "{inn:?}");
    assert_eq!(inn.digest, out.digest, "the same bytes, in order");
    assert_eq!(inn.wrong_type, 0, "{inn:?}");
    assert_eq!(inn.bad_length, 0, "{inn:?}");
    assert_eq!(recorder.recorder.messages.get(ODOMETRY), Some(&sent), "{:?}", recorder.recorder);
    assert_eq!(bp.bridge.security.mode, "mutual_tls");
    // The rogue without a certificate, the plain-TCP one and the one with another Zenoh id: each
    // attempt refused and counted, with its reason.
    let tls = bp.bridge.security.tls.as_ref().expect("mutual TLS");
    let refused = tls.refused_unauthenticated.expect("refused_unauthenticated");
    let links = tls.links.as_ref().expect("the relays' counts");
    eprintln!("refused links: {refused}: {links:?}");
    assert!(refused >= 3, "refused_unauthenticated {refused}: {}", b["bridge"]["security"]);
    let reasons: Vec<&str> = links.refused.iter().map(|r| r.reason.as_str()).collect();
    assert!(reasons.iter().any(|r| r.contains("came as another Zenoh id")), "{reasons:?}");
    assert!(reasons.iter().any(|r| r.contains("handshake")), "{reasons:?}");
    assert!(base.log().contains("TLS link refused"), "warned");
    // auv2's puts under auv1 reached the base station (it declares its subscriptions to every
    // host) and were refused there by the access control, counted on the route with the host.
    let wrong = bp.bridge.inbound[ODOMETRY].refused_wrong_robot.expect("refused_wrong_robot");
    let hosts = &tls.refused.as_ref().expect("the access control's refusals").refused_wrong_robot;
    eprintln!("refused for the wrong robot: {wrong} of auv2's {}: {hosts:?}", auv2.1);
    assert!(wrong >= auv2.1 * 9 / 10 && wrong <= auv2.1, "{wrong} of {}: {}", auv2.1, b["bridge"]);
    assert_eq!(hosts[0].certificate.as_deref(), Some("auv2"), "{hosts:?}");
    assert!(base.log().contains("the access control refused messages from a host"), "warned");
    assert_eq!(sup.run.end_reason, supervisor::outcome::EndReason::EndOfStream, "{:?}", sup.run);

    // The capture holds the run's traffic, none of it readable: the wire signature travels with
    // every message (the Zenoh attachment), and over plain TCP it would be in the clear.
    let bytes = std::fs::read(&pcap).expect("the capture");
    assert!(bytes.len() > 20_000, "tcpdump captured only {} bytes", bytes.len());
    let signature = bridge_stage::signature(wire_topics::topic(ODOMETRY).expect("topic"));
    for needle in [signature.as_str(), "slam-wire", "pipeline/sensors/odometry"] {
        assert!(!bytes.windows(needle.len()).any(|w| w == needle.as_bytes()), "`{needle}` in the clear on the link");
    }
    for run in [&robot, &base] {
        assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new(), "iceoryx2 files left behind");
    }
}

/// The live view off loopback: the viewer listens on every address of its network namespace
/// (`host = "0.0.0.0"`) with TLS and a token (`supervisor certs --viewer-token`), so the Foxglove
/// SDK's server sits on loopback behind the viewer's gate. A Foxglove WebSocket client (Python
/// `websockets`, as tests/tests/viewer.rs uses) with the CA and the token decodes the live
/// process states; one with a wrong token gets 401, one speaking plain `ws://` and one that does
/// not trust the certificate fail the handshake; each is counted in summary.json `viewer.gate`.
#[test]
fn the_live_view_off_loopback_needs_tls_and_the_token() {
    let ns = NetNs::required("secview");
    let dir = tempfile::tempdir().expect("tmp");
    let certs = dir.path();
    make_certs(certs, &["view"]);
    let made = Command::new(pipeline_tests::bin("supervisor"))
        .args(["certs", "--viewer-token", "--dir"])
        .arg(certs)
        .output()
        .expect("supervisor certs --viewer-token runs");
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let token = std::fs::read_to_string(certs.join("viewer.token")).expect("the token").trim().to_string();
    let port = 8765;
    let mut run = TestRun::new("secview");
    let cfg = run.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"view\"]\nduration_s = 200",
        &format!(
            r#"
[processes.view]
kind = "viewer"
[processes.view.settings]
host = "0.0.0.0"
port = {port}
tls = {{ certificate = {:?}, private_key = {:?} }}
token_file = {:?}
end_after = ["ingest"]

[processes.ingest]
kind = "ingest"
after = ["view"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 8.0
progress_interval_s = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 6.0
[processes.ingest.settings.sim.sensors.depth_camera]
rate_hz = 0.0
"#,
            certs.join("view.pem"),
            certs.join("view.key"),
            certs.join("viewer.token")
        ),
    );
    run.start_supervisor_in(&ns.wrapper(), &cfg, &[]);
    run.wait_for_log("live view over TLS with a token", 1, Duration::from_secs(60));
    let client = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python/foxglove_ws_client.py");
    let ca = certs.join("ca.pem");
    let attempt = |url: &str, ca: Option<&Path>, refused: bool| -> serde_json::Value {
        let mut cmd = ns.command("python3");
        cmd.arg(&client).args(["--url", url, "--timeout-s", "60"]);
        if let Some(c) = ca {
            cmd.arg("--ca").arg(c);
        }
        if refused {
            cmd.arg("--expect-refused");
        } else {
            cmd.args(["--want", "/processes"]);
        }
        let out = cmd.output().expect("python3 runs the Foxglove client");
        let stdout = String::from_utf8_lossy(&out.stdout).to_string();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{url}: {stderr}\n{stdout}");
        if !stderr.trim().is_empty() {
            eprintln!("{url}: {stderr}");
        }
        serde_json::from_str(stdout.lines().last().unwrap_or_default()).expect("the client's JSON line")
    };
    let wrong = attempt(&format!("wss://127.0.0.1:{port}/?token=not-{token}"), Some(&ca), true);
    assert_eq!(wrong["refused"], "http 401", "{wrong}");
    let none = attempt(&format!("wss://127.0.0.1:{port}/"), Some(&ca), true);
    assert_eq!(none["refused"], "http 401", "{none}");
    let plain = attempt(&format!("ws://127.0.0.1:{port}/?token={token}"), None, true);
    assert!(plain["refused"].as_str().is_some_and(|r| r.starts_with("closed")), "{plain}");
    let untrusted = attempt(&format!("wss://127.0.0.1:{port}/?token={token}"), None, true);
    assert!(untrusted["refused"].as_str().is_some_and(|r| r.contains("CERTIFICATE_VERIFY_FAILED")), "{untrusted}");
    let good = attempt(&format!("wss://127.0.0.1:{port}/?token={token}"), Some(&ca), false);
    assert!(good["topics"]["/processes"]["count"].as_u64().is_some_and(|n| n >= 1), "{good}");

    let st = run.wait_supervisor(LONG).expect("the run ends with the mission");
    assert_eq!(st.code(), Some(0), "{}", run.log());
    let viewer: viewer_stage::summary::ViewerPart = crate::summary_schema::part(&run.summary());
    let v = &viewer.viewer;
    eprintln!("viewer {v:?}");
    assert!(v.tls, "{v:?}");
    let g = v.gate.as_ref().expect("the TLS gate's counts");
    assert!(g.admitted >= 1, "{g:?}");
    assert_eq!(g.refused_token, 2, "{g:?}");
    assert!(g.refused_tls >= 2, "{g:?}");
    assert!(run.log().contains("refused a client without the token"), "warned");
    assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new(), "iceoryx2 files left behind");
}
