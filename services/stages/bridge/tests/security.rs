//! The bridge's Zenoh sessions as its TLS settings make them (`session::zenoh_config`), on loopback
//! only, with certificates made here (rcgen): a base station that receives `auv1`'s poses gets
//! them from `auv1` and from nobody else:
//! - `auv2`, whose certificate the same CA signed, connects but cannot publish under `auv1`, nor
//!   under its own name (the base station's config does not receive from it);
//! - a peer without a certificate, one with a certificate named `auv1` from another CA, and one
//!   speaking plain TCP to the TLS port never get in;
//! - `auv1`'s link closes when its certificate expires, and it cannot come back with it.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bridge_stage::BridgeSettings;
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair, KeyUsagePurpose,
};
use zenoh::Wait;

const POSE: &str = "pipeline/fusion/pose";

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").expect("bind").local_addr().expect("addr").port()
}

struct Ca {
    issuer: Issuer<'static, KeyPair>,
    dir: PathBuf,
}

impl Ca {
    fn new(dir: &Path, tag: &str) -> Self {
        let key = KeyPair::generate().unwrap();
        let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
        p.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
        p.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::DigitalSignature];
        p.distinguished_name.push(DnType::CommonName, format!("test CA {tag}"));
        let cert = p.self_signed(&key).unwrap();
        let dir = dir.join(tag);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("ca.pem"), cert.pem()).unwrap();
        Self { issuer: Issuer::new(p, key), dir }
    }

    /// Writes `<name>.pem`/`.key`, valid for `valid` from now; returns the TOML `tls` table.
    fn host(&self, name: &str, valid: Duration) -> String {
        let mut p = CertificateParams::new(vec![name.to_string(), "127.0.0.1".into()]).unwrap();
        p.distinguished_name.push(DnType::CommonName, name);
        p.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        p.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth, ExtendedKeyUsagePurpose::ClientAuth];
        p.not_before = time::OffsetDateTime::now_utc() - time::Duration::minutes(5);
        p.not_after = time::OffsetDateTime::now_utc() + valid;
        let key = KeyPair::generate().unwrap();
        let cert = p.signed_by(&key, &self.issuer).unwrap();
        let (c, k) = (self.dir.join(format!("{name}.pem")), self.dir.join(format!("{name}.key")));
        std::fs::write(&c, cert.pem()).unwrap();
        std::fs::write(&k, key.serialize_pem()).unwrap();
        format!("tls = {{ ca_certificate = {:?}, certificate = {c:?}, private_key = {k:?} }}", self.dir.join("ca.pem"))
    }
}

fn settings(text: &str) -> BridgeSettings {
    let s: BridgeSettings = toml::from_str(text).unwrap_or_else(|e| panic!("{e}\n{text}"));
    let issues = pipeline_runtime::Validate::issues(&s);
    assert!(issues.is_empty(), "{issues}\n{text}");
    s
}

/// A bridge's session and its TLS relays.
struct Host {
    session: zenoh::Session,
    _relays: Option<bridge_stage::relay::Relays>,
}

impl std::ops::Deref for Host {
    type Target = zenoh::Session;
    fn deref(&self) -> &zenoh::Session {
        &self.session
    }
}

fn open(s: &BridgeSettings) -> Host {
    let (session, relays) = bridge_stage::session::open_session(s, &Default::default()).expect("session");
    Host { session, _relays: relays }
}

/// A robot's session: connects to the base station with `tls` and puts on `robot`'s pose key.
fn robot(robot: &str, tls: &str, port: u16) -> Host {
    open(&settings(&format!(
        "robot = \"{robot}\"\nout = [{{ service = \"{POSE}\" }}]\n[zenoh]\nconnect = [\"tls/127.0.0.1:{port}\"]\n{tls}\n"
    )))
}

fn put(s: &zenoh::Session, key: &str, n: usize) {
    for _ in 0..n {
        s.put(key, vec![1u8; 8]).wait().expect("put");
    }
}

fn wait_until(what: &str, limit: Duration, mut f: impl FnMut() -> bool) {
    let t0 = Instant::now();
    while !f() {
        assert!(t0.elapsed() < limit, "{what}: not within {limit:?}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn peers(s: &zenoh::Session) -> usize {
    s.info().peers_zid().wait().count()
}

/// A TLS client that trusts `ca` but has no certificate of its own: connects to `port`, sends a
/// few bytes and reads. Returns how that ended: "refused: ..." when the server closed the
/// connection or alerted, "got N bytes" when it answered.
fn tls_without_certificate(ca: &Path, port: u16) -> String {
    use rustls::pki_types::{CertificateDer, pem::PemObject};
    use std::io::{Read, Write};
    let mut roots = rustls::RootCertStore::empty();
    for c in CertificateDer::pem_file_iter(ca).unwrap() {
        roots.add(c.unwrap()).unwrap();
    }
    let config = rustls::ClientConfig::builder_with_provider(Arc::new(rustls::crypto::aws_lc_rs::default_provider()))
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots)
        .with_no_client_auth();
    let conn = rustls::ClientConnection::new(Arc::new(config), "127.0.0.1".try_into().unwrap()).unwrap();
    let sock = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    sock.set_read_timeout(Some(Duration::from_secs(15))).unwrap();
    let mut tls = rustls::StreamOwned::new(conn, sock);
    // What a Zenoh peer would send first (any bytes: the server must not take them).
    if let Err(e) = tls.write_all(&[0u8; 16]).and_then(|()| tls.flush()) {
        return format!("refused: {e}");
    }
    let mut buf = [0u8; 64];
    match tls.read(&mut buf) {
        Ok(0) => "refused: closed".into(),
        Ok(n) => format!("got {n} bytes"),
        Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {
            "no answer within 15 s (neither refused nor answered)".into()
        }
        Err(e) => format!("refused: {e}"),
    }
}

#[test]
fn only_the_robot_named_by_its_certificate_publishes_under_its_name() {
    let root = tempfile::tempdir().unwrap();
    let ca = Ca::new(root.path(), "ours");
    let other = Ca::new(root.path(), "theirs");
    let port = free_port();
    let base = open(&settings(&format!(
        "in = [{{ from = \"auv1\", service = \"{POSE}\" }}]\n[zenoh]\nlisten = [\"tls/127.0.0.1:{port}\"]\n{}\n",
        ca.host("base", Duration::from_secs(3600))
    )));
    let got: Arc<Mutex<Vec<String>>> = Arc::default();
    let mut subs = vec![];
    for r in ["auv1", "auv2"] {
        let g = got.clone();
        subs.push(
            base.declare_subscriber(format!("slam/{r}/{POSE}"))
                .callback(move |s| g.lock().unwrap().push(s.key_expr().to_string()))
                .wait()
                .unwrap(),
        );
    }
    let count = |r: &str| got.lock().unwrap().iter().filter(|k| k.starts_with(&format!("slam/{r}/"))).count();

    // A rogue host whose certificate the same CA signed, for another robot.
    let auv2 = robot("auv2", &ca.host("auv2", Duration::from_secs(3600)), port);
    wait_until("auv2 connects (its certificate is valid)", Duration::from_secs(20), || peers(&auv2) == 1);
    put(&auv2, &format!("slam/auv1/{POSE}"), 50);
    put(&auv2, &format!("slam/auv2/{POSE}"), 50);

    // Hosts that never get in: a TLS client without a certificate (a plain rustls client: the
    // relays do the TLS), a certificate named auv1 from another CA, plain TCP.
    let no_cert = tls_without_certificate(&ca.dir.join("ca.pem"), port);
    // Refused by the server (its alert, or the connection closed), not by the client itself.
    assert!(
        no_cert.starts_with("refused")
            && ["CertificateRequired", "closed", "reset"].iter().any(|w| no_cert.contains(w)),
        "a TLS client without a certificate: {no_cert}"
    );
    let forged = robot(
        "auv1",
        &other
            .host("auv1", Duration::from_secs(3600))
            .replace(&format!("{:?}", other.dir.join("ca.pem")), &format!("{:?}", ca.dir.join("ca.pem"))),
        port,
    );
    let plain = {
        let mut c = zenoh::Config::default();
        c.insert_json5("mode", "\"peer\"").unwrap();
        c.insert_json5("scouting/multicast/enabled", "false").unwrap();
        c.insert_json5("connect/endpoints", &format!("[\"tcp/127.0.0.1:{port}\"]")).unwrap();
        c.insert_json5("connect/exit_on_failure", "false").unwrap();
        zenoh::open(c).wait().expect("session")
    };

    // The robot itself, with a certificate that expires in 10 s.
    let auv1 = robot("auv1", &ca.host("auv1", Duration::from_secs(10)), port);
    wait_until("auv1 connects", Duration::from_secs(20), || peers(&auv1) == 1);
    wait_until("auv1's 20 poses arrive", Duration::from_secs(20), || {
        put(&auv1, &format!("slam/auv1/{POSE}"), 1);
        count("auv1") >= 20
    });
    for (who, s) in [("auv1 from another CA", &*forged), ("plain TCP", &plain)] {
        put(s, &format!("slam/auv1/{POSE}"), 20);
        assert_eq!(peers(s), 0, "{who} got in");
    }
    put(&auv2, &format!("slam/auv1/{POSE}"), 50);
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(count("auv2"), 0, "auv2 published under its own name, which the base does not receive");
    // Every pose under auv1 came from auv1 (it put one at a time until 20 arrived).
    let from_auv1 = count("auv1");
    assert!((20..=25).contains(&from_auv1), "{from_auv1} poses under auv1: some came from another host");
    assert_eq!(peers(&base), 2, "the base station is linked to auv1 and auv2 only");

    // auv1's certificate expires: the base station closes its link, and it cannot reconnect.
    wait_until("the base closes auv1's link when its certificate expires", Duration::from_secs(30), || {
        peers(&base) == 1
    });
    std::thread::sleep(Duration::from_secs(3));
    assert_eq!(peers(&auv1), 0, "auv1 came back with an expired certificate");
    let before = count("auv1");
    put(&auv1, &format!("slam/auv1/{POSE}"), 20);
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(count("auv1"), before);
    drop(subs);
    for s in [auv1, auv2, forged, base] {
        s.session.close().wait().unwrap();
    }
    plain.close().wait().unwrap();
}
