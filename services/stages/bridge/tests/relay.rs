//! The bridge's TLS relays ([`bridge_stage::relay`]) with sockets in place of the Zenoh
//! sessions, on loopback, certificates made here (rcgen):
//! - both directions at full speed at once, over one TLS connection, arrive intact (Zenoh's own
//!   TLS link loses messages and can crash exactly there: Zenoh issue #2557);
//! - a peer whose first message comes in the same segment as its TLS Finished is not stalled;
//! - a peer whose first Zenoh message carries another Zenoh id than its certificate's name is
//!   refused and counted.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use bridge_stage::TlsSettings;
use bridge_stage::relay::{Relays, zid_of};
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair, KeyUsagePurpose,
};

/// Makes a CA and a certificate per name in `dir`; returns each name's settings.
fn certs(dir: &Path, names: &[&str]) -> Vec<TlsSettings> {
    let key = KeyPair::generate().unwrap();
    let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
    p.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    p.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::DigitalSignature];
    p.distinguished_name.push(DnType::CommonName, "test CA");
    std::fs::write(dir.join("ca.pem"), p.self_signed(&key).unwrap().pem()).unwrap();
    let issuer = Issuer::new(p, key);
    names
        .iter()
        .map(|name| {
            let mut p = CertificateParams::new(vec![name.to_string(), "127.0.0.1".into()]).unwrap();
            p.distinguished_name.push(DnType::CommonName, *name);
            p.key_usages = vec![KeyUsagePurpose::DigitalSignature];
            p.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth, ExtendedKeyUsagePurpose::ClientAuth];
            let key = KeyPair::generate().unwrap();
            let cert = p.signed_by(&key, &issuer).unwrap();
            std::fs::write(dir.join(format!("{name}.pem")), cert.pem()).unwrap();
            std::fs::write(dir.join(format!("{name}.key")), key.serialize_pem()).unwrap();
            TlsSettings {
                ca_certificate: dir.join("ca.pem"),
                certificate: dir.join(format!("{name}.pem")),
                private_key: dir.join(format!("{name}.key")),
                verify_name: true,
                receivers: vec![],
                revoked: None,
            }
        })
        .collect()
}

/// A Zenoh InitSyn/InitAck as its first batch goes on a stream link, with `zid`, then `rest`.
fn init(zid: u128, rest: &[u8]) -> Vec<u8> {
    let mut m = vec![0, 0, 0x01, 0x09, (15 << 4) | 0x01];
    m.extend_from_slice(&zid.to_le_bytes());
    let len = (m.len() - 2) as u16;
    m[..2].copy_from_slice(&len.to_le_bytes());
    m.extend_from_slice(rest);
    m
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// The path of a session's Unix-socket endpoint.
fn socket(endpoint: &str) -> std::path::PathBuf {
    endpoint.strip_prefix("unixsock-stream/").expect("a unixsock-stream endpoint").into()
}

/// `n` bytes of a pattern that depends on `seed`.
fn pattern(seed: u8, n: usize) -> Vec<u8> {
    (0..n).map(|i| (i as u64).wrapping_mul(2654435761).wrapping_add(u64::from(seed)) as u8).collect()
}

#[test]
fn both_directions_at_full_speed_over_one_tls_connection_arrive_intact() {
    let dir = tempfile::tempdir().unwrap();
    let tls = certs(dir.path(), &["base", "auv1"]);
    let port = free_port();
    let base = Relays::start(&[format!("tls/127.0.0.1:{port}")], &[], &tls[0], &Default::default()).unwrap();
    let inner = UnixListener::bind(socket(&base.zenoh_listen[0])).expect("the base session's loopback port");
    let robot = Relays::start(&[], &[format!("tls/127.0.0.1:{port}")], &tls[1], &Default::default()).unwrap();

    const N: usize = 64 << 20;
    let (up, down) = (Arc::new(pattern(1, N)), Arc::new(pattern(2, N)));
    // The robot's "session": dials its relay, says InitSyn, then streams `up` while reading `down`.
    let mut r = UnixStream::connect(socket(&robot.zenoh_connect[0])).unwrap();
    r.write_all(&init(zid_of("auv1"), &[])).unwrap();
    let (mut b, _) = inner.accept().unwrap();
    let mut syn = vec![0u8; init(0, &[]).len()];
    b.read_exact(&mut syn).unwrap();
    assert_eq!(syn, init(zid_of("auv1"), &[]), "the robot's first message, as sent");
    b.write_all(&init(zid_of("base"), &[])).unwrap();
    let mut ack = vec![0u8; syn.len()];
    r.read_exact(&mut ack).unwrap();
    assert_eq!(ack, init(zid_of("base"), &[]));

    let send = |mut s: UnixStream, data: Arc<Vec<u8>>| {
        std::thread::spawn(move || {
            for c in data.chunks(100_003) {
                s.write_all(c).unwrap();
            }
        })
    };
    let recv = |mut s: UnixStream| {
        std::thread::spawn(move || {
            let mut got = vec![0u8; N];
            s.read_exact(&mut got).unwrap();
            got
        })
    };
    let t = [send(r.try_clone().unwrap(), up.clone()), send(b.try_clone().unwrap(), down.clone())];
    let (at_base, at_robot) = (recv(b.try_clone().unwrap()), recv(r.try_clone().unwrap()));
    for h in t {
        h.join().unwrap();
    }
    assert!(at_base.join().unwrap() == *up, "robot to base: bytes differ");
    assert!(at_robot.join().unwrap() == *down, "base to robot: bytes differ");
    let c = base.counts();
    assert_eq!((c.links_opened, c.refused.len()), (1, 0), "{c:?}");
}

/// A TLS client of `tls`'s certificate connected to `port`, its handshake done but its Finished
/// still queued (not sent).
fn raw_client(tls: &TlsSettings, port: u16) -> (rustls::ClientConnection, TcpStream) {
    use rustls::pki_types::pem::PemObject;
    let provider = Arc::new(rustls::crypto::aws_lc_rs::default_provider());
    let mut roots = rustls::RootCertStore::empty();
    for c in rustls::pki_types::CertificateDer::pem_file_iter(&tls.ca_certificate).unwrap() {
        roots.add(c.unwrap()).unwrap();
    }
    let chain: Vec<_> =
        rustls::pki_types::CertificateDer::pem_file_iter(&tls.certificate).unwrap().map(|c| c.unwrap()).collect();
    let key = rustls::pki_types::PrivateKeyDer::from_pem_file(&tls.private_key).unwrap();
    let config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots)
        .with_client_auth_cert(chain, key)
        .unwrap();
    let mut c = rustls::ClientConnection::new(Arc::new(config), "127.0.0.1".try_into().unwrap()).unwrap();
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    while c.is_handshaking() {
        if c.wants_write() {
            c.write_tls(&mut s).unwrap();
        } else {
            c.read_tls(&mut s).unwrap();
            c.process_new_packets().unwrap();
        }
    }
    (c, s)
}

#[test]
fn bytes_after_the_peers_close_notify_are_dropped_and_the_link_closes() {
    let dir = tempfile::tempdir().unwrap();
    let tls = certs(dir.path(), &["base", "auv1"]);
    let port = free_port();
    let base = Relays::start(&[format!("tls/127.0.0.1:{port}")], &[], &tls[0], &Default::default()).unwrap();
    let _inner = UnixListener::bind(socket(&base.zenoh_listen[0])).unwrap();
    let (mut c, mut s) = raw_client(&tls[1], port);
    // Finished, a 20 kB message, close_notify, then 64 kB more, in one write.
    c.writer().write_all(&init(zid_of("auv1"), &vec![7u8; 20_000])).unwrap();
    c.send_close_notify();
    let mut all = vec![];
    while c.wants_write() {
        c.write_tls(&mut all).unwrap();
    }
    all.extend(std::iter::repeat_n(0x17u8, 65_536));
    s.write_all(&all).unwrap();
    let mut buf = [0u8; 64];
    let t0 = std::time::Instant::now();
    loop {
        match s.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(_) => assert!(t0.elapsed() < Duration::from_secs(10), "the link did not close"),
        }
    }
    assert!(t0.elapsed() < Duration::from_secs(9), "the relay closed the link only at its timeout");
}

#[test]
fn a_first_message_in_the_same_segment_as_the_tls_finished_is_not_held_back() {
    let dir = tempfile::tempdir().unwrap();
    let tls = certs(dir.path(), &["base", "auv1"]);
    let port = free_port();
    let base = Relays::start(&[format!("tls/127.0.0.1:{port}")], &[], &tls[0], &Default::default()).unwrap();
    let inner = UnixListener::bind(socket(&base.zenoh_listen[0])).unwrap();

    // A client that sends its Finished and its first message in one write.
    let (mut c, mut s) = raw_client(&tls[1], port);
    // The Finished is queued, not sent: the first message joins it.
    let first = init(zid_of("auv1"), b"and more");
    c.writer().write_all(&first).unwrap();
    let mut both = vec![];
    while c.wants_write() {
        c.write_tls(&mut both).unwrap();
    }
    s.write_all(&both).unwrap();
    let (mut b, _) = inner.accept().unwrap();
    b.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let mut got = vec![0u8; first.len()];
    b.read_exact(&mut got).expect("the first message comes through without more bytes after it");
    assert_eq!(got, first);
}

#[test]
fn a_peer_with_another_zenoh_id_than_its_certificates_name_is_refused_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let tls = certs(dir.path(), &["base", "auv2"]);
    let port = free_port();
    let base = Relays::start(&[format!("tls/127.0.0.1:{port}")], &[], &tls[0], &Default::default()).unwrap();
    let inner = UnixListener::bind(socket(&base.zenoh_listen[0])).unwrap();
    inner.set_nonblocking(true).unwrap();
    let robot = Relays::start(&[], &[format!("tls/127.0.0.1:{port}")], &tls[1], &Default::default()).unwrap();
    // auv2's certificate, auv1's Zenoh id.
    let mut r = UnixStream::connect(socket(&robot.zenoh_connect[0])).unwrap();
    r.write_all(&init(zid_of("auv1"), b"forged")).unwrap();
    r.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let mut buf = [0u8; 16];
    assert_eq!(r.read(&mut buf).unwrap_or(0), 0, "the link closes");
    let c = base.counts();
    assert_eq!(c.links_opened, 0, "{c:?}");
    assert_eq!(c.refused.len(), 1, "{c:?}");
    assert!(
        c.refused[0].reason.contains("`auv2`'s") && c.refused[0].reason.contains("came as another Zenoh id"),
        "{c:?}"
    );
    // Nothing of it reached the session (a connection may have been opened, no byte sent).
    if let Ok((mut b, _)) = inner.accept() {
        b.set_nonblocking(false).unwrap();
        b.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
        assert_eq!(b.read(&mut buf).unwrap_or(0), 0, "bytes of a refused peer reached the session");
    }
}

#[test]
fn a_base_station_not_up_is_unreachable_not_a_refusal() {
    let dir = tempfile::tempdir().unwrap();
    let tls = certs(dir.path(), &["auv1"]);
    let port = free_port();
    let robot = Relays::start(&[], &[format!("tls/127.0.0.1:{port}")], &tls[0], &Default::default()).unwrap();
    let mut r = UnixStream::connect(socket(&robot.zenoh_connect[0])).unwrap();
    // The relay may find the base station unreachable and close the session's link before the
    // first message is written: a broken pipe then is that same closing (CI, 2026-12-07).
    match r.write_all(&init(zid_of("auv1"), &[])) {
        Ok(()) => {}
        Err(e) if matches!(e.kind(), std::io::ErrorKind::BrokenPipe | std::io::ErrorKind::ConnectionReset) => {}
        Err(e) => panic!("writing the session's first message: {e}"),
    }
    r.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let mut buf = [0u8; 16];
    assert_eq!(r.read(&mut buf).unwrap_or(0), 0, "the session's link closes");
    // The link closes before the failure is counted: wait for the count.
    let t0 = std::time::Instant::now();
    while robot.counts().unreachable.is_empty() && t0.elapsed() < Duration::from_secs(5) {
        std::thread::sleep(Duration::from_millis(20));
    }
    let c = robot.counts();
    assert!(c.refused.is_empty(), "{c:?}");
    assert_eq!(c.unreachable.len(), 1, "{c:?}");
    assert!(c.unreachable[0].reason.starts_with("cannot connect"), "{c:?}");
    assert_eq!(robot.refused_total(), 0);
}
