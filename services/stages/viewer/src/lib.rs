//! The `viewer` process kind: a live view of a run in Foxglove. A WebSocket server (the Foxglove
//! SDK's, protocol `foxglove.websocket.v1`) on the configured address shows, with Foxglove's own
//! schemas (protobuf-encoded, the schemas advertised with each channel, so the stock Foxglove
//! app needs no plug-in):
//!
//! | topic | schema | what |
//! |---|---|---|
//! | `/ground_truth/path`, `/slam/path`, `/buoy/path`, `/fused/path`, `/grid_slam/path` | `foxglove.PosesInFrame` | the trajectories so far (world frame; ground truth from `<out_dir>/ground_truth.tum` as the source writes it) |
//! | `/fused/pose` | `foxglove.PoseInFrame` | the latest fused pose |
//! | `/cloud` | `foxglove.PointCloud` | the current point cloud (x, y, z float32; placed at the sensor pose when it has one) |
//! | `/landmarks` | `foxglove.PointCloud` | the landmark map (the fused global map once it holds a landmark, else SLAM's) |
//! | `/octree` | `foxglove.PointCloud` | the octree's occupied voxels (centres; x, y, z, occupancy, class) |
//! | `/grid` | `foxglove.Grid` | the 2-D SLAM's occupancy grid (int8, -1 unknown, 0-100) |
//! | `/processes` | `foxglove.Log` | each process's state from its heartbeats, once a second |
//!
//! It never slows the pipeline: every wake-up drains every input at once (keeping only what it
//! shows), converts only for channels a client subscribes to and at most at the configured rates,
//! and the SDK drops the oldest queued messages of a slow client. What it skips is counted in its
//! summary part (`viewer`).

pub mod gate;
pub mod stage;
pub mod summary;

use pipeline_runtime::Validate;
use pipeline_runtime::config::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};

/// Settings of the `viewer` process.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ViewerSettings {
    /// Address the WebSocket server listens on. The Foxglove WebSocket protocol has neither
    /// authentication nor encryption: any address but loopback (`127.0.0.1`, `::1`) needs `tls`
    /// and `token_file` (a client then connects with `wss://<host>:<port>/?token=<token>`), or
    /// `insecure = true` (anyone who reaches it watches the run). From another machine, loopback
    /// and a tunnel work too: `ssh -L 8765:127.0.0.1:8765 <this host>` (docs/security.md).
    pub host: String,
    /// Allow a `host` other than loopback without TLS and a token (warned at start and in
    /// summary.json).
    pub insecure: bool,
    /// TLS for the view (`wss://`): this host's certificate and key (PEM; `supervisor certs`
    /// makes them). Needs `token_file`.
    pub tls: Option<ViewerTls>,
    /// The file holding the token a client must give (`?token=<token>` in the URL, or
    /// `Authorization: Bearer <token>`); `supervisor certs --viewer-token` makes one. Needs `tls`.
    pub token_file: Option<std::path::PathBuf>,
    /// Its port (Foxglove's default is 8765; 0 = any free port, written to the log and the summary).
    pub port: u16,
    /// Largest rate of `/cloud`, Hz (the latest cloud is shown; the others are counted as skipped).
    pub cloud_max_hz: f64,
    /// Largest rate of `/octree`, `/landmarks` and `/grid`, Hz.
    pub map_max_hz: f64,
    /// Largest rate of the `/*/path` messages, Hz.
    pub path_max_hz: f64,
    /// Poses kept per trajectory (older ones are thinned to every second pose when it is full).
    pub path_max_poses: usize,
    /// Messages the SDK queues per client before it drops the oldest.
    pub client_backlog: usize,
    /// Processes whose end of stream ends the view; empty: it runs until stopped.
    pub end_after: Vec<String>,
}

/// The view's TLS certificate and key.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewerTls {
    /// This host's certificate (PEM), e.g. `certs/base.pem`.
    pub certificate: std::path::PathBuf,
    /// Its private key (PEM), e.g. `certs/base.key`.
    pub private_key: std::path::PathBuf,
}

/// Shortest token accepted, characters.
pub const MIN_TOKEN_LEN: usize = 16;

/// Reads a token file: its first line, trimmed; errors name the file.
pub fn read_token(path: &std::path::Path) -> Result<String, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let token = text.lines().next().unwrap_or_default().trim().to_string();
    if token.len() < MIN_TOKEN_LEN || !token.chars().all(|c| c.is_ascii_alphanumeric() || "-_.~".contains(c)) {
        return Err(format!(
            "{}: the token must be at least {MIN_TOKEN_LEN} characters of A-Z a-z 0-9 - _ . ~ (make one: supervisor certs \
             --viewer-token)",
            path.display()
        ));
    }
    Ok(token)
}

impl Default for ViewerSettings {
    fn default() -> Self {
        Self {
            host: "127.0.0.1".into(),
            insecure: false,
            tls: None,
            token_file: None,
            port: 8765,
            cloud_max_hz: 5.0,
            map_max_hz: 1.0,
            path_max_hz: 5.0,
            path_max_poses: 20_000,
            client_backlog: 256,
            end_after: vec![],
        }
    }
}

impl Validate for ViewerSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(
            self.host.parse::<std::net::IpAddr>().is_ok(),
            "host",
            format!("must be an IP address (e.g. 127.0.0.1 or 0.0.0.0), got `{}`", self.host),
        );
        let secured = self.tls.is_some() && self.token_file.is_some();
        if let Ok(ip) = self.host.parse::<std::net::IpAddr>() {
            issues.check(
                ip.is_loopback() || self.insecure || secured,
                "host",
                format!(
                    "`{}` would let anyone who reaches it watch the run: give `tls` and `token_file` (clients \
                     connect with wss://...?token=...), or keep 127.0.0.1 and tunnel (ssh -L 8765:127.0.0.1:8765 \
                     <host>), or set `insecure = true`",
                    self.host
                ),
            );
        }
        issues.check(
            self.tls.is_some() == self.token_file.is_some(),
            if self.tls.is_some() { "token_file" } else { "tls" },
            "`tls` and `token_file` go together: TLS keeps the link private, the token keeps strangers out",
        );
        if let Some(t) = &self.tls {
            for (field, p) in [("certificate", &t.certificate), ("private_key", &t.private_key)] {
                if let Err(e) = std::fs::File::open(p) {
                    issues.push(
                        format!("tls.{field}"),
                        format!("cannot read {}: {e} (make one: supervisor certs --name <this host>)", p.display()),
                    );
                }
            }
        }
        if let Some(p) = &self.token_file
            && let Err(e) = read_token(p)
        {
            issues.push("token_file", e);
        }
        for (field, v) in
            [("cloud_max_hz", self.cloud_max_hz), ("map_max_hz", self.map_max_hz), ("path_max_hz", self.path_max_hz)]
        {
            issues.check(
                v.is_finite() && v > 0.0 && v <= 1000.0,
                field,
                format!("must be a rate in (0, 1000] Hz, got {v}"),
            );
        }
        issues.check((2..=10_000_000).contains(&self.path_max_poses), "path_max_poses", "must be 2..=10000000");
        issues.check((1..=1_000_000).contains(&self.client_backlog), "client_backlog", "must be 1..=1000000");
    }
}

impl ProcessSettings for ViewerSettings {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_settings_name_their_key() {
        let s =
            ViewerSettings { host: "localhost:1".into(), cloud_max_hz: 0.0, path_max_poses: 1, ..Default::default() };
        let mut issues = Issues::at("processes.view.settings");
        s.validate(&mut issues);
        let text = format!("{issues:?}");
        for key in ["processes.view.settings.host", "processes.view.settings.cloud_max_hz", "path_max_poses"] {
            assert!(text.contains(key), "{key} in {text}");
        }
        let mut issues = Issues::at("k");
        ViewerSettings::default().validate(&mut issues);
        assert!(issues.is_empty(), "{issues:?}");
        let open = ViewerSettings { host: "0.0.0.0".into(), ..Default::default() };
        let mut issues = Issues::at("k");
        open.validate(&mut issues);
        assert!(format!("{issues:?}").contains("insecure = true"), "{issues:?}");
        let mut issues = Issues::at("k");
        ViewerSettings { insecure: true, ..open.clone() }.validate(&mut issues);
        assert!(issues.is_empty(), "{issues:?}");
        // TLS with a token opens any address; one without the other is an error.
        let dir = tempfile::tempdir().unwrap();
        let (cert, key, token) = (dir.path().join("c.pem"), dir.path().join("c.key"), dir.path().join("t"));
        for p in [&cert, &key] {
            std::fs::write(p, "x").unwrap();
        }
        std::fs::write(&token, "0123456789abcdef0123\n").unwrap();
        let tls = Some(ViewerTls { certificate: cert.clone(), private_key: key.clone() });
        let mut issues = Issues::at("k");
        ViewerSettings { tls: tls.clone(), token_file: Some(token.clone()), ..open.clone() }.validate(&mut issues);
        assert!(issues.is_empty(), "{issues:?}");
        let mut issues = Issues::at("k");
        ViewerSettings { tls: tls.clone(), ..open.clone() }.validate(&mut issues);
        assert!(format!("{issues:?}").contains("k.token_file"), "{issues:?}");
        std::fs::write(&token, "short\n").unwrap();
        let mut issues = Issues::at("k");
        ViewerSettings { tls, token_file: Some(token), ..open }.validate(&mut issues);
        assert!(format!("{issues:?}").contains("at least 16"), "{issues:?}");
    }
}
