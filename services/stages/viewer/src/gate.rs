//! The live view's front door off loopback: TLS and a token in front of the Foxglove SDK's
//! WebSocket server (docs/security.md).
//!
//! The SDK's server (0.30) can encrypt but cannot check a client: its handshake looks only at the
//! subprotocol, and no hook sees a client before it is served. So with `tls` set the SDK listens
//! on loopback only (an ephemeral port) and this gate listens on the configured address: it
//! completes the TLS handshake (rustls, the certificate `supervisor certs` made for this host),
//! reads the WebSocket upgrade request and lets it through only with the token, given as
//! `?token=<token>` in the URL (what the Foxglove app can send: a browser's WebSocket cannot set
//! headers) or as `Authorization: Bearer <token>`. A client without it gets `401 Unauthorized`
//! and is closed; one that fails the handshake (plain `ws://`, a certificate it does not trust)
//! never gets that far. Both are counted ([`GateCounts`]) and warned about once per reason. An
//! admitted client's bytes are copied both ways to the SDK's server as they are.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};

/// Largest upgrade request read (a browser's is well under 2 KiB).
const MAX_REQUEST: usize = 16 * 1024;
/// Longest a client may take for the TLS handshake and its request.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// What the gate let in and kept out.
#[derive(Debug, Default)]
pub struct GateCounts {
    /// Clients let through (right token).
    pub admitted: AtomicU64,
    /// Clients refused for a missing or wrong token (answered 401).
    pub refused_token: AtomicU64,
    /// Connections whose TLS handshake failed (not TLS, or the client refused our certificate).
    pub refused_tls: AtomicU64,
    /// Requests that were not a WebSocket upgrade request within limits (answered 400).
    pub refused_request: AtomicU64,
    warned_token: AtomicBool,
    warned_tls: AtomicBool,
}

impl GateCounts {
    /// The counts (summary.json `viewer.gate`).
    pub fn summary(&self) -> crate::summary::GateSummary {
        crate::summary::GateSummary {
            admitted: self.admitted.load(Ordering::Relaxed),
            refused_token: self.refused_token.load(Ordering::Relaxed),
            refused_tls: self.refused_tls.load(Ordering::Relaxed),
            refused_request: self.refused_request.load(Ordering::Relaxed),
        }
    }
}

/// Why a gate cannot start.
#[derive(Debug, thiserror::Error)]
pub enum GateError {
    /// A certificate or key file is missing or unreadable.
    #[error("{path}: {what}")]
    File {
        /// The file.
        path: String,
        /// What is wrong.
        what: String,
    },
    /// rustls refused the certificate and key.
    #[error("TLS: {0}")]
    Tls(String),
    /// The address cannot be listened on.
    #[error("cannot listen on {addr}: {err}")]
    Listen {
        /// The address.
        addr: String,
        /// The error.
        err: std::io::Error,
    },
}

/// The running gate: stops when dropped.
pub struct Gate {
    addr: SocketAddr,
    counts: Arc<GateCounts>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Gate {
    /// The address it listens on (the port chosen when 0 was asked).
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// What it let in and kept out.
    pub fn counts(&self) -> &GateCounts {
        &self.counts
    }
}

impl Drop for Gate {
    fn drop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The TLS configuration of a certificate chain and key (PEM files).
pub fn tls_config(
    certificate: &std::path::Path,
    private_key: &std::path::Path,
) -> Result<rustls::ServerConfig, GateError> {
    use rustls::pki_types::pem::PemObject as _;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let file_err = |p: &std::path::Path, e: &dyn std::fmt::Display| GateError::File {
        path: p.display().to_string(),
        what: format!("{e} (make one: supervisor certs --name <this host>)"),
    };
    let chain: Vec<CertificateDer<'static>> = CertificateDer::pem_file_iter(certificate)
        .map_err(|e| file_err(certificate, &e))?
        .collect::<Result<_, _>>()
        .map_err(|e| file_err(certificate, &e))?;
    if chain.is_empty() {
        return Err(file_err(certificate, &"no certificate in it"));
    }
    let key = PrivateKeyDer::from_pem_file(private_key).map_err(|e| file_err(private_key, &e))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| GateError::Tls(e.to_string()))?
        .with_no_client_auth()
        .with_single_cert(chain, key)
        .map_err(|e| GateError::Tls(format!("{} with {}: {e}", certificate.display(), private_key.display())))?;
    // No TLS 1.3 session tickets. A viewer connects once, so resumption gains nothing, and the
    // tickets arrive after the handshake, before the client's upgrade request: a client that
    // reads on one thread while it writes the request on another (Python's `websockets.sync`)
    // then stalled in 1 connection of ~15 under load here (2026-12-05: its request never left,
    // seen in a capture), and the gate answered 400 ten seconds later.
    config.send_tls13_tickets = 0;
    Ok(config)
}

/// Whether an upgrade request's head (request line and headers) carries `token`, as
/// `?token=<token>` in the target or `Authorization: Bearer <token>`. Compared in constant time.
pub fn has_token(head: &str, token: &str) -> bool {
    let mut lines = head.split("\r\n");
    let target = lines.next().and_then(|l| l.split(' ').nth(1)).unwrap_or_default();
    let from_query = target
        .split_once('?')
        .map(|(_, q)| q)
        .unwrap_or_default()
        .split('&')
        .filter_map(|kv| kv.strip_prefix("token="))
        .any(|t| same(t, token));
    let from_header = lines.filter_map(|l| l.split_once(':')).any(|(name, value)| {
        name.trim().eq_ignore_ascii_case("authorization")
            && value.trim().strip_prefix("Bearer ").is_some_and(|t| same(t.trim(), token))
    });
    from_query || from_header
}

/// Equal strings, in time independent of where they differ.
fn same(a: &str, b: &str) -> bool {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// Starts the gate on `bind`, letting clients with `token` through to `upstream` (the SDK's
/// server on loopback).
pub fn start(
    bind: SocketAddr,
    upstream: SocketAddr,
    tls: rustls::ServerConfig,
    token: String,
) -> Result<Gate, GateError> {
    let listener =
        std::net::TcpListener::bind(bind).map_err(|err| GateError::Listen { addr: bind.to_string(), err })?;
    let addr = listener.local_addr().map_err(|err| GateError::Listen { addr: bind.to_string(), err })?;
    listener.set_nonblocking(true).map_err(|err| GateError::Listen { addr: bind.to_string(), err })?;
    let counts = Arc::new(GateCounts::default());
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let c = counts.clone();
    let thread = std::thread::Builder::new()
        .name("viewer-gate".into())
        .spawn(move || {
            let rt = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
                Ok(rt) => rt,
                Err(e) => {
                    tracing::error!("the live view's TLS gate cannot start its runtime: {e}");
                    return;
                }
            };
            rt.block_on(serve(listener, upstream, Arc::new(tls), Arc::new(token), c, stopped));
        })
        .map_err(|err| GateError::Listen { addr: bind.to_string(), err })?;
    Ok(Gate { addr, counts, stop: Some(stop), thread: Some(thread) })
}

async fn serve(
    listener: std::net::TcpListener,
    upstream: SocketAddr,
    tls: Arc<rustls::ServerConfig>,
    token: Arc<String>,
    counts: Arc<GateCounts>,
    mut stopped: tokio::sync::oneshot::Receiver<()>,
) {
    let listener = match tokio::net::TcpListener::from_std(listener) {
        Ok(l) => l,
        Err(e) => {
            tracing::error!("the live view's TLS gate cannot listen: {e}");
            return;
        }
    };
    let acceptor = tokio_rustls::TlsAcceptor::from(tls);
    loop {
        tokio::select! {
            _ = &mut stopped => return,
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    let (acceptor, token, counts) = (acceptor.clone(), token.clone(), counts.clone());
                    tokio::spawn(async move { client(stream, peer, upstream, acceptor, &token, &counts).await });
                }
                Err(e) => {
                    tracing::warn!("the live view's TLS gate: accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            },
        }
    }
}

/// One client: handshake, token, then bytes both ways.
async fn client(
    stream: tokio::net::TcpStream,
    peer: SocketAddr,
    upstream: SocketAddr,
    acceptor: tokio_rustls::TlsAcceptor,
    token: &str,
    counts: &GateCounts,
) {
    let mut tls = match tokio::time::timeout(HANDSHAKE_TIMEOUT, acceptor.accept(stream)).await {
        Ok(Ok(t)) => t,
        Ok(Err(e)) => {
            counts.refused_tls.fetch_add(1, Ordering::Relaxed);
            if !counts.warned_tls.swap(true, Ordering::Relaxed) {
                tracing::warn!(%peer, "live view: a connection failed the TLS handshake (not wss://, or the client does \
                    not trust this certificate): {e} (counted in summary.json viewer.gate; warned once)");
            }
            return;
        }
        Err(_) => {
            counts.refused_tls.fetch_add(1, Ordering::Relaxed);
            return;
        }
    };
    // The upgrade request's head.
    let mut buf = Vec::with_capacity(2048);
    let head_end = loop {
        if let Some(i) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break Some(i);
        }
        if buf.len() >= MAX_REQUEST {
            break None;
        }
        let mut chunk = [0u8; 2048];
        match tokio::time::timeout(HANDSHAKE_TIMEOUT, tls.read(&mut chunk)).await {
            Ok(Ok(0)) | Ok(Err(_)) | Err(_) => break None,
            Ok(Ok(n)) => buf.extend_from_slice(&chunk[..n]),
        }
    };
    let Some(end) = head_end else {
        counts.refused_request.fetch_add(1, Ordering::Relaxed);
        let _ = tls.write_all(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n").await;
        let _ = tls.shutdown().await;
        return;
    };
    let head = String::from_utf8_lossy(&buf[..end]);
    if !has_token(&head, token) {
        counts.refused_token.fetch_add(1, Ordering::Relaxed);
        if !counts.warned_token.swap(true, Ordering::Relaxed) {
            tracing::warn!(%peer, "live view: refused a client without the token (answered 401; counted in \
                summary.json viewer.gate; warned once)");
        }
        let _ = tls.write_all(b"HTTP/1.1 401 Unauthorized\r\nContent-Length: 0\r\nConnection: close\r\n\r\n").await;
        let _ = tls.shutdown().await;
        return;
    }
    let mut up = match tokio::net::TcpStream::connect(upstream).await {
        Ok(u) => u,
        Err(e) => {
            tracing::warn!(%peer, "live view: the Foxglove server on {upstream} cannot be reached: {e}");
            return;
        }
    };
    let _ = up.set_nodelay(true);
    if up.write_all(&buf).await.is_err() {
        return;
    }
    counts.admitted.fetch_add(1, Ordering::Relaxed);
    tracing::info!(%peer, "live view: a client with the token connected over TLS");
    let _ = tokio::io::copy_bidirectional(&mut tls, &mut up).await;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_token_is_taken_from_the_query_or_a_bearer_header_only() {
        let t = "s3cr3t-t0ken";
        let req = |target: &str, extra: &str| format!("GET {target} HTTP/1.1\r\nHost: h\r\n{extra}Upgrade: websocket");
        assert!(has_token(&req("/?token=s3cr3t-t0ken", ""), t));
        assert!(has_token(&req("/?a=1&token=s3cr3t-t0ken&b=2", ""), t));
        assert!(has_token(&req("/", "authorization: Bearer s3cr3t-t0ken\r\n"), t));
        assert!(!has_token(&req("/", ""), t));
        assert!(!has_token(&req("/?token=s3cr3t-t0keN", ""), t));
        assert!(!has_token(&req("/?token=s3cr3t-t0ken2", ""), t));
        assert!(!has_token(&req("/?xtoken=s3cr3t-t0ken", ""), t));
        assert!(!has_token(&req("/", "X-Token: s3cr3t-t0ken\r\n"), t));
        assert!(!has_token(&req("/", "Authorization: Basic s3cr3t-t0ken\r\n"), t));
    }
}
