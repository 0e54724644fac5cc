//! The Zenoh session of a bridge (its configuration from the settings, TLS relays) and the watch
//! on the certificate revocation list.

use crate::BridgeSettings;
use crate::{lock, zenoh_err};
use pipeline_runtime::StageError;
use std::collections::BTreeSet;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use zenoh::Wait;

/// A thread that reads the revocation list every [`REVOCATION_POLL`] and flags a change.
pub(crate) struct RevocationWatch {
    pub(crate) changed: Arc<Mutex<Option<BTreeSet<String>>>>,
    pub(crate) stop: Arc<AtomicBool>,
    pub(crate) thread: Option<std::thread::JoinHandle<()>>,
}

/// How often the revocation list is read.
pub(crate) const REVOCATION_POLL: Duration = Duration::from_millis(500);

impl RevocationWatch {
    pub(crate) fn start(path: std::path::PathBuf, now: BTreeSet<String>) -> Result<Self, StageError> {
        let changed = Arc::new(Mutex::new(None));
        let stop = Arc::new(AtomicBool::new(false));
        let (c, sp) = (changed.clone(), stop.clone());
        let tls = crate::TlsSettings {
            ca_certificate: std::path::PathBuf::new(),
            certificate: std::path::PathBuf::new(),
            private_key: std::path::PathBuf::new(),
            verify_name: true,
            receivers: vec![],
            revoked: Some(path),
        };
        let thread = std::thread::Builder::new()
            .name("revocations".into())
            .spawn(move || {
                let mut last = now;
                while !sp.load(Ordering::Relaxed) {
                    std::thread::sleep(REVOCATION_POLL);
                    // An unreadable list keeps the one in force.
                    match tls.read_revoked() {
                        Ok(r) if r != last => {
                            *lock(&c) = Some(r.clone());
                            last = r;
                        }
                        Ok(_) => {}
                        Err(e) => tracing::debug!("revocation list unreadable: {e}"),
                    }
                }
            })
            .map_err(|e| StageError::Settings(format!("revocation thread: {e}")))?;
        Ok(Self { changed, stop, thread: Some(thread) })
    }

    /// The new list, when it changed since the last call.
    pub(crate) fn changed(&self) -> Option<BTreeSet<String>> {
        lock(&self.changed).take()
    }
}

impl Drop for RevocationWatch {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The Zenoh configuration of `settings` (errors name the key). With `tls`, the session speaks
/// over Unix sockets to `relays` ([`crate::relay`]), which do the TLS: its endpoints are
/// theirs, its Zenoh id is derived from this host's certificate name, and its access control
/// names hosts by their ids ([`crate::access_control`]).
pub fn zenoh_config(
    s: &BridgeSettings,
    revoked: &std::collections::BTreeSet<String>,
    relays: Option<&crate::relay::Relays>,
) -> Result<zenoh::Config, StageError> {
    let mut c = zenoh::Config::default();
    let json = |v: &dyn erased::Json| v.json();
    let set = |c: &mut zenoh::Config, k: &str, v: String| {
        c.insert_json5(k, &v).map_err(|e| StageError::Settings(format!("zenoh.{k} = {v}: {e}")))
    };
    set(&mut c, "mode", json(&s.zenoh.mode))?;
    match (&s.zenoh.tls, relays) {
        (None, _) => {
            set(&mut c, "listen/endpoints", json(&s.zenoh.listen))?;
            set(&mut c, "connect/endpoints", json(&s.zenoh.connect))?;
        }
        (Some(_), None) => {
            return Err(StageError::Settings(
                "zenoh.tls: the TLS relays are not started (session::open_session)".into(),
            ));
        }
        (Some(t), Some(r)) => {
            set(&mut c, "listen/endpoints", json(&r.zenoh_listen))?;
            set(&mut c, "connect/endpoints", json(&r.zenoh_connect))?;
            // Only the relays' Unix sockets: TLS is theirs.
            set(&mut c, "transport/link/protocols", json(&["unixsock-stream"]))?;
            let own = crate::read_certificate(&t.certificate)
                .map_err(|e| StageError::Settings(format!("zenoh.tls.certificate: {e}")))?;
            set(&mut c, "id", json(&crate::relay::zid_hex(&own.common_name)))?;
            set(&mut c, "access_control", crate::access_control(s, revoked).to_string())?;
        }
    }
    set(&mut c, "scouting/multicast/enabled", s.zenoh.multicast_scouting.to_string())?;
    // Keep trying the peers named in `connect` if they are not up yet (or go away).
    set(&mut c, "connect/exit_on_failure", "false".into())?;
    // A reliable send blocked by a link outage waits as long as the lease keeps the link: with
    // Zenoh's default (5 s, half the default lease) a 2 s outage could close the link (TCP's
    // retransmission back-off resumes the flow up to one outage after the link is back) and
    // lose every message in flight.
    let lease_ms = (s.zenoh.lease_s * 1e3).round() as u64;
    set(&mut c, "transport/link/tx/lease", lease_ms.to_string())?;
    set(&mut c, "transport/link/tx/queue/congestion_control/block/wait_before_close", (lease_ms * 1000).to_string())?;
    Ok(c)
}

/// Opens the Zenoh session of `settings`, behind TLS relays when `tls` is set
/// ([`crate::relay`]); the relays must live as long as the session.
pub fn open_session(
    s: &BridgeSettings,
    revoked: &std::collections::BTreeSet<String>,
) -> Result<(zenoh::Session, Option<crate::relay::Relays>), StageError> {
    let relays = match &s.zenoh.tls {
        None => None,
        Some(t) => Some(crate::relay::Relays::start(&s.zenoh.listen, &s.zenoh.connect, t, revoked)?),
    };
    let config = zenoh_config(s, revoked, relays.as_ref())?;
    let session = zenoh::open(config).wait().map_err(|e| {
        zenoh_err(
            format!(
                "cannot open a session (mode {}, listen {:?}, connect {:?})",
                s.zenoh.mode, s.zenoh.listen, s.zenoh.connect
            ),
            e,
        )
    })?;
    Ok((session, relays))
}

mod erased {
    /// JSON text of a setting value.
    pub trait Json {
        fn json(&self) -> String;
    }
    impl<T: serde::Serialize> Json for T {
        fn json(&self) -> String {
            serde_json::to_string(self).unwrap_or_default()
        }
    }
}
