//! The Zenoh bridge (issue #16): one pipeline spanning several hosts. A `bridge` process forwards
//! configured services from its host's iceoryx2 pipeline to Zenoh (`out`) and from Zenoh into its
//! host's pipeline (`in`).
//!
//! - **Keys**: a service `s` of robot `r` travels on the key `<namespace>/<r>/<s>` (e.g.
//!   `slam/r1/pipeline/fusion/pose`). The value is the message exactly as on the wire
//!   (docs/WIRE_FORMAT.md): the user header's bytes followed by the payload's bytes. The Zenoh
//!   attachment carries the wire signature ([`signature`]: wire version, user header and payload
//!   type names, slice or not); a receiver checks it and the length against its own types, and a
//!   mismatch is counted and logged, never published.
//! - **Received messages** are written into loaned iceoryx2 samples with the contract's QoS,
//!   `seq` and `publish_ns` stamped anew, `origin_ns` kept: end-to-end latency spans both hosts.
//!   `origin_ns` is on the sender's `CLOCK_MONOTONIC`: on one machine (two pipelines on loopback
//!   or in network namespaces: the same boot id) it is kept as is; from another machine it is
//!   moved onto this one's clock by the offset the bridge measures ([`clock`]; `clock = "auto"`).
//! - **Policy per route**: `reliable` (Zenoh congestion control `Block`: a slow link slows the
//!   sender down, nothing is dropped) for poses, fixes and ends of stream; `drop_oldest`
//!   (congestion control `Drop`, with `max_rate_hz`) for clouds and voxel maps over a slow link.
//! - **End of stream**: when its inputs are over, an `out` bridge sends an end marker on
//!   `<namespace>/<robot>/_bridge/end` with the count it sent per service, and waits (up to
//!   `end_ack_timeout_s`) for a receiving bridge's acknowledgement. An `in` bridge that has the
//!   end markers of every robot it receives from (and has published what came before them) ends
//!   its own stream, so the processes after it end as in a one-host pipeline; what it did not get
//!   is counted per service (sent by the other side minus received).
//!
//! Everything is counted per route and direction in summary.json (`bridge.out`, `bridge.in`).

pub mod buffers;
pub mod clock;
pub mod counts;
pub mod inbox;
pub mod order;
pub mod refusals;
pub mod relay;
pub mod routes;
pub mod session;
pub mod stage;
pub mod summary;

use pipeline_runtime::Validate;
use pipeline_runtime::config::{Issues, ProcessSettings};
use serde::Deserialize;
use wire_topics::{TOPICS, Topic, topic};

/// The bridge's settings (`[processes.<name>.settings]`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BridgeSettings {
    /// First chunk of every key: keeps several deployments apart on one Zenoh network.
    #[serde(default = "default_namespace")]
    pub namespace: String,
    /// This pipeline's name in the keys it publishes (`out`).
    #[serde(default)]
    pub robot: String,
    /// The Zenoh session.
    #[serde(default)]
    pub zenoh: ZenohSettings,
    /// Services sent from this pipeline to Zenoh.
    #[serde(default)]
    pub out: Vec<OutRoute>,
    /// Services received from Zenoh into this pipeline.
    #[serde(default, rename = "in")]
    pub inbound: Vec<InRoute>,
    /// Processes whose end ends the `out` direction (empty: the first upstream process to end).
    #[serde(default)]
    pub end_after: Vec<String>,
    /// Before its first message, wait this long for a subscriber on the other side of every
    /// reliable `out` route (what is sent before the other side subscribes is lost), s; 0: do
    /// not wait.
    #[serde(default = "default_wait")]
    pub wait_for_remote_s: f64,
    /// After the end marker, wait this long for the other side's acknowledgement, s.
    #[serde(default = "default_ack")]
    pub end_ack_timeout_s: f64,
    /// Received messages queued per `in` route before they are published: when a route's queue is
    /// full (this many messages, or [`Accept::queue_mib`]), its link is held back (for at most
    /// 5 s at a time, then the route's oldest message is dropped and counted). A flood on one
    /// route never holds another's.
    #[serde(default = "default_queue")]
    pub queue_messages: usize,
    /// What a message from an authenticated robot must pass before it enters this pipeline.
    #[serde(default)]
    pub accept: Accept,
    /// What becomes of a received message's `origin_ns` (stamped on the sender's clock).
    #[serde(default)]
    pub clock: ClockMode,
}

/// Defence in depth on what an `in` route publishes (docs/security.md): a message from a robot
/// whose certificate the CA signed is still checked, and a flood is bounded. Every refusal is
/// counted per route and reason in summary.json (`bridge.in.<route>.counts`) and warned once
/// per route and reason, naming the robot.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Accept {
    /// Most messages per second per `in` route (a token bucket holding one second's worth, so a
    /// burst up to that is let through); more are dropped at once and counted (`rate_dropped`).
    /// 0: no limit. A route's own `max_rate_hz` overrides it.
    #[serde(default = "default_in_rate")]
    pub max_rate_hz: f64,
    /// Most bytes queued per `in` route, MiB (see `queue_messages`).
    #[serde(default = "default_queue_mib")]
    pub queue_mib: f64,
    /// A message whose `origin_ns` (on this machine's clock, once the sender's clock is known) is
    /// later than now by more than this is refused (`refused_time`), s.
    #[serde(default = "default_future")]
    pub max_future_s: f64,
    /// A message whose `origin_ns` is older than this is refused (`refused_time`), s.
    #[serde(default = "default_age")]
    pub max_age_s: f64,
}

impl Default for Accept {
    fn default() -> Self {
        Self {
            max_rate_hz: default_in_rate(),
            queue_mib: default_queue_mib(),
            max_future_s: default_future(),
            max_age_s: default_age(),
        }
    }
}

fn default_in_rate() -> f64 {
    1000.0
}
fn default_queue_mib() -> f64 {
    256.0
}
fn default_future() -> f64 {
    1.0
}
fn default_age() -> f64 {
    120.0
}

/// How a receiving bridge maps the sender's `origin_ns` onto its own clock ([`clock`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default, serde::Serialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ClockMode {
    /// Kept when the sender runs on this machine (same boot id: one clock), moved by the
    /// measured offset when it runs on another.
    #[default]
    Auto,
    /// Always kept as sent (no offset measured).
    Keep,
    /// Always moved by the measured offset, even on one machine (to check the measurement).
    Measure,
}

fn default_namespace() -> String {
    "slam".into()
}
fn default_wait() -> f64 {
    20.0
}
fn default_ack() -> f64 {
    30.0
}
fn default_queue() -> usize {
    4096
}

/// The Zenoh session of a bridge.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohSettings {
    /// `peer`, `client` (through a router: `connect` names it) or `router`.
    #[serde(default = "default_mode")]
    pub mode: String,
    /// Endpoints to listen on, e.g. `tcp/0.0.0.0:7447`.
    #[serde(default)]
    pub listen: Vec<String>,
    /// Endpoints to connect to (a peer's or a `zenohd` router's), e.g. `tcp/10.0.0.2:7447`.
    #[serde(default)]
    pub connect: Vec<String>,
    /// Find peers by UDP multicast scouting (off: many networks block multicast; name the
    /// endpoints instead).
    #[serde(default)]
    pub multicast_scouting: bool,
    /// Mutual TLS (docs/security.md): every link is encrypted, and only hosts whose certificate
    /// the CA signed get in, each only under its own name. Required unless `insecure`.
    #[serde(default)]
    pub tls: Option<TlsSettings>,
    /// Plain TCP links: anyone on the network may read them, connect, and publish under any
    /// robot's name. Only with this set (warned at start and in summary.json).
    #[serde(default)]
    pub insecure: bool,
    /// How long a link may stay silent before it is taken for dead and closed (Zenoh's lease,
    /// announced to the peer), seconds. A reliable route's send waits for room as long as the
    /// link lives (Zenoh's `wait_before_close` is set to the lease, not its 5 s default), so an
    /// outage shorter than about half of it loses nothing: TCP's retransmission back-off can
    /// make the silence up to twice the outage. A longer outage closes the link: what was in
    /// flight is lost and counted (`lost_on_the_way` on the receiving side). Longer leases
    /// notice a peer that died later.
    #[serde(default = "default_lease_s")]
    pub lease_s: f64,
}

fn default_lease_s() -> f64 {
    10.0
}

/// The certificates of a bridge's mutual TLS (made by `supervisor certs`; PEM files, relative
/// paths from the working directory).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsSettings {
    /// The CA that signed every host's certificate: a peer whose certificate it did not sign
    /// cannot connect.
    pub ca_certificate: std::path::PathBuf,
    /// This host's certificate, signed by the CA; its common name is this host's name (an `out`
    /// bridge's `robot`).
    pub certificate: std::path::PathBuf,
    /// This host's private key.
    pub private_key: std::path::PathBuf,
    /// When connecting, check that the listener's certificate names the address dialled (its
    /// subject alternative names: `supervisor certs --san`).
    #[serde(default = "yes")]
    pub verify_name: bool,
    /// The hosts (certificate common names) that may subscribe to this bridge's `out` routes;
    /// empty: any host whose certificate the CA signed.
    #[serde(default)]
    pub receivers: Vec<String>,
    /// The revocation list (`supervisor certs --revoke`: one host name per line, `#` comments);
    /// default `revoked.txt` next to `ca_certificate`; a missing file revokes nobody. A revoked
    /// host's links are refused after the TLS handshake, and the access control leaves it out.
    /// The bridge watches the file and restarts to apply a change (its restart policy must allow
    /// it: the default).
    #[serde(default)]
    pub revoked: Option<std::path::PathBuf>,
}

impl TlsSettings {
    /// The revocation list's file.
    pub fn revocation_list(&self) -> std::path::PathBuf {
        self.revoked
            .clone()
            .unwrap_or_else(|| self.ca_certificate.parent().unwrap_or(std::path::Path::new(".")).join("revoked.txt"))
    }

    /// The revoked host names (none when the file does not exist).
    pub fn read_revoked(&self) -> Result<std::collections::BTreeSet<String>, String> {
        let path = self.revocation_list();
        match std::fs::read_to_string(&path) {
            Ok(text) => Ok(text
                .lines()
                .filter_map(|l| l.split('#').next())
                .map(str::trim)
                .filter(|l| !l.is_empty())
                .map(String::from)
                .collect()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Default::default()),
            Err(e) => Err(format!("{}: {e}", path.display())),
        }
    }
}

fn yes() -> bool {
    true
}

fn default_mode() -> String {
    "peer".into()
}

impl Default for ZenohSettings {
    fn default() -> Self {
        Self {
            mode: default_mode(),
            listen: vec![],
            connect: vec![],
            multicast_scouting: false,
            tls: None,
            insecure: false,
            lease_s: default_lease_s(),
        }
    }
}

/// What a route does when the link cannot keep up.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Policy {
    /// Block the sender until the link takes the message (nothing dropped).
    #[default]
    Reliable,
    /// Drop rather than wait, and send at most `max_rate_hz`.
    DropOldest,
}

/// A service sent to Zenoh.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutRoute {
    /// The local service (one of the contract's, e.g. `pipeline/fusion/pose`).
    pub service: String,
    /// `reliable` (default) or `drop_oldest`.
    #[serde(default)]
    pub policy: Policy,
    /// Most messages per second sent (drop_oldest only; 0: no limit).
    #[serde(default)]
    pub max_rate_hz: f64,
}

/// A service received from Zenoh.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InRoute {
    /// The robot (the sending bridge's `robot`).
    pub from: String,
    /// The service as the sender names it.
    pub service: String,
    /// The local service it is published on (default: the same name). Two robots' streams of one
    /// service are kept apart by publishing them on different local names (e.g.
    /// `r2/pipeline/fusion/pose`); the wire types are those of `service`.
    #[serde(default)]
    pub local: String,
    /// When a local subscriber's queue is full (on a service that does not overwrite): `wait`
    /// (default: lossless, the wait holds the link back and a reliable sender with it) or `drop`
    /// (the newest message is not delivered to that subscriber, counted: for clouds and voxel
    /// maps the sender sends `drop_oldest`).
    #[serde(default)]
    pub when_full: WhenFull,
    /// Most messages per second taken on this route (overrides `accept.max_rate_hz`; 0: no limit).
    #[serde(default)]
    pub max_rate_hz: Option<f64>,
}

/// What an `in` route does when a local subscriber is full.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum WhenFull {
    /// Wait for room (lossless; slows the link down).
    #[default]
    Wait,
    /// Do not deliver to that subscriber; counted.
    Drop,
}

impl InRoute {
    /// The local service name.
    pub fn local_service(&self) -> &str {
        if self.local.is_empty() { &self.service } else { &self.local }
    }
}

/// The wire signature of a topic, sent as each message's Zenoh attachment and checked on receipt.
pub fn signature(t: &Topic) -> String {
    format!(
        "slam-wire;v={};h={};p={};slice={}",
        shared_types::WIRE_VERSION,
        (t.header)().type_name,
        t.payload_type_name(),
        t.slice
    )
}

/// The Zenoh key of `service` sent by `robot`.
pub fn key(namespace: &str, robot: &str, service: &str) -> String {
    format!("{namespace}/{robot}/{service}")
}

/// The key of `robot`'s end marker.
pub fn end_key(namespace: &str, robot: &str) -> String {
    format!("{namespace}/{robot}/_bridge/end")
}

/// The key on which receiving bridges ask `robot`'s bridge for its clock ([`clock`]).
pub fn clock_ask_key(namespace: &str, robot: &str) -> String {
    format!("{namespace}/{robot}/_bridge/clock/ask")
}

/// The key on which `robot`'s bridge answers ([`clock`]).
pub fn clock_answer_key(namespace: &str, robot: &str) -> String {
    format!("{namespace}/{robot}/_bridge/clock/answer")
}

/// The key of the acknowledgement of `robot`'s end marker.
pub fn ack_key(namespace: &str, robot: &str) -> String {
    format!("{namespace}/{robot}/_bridge/ack")
}

/// A key chunk: letters, digits, `_`, `-`, `.` (no Zenoh wildcards or separators).
fn is_chunk(s: &str) -> bool {
    !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || "_-.".contains(c))
}

/// A service name usable in a key: chunks joined by `/`.
fn is_path(s: &str) -> bool {
    !s.is_empty() && s.split('/').all(is_chunk)
}

fn topics_list() -> String {
    TOPICS.iter().map(|t| t.service).collect::<Vec<_>>().join(", ")
}

/// Checks an endpoint `<protocol>/<address>` (the transports built in: TCP and TLS).
fn endpoint_ok(e: &str) -> bool {
    match e.split_once('/') {
        Some((proto, addr)) => ["tcp", "tls"].contains(&proto) && !addr.is_empty(),
        None => false,
    }
}

/// What a host's certificate says (docs/security.md).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct CertificateInfo {
    /// Its subject's common name: the host's name.
    pub common_name: String,
    /// Valid from (Unix time, s).
    pub not_before_unix_s: i64,
    /// Valid until (Unix time, s).
    pub not_after_unix_s: i64,
}

/// Reads the first certificate of a PEM file.
pub fn read_certificate(path: &std::path::Path) -> Result<CertificateInfo, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let (_, pem) = x509_parser::pem::parse_x509_pem(&bytes)
        .map_err(|e| format!("{}: not a PEM certificate ({e})", path.display()))?;
    let cert = pem.parse_x509().map_err(|e| format!("{}: not an X.509 certificate ({e})", path.display()))?;
    let common_name =
        cert.subject().iter_common_name().next().and_then(|c| c.as_str().ok()).unwrap_or_default().to_string();
    let v = cert.validity();
    Ok(CertificateInfo {
        common_name,
        not_before_unix_s: v.not_before.timestamp(),
        not_after_unix_s: v.not_after.timestamp(),
    })
}

/// Zenoh message kinds an access control rule may name (all of them: a rule of this bridge
/// allows everything on the keys it names, nothing elsewhere).
const ACL_MESSAGES: [&str; 9] = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
];

/// The Zenoh access control of a TLS bridge (`access_control` of its session): everything not
/// allowed is denied. A robot `r` this bridge receives from (an `in` route's `from`) may exchange
/// only keys under `<namespace>/r/` and only as the host whose Zenoh id is `r`'s
/// ([`relay::zid_of`]: the TLS relays let a host through only with the id of its certificate's
/// name); the keys of this bridge's own `robot` (its `out` routes, end markers, clock) go only to
/// `receivers` (their certificates' names; none named: any host the relays let in, i.e. any
/// host the CA signed). So a host cannot publish under another robot's name, and one the config
/// does not name gets nothing. (Zenoh itself sees only the relays' Unix sockets.)
///
/// A receiving bridge also denies everything to any host explicitly ([`refusals_counted`]:
/// unless it also sends to any host, whose rule that would override), except that its
/// subscriptions to the `in` routes' keys are declared to every host: a host that publishes
/// under a robot's key it may not use then sends, and Zenoh refuses the messages here and
/// reports each with the host's identity, which the bridge counts ([`refusals`]).
///
/// A revoked host (`revoked`: [`TlsSettings::read_revoked`]) is left out of every rule: it
/// matches only the catch-all, or nothing, and gets nothing in or out.
pub fn access_control(s: &BridgeSettings, revoked: &std::collections::BTreeSet<String>) -> serde_json::Value {
    let mut rules = vec![];
    let mut subjects = vec![];
    let mut policies = vec![];
    let mut from: Vec<&str> = s.inbound.iter().map(|r| r.from.as_str()).filter(|r| !revoked.contains(*r)).collect();
    from.sort_unstable();
    from.dedup();
    for r in from {
        let id = format!("robot {r}");
        rules.push(serde_json::json!({
            "id": id, "permission": "allow", "flows": ["ingress", "egress"],
            "messages": ACL_MESSAGES, "key_exprs": [format!("{}/{r}/**", s.namespace)],
        }));
        subjects.push(serde_json::json!({ "id": id, "zids": [relay::zid_hex(r)] }));
        policies.push(serde_json::json!({ "rules": [id], "subjects": [id] }));
    }
    if !s.robot.is_empty() && !s.out.is_empty() {
        let id = format!("receivers of {}", s.robot);
        rules.push(serde_json::json!({
            "id": id, "permission": "allow", "flows": ["ingress", "egress"],
            "messages": ACL_MESSAGES, "key_exprs": [format!("{}/{}/**", s.namespace, s.robot)],
        }));
        let named = s.zenoh.tls.as_ref().map(|t| t.receivers.clone()).unwrap_or_default();
        let receivers: Vec<String> = named.iter().filter(|r| !revoked.contains(*r)).cloned().collect();
        // (Every receiver revoked: no subject, nobody gets the keys.)
        if named.is_empty() || !receivers.is_empty() {
            subjects.push(if named.is_empty() {
                serde_json::json!({ "id": id, "link_protocols": ["unixsock-stream"] })
            } else {
                let zids: Vec<String> = receivers.iter().map(|r| relay::zid_hex(r)).collect();
                serde_json::json!({ "id": id, "zids": zids })
            });
            policies.push(serde_json::json!({ "rules": [id], "subjects": [id] }));
        }
    }
    if refusals_counted(s) {
        // Every TLS host: nothing in and nothing out (as by default), except that it learns what
        // this bridge subscribes to, so that a host publishing under another robot's keys does
        // send, and is refused here, counted (otherwise its Zenoh would keep the messages).
        let id = "any other host";
        let not_subscriptions: Vec<&str> =
            ACL_MESSAGES.iter().copied().filter(|m| *m != "declare_subscriber").collect();
        let mut keys: Vec<String> = s.inbound.iter().map(|r| key(&s.namespace, &r.from, &r.service)).collect();
        keys.sort_unstable();
        keys.dedup();
        rules.push(serde_json::json!({
            "id": "deny in", "permission": "deny", "flows": ["ingress"], "messages": ACL_MESSAGES, "key_exprs": ["**"],
        }));
        rules.push(serde_json::json!({
            "id": "deny out", "permission": "deny", "flows": ["egress"], "messages": not_subscriptions,
            "key_exprs": ["**"],
        }));
        rules.push(serde_json::json!({
            "id": "subscriptions out", "permission": "allow", "flows": ["egress"], "messages": ["declare_subscriber"],
            "key_exprs": keys,
        }));
        subjects.push(serde_json::json!({ "id": id, "link_protocols": ["unixsock-stream"] }));
        policies.push(serde_json::json!({ "rules": ["deny in", "deny out", "subscriptions out"], "subjects": [id] }));
    }
    serde_json::json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    })
}

/// Whether a bridge counts the messages its access control refuses per host and route
/// (`refused_wrong_robot`): it receives from robots, over TLS, and does not also send to every
/// host (empty `receivers`: a rule for every TLS link, which a deny rule for every TLS link
/// would cancel in Zenoh, where a subject's deny wins over its allow).
pub fn refusals_counted(s: &BridgeSettings) -> bool {
    let receivers = s.zenoh.tls.as_ref().map(|t| t.receivers.len());
    !s.inbound.is_empty() && receivers.is_some() && !(receivers == Some(0) && !s.robot.is_empty() && !s.out.is_empty())
}

fn unix_now_s() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs() as i64).unwrap_or(0)
}

/// What is wrong with running under the revocation list `revoked` (see [`TlsSettings::revoked`]):
/// this host's own certificate is revoked.
pub fn revocation_problem(own_name: Option<&str>, revoked: &std::collections::BTreeSet<String>) -> Option<String> {
    own_name
        .filter(|n| revoked.contains(*n))
        .map(|n| format!("this host's certificate (CN {n}) is revoked: make it a new name, or delete its line"))
}

/// Revoked hosts the access control cannot leave out: an `out` bridge whose `receivers` is empty
/// sends to any host the CA signed (Zenoh's access control cannot say "every host but these").
pub fn revocation_gap(s: &BridgeSettings, revoked: &std::collections::BTreeSet<String>) -> Option<String> {
    let receivers_empty = s.zenoh.tls.as_ref().is_some_and(|t| t.receivers.is_empty());
    (!revoked.is_empty() && receivers_empty && !s.out.is_empty()).then(|| {
        format!(
            "hosts are revoked ({}) but `receivers` is empty: any host the CA signed, revoked ones too, may subscribe \
             to this robot's keys (Zenoh's access control cannot say \"every host but these\"): name the receivers \
             (zenoh.tls.receivers) to keep them out",
            revoked.iter().cloned().collect::<Vec<_>>().join(", ")
        )
    })
}

/// Checks the `tls` settings: endpoints, files, the certificate's name against `robot`.
fn validate_tls(s: &BridgeSettings, t: &TlsSettings, issues: &mut Issues) {
    let z = &s.zenoh;
    for (field, list) in [("listen", &z.listen), ("connect", &z.connect)] {
        for (i, e) in list.iter().enumerate() {
            issues.check(
                !e.starts_with("tcp/"),
                format!("zenoh.{field}[{i}]"),
                format!("`{e}` is plain TCP but `tls` is set: write tls/{}", e.trim_start_matches("tcp/")),
            );
        }
    }
    let now = unix_now_s();
    for (field, path) in [("ca_certificate", &t.ca_certificate), ("certificate", &t.certificate)] {
        match read_certificate(path) {
            Err(e) => issues.push(format!("zenoh.tls.{field}"), format!("{e} (make one: supervisor certs)")),
            Ok(c) => {
                issues.check(
                    c.not_after_unix_s > now,
                    format!("zenoh.tls.{field}"),
                    format!("{} expired (CN {}): make a new one (supervisor certs)", path.display(), c.common_name),
                );
                if field == "certificate" && !s.out.is_empty() {
                    issues.check(
                        c.common_name == s.robot,
                        "zenoh.tls.certificate",
                        format!(
                            "{} is `{}`'s certificate, but this bridge sends as robot `{}`: receivers accept a robot's \
                             keys only over a link authenticated by that robot's own certificate",
                            path.display(),
                            c.common_name,
                            s.robot
                        ),
                    );
                }
            }
        }
    }
    if let Err(e) = std::fs::File::open(&t.private_key) {
        issues.push("zenoh.tls.private_key", format!("cannot read {}: {e}", t.private_key.display()));
    }
    for (i, r) in t.receivers.iter().enumerate() {
        issues.check(is_chunk(r), format!("zenoh.tls.receivers[{i}]"), "a host's name (letters, digits, _ - .)");
    }
    match t.read_revoked() {
        Err(e) => issues.push("zenoh.tls.revoked", format!("cannot read the revocation list: {e}")),
        Ok(revoked) => {
            let own = read_certificate(&t.certificate).ok().map(|c| c.common_name);
            if let Some(p) = revocation_problem(own.as_deref(), &revoked) {
                issues.push("zenoh.tls.revoked", format!("{}: {p}", t.revocation_list().display()));
            }
        }
    }
}

/// Checks the `zenoh` table: the mode, the endpoints, the lease, TLS or the explicit insecure mode.
fn validate_zenoh(s: &BridgeSettings, issues: &mut Issues) {
    let z = &s.zenoh;
    issues.check(
        ["peer", "client", "router"].contains(&z.mode.as_str()),
        "zenoh.mode",
        format!("`{}`: one of peer, client, router", z.mode),
    );
    for (field, list) in [("listen", &z.listen), ("connect", &z.connect)] {
        for (i, e) in list.iter().enumerate() {
            issues.check(
                endpoint_ok(e),
                format!("zenoh.{field}[{i}]"),
                format!("`{e}`: an endpoint is <protocol>/<address>, e.g. tcp/192.168.1.2:7447"),
            );
        }
    }
    issues.check(
        z.lease_s.is_finite() && (1.0..=3600.0).contains(&z.lease_s),
        "zenoh.lease_s",
        format!("{}: seconds from 1 to 3600", z.lease_s),
    );
    match (&z.tls, z.insecure) {
        (None, false) => issues.push(
            "zenoh.tls",
            "a link between hosts must be authenticated and encrypted: give `tls` (certificates made by \
                 `supervisor certs`, docs/security.md), or set `insecure = true` for plain TCP that anyone \
                 on the network may read and publish into",
        ),
        (Some(_), true) => issues.push("zenoh.insecure", "`insecure = true` and `tls` together: choose one"),
        (Some(t), false) => validate_tls(s, t, issues),
        (None, true) => {
            for (field, list) in [("listen", &z.listen), ("connect", &z.connect)] {
                for (i, e) in list.iter().enumerate() {
                    issues.check(
                        !e.starts_with("tls/"),
                        format!("zenoh.{field}[{i}]"),
                        format!("`{e}` is TLS but no `tls` certificates are given"),
                    );
                }
            }
        }
    }
    if z.mode == "client" {
        issues.check(!z.connect.is_empty(), "zenoh.connect", "a client needs a router or peer to connect to");
    }
    if z.listen.is_empty() && z.connect.is_empty() && !z.multicast_scouting {
        issues.push(
            "zenoh",
            "with neither `listen` nor `connect` endpoints and multicast scouting off, the bridge can reach no one",
        );
    }
}

/// Checks the `out` and `in` routes: services that can be bridged, each routed once, rates, local
/// names that neither clash nor loop back.
fn validate_routes(s: &BridgeSettings, issues: &mut Issues) {
    let mut seen = std::collections::BTreeSet::new();
    for (i, r) in s.out.iter().enumerate() {
        issues.check(
            topic(&r.service).is_some(),
            format!("out[{i}].service"),
            format!("`{}` is not a service that can be bridged (one of: {})", r.service, topics_list()),
        );
        issues.check(
            seen.insert(r.service.clone()),
            format!("out[{i}].service"),
            format!("`{}` is routed twice", r.service),
        );
        issues.check(
            r.max_rate_hz.is_finite() && r.max_rate_hz >= 0.0,
            format!("out[{i}].max_rate_hz"),
            "must be >= 0",
        );
        issues.check(
            r.max_rate_hz == 0.0 || r.policy == Policy::DropOldest,
            format!("out[{i}].max_rate_hz"),
            "a rate limit drops messages: set `policy = \"drop_oldest\"` too",
        );
    }
    // A local service may take several robots' streams of one service (e.g. every robot's
    // clouds into one map), never two services or one robot twice.
    let mut locals: std::collections::BTreeMap<&str, (&str, Vec<&str>)> = std::collections::BTreeMap::new();
    for (i, r) in s.inbound.iter().enumerate() {
        issues.check(is_chunk(&r.from), format!("in[{i}].from"), "the sending robot's name (letters, digits, _ - .)");
        issues.check(
            topic(&r.service).is_some(),
            format!("in[{i}].service"),
            format!("`{}` is not a service that can be bridged (one of: {})", r.service, topics_list()),
        );
        issues.check(is_path(r.local_service()), format!("in[{i}].local"), "a service name: chunks joined by /");
        let entry = locals.entry(r.local_service()).or_insert((r.service.as_str(), vec![]));
        issues.check(
            entry.0 == r.service && !entry.1.contains(&r.from.as_str()),
            format!("in[{i}].local"),
            format!(
                "`{}` is published by two routes of {}: give one a `local` name",
                r.local_service(),
                if entry.0 == r.service { "one robot" } else { "different services" }
            ),
        );
        entry.1.push(r.from.as_str());
        if let Some(hz) = r.max_rate_hz {
            issues.check(hz.is_finite() && hz >= 0.0, format!("in[{i}].max_rate_hz"), "must be >= 0");
        }
        issues.check(
            !s.out.iter().any(|o| o.service == r.local_service()),
            format!("in[{i}].local"),
            format!("`{}` is also sent out: it would loop back", r.local_service()),
        );
    }
}

impl Validate for BridgeSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(is_path(&self.namespace), "namespace", "must be key chunks (letters, digits, _ - .) joined by /");
        if !self.out.is_empty() {
            issues.check(
                is_chunk(&self.robot),
                "robot",
                "an `out` bridge needs its robot's name (letters, digits, _ - .)",
            );
        } else if !self.robot.is_empty() {
            issues.check(is_chunk(&self.robot), "robot", "letters, digits, _ - . only");
        }
        issues.check(
            !self.out.is_empty() || !self.inbound.is_empty(),
            "out",
            "the bridge forwards nothing: give `out` and/or `in` routes",
        );
        validate_zenoh(self, issues);
        validate_routes(self, issues);
        for (field, v) in [("wait_for_remote_s", self.wait_for_remote_s), ("end_ack_timeout_s", self.end_ack_timeout_s)]
        {
            issues.check(v.is_finite() && v >= 0.0, field, "must be >= 0");
        }
        issues.check(self.queue_messages >= 1, "queue_messages", "must be at least 1");
        let a = &self.accept;
        for (field, v) in [("max_rate_hz", a.max_rate_hz), ("max_future_s", a.max_future_s), ("max_age_s", a.max_age_s)]
        {
            issues.check(v.is_finite() && v >= 0.0, format!("accept.{field}"), "must be >= 0");
        }
        issues.check(a.queue_mib.is_finite() && a.queue_mib > 0.0, "accept.queue_mib", "must be > 0");
    }
}

impl ProcessSettings for BridgeSettings {}

/// Locks `m`, taking over a lock poisoned by a panicked thread (the data stays usable: counters
/// and queues).
pub(crate) fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// A stage error for a failed Zenoh call `what`.
pub(crate) fn zenoh_err(what: impl std::fmt::Display, e: impl std::fmt::Display) -> pipeline_runtime::StageError {
    pipeline_runtime::StageError::msg(format!("zenoh: {what}: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn issues(text: &str) -> Vec<String> {
        let s: BridgeSettings = toml::from_str(text).expect("parses");
        let mut i = Issues::at("processes.b.settings");
        s.validate(&mut i);
        i.iter().map(|c| format!("{}: {}", c.key, c.message)).collect()
    }

    #[test]
    fn settings_errors_name_the_key() {
        let ok = r#"
robot = "r1"
zenoh = { listen = ["tcp/127.0.0.1:7447"], insecure = true }
out = [{ service = "pipeline/fusion/pose" }, { service = "pipeline/sensors/cloud", policy = "drop_oldest", max_rate_hz = 2.0 }]
in = [{ from = "r2", service = "pipeline/fusion/pose", local = "r2/pipeline/fusion/pose" }]
"#;
        assert!(issues(ok).is_empty(), "{:?}", issues(ok));
        let bad = r#"
robot = "r/1"
zenoh = { mode = "mesh", connect = ["127.0.0.1:7447"], lease_s = 0.1 }
out = [{ service = "pipeline/nope" }, { service = "pipeline/sensors/cloud", max_rate_hz = 2.0 }]
in = [{ from = "r2", service = "pipeline/fusion/pose" }, { from = "r3", service = "pipeline/fusion/pose" },
      { from = "r2", service = "pipeline/fusion/pose" }, { from = "r4", service = "pipeline/slam/pose", local = "pipeline/fusion/pose" }]
"#;
        let got = issues(bad).join("\n");
        for needle in [
            "processes.b.settings.robot",
            "processes.b.settings.zenoh.mode: `mesh`",
            "processes.b.settings.zenoh.connect[0]: `127.0.0.1:7447`",
            "processes.b.settings.zenoh.lease_s: 0.1",
            "processes.b.settings.out[0].service: `pipeline/nope`",
            "processes.b.settings.out[1].max_rate_hz",
            "processes.b.settings.in[2].local: `pipeline/fusion/pose` is published by two routes of one robot",
            "processes.b.settings.in[3].local: `pipeline/fusion/pose` is published by two routes of different services",
        ] {
            assert!(got.contains(needle), "missing {needle:?} in\n{got}");
        }
        let nothing = issues("zenoh = { listen = [\"tcp/127.0.0.1:1\"] }").join("\n");
        assert!(nothing.contains("forwards nothing"), "{nothing}");
        let deaf = issues("robot = \"r\"\nout = [{ service = \"pipeline/fusion/pose\" }]").join("\n");
        assert!(deaf.contains("can reach no one"), "{deaf}");
    }

    #[test]
    fn keys_and_signatures() {
        assert_eq!(key("slam", "r1", "pipeline/fusion/pose"), "slam/r1/pipeline/fusion/pose");
        let pose = topic("pipeline/fusion/pose").unwrap();
        let cloud = topic("pipeline/sensors/cloud").unwrap();
        assert!(signature(pose).contains("slice=false"));
        assert!(signature(cloud).contains("slice=true"));
        assert_ne!(signature(pose), signature(cloud));
    }
}
