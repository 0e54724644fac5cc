//! The bridge's link between hosts: mutual TLS done by the bridge itself, its Zenoh session
//! behind it on loopback (docs/security.md, "The TLS link").
//!
//! **Why not Zenoh's own TLS link.** Zenoh's TLS link (zenoh-link-tls 1.10) hands one rustls
//! connection to two tasks at once, its sending one and its receiving one (an `UnsafeCell`;
//! Zenoh issue #2557, open). rustls does not allow that: a message being decrypted swaps the
//! connection's state while a send reads it, and the link closes (what was in flight is lost) or
//! the process dies (seen here: a 140 TB allocation in `rustls::Error::clone` under
//! `ConnectionCommon::write`). In `bridge_bench` the TLS rows lost 1 to 100 of 600-900 messages
//! on a reliable route; plain TCP lost none.
//!
//! **What this does instead.** The Zenoh session speaks only over Unix sockets in a directory of
//! this process (mode 0700: no other user reaches them). Each `tls/<address>` of the settings is
//! a [`Relays`] endpoint of this process:
//! - `listen`: a TLS server on the address; each link it accepts is joined to the session's
//!   Unix-socket listener;
//! - `connect`: a Unix socket the session dials; each link it accepts is joined to a TLS
//!   client connection to the address.
//!
//! The TLS is rustls over aws-lc-rs, mutual: a peer needs a certificate the CA signed, not
//! expired, not revoked. Why aws-lc-rs: a cloud is encrypted by the sending bridge and decrypted
//! by the receiving one, so the AEAD's speed is the secure link's cost over plain TCP; on this
//! project's 2-core x86-64 machine (VAES, AVX-512) aws-lc-rs seals AES-256-GCM at about 20 GB/s,
//! ring at 10 GB/s (docs/bridge.md, "Over mutual TLS"). One rustls connection per link,
//! behind a mutex held only while it encrypts or decrypts, never across a socket call; the two
//! directions run on two threads ([`Joined`]).
//!
//! **Who is who.** Zenoh's access control names hosts by their Zenoh id, which on a Unix socket
//! is all it knows of them. A host's id is derived from its certificate's name ([`zid_of`]); a link
//! gets through only when the first Zenoh message the peer sends on it (its InitSyn when it
//! dialled, its InitAck when it was dialled) carries the id of the name its certificate bears
//! ([`first_zid`]). So a host with `auv2`'s certificate is `auv2` to the access control, and
//! cannot be anyone else.
//!
//! Refused links are counted per peer address and reason, and warned about once per pair.

use std::collections::{BTreeMap, BTreeSet};
use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName, UnixTime};

use pipeline_runtime::StageError;

mod tls;
use tls::*;

/// The longest a TLS handshake and the peer's first Zenoh message may take.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// Handshakes in progress at most (more: refused and counted, against a flood of half-open
/// connections), and from one address.
const MAX_HANDSHAKES: usize = 32;
const MAX_HANDSHAKES_PER_PEER: usize = 4;
/// Bytes read from a socket at once.
const CHUNK: usize = 256 * 1024;
/// A link whose peer's certificate expires is closed at expiry; the receiving thread looks at the
/// clock at least this often.
const EXPIRY_CHECK: Duration = Duration::from_secs(30);

/// Zenoh's transport message id of InitSyn and InitAck (zenoh-protocol, `transport::id::INIT`).
const ZENOH_INIT: u8 = 0x01;

/// The Zenoh id of the host whose certificate is named `name` (lowercase hex as Zenoh writes it):
/// the first 16 bytes of SHA-256 over `slam-bridge zid\0` and the name, its top bit set (ids have
/// no leading zero digit).
pub fn zid_of(name: &str) -> u128 {
    use sha2::Digest;
    let mut h = sha2::Sha256::new();
    h.update(b"slam-bridge zid\0");
    h.update(name.as_bytes());
    let d = h.finalize();
    let mut b = [0u8; 16];
    b.copy_from_slice(&d[..16]);
    u128::from_be_bytes(b) | (1u128 << 127)
}

/// [`zid_of`] as Zenoh's configuration and logs write it.
pub fn zid_hex(name: &str) -> String {
    format!("{:x}", zid_of(name))
}

/// The Zenoh id in the first transport message of a link, as the peer sent it (plain bytes after
/// the TLS): a 2-byte little-endian batch length, the message header (id [`ZENOH_INIT`] in its
/// low 5 bits), the protocol version, a byte whose high 4 bits are the id's length less one, then
/// the id's bytes, least significant first (Zenoh 1.x, protocol version 9). `Ok(None)`: not
/// enough bytes yet.
pub fn first_zid(bytes: &[u8]) -> Result<Option<u128>, String> {
    if bytes.len() < 5 {
        return Ok(None);
    }
    let header = bytes[2];
    if header & 0x1f != ZENOH_INIT {
        return Err(format!("the first message is not Zenoh's InitSyn or InitAck (header {header:#04x})"));
    }
    let len = usize::from(bytes[4] >> 4) + 1;
    let Some(id) = bytes.get(5..5 + len) else {
        return Ok(None);
    };
    let mut le = [0u8; 16];
    le[..len].copy_from_slice(id);
    Ok(Some(u128::from_le_bytes(le)))
}

/// What a certificate says of its holder.
#[derive(Debug, Clone)]
struct Peer {
    name: String,
    not_after_unix_s: i64,
}

fn peer_of(der: &[u8]) -> Result<Peer, String> {
    let (_, cert) = x509_parser::parse_x509_certificate(der).map_err(|e| format!("not an X.509 certificate ({e})"))?;
    let name = cert
        .subject()
        .iter_common_name()
        .next()
        .and_then(|c| c.as_str().ok())
        .ok_or("the certificate has no common name")?
        .to_string();
    Ok(Peer { name, not_after_unix_s: cert.validity().not_after.timestamp() })
}

fn unix_now_s() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs() as i64).unwrap_or(0)
}

/// Peer and reason pairs counted apart at most (more: counted under [`OTHER_PEERS`], so that a
/// flood from many addresses does not grow the counts without bound).
const MAX_PAIRS: usize = 256;
/// The peer name of the pairs over [`MAX_PAIRS`].
const OTHER_PEERS: &str = "other peers";

/// Counts one more link for `peer` and `reason`; returns the pair's count.
fn count(counts: &mut BTreeMap<(String, String), u64>, peer: &str, reason: &str) -> u64 {
    let mut k = (peer.to_string(), reason.to_string());
    if counts.len() >= MAX_PAIRS && !counts.contains_key(&k) {
        k.0 = OTHER_PEERS.into();
    }
    let n = counts.entry(k).or_default();
    *n += 1;
    *n
}

/// Refused links per peer address and reason (the first of each pair is warned about).
#[derive(Debug, Default)]
struct Refused {
    counts: BTreeMap<(String, String), u64>,
}

/// Zenoh id (hex, as Zenoh writes it) → certificate name, of every peer a link was opened with.
pub type Names = Arc<Mutex<BTreeMap<String, String>>>;

/// What the relays share with their threads.
struct Shared {
    stop: AtomicBool,
    server: Arc<rustls::ServerConfig>,
    client: Arc<rustls::ClientConfig>,
    revoked: BTreeSet<String>,
    refused: Mutex<Refused>,
    /// Links not opened because the peer (or this host's session) could not be reached, per
    /// peer and reason.
    unreachable: Mutex<BTreeMap<(String, String), u64>>,
    /// Zenoh id (hex) → certificate name, of every peer a link was opened with.
    names: Names,
    /// Open links' sockets (network, session), shut down when the relays stop.
    open: Mutex<BTreeMap<u64, (TcpStream, UnixStream)>>,
    next_link: AtomicU64,
    links_opened: AtomicU64,
    links_expired: AtomicU64,
    /// Handshakes in progress per peer address (from the network).
    handshakes: Mutex<BTreeMap<String, usize>>,
    /// The accept threads.
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Shared {
    fn refuse(&self, peer: &str, reason: String) {
        let n = count(&mut lock(&self.refused).counts, peer, &reason);
        if n == 1 {
            tracing::warn!(%peer, "TLS link refused: {reason} (counted: bridge.security.links.refused)");
        }
    }

    /// Counts a handshake from `peer` in, unless there are too many.
    fn handshake_begins(&self, peer: &str) -> bool {
        let mut h = lock(&self.handshakes);
        let total: usize = h.values().sum();
        let n = h.get(peer).copied().unwrap_or(0);
        if total >= MAX_HANDSHAKES || n >= MAX_HANDSHAKES_PER_PEER {
            return false;
        }
        h.insert(peer.to_string(), n + 1);
        true
    }

    fn handshake_ends(&self, peer: &str) {
        let mut h = lock(&self.handshakes);
        if let Some(n) = h.get_mut(peer) {
            *n -= 1;
            if *n == 0 {
                h.remove(peer);
            }
        }
    }

    fn unreachable(&self, peer: &str, reason: String) {
        let n = count(&mut lock(&self.unreachable), peer, &reason);
        if n == 1 {
            tracing::warn!(%peer, "TLS link not opened: {reason} (Zenoh tries again; counted: bridge.security.links.unreachable)");
        } else {
            tracing::debug!(%peer, "TLS link not opened: {reason}");
        }
    }

    fn spawn(self: &Arc<Self>, name: &str, f: impl FnOnce() + Send + 'static) -> std::io::Result<()> {
        let h = std::thread::Builder::new().name(name.into()).spawn(f)?;
        let mut t = lock(&self.threads);
        t.retain(|h| !h.is_finished());
        t.push(h);
        Ok(())
    }
}

/// The TLS endpoints of one bridge and the loopback endpoints its Zenoh session uses instead.
pub struct Relays {
    shared: Arc<Shared>,
    /// What the Zenoh session listens on (one per `listen` address).
    pub zenoh_listen: Vec<String>,
    /// What the Zenoh session connects to (one per `connect` address).
    pub zenoh_connect: Vec<String>,
    /// The relays' own listeners, to wake their accept threads when stopping.
    wake: Vec<Wake>,
    /// The directory of the session's sockets (mode 0700), removed when the relays stop.
    dir: PathBuf,
}

/// A listener to shut down and connect to, to wake its accept thread.
enum Wake {
    Tcp(SocketAddr, Option<TcpListener>),
    Unix(PathBuf, Option<UnixListener>),
}

/// What the relays counted (summary.json `bridge.security`).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct RelayCounts {
    /// Links opened (TLS handshake and identity checked).
    pub links_opened: u64,
    /// Links closed because the peer's certificate expired.
    pub links_expired: u64,
    /// Links refused, per peer address and reason.
    pub refused: Vec<RefusedLinks>,
    /// Links not opened because the peer (or this host's session) could not be reached, per
    /// address and reason (not refusals: a base station not up yet, a link cut).
    pub unreachable: Vec<RefusedLinks>,
}

/// Links refused (or not opened) with one peer address for one reason.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct RefusedLinks {
    /// Its address (a dialled peer: the address dialled).
    pub peer: String,
    /// Why.
    pub reason: String,
    /// How many.
    pub links: u64,
}

/// The prefix of the session sockets' directories.
const DIR_PREFIX: &str = "slam-bridge-";

/// Removes the socket directories of bridges that are gone (killed: they could not remove their
/// own).
fn sweep_dirs() {
    let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else { return };
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(pid) = name.to_str().and_then(|n| n.strip_prefix(DIR_PREFIX)).and_then(|r| r.split('-').next()) else {
            continue;
        };
        if pid.parse::<u32>().is_ok() && !Path::new("/proc").join(pid).exists() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// Makes a directory only this user may enter, for the session's Unix sockets.
fn private_dir() -> std::io::Result<PathBuf> {
    use std::os::unix::fs::DirBuilderExt;
    sweep_dirs();
    static N: AtomicU64 = AtomicU64::new(0);
    let nanos =
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.subsec_nanos()).unwrap_or(0);
    loop {
        let n = N.fetch_add(1, Ordering::Relaxed);
        let d = std::env::temp_dir().join(format!("{DIR_PREFIX}{}-{n}-{nanos:x}", std::process::id()));
        match std::fs::DirBuilder::new().mode(0o700).create(&d) {
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            r => return r.map(|()| d),
        }
    }
}

/// Zenoh's endpoint of the Unix socket at `p`.
fn unix_endpoint(p: &Path) -> String {
    format!("unixsock-stream/{}", p.display())
}

/// Splits `tls/<host>:<port>` into the address text.
fn tls_address(endpoint: &str) -> Result<&str, String> {
    endpoint.strip_prefix("tls/").ok_or_else(|| format!("`{endpoint}` is not a tls/<host>:<port> endpoint"))
}

impl Relays {
    /// Starts a TLS relay for every `tls/` endpoint of `listen` and `connect`.
    pub fn start(
        listen: &[String],
        connect: &[String],
        tls: &crate::TlsSettings,
        revoked: &BTreeSet<String>,
    ) -> Result<Self, StageError> {
        let (server, client) = configs(tls).map_err(|e| StageError::Settings(format!("zenoh.tls: {e}")))?;
        let shared = Arc::new(Shared {
            stop: AtomicBool::new(false),
            server: Arc::new(server),
            client: Arc::new(client),
            revoked: revoked.clone(),
            refused: Mutex::default(),
            unreachable: Mutex::default(),
            names: Names::default(),
            open: Mutex::default(),
            next_link: AtomicU64::new(0),
            links_opened: AtomicU64::new(0),
            links_expired: AtomicU64::new(0),
            handshakes: Mutex::default(),
            threads: Mutex::default(),
        });
        let io = |what: String| move |e: std::io::Error| StageError::Settings(format!("{what}: {e}"));
        let dir = private_dir().map_err(io("a directory for the session's sockets".into()))?;
        let mut relays =
            Relays { shared: shared.clone(), zenoh_listen: vec![], zenoh_connect: vec![], wake: vec![], dir };
        for (i, e) in listen.iter().enumerate() {
            let addr = tls_address(e).map_err(StageError::Settings)?;
            let public = TcpListener::bind(addr).map_err(io(format!("zenoh.listen[{i}]: cannot listen on {addr}")))?;
            let inner = relays.dir.join(format!("session-{i}.sock"));
            relays.zenoh_listen.push(unix_endpoint(&inner));
            relays.wake.push(Wake::Tcp(wake_address(&public)?, public.try_clone().ok()));
            let sh = shared.clone();
            shared
                .spawn("tls-accept", move || accept_loop(&sh, Listener::Tcp(public), Side::Server { inner }))
                .map_err(io("thread".into()))?;
        }
        for (i, e) in connect.iter().enumerate() {
            let addr = tls_address(e).map_err(StageError::Settings)?.to_string();
            let host =
                addr.rsplit_once(':').map(|(h, _)| h.trim_start_matches('[').trim_end_matches(']')).unwrap_or("");
            let name = ServerName::try_from(host.to_string())
                .map_err(|e| StageError::Settings(format!("zenoh.connect[{i}]: `{host}` is no host name ({e})")))?;
            let at = relays.dir.join(format!("dial-{i}.sock"));
            let local = UnixListener::bind(&at).map_err(io(format!("{}", at.display())))?;
            relays.zenoh_connect.push(unix_endpoint(&at));
            relays.wake.push(Wake::Unix(at, local.try_clone().ok()));
            let sh = shared.clone();
            shared
                .spawn("tls-dial", move || accept_loop(&sh, Listener::Unix(local), Side::Client { remote: addr, name }))
                .map_err(io("thread".into()))?;
        }
        Ok(relays)
    }

    /// The certificate names of the hosts links were opened with, by Zenoh id (hex), as they
    /// open.
    pub fn names(&self) -> Names {
        self.shared.names.clone()
    }

    /// What was counted so far.
    pub fn counts(&self) -> RelayCounts {
        RelayCounts {
            links_opened: self.shared.links_opened.load(Ordering::Relaxed),
            links_expired: self.shared.links_expired.load(Ordering::Relaxed),
            refused: lock(&self.shared.refused)
                .counts
                .iter()
                .map(|((peer, reason), &links)| RefusedLinks { peer: peer.clone(), reason: reason.clone(), links })
                .collect(),
            unreachable: lock(&self.shared.unreachable)
                .iter()
                .map(|((peer, reason), &links)| RefusedLinks { peer: peer.clone(), reason: reason.clone(), links })
                .collect(),
        }
    }

    /// Links refused in all.
    pub fn refused_total(&self) -> u64 {
        lock(&self.shared.refused).counts.values().sum()
    }
}

/// Where to connect to wake an accept thread blocked on `l`.
fn wake_address(l: &TcpListener) -> Result<SocketAddr, StageError> {
    let mut a = l.local_addr().map_err(|e| StageError::Settings(format!("listener address: {e}")))?;
    if a.ip().is_unspecified() {
        a.set_ip(if a.is_ipv4() { [127, 0, 0, 1].into() } else { std::net::Ipv6Addr::LOCALHOST.into() });
    }
    Ok(a)
}

impl Drop for Relays {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        // A listening socket shut down wakes its accept (Linux: EINVAL); a connection too, in
        // case it does not.
        use nix::sys::socket::{Shutdown as How, shutdown};
        use std::os::fd::AsRawFd;
        for w in &self.wake {
            let _ = match w {
                Wake::Tcp(a, l) => {
                    if let Some(l) = l {
                        let _ = shutdown(l.as_raw_fd(), How::Both);
                    }
                    TcpStream::connect_timeout(a, Duration::from_millis(200)).map(drop)
                }
                Wake::Unix(p, l) => {
                    if let Some(l) = l {
                        let _ = shutdown(l.as_raw_fd(), How::Both);
                    }
                    UnixStream::connect(p).map(drop)
                }
            };
        }
        for (a, b) in lock(&self.shared.open).values() {
            let _ = a.shutdown(Shutdown::Both);
            let _ = b.shutdown(Shutdown::Both);
        }
        let threads = std::mem::take(&mut *lock(&self.shared.threads));
        for t in threads {
            let _ = t.join();
        }
        if let Err(e) = std::fs::remove_dir_all(&self.dir) {
            tracing::debug!("{}: {e}", self.dir.display());
        }
    }
}

/// Which way a relay's links go.
#[derive(Clone)]
enum Side {
    /// TLS from the network, joined to the session's listener at `inner`.
    Server { inner: PathBuf },
    /// Dialled by the session on loopback, joined to a TLS connection to `remote`.
    Client { remote: String, name: ServerName<'static> },
}

/// A relay's listener: TLS from the network, or the session's dialling on a Unix socket.
enum Listener {
    Tcp(TcpListener),
    Unix(UnixListener),
}

/// A connection a relay accepted.
enum Accepted {
    /// From the network, and where from.
    Tcp(TcpStream, SocketAddr),
    /// The session dialling.
    Unix(UnixStream),
}

impl Accepted {
    fn from(&self) -> String {
        match self {
            Accepted::Tcp(_, a) => a.ip().to_string(),
            Accepted::Unix(_) => "this host's session".into(),
        }
    }
}

fn accept_loop(shared: &Arc<Shared>, listener: Listener, side: Side) {
    loop {
        let accepted = match &listener {
            Listener::Tcp(l) => l.accept().map(|(s, a)| Accepted::Tcp(s, a)),
            Listener::Unix(l) => l.accept().map(|(s, _)| Accepted::Unix(s)),
        };
        if shared.stop.load(Ordering::SeqCst) {
            return;
        }
        let sock = match accepted {
            Ok(a) => a,
            Err(e) => {
                tracing::warn!("TLS relay: accept failed: {e}");
                std::thread::sleep(Duration::from_millis(100));
                continue;
            }
        };
        // Handshakes from the network: at most MAX_HANDSHAKES at once, MAX_HANDSHAKES_PER_PEER
        // from one address (the session's own dialling is not counted).
        let from = sock.from();
        let counted = matches!(sock, Accepted::Tcp(..));
        if counted && !shared.handshake_begins(&from) {
            shared.refuse(&from, "too many handshakes at once".into());
            continue;
        }
        let (sh, side, peer) = (shared.clone(), side.clone(), from.clone());
        // Not joined when the relays stop: an open link's sockets are shut down then, and a
        // handshake in progress ends by its deadline (HANDSHAKE_TIMEOUT), so stopping never
        // waits for a peer.
        let spawned = std::thread::Builder::new().name("tls-link".into()).spawn(move || {
            let opened = open(&sh, sock, &side);
            if counted {
                sh.handshake_ends(&peer);
            }
            match opened {
                Ok(link) => link.run(&sh),
                Err(Failure::Refused(peer, reason)) => sh.refuse(&peer, reason),
                Err(Failure::Unreachable(peer, reason)) => sh.unreachable(&peer, reason),
            }
        });
        if let Err(e) = spawned {
            if counted {
                shared.handshake_ends(&from);
            }
            tracing::warn!("TLS relay: no thread for a link: {e}");
        }
    }
}

/// A link between a TLS connection and a loopback one, its handshake done.
struct Joined {
    tls: Mutex<rustls::Connection>,
    /// Held while a thread sends what rustls made, so that records go out in the order made.
    order: Mutex<()>,
    net: TcpStream,
    local: UnixStream,
    peer: Peer,
    peer_addr: String,
}

/// Why a handshake failed, in words that do not depend on what the peer sent (counted per reason:
/// the peer must not be able to make a new reason per attempt).
fn handshake_failure(e: &std::io::Error) -> String {
    use rustls::CertificateError as C;
    let Some(t) = e.get_ref().and_then(|i| i.downcast_ref::<rustls::Error>()) else {
        return format!("{:?}", e.kind());
    };
    match t {
        rustls::Error::NoCertificatesPresented => "no certificate".into(),
        rustls::Error::InvalidCertificate(c) => match c {
            C::Expired | C::ExpiredContext { .. } => "certificate expired".into(),
            C::NotValidYet | C::NotValidYetContext { .. } => "certificate not valid yet".into(),
            C::UnknownIssuer => "certificate not signed by the CA".into(),
            C::NotValidForName | C::NotValidForNameContext { .. } => {
                "certificate does not name the address dialled".into()
            }
            C::Revoked => "certificate revoked".into(),
            C::BadSignature => "bad certificate signature".into(),
            other => format!("certificate refused ({})", variant(other)),
        },
        rustls::Error::AlertReceived(a) => format!("the peer refused ({a:?})"),
        other => variant(other),
    }
}

/// The name of an enum value's variant (its `Debug` text up to the first field).
fn variant(v: &dyn std::fmt::Debug) -> String {
    let d = format!("{v:?}");
    d.split(['(', '{', ' ']).next().unwrap_or_default().to_string()
}

/// Why a link was not opened, and with whom.
enum Failure {
    /// The peer was refused (or refused this host): counted in `refused`.
    Refused(String, String),
    /// The peer or this host's session could not be reached: counted in `unreachable`.
    Unreachable(String, String),
}

/// How long the server side waits for its session's socket (the session starts after the
/// relays).
const SESSION_WAIT: Duration = Duration::from_secs(5);

/// Connects to the session's socket at `inner`, waiting up to [`SESSION_WAIT`] for it.
fn connect_session(inner: &Path, stop: &AtomicBool) -> std::io::Result<UnixStream> {
    let t0 = std::time::Instant::now();
    loop {
        match UnixStream::connect(inner) {
            Err(e) if t0.elapsed() < SESSION_WAIT && !stop.load(Ordering::SeqCst) => {
                tracing::debug!("{}: {e}: the session is not listening yet", inner.display());
                std::thread::sleep(Duration::from_millis(50));
            }
            r => return r,
        }
    }
}

/// Handshake and identity checks of a new link.
fn open(shared: &Shared, sock: Accepted, side: &Side) -> Result<Joined, Failure> {
    let refused = |peer: &str, why: String| Failure::Refused(peer.to_string(), why);
    let io = |peer: &str, what: &str, e: std::io::Error| Failure::Unreachable(peer.to_string(), format!("{what}: {e}"));
    let (mut net, local, mut conn, peer_addr): (TcpStream, Option<UnixStream>, rustls::Connection, String) =
        match (sock, side) {
            (Accepted::Tcp(sock, from), Side::Server { .. }) => {
                let p = from.ip().to_string();
                let c = rustls::ServerConnection::new(shared.server.clone()).map_err(|e| refused(&p, e.to_string()))?;
                (sock, None, c.into(), p)
            }
            (Accepted::Unix(sock), Side::Client { remote, name }) => {
                let addr = remote
                    .to_socket_addrs()
                    .ok()
                    .and_then(|mut a| a.next())
                    .ok_or_else(|| Failure::Unreachable(remote.clone(), "cannot resolve the address".into()))?;
                let net = TcpStream::connect_timeout(&addr, HANDSHAKE_TIMEOUT)
                    .map_err(|e| io(remote, "cannot connect", e))?;
                let c = rustls::ClientConnection::new(shared.client.clone(), name.clone())
                    .map_err(|e| refused(remote, e.to_string()))?;
                (net, Some(sock), c.into(), remote.clone())
            }
            (s, _) => unreachable!("a relay accepts on one kind of listener only ({})", s.from()),
        };
    let _ = net.set_nodelay(true);
    // One deadline for the whole handshake (a timeout per read would let a peer that sends a
    // byte now and then hold its slot for ever).
    let t0 = std::time::Instant::now();
    while conn.is_handshaking() {
        let Some(left) = HANDSHAKE_TIMEOUT.checked_sub(t0.elapsed()).filter(|l| !l.is_zero()) else {
            return Err(refused(
                &peer_addr,
                format!("TLS handshake not done within {} s", HANDSHAKE_TIMEOUT.as_secs()),
            ));
        };
        net.set_read_timeout(Some(left)).map_err(|e| io(&peer_addr, "socket", e))?;
        net.set_write_timeout(Some(left)).map_err(|e| io(&peer_addr, "socket", e))?;
        if let Err(e) = conn.complete_io(&mut net) {
            // Tell the peer why (rustls queued an alert), if it still listens.
            let _ = conn.write_tls(&mut net);
            return Err(refused(&peer_addr, format!("TLS handshake failed: {}", handshake_failure(&e))));
        }
    }
    let der =
        conn.peer_certificates().and_then(|c| c.first()).ok_or_else(|| refused(&peer_addr, "no certificate".into()))?;
    let peer = peer_of(der).map_err(|e| refused(&peer_addr, e))?;
    if shared.revoked.contains(&peer.name) {
        return Err(refused(&peer_addr, format!("certificate of `{}` revoked", peer.name)));
    }
    let local = match (local, side) {
        (Some(l), _) => l,
        (None, Side::Server { inner }) => connect_session(inner, &shared.stop).map_err(|e| {
            Failure::Unreachable(peer_addr.clone(), format!("this host's Zenoh session ({}): {e}", inner.display()))
        })?,
        (None, Side::Client { .. }) => unreachable!("a client side has its loopback socket"),
    };
    conn.set_buffer_limit(None);
    Ok(Joined { tls: Mutex::new(conn), order: Mutex::new(()), net, local, peer, peer_addr })
}

/// A socket's `send` that never blocks (`MSG_DONTWAIT`): a full socket answers `WouldBlock`.
struct DontWait<'a>(&'a TcpStream);

impl Write for DontWait<'_> {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.write_vectored(&[std::io::IoSlice::new(b)])
    }

    fn write_vectored(&mut self, bufs: &[std::io::IoSlice<'_>]) -> std::io::Result<usize> {
        use nix::sys::socket::{MsgFlags, SockaddrStorage, sendmsg};
        use std::os::fd::AsRawFd;
        let flags = MsgFlags::MSG_DONTWAIT | MsgFlags::MSG_NOSIGNAL;
        sendmsg::<SockaddrStorage>(self.0.as_raw_fd(), bufs, &[], flags, None).map_err(std::io::Error::from)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// Plain bytes decrypted, in a buffer that is zeroed only where it grows.
#[derive(Default)]
struct Plain {
    buf: Vec<u8>,
    len: usize,
}

impl Plain {
    /// Room for `k` more bytes, to be filled.
    fn grow(&mut self, k: usize) -> &mut [u8] {
        if self.buf.len() < self.len + k {
            self.buf.resize(self.len + k, 0);
        }
        self.len += k;
        &mut self.buf[self.len - k..self.len]
    }

    fn bytes(&self) -> &[u8] {
        &self.buf[..self.len]
    }

    fn clear(&mut self) {
        self.len = 0;
    }
}

/// Why a link ended.
enum End {
    /// By either side.
    Closed,
    Expired,
    Refused(String),
}

impl Joined {
    /// Sends what rustls has to send (records in the order made).
    fn flush(&self) -> std::io::Result<()> {
        let order = lock(&self.order);
        self.send_made(&order)
    }

    /// Sends what rustls made, straight from its buffers: the connection is held only for sends
    /// that do not block; when the socket is full, this waits for room with the connection let
    /// go (the other direction goes on decrypting). `_order`: records go out in the order made.
    fn send_made(&self, _order: &std::sync::MutexGuard<'_, ()>) -> std::io::Result<()> {
        loop {
            let sent = {
                let mut t = lock(&self.tls);
                if !t.wants_write() {
                    return Ok(());
                }
                t.write_tls(&mut DontWait(&self.net))
            };
            match sent {
                Ok(_) => {}
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    // Room on the network, or the session gone (then nothing more is worth
                    // sending: a peer that stops reading cannot hold the link after it).
                    use nix::poll::{PollFd, PollFlags, PollTimeout, poll};
                    use std::os::fd::AsFd;
                    let mut fds = [
                        PollFd::new(self.net.as_fd(), PollFlags::POLLOUT),
                        PollFd::new(self.local.as_fd(), PollFlags::from_bits_retain(libc::POLLRDHUP)),
                    ];
                    match poll(&mut fds, PollTimeout::NONE) {
                        Ok(_) | Err(nix::errno::Errno::EINTR) => {}
                        Err(e) => return Err(e.into()),
                    }
                    let gone = PollFlags::from_bits_retain(libc::POLLRDHUP) | PollFlags::POLLHUP | PollFlags::POLLERR;
                    if fds[1].revents().is_some_and(|r| r.intersects(gone)) {
                        return Err(std::io::Error::new(
                            std::io::ErrorKind::BrokenPipe,
                            "this host's session closed the link while the peer took nothing",
                        ));
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
    }

    fn shutdown(&self) {
        let _ = self.net.shutdown(Shutdown::Both);
        let _ = self.local.shutdown(Shutdown::Both);
    }

    /// Runs the link until either side closes it: this host's bytes go out at once (the side that
    /// dialled speaks first), the peer's come in once its first Zenoh message has shown who it is.
    fn run(self, shared: &Arc<Shared>) {
        let id = shared.next_link.fetch_add(1, Ordering::Relaxed);
        match (self.net.try_clone(), self.local.try_clone()) {
            (Ok(a), Ok(b)) => {
                lock(&shared.open).insert(id, (a, b));
            }
            _ => return self.shutdown(),
        }
        if shared.stop.load(Ordering::SeqCst) {
            lock(&shared.open).remove(&id);
            return self.shutdown();
        }
        let _ = self.net.set_write_timeout(None);
        let this = Arc::new(self);
        let other = this.clone();
        let up = std::thread::Builder::new().name("tls-send".into()).spawn(move || {
            let r = other.local_to_net();
            other.shutdown();
            r
        });
        let end = this.net_to_local(shared);
        if let Ok(End::Refused(reason)) = &end {
            // Counted before the peer sees the link close.
            shared.refuse(&this.peer_addr, reason.clone());
        }
        this.shutdown();
        if let Ok(h) = up {
            let _ = h.join();
        }
        lock(&shared.open).remove(&id);
        let (peer, name) = (&this.peer_addr, &this.peer.name);
        match end {
            Ok(End::Refused(_)) => {}
            Ok(End::Expired) => {
                shared.links_expired.fetch_add(1, Ordering::Relaxed);
                tracing::warn!(%peer, %name, "TLS link closed: the peer's certificate expired");
            }
            Ok(End::Closed) => tracing::info!(%peer, %name, "TLS link closed"),
            Err(e) => tracing::info!(%peer, %name, "TLS link closed: {e}"),
        }
    }

    /// Hands `bytes` from the network to rustls, appends the plain bytes to `plain` and sends
    /// what rustls has to answer (unless the sending thread is sending: it sends that too; this
    /// thread must not wait for it, or neither side would read while both wait for room).
    /// Returns whether the peer closed the TLS session.
    fn decrypt(&self, mut bytes: &[u8], plain: &mut Plain) -> std::io::Result<bool> {
        let mut closed = false;
        let answer;
        {
            let mut t = lock(&self.tls);
            // Records already waiting are the sending thread's: it is sending them (it holds
            // `order` until rustls has nothing left) and will send ours after them.
            let waiting = t.wants_write();
            // At least once: the handshake may have read records after its own (the peer's first
            // message, in the same segment as its Finished), which wait in rustls.
            loop {
                if !bytes.is_empty() && t.read_tls(&mut bytes)? == 0 {
                    // rustls takes nothing more once the peer closed: the rest is dropped.
                    break;
                }
                let state = match t.process_new_packets() {
                    Ok(s) => s,
                    Err(e) => {
                        drop(t);
                        // Tell the peer (an alert), unless the sending thread is waiting for room.
                        if let Ok(order) = self.order.try_lock() {
                            let _ = self.send_made(&order);
                        }
                        return Err(std::io::Error::new(std::io::ErrorKind::InvalidData, e));
                    }
                };
                let k = state.plaintext_bytes_to_read();
                if k > 0 {
                    t.reader().read_exact(plain.grow(k))?;
                }
                closed |= state.peer_has_closed();
                if bytes.is_empty() || closed {
                    break;
                }
            }
            answer = !waiting && t.wants_write();
        }
        if answer {
            self.flush()?;
        }
        Ok(closed)
    }

    /// Network to loopback until the peer closes; closes at the peer certificate's expiry. Nothing
    /// goes through before the peer's first Zenoh message has the Zenoh id of its certificate's
    /// name (within [`HANDSHAKE_TIMEOUT`]).
    fn net_to_local(&self, shared: &Shared) -> std::io::Result<End> {
        let mut buf = vec![0u8; CHUNK];
        let mut plain = Plain::default();
        let mut local = &self.local;
        let expected = zid_of(&self.peer.name);
        let t0 = std::time::Instant::now();
        // The peer's bytes until its identity is checked.
        let mut pending: Option<Vec<u8>> = Some(vec![]);
        let mut held = true;
        loop {
            let left = self.peer.not_after_unix_s - unix_now_s();
            if left <= 0 {
                return Ok(End::Expired);
            }
            let mut wait = EXPIRY_CHECK.min(Duration::from_secs(left as u64)).max(Duration::from_millis(1));
            if pending.is_some() {
                let Some(w) = HANDSHAKE_TIMEOUT.checked_sub(t0.elapsed()).filter(|w| !w.is_zero()) else {
                    return Ok(End::Refused(format!(
                        "no Zenoh message from `{}` within {} s of the handshake",
                        self.peer.name,
                        HANDSHAKE_TIMEOUT.as_secs()
                    )));
                };
                wait = wait.min(w);
            }
            // First what rustls already holds, then from the socket.
            let n = if std::mem::take(&mut held) {
                0
            } else {
                self.net.set_read_timeout(Some(wait))?;
                match (&self.net).read(&mut buf) {
                    Ok(0) => {
                        let _ = self.local.shutdown(Shutdown::Write);
                        return Ok(End::Closed);
                    }
                    Ok(n) => n,
                    Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {
                        continue;
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                    Err(e) => return Err(e),
                }
            };
            plain.clear();
            let closed = self.decrypt(&buf[..n], &mut plain)?;
            if let Some(p) = &mut pending {
                p.extend_from_slice(plain.bytes());
                plain.clear();
                match first_zid(p) {
                    Err(e) => return Ok(End::Refused(e)),
                    Ok(None) => {}
                    Ok(Some(zid)) if zid != expected => {
                        tracing::debug!(peer = %self.peer_addr, "came as Zenoh id {zid:x}");
                        return Ok(End::Refused(format!(
                            "its certificate is `{}`'s (Zenoh id {expected:x}) but it came as another Zenoh id (a \
                             Zenoh peer of your own with this certificate: set its `id` to \"{expected:x}\")",
                            self.peer.name
                        )));
                    }
                    Ok(Some(_)) => {
                        let zid = format!("{expected:x}");
                        lock(&shared.names).insert(zid.clone(), self.peer.name.clone());
                        shared.links_opened.fetch_add(1, Ordering::Relaxed);
                        tracing::info!(peer = %self.peer_addr, name = %self.peer.name, %zid, "TLS link open");
                        local.write_all(p)?;
                        pending = None;
                    }
                }
            }
            if !plain.bytes().is_empty() {
                local.write_all(plain.bytes())?;
            }
            if closed {
                let _ = self.local.shutdown(Shutdown::Write);
                return Ok(End::Closed);
            }
        }
    }

    /// Loopback to network until this host's session closes the link.
    fn local_to_net(&self) -> std::io::Result<()> {
        let mut buf = vec![0u8; CHUNK];
        let mut local = &self.local;
        loop {
            let n = match local.read(&mut buf) {
                Ok(0) => {
                    lock(&self.tls).send_close_notify();
                    let _ = self.flush();
                    let _ = self.net.shutdown(Shutdown::Write);
                    return Ok(());
                }
                Ok(n) => n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(e),
            };
            let order = lock(&self.order);
            lock(&self.tls).writer().write_all(&buf[..n])?;
            self.send_made(&order)?;
        }
    }
}

#[cfg(test)]
mod tests;
