//! Messages that the access control refused, per host and route ([`Refusals`]).
//!
//! Zenoh's access control drops a refused message without telling the application; it reports
//! each decision only in its log at TRACE (target
//! `zenoh::net::routing::interceptor::access_control`), with the host's Zenoh id, its identity
//! (interface, link protocol, id, joined by `+`; the certificate's name comes from the TLS relays,
//! which know it by the id: [`Refusals::names_from`]) and the key. The bridge watches
//! those events ([`pipeline_runtime::logging::watch_events`]: they are never printed unless
//! `RUST_LOG` asks) and counts the refused puts per host and route. A decision is reported once
//! per subject the host matches (a robot's own rule and the catch-all deny of
//! [`crate::access_control`], in any order) and then once per message from Zenoh's cache, so a
//! first "unauthorized" followed by "authorized" for the same host and key is taken back. The
//! decisions Zenoh takes to fill its cache for a key (announced by "caching permissions for",
//! ended by the last kind of message it decides, a liveliness subscriber) concern no message and
//! are not counted.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The access-control log events watched.
const TARGET: &str = "zenoh::net::routing::interceptor::access_control";
/// What every event about a received message says.
const INGRESS: &str = "(ingress)";
/// What the events about received puts say.
const PUT: &str = " to Put (ingress) on ";
/// What Zenoh says before it decides every kind of message for a key, to cache the decisions.
const CACHE_FILL: &str = "ACL (ingress): caching permissions for";
/// The last kind of message decided when filling the cache.
const CACHE_FILL_LAST: &str = " to Declare Liveliness Subscriber (ingress) on ";
/// What Zenoh says when a host with a valid certificate matches no subject of the access control.
const NO_SUBJECT: &str = "did not match any configured ACL subject";
/// How long a count must stand before it is warned about (a first refusal taken back by the
/// next event of the same decision stands for microseconds).
const SETTLE: Duration = Duration::from_millis(200);

/// One access-control decision about a received put.
#[derive(Debug, PartialEq, Eq)]
struct Decision<'a> {
    /// The host's Zenoh id.
    zid: &'a str,
    /// Its identity (first decision only; the cached ones name only the id).
    identity: Option<&'a str>,
    denied: bool,
    /// From Zenoh's cache: the final decision for one message.
    cached: bool,
    key: &'a str,
}

/// Reads a decision about a received put from Zenoh's log message.
fn parse(message: &str) -> Option<Decision<'_>> {
    let (cached, rest) = match message.strip_prefix("Using cached result: ") {
        Some(rest) => (true, rest),
        None => (false, message),
    };
    let (who, key) = rest.split_once(PUT)?;
    let (who, denied) = match who.strip_suffix(" is unauthorized") {
        Some(w) => (w, true),
        None => (who.strip_suffix(" is authorized")?, false),
    };
    let (zid, identity) = match who.split_once(" on ") {
        Some((z, i)) => (z, Some(i)),
        None => (who, None),
    };
    Some(Decision { zid, identity, denied, cached, key: key.trim() })
}

/// The certificate's common name in a host's identity as Zenoh writes it
/// (`Interface(lo)+CertCommonName(auv2)+Transport(Tls)+<zid>`).
fn certificate_name(identity: &str) -> Option<&str> {
    identity.split('+').find_map(|p| p.strip_prefix("CertCommonName(")?.strip_suffix(')'))
}

#[derive(Debug, Default)]
struct Count {
    messages: u64,
    /// When the count last became non-zero.
    since: Option<Instant>,
}

#[derive(Debug, Default)]
struct State {
    /// The `in` routes' keys and names.
    routes: HashMap<String, String>,
    /// Per (host id, route or other key): refused puts.
    counts: BTreeMap<(String, String), Count>,
    /// Per host id: its identity.
    identities: HashMap<String, String>,
    /// Hosts that matched no subject: everything they send is refused, uncounted.
    without_role: BTreeSet<String>,
    /// The revoked hosts' names (said in the warnings).
    revoked: BTreeSet<String>,
    /// The certificate names of the hosts by Zenoh id, from the TLS relays.
    names: Option<crate::relay::Names>,
    warned: BTreeSet<(String, String)>,
}

/// The route name of a refused key: one of the `in` routes, or `other: <key>` (at most
/// [`MAX_OTHER_KEYS`] kept apart, then `other keys`).
const MAX_OTHER_KEYS: usize = 32;

impl State {
    /// The certificate name of the host `zid`: from the TLS relays, or from Zenoh's identity.
    fn certificate(&self, zid: &str) -> Option<String> {
        let relayed = self.names.as_ref().and_then(|n| n.lock().unwrap_or_else(|p| p.into_inner()).get(zid).cloned());
        relayed.or_else(|| self.identities.get(zid).and_then(|i| certificate_name(i)).map(str::to_string))
    }

    fn route_of(&self, key: &str) -> String {
        if let Some(r) = self.routes.get(key) {
            return r.clone();
        }
        let other = format!("other: {key}");
        let others = self.counts.keys().filter(|(_, r)| r.starts_with("other: ")).count();
        if others < MAX_OTHER_KEYS || self.counts.keys().any(|(_, r)| *r == other) {
            other
        } else {
            "other keys".into()
        }
    }

    fn on_put(&mut self, d: Decision<'_>) {
        if let Some(i) = d.identity {
            self.identities.entry(d.zid.to_string()).or_insert_with(|| i.to_string());
        }
        let route = self.route_of(d.key);
        let c = self.counts.entry((d.zid.to_string(), route)).or_default();
        match (d.cached, d.denied) {
            (_, true) => {
                c.messages += 1;
                c.since.get_or_insert_with(Instant::now);
            }
            // A first decision allowed after a first "unauthorized" from the catch-all rule.
            (false, false) if c.messages > 0 => {
                c.messages -= 1;
                if c.messages == 0 {
                    c.since = None;
                }
            }
            _ => {}
        }
    }
}

/// The counts of refused messages of one bridge (see the module docs).
#[derive(Clone)]
pub struct Refusals(Arc<Mutex<State>>);

fn lock(m: &Mutex<State>) -> std::sync::MutexGuard<'_, State> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Refusals {
    /// Starts watching Zenoh's access-control decisions; `routes`: each `in` route's key and
    /// name; `revoked`: the revoked hosts' names.
    pub fn watch(revoked: BTreeSet<String>, routes: impl IntoIterator<Item = (String, String)>) -> Self {
        let state = State { routes: routes.into_iter().collect(), revoked, ..Default::default() };
        let r = Self(Arc::new(Mutex::new(state)));
        let s = r.0.clone();
        pipeline_runtime::logging::watch_events(TARGET, INGRESS, move |m| {
            thread_local! {
                /// The key whose decisions Zenoh is filling its cache with, on this thread.
                static FILLING: std::cell::RefCell<Option<String>> = const { std::cell::RefCell::new(None) };
            }
            if let Some(rest) = m.split_once(CACHE_FILL).map(|(_, r)| r) {
                let key = rest.trim().trim_start_matches('`').split('`').next().unwrap_or_default();
                FILLING.set(Some(key.to_string()));
                return;
            }
            let filling = FILLING.with_borrow(|f| {
                f.as_deref().is_some_and(|k| {
                    !m.starts_with("Using cached result") && m.trim_end().ends_with(&format!(" on {k}"))
                })
            });
            if filling {
                if m.contains(CACHE_FILL_LAST) {
                    FILLING.set(None);
                }
                // No message, but it names the host.
                if let Some((zid, identity)) = m.split_once(" is ").and_then(|(who, _)| who.split_once(" on ")) {
                    lock(&s).identities.entry(zid.to_string()).or_insert_with(|| identity.to_string());
                }
                return;
            }
            FILLING.set(None);
            if let Some(d) = parse(m) {
                lock(&s).on_put(d);
            }
        });
        let s = r.0.clone();
        pipeline_runtime::logging::watch_events(TARGET, NO_SUBJECT, move |m| {
            if let Some(zid) = m.split_whitespace().next() {
                lock(&s).without_role.insert(zid.to_string());
            }
        });
        r
    }

    /// Names hosts by the certificate names the TLS relays saw ([`crate::relay`]: Zenoh itself
    /// sees loopback links only).
    pub fn names_from(&self, names: crate::relay::Names) {
        lock(&self.0).names = Some(names);
    }

    /// Warns once per host and route about refused messages (those counted for a while).
    pub fn warn_new(&self) {
        let mut st = lock(&self.0);
        let new: Vec<(String, String, u64)> = st
            .counts
            .iter()
            .filter(|(k, c)| c.messages > 0 && c.since.is_some_and(|t| t.elapsed() >= SETTLE) && !st.warned.contains(k))
            .map(|((z, r), c)| (z.clone(), r.clone(), c.messages))
            .collect();
        for (zid, route, n) in new {
            let certificate = st.certificate(&zid).unwrap_or_else(|| "?".into());
            let revoked = st.revoked.contains(&certificate);
            tracing::warn!(peer = %zid, %certificate, revoked, %route, refused_so_far = n,
                "the access control refused messages from a host with a valid certificate that may not publish \
                 them (not the robot whose keys they are): counted in summary.json bridge.security (warned once \
                 per host and route)");
            st.warned.insert((zid, route));
        }
        let unwarned: Vec<String> =
            st.without_role.iter().filter(|z| !st.warned.contains(&((*z).clone(), String::new()))).cloned().collect();
        for zid in unwarned {
            tracing::warn!(peer = %zid,
                "a host with a certificate the CA signed connected, but the config gives its name no role: \
                 everything it sends is refused (uncounted)");
            st.warned.insert((zid, String::new()));
        }
    }

    /// Refused messages per `in` route name (summed over hosts).
    pub fn per_route(&self) -> BTreeMap<String, u64> {
        let st = lock(&self.0);
        let mut m = BTreeMap::new();
        for ((_, route), c) in &st.counts {
            if c.messages > 0 {
                *m.entry(route.clone()).or_default() += c.messages;
            }
        }
        m
    }

    /// Every host and route with refused messages, and the hosts without a role.
    pub fn summary(&self) -> crate::summary::RefusalsSummary {
        let st = lock(&self.0);
        let hosts = st
            .counts
            .iter()
            .filter(|(_, c)| c.messages > 0)
            .map(|((zid, route), c)| crate::summary::RefusedHost {
                peer: zid.clone(),
                certificate: st.certificate(zid),
                identity: st.identities.get(zid).cloned(),
                route: route.clone(),
                messages: c.messages,
            })
            .collect();
        crate::summary::RefusalsSummary { refused_wrong_robot: hosts, hosts_without_role: st.without_role.clone() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zenohs_decisions_are_read() {
        let d = parse("d1f0 on lo+auv2+tls+d1f0 is unauthorized to Put (ingress) on slam/auv1/pipeline/fusion/pose");
        assert_eq!(
            d,
            Some(Decision {
                zid: "d1f0",
                identity: Some("lo+auv2+tls+d1f0"),
                denied: true,
                cached: false,
                key: "slam/auv1/pipeline/fusion/pose"
            })
        );
        let d = parse("Using cached result: d1f0 is authorized to Put (ingress) on slam/auv1/x").unwrap();
        assert_eq!((d.zid, d.identity, d.denied, d.cached), ("d1f0", None, false, true));
        assert_eq!(parse("d1f0 on x is unauthorized to Declare Subscriber (ingress) on k"), None);
        assert_eq!(parse("something else"), None);
        assert_eq!(certificate_name("Interface(lo)+CertCommonName(auv2)+Transport(Tls)+d1f0"), Some("auv2"));
        assert_eq!(certificate_name("Transport(Tcp)+d1f0"), None);
    }

    #[test]
    fn decisions_that_fill_zenohs_cache_are_no_messages() {
        let r = Refusals::watch(BTreeSet::new(), [("slam/a/k".to_string(), "k".to_string())]);
        let _g = pipeline_runtime::logging::init("test", pipeline_runtime::LogFormat::Text);
        let log = |m: &str| tracing::trace!(target: "zenoh::net::routing::interceptor::access_control", "{m}");
        log("ACL (ingress): caching permissions for `slam/a/k` ...");
        log("z on lo+b+tls+z is unauthorized to Query (ingress) on slam/a/k");
        log("z on lo+b+tls+z is unauthorized to Put (ingress) on slam/a/k");
        log("z on lo+b+tls+z is unauthorized to Declare Liveliness Subscriber (ingress) on slam/a/k");
        log("Using cached result: z is unauthorized to Put (ingress) on slam/a/k");
        // A host matching no subject: its cache fill says nothing; the next decisions count.
        log("ACL (ingress): caching permissions for `slam/a/other` ...");
        log("Using cached result: y is unauthorized to Put (ingress) on slam/a/k");
        log("y on lo+c+tls+y is unauthorized to Put (ingress) on slam/a/k");
        assert_eq!(r.per_route(), [("k".to_string(), 3)].into());
    }

    #[test]
    fn a_first_refusal_taken_back_by_the_same_decision_is_not_counted() {
        let mut st = State { routes: [("k".to_string(), "pose".to_string())].into(), ..Default::default() };
        // The robot itself: the catch-all's deny, then its own rule's allow; then cached allows.
        st.on_put(parse("r1 on auv1 is unauthorized to Put (ingress) on k").unwrap());
        st.on_put(parse("r1 on auv1 is authorized to Put (ingress) on k").unwrap());
        st.on_put(parse("Using cached result: r1 is authorized to Put (ingress) on k").unwrap());
        // Another host: denied, then denied from the cache.
        st.on_put(parse("x9 on auv2 is unauthorized to Put (ingress) on k").unwrap());
        for _ in 0..4 {
            st.on_put(parse("Using cached result: x9 is unauthorized to Put (ingress) on k").unwrap());
        }
        st.on_put(parse("Using cached result: x9 is unauthorized to Put (ingress) on slam/z").unwrap());
        let r = Refusals(Arc::new(Mutex::new(st)));
        assert_eq!(r.per_route(), [("pose".to_string(), 5), ("other: slam/z".to_string(), 1)].into());
        let j = r.summary();
        assert_eq!(j.refused_wrong_robot.len(), 2);
        assert_eq!(j.refused_wrong_robot[0].identity.as_deref(), Some("auv2"));
    }
}
