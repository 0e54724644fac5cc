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
//! | `/landmarks` | `foxglove.PointCloud` | the landmark map (the fused global map, else SLAM's) |
//! | `/octree` | `foxglove.PointCloud` | the octree's occupied voxels (centres; x, y, z, occupancy, class) |
//! | `/grid` | `foxglove.Grid` | the 2-D SLAM's occupancy grid (int8, -1 unknown, 0-100) |
//! | `/processes` | `foxglove.Log` | each process's state from its heartbeats, once a second |
//!
//! It never slows the pipeline: every wake-up drains every input at once (keeping only what it
//! shows), converts only for channels a client subscribes to and at most at the configured rates,
//! and the SDK drops the oldest queued messages of a slow client. What it skips is counted in its
//! summary part (`viewer`).

pub mod stage;

use pipeline_runtime::config::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};

/// Settings of the `viewer` process.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ViewerSettings {
    /// Address the WebSocket server listens on. The Foxglove WebSocket protocol has neither
    /// authentication nor encryption: any address but loopback (`127.0.0.1`, `::1`) lets anyone
    /// who reaches it watch the run, and needs `insecure = true`. From another machine, keep
    /// loopback and tunnel: `ssh -L 8765:127.0.0.1:8765 <this host>` (README "Security").
    pub host: String,
    /// Allow a `host` other than loopback (warned at start and in summary.json).
    pub insecure: bool,
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

impl Default for ViewerSettings {
    fn default() -> Self {
        Self {
            host: "127.0.0.1".into(),
            insecure: false,
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

impl ProcessSettings for ViewerSettings {
    fn validate(&self, key: &str, issues: &mut Issues) {
        issues.check(
            self.host.parse::<std::net::IpAddr>().is_ok(),
            format!("{key}.host"),
            format!("must be an IP address (e.g. 127.0.0.1 or 0.0.0.0), got `{}`", self.host),
        );
        if let Ok(ip) = self.host.parse::<std::net::IpAddr>() {
            issues.check(
                ip.is_loopback() || self.insecure,
                format!("{key}.host"),
                format!(
                    "`{}` lets anyone who reaches it watch the run (the viewer has no authentication or \
                     encryption): keep 127.0.0.1 and tunnel (ssh -L 8765:127.0.0.1:8765 <host>), or set \
                     `insecure = true`",
                    self.host
                ),
            );
        }
        for (field, v) in
            [("cloud_max_hz", self.cloud_max_hz), ("map_max_hz", self.map_max_hz), ("path_max_hz", self.path_max_hz)]
        {
            issues.check(
                v.is_finite() && v > 0.0 && v <= 1000.0,
                format!("{key}.{field}"),
                format!("must be a rate in (0, 1000] Hz, got {v}"),
            );
        }
        issues.check(
            (2..=10_000_000).contains(&self.path_max_poses),
            format!("{key}.path_max_poses"),
            "must be 2..=10000000",
        );
        issues.check(
            (1..=1_000_000).contains(&self.client_backlog),
            format!("{key}.client_backlog"),
            "must be 1..=1000000",
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_settings_name_their_key() {
        let s =
            ViewerSettings { host: "localhost:1".into(), cloud_max_hz: 0.0, path_max_poses: 1, ..Default::default() };
        let mut issues = Issues::default();
        s.validate("processes.view.settings", &mut issues);
        let text = format!("{issues:?}");
        for key in ["processes.view.settings.host", "processes.view.settings.cloud_max_hz", "path_max_poses"] {
            assert!(text.contains(key), "{key} in {text}");
        }
        let mut issues = Issues::default();
        ViewerSettings::default().validate("k", &mut issues);
        assert!(issues.is_empty(), "{issues:?}");
        let open = ViewerSettings { host: "0.0.0.0".into(), ..Default::default() };
        let mut issues = Issues::default();
        open.validate("k", &mut issues);
        assert!(format!("{issues:?}").contains("insecure = true"), "{issues:?}");
        let mut issues = Issues::default();
        ViewerSettings { insecure: true, ..open }.validate("k", &mut issues);
        assert!(issues.is_empty(), "{issues:?}");
    }
}
