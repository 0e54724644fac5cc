//! Replay of a CARMEN 2-D laser log (`source = "carmen"`): each scan becomes a
//! [`Item::PlanarOdometry`] and a [`Item::Laser`] with the same stamp (the log's `ipc_timestamp`,
//! so trajectories can be scored against the data set's relations), in file order.
//!
//! The Radish "corrected" logs (../shared/data/carmen) carry SLAM-corrected poses instead of raw
//! odometry: with `add_drift = true` the odometry published is those poses distorted by the seeded
//! [`DriftModel`] (its parameters are in the settings and in the source's description), and the
//! corrected poses themselves are written as `ground_truth.tum` (a reference: gmapping's output,
//! not surveyed truth). Warts are counted (summary.json `data_warts`) and warned about once:
//! malformed lines, a truncated file, scans whose stamp does not increase (published as they are:
//! the consumer refuses and counts them), scans without odometry (not published).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use datasets::carmen::{CarmenLog, OdometrySource, read_carmen};
use grid_slam::Pose2;
use grid_slam::drift::DriftModel;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use pipeline_runtime::Issues;
use pipeline_runtime::Validate;
use serde::{Deserialize, Serialize};
use shared_types::{LASER_MAX_IS_NO_RETURN, LaserScanHeader, PlanarOdometry};

use crate::{Item, Source, SourceError};

/// CARMEN log settings (`[processes.<name>.settings.carmen]`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CarmenSettings {
    /// The log (`.log`, `.clf`, plain, `.gz` or `.bz2`), relative to the config's directory.
    pub file: PathBuf,
    /// Where each scan's odometry comes from: `auto` (ODOM lines when the log has any, else the
    /// laser lines' pose fields), `odom_lines` or `laser_lines`.
    pub odometry: OdometrySource,
    /// Distort the odometry by `drift` (for logs whose odometry is already SLAM-corrected), and
    /// write the undistorted poses as the reference trajectory.
    pub add_drift: bool,
    /// The drift model (used with `add_drift`).
    pub drift: DriftModel,
    /// Ranges at or above this are "no return" when the line does not state the laser's maximum
    /// (FLASER lines do not; SICK lasers log 81.91 m for no return), m.
    pub range_max_m: f64,
    /// Ranges below this are invalid, m.
    pub range_min_m: f64,
    /// The laser's pose on the robot, `body_from_laser` (x m, y m, yaw rad).
    pub body_from_laser: [f64; 3],
    /// Replay only the first this many scans (0: all).
    pub max_scans: usize,
}

impl Default for CarmenSettings {
    fn default() -> Self {
        Self {
            file: PathBuf::from("../../shared/data/carmen/freiburg-079-corrected.log.gz"),
            odometry: OdometrySource::Auto,
            add_drift: false,
            drift: DriftModel::default(),
            range_max_m: 80.0,
            range_min_m: 0.01,
            body_from_laser: [0.0; 3],
            max_scans: 0,
        }
    }
}

impl Validate for CarmenSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(!self.file.as_os_str().is_empty(), "file", "no log file");
        issues.check(
            self.range_min_m.is_finite() && self.range_min_m >= 0.0 && self.range_max_m > self.range_min_m,
            "range_max_m",
            "needs 0 <= range_min_m < range_max_m",
        );
        issues.check(self.body_from_laser.iter().all(|v| v.is_finite()), "body_from_laser", "must be finite");
        let d = &self.drift;
        issues.check(
            [
                d.trans_scale,
                d.trans_noise,
                d.lateral_noise,
                d.rot_scale,
                d.rot_bias_per_m,
                d.rot_noise,
                d.rot_noise_per_m,
            ]
            .iter()
            .all(|v| v.is_finite())
                && d.trans_noise >= 0.0
                && d.lateral_noise >= 0.0
                && d.rot_noise >= 0.0
                && d.rot_noise_per_m >= 0.0,
            "drift",
            "values must be finite, the noises >= 0",
        );
    }
}

/// The replay.
pub struct CarmenSource {
    path: PathBuf,
    log: CarmenLog,
    /// (scan index, odometry published with it), in file order.
    scans: Vec<(usize, Pose2)>,
    /// Per scan, the odometry published before its own (stamp, pose): the ODOM lines strictly
    /// between the scan before it and it (drifted like the scans' with `add_drift`).
    between: Vec<Vec<(f64, Pose2)>>,
    /// How many of the current scan's `between` went out.
    between_sent: usize,
    truth: Vec<(f64, Isometry3<f64>)>,
    settings: CarmenSettings,
    next: usize,
    /// The odometry of the current scan went out; its laser goes next.
    odometry_sent: bool,
    last_stamp_s: f64,
    warts: BTreeMap<&'static str, u64>,
}

fn stamp_ns(t_s: f64) -> u64 {
    (t_s.max(0.0) * 1e9).round() as u64
}

fn iso(p: &Pose2) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(p.x_m, p.y_m, 0.0),
        UnitQuaternion::from_euler_angles(0.0, 0.0, p.theta_rad),
    )
}

impl CarmenSource {
    /// Reads the log named by `settings.file` (relative to `config_dir`).
    pub fn load(config_dir: &Path, settings: &CarmenSettings) -> Result<Self, SourceError> {
        let path = crate::resolve(config_dir, &settings.file);
        let log = read_carmen(&path)?;
        let mut warts = BTreeMap::new();
        if log.report.bad_lines > 0 {
            warts.insert("malformed_lines_skipped", log.report.bad_lines as u64);
            for p in &log.report.problems {
                tracing::warn!("skipped: {p}");
            }
        }
        if let Some(t) = &log.report.truncated {
            warts.insert("file_truncated", 1);
            tracing::warn!("{t}: the replay ends there");
        }
        let skipped: usize = log.report.skipped_types.values().sum();
        if skipped > 0 {
            warts.insert("other_message_lines_skipped", skipped as u64);
            tracing::info!("message types not replayed: {:?}", log.report.skipped_types);
        }
        match log.front_laser_offset_m() {
            Ok(Some(x)) if (x - settings.body_from_laser[0]).abs() > 1e-9 => tracing::info!(
                "the log states its front laser {x:+.3} m ahead of the robot (PARAM robot_frontlaser_offset); \
                 body_from_laser is {:?}: on a raw log whose odometry is the robot's, set \
                 [carmen] body_from_laser = [{x}, 0.0, 0.0] (the corrected logs' poses are the laser's: keep 0 there)",
                settings.body_from_laser
            ),
            Ok(_) => {}
            Err(e) => tracing::warn!("{e}: ignored"),
        }
        if log.scans.is_empty() {
            return Err(SourceError::Settings(format!(
                "{}: no laser scans (FLASER, RAWLASER or ROBOTLASER1 lines) in the log",
                path.display()
            )));
        }
        let odo = log.scan_odometry(settings.odometry);
        let mut scans = Vec::with_capacity(odo.len());
        let mut without = 0u64;
        for (i, o) in odo.iter().enumerate() {
            match o {
                Some(o) => scans.push((i, Pose2 { x_m: o[0], y_m: o[1], theta_rad: o[2] })),
                None => without += 1,
            }
        }
        if without > 0 {
            warts.insert("scans_without_odometry", without);
            tracing::warn!(
                scans = without,
                "scans without odometry (no pose fields, or outside the ODOM lines): not replayed"
            );
        }
        if settings.max_scans > 0 {
            scans.truncate(settings.max_scans);
        }
        if scans.is_empty() {
            return Err(SourceError::Settings(format!(
                "{}: no scan has odometry ({:?}): set carmen.odometry to the source the log has",
                path.display(),
                settings.odometry
            )));
        }
        {
            let (_, left_out) = log.odometry_in_order();
            if left_out > 0 {
                warts.insert("odom_lines_out_of_order", left_out as u64);
                tracing::warn!(
                    lines = left_out,
                    "ODOM lines whose stamp is not after the one before (resets with stamp 0, stray stamps): left out"
                );
            }
        }
        let mut truth = Vec::new();
        let track: Vec<(f64, Pose2)> = log
            .odometry_in_order()
            .0
            .into_iter()
            .map(|(t, o)| (t, Pose2 { x_m: o[0], y_m: o[1], theta_rad: o[2] }))
            .collect();
        let at_scans: Vec<(f64, Pose2)> = scans.iter().map(|(i, p)| (log.scans[*i].stamp_s, *p)).collect();
        let between = if settings.add_drift {
            truth = at_scans.iter().map(|(t, p)| (*t, iso(p))).collect();
            truth.sort_by(|a, b| a.0.total_cmp(&b.0));
            truth.dedup_by(|a, b| a.0 == b.0);
            let (drifted, between) = settings.drift.apply_between(&at_scans, &track);
            for (s, d) in scans.iter_mut().zip(drifted) {
                s.1 = d;
            }
            between
        } else {
            grid_slam::densify::between_samples(&at_scans, &at_scans, &track)
        };
        Ok(Self {
            path,
            log,
            scans,
            between,
            between_sent: 0,
            truth,
            settings: settings.clone(),
            next: 0,
            odometry_sent: false,
            last_stamp_s: f64::NEG_INFINITY,
            warts,
        })
    }
}

impl Source for CarmenSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        let Some(&(i, odom)) = self.scans.get(self.next) else { return Ok(None) };
        if let Some((t, o)) = self.between.get(self.next).and_then(|b| b.get(self.between_sent)) {
            self.between_sent += 1;
            let odometry =
                PlanarOdometry { position_m: [o.x_m, o.y_m], yaw_rad: o.theta_rad, flags: 0, ..Default::default() };
            return Ok(Some(Item::PlanarOdometry { stamp_ns: stamp_ns(*t), odometry }));
        }
        let scan = &self.log.scans[i];
        let stamp = stamp_ns(scan.stamp_s);
        if !self.odometry_sent {
            self.odometry_sent = true;
            if scan.stamp_s <= self.last_stamp_s {
                let n = self.warts.entry("scans_not_after_the_previous").or_default();
                if *n == 0 {
                    tracing::warn!(
                        "{}:{}: scan stamp {:.6} s is not after the previous one ({:.6} s): published as it is",
                        self.path.display(),
                        scan.line,
                        scan.stamp_s,
                        self.last_stamp_s
                    );
                }
                *n += 1;
            }
            self.last_stamp_s = self.last_stamp_s.max(scan.stamp_s);
            let odometry = PlanarOdometry {
                position_m: [odom.x_m, odom.y_m],
                yaw_rad: odom.theta_rad,
                flags: 0,
                ..Default::default()
            };
            return Ok(Some(Item::PlanarOdometry { stamp_ns: stamp, odometry }));
        }
        self.odometry_sent = false;
        self.next += 1;
        self.between_sent = 0;
        let [x, y, yaw] = self.settings.body_from_laser;
        let header = LaserScanHeader {
            angle_min_rad: scan.angle_min_rad,
            angle_increment_rad: scan.angle_increment_rad,
            range_min_m: self.settings.range_min_m,
            range_max_m: scan.range_max_m.unwrap_or(self.settings.range_max_m),
            body_from_laser_xy_m: [x, y],
            body_from_laser_yaw_rad: yaw,
            beams: scan.ranges.len() as u32,
            flags: LASER_MAX_IS_NO_RETURN,
            ..Default::default()
        };
        Ok(Some(Item::Laser { stamp_ns: stamp, header, ranges: scan.ranges.clone() }))
    }

    fn progress(&self) -> Option<f64> {
        Some(self.next as f64 / self.scans.len().max(1) as f64)
    }

    fn truth(&self, from: usize, out: &mut Vec<(f64, Isometry3<f64>)>) {
        // A replay knows all of it, but only what has been replayed is scored.
        let t_now = self.last_stamp_s;
        let known = self.truth.partition_point(|(t, _)| *t <= t_now);
        out.extend(self.truth.iter().take(known).skip(from).copied());
    }

    fn warts(&self) -> BTreeMap<&'static str, u64> {
        self.warts.iter().filter(|(_, n)| **n > 0).map(|(k, n)| (*k, *n)).collect()
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        Ok(())
    }

    fn describe(&self) -> String {
        let span = self.scans.last().map_or(0.0, |l| self.log.scans[l.0].stamp_s)
            - self.scans.first().map_or(0.0, |f| self.log.scans[f.0].stamp_s);
        let drift = if self.settings.add_drift {
            let d = &self.settings.drift;
            format!(
                "; odometry = the log's poses with seeded drift (seed {}, scale {:+}/{:+}, noise {}/m {}/m lateral, \
                 heading {} rad/m bias, {}·|dθ| + {} rad/m noise)",
                d.seed,
                d.trans_scale,
                d.rot_scale,
                d.trans_noise,
                d.lateral_noise,
                d.rot_bias_per_m,
                d.rot_noise,
                d.rot_noise_per_m
            )
        } else {
            String::new()
        };
        format!("CARMEN log {} ({} scans, {span:.0} s){drift}", self.path.display(), self.scans.len())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flaser(t: f64, x: f64) -> String {
        let r: Vec<String> = (0..180).map(|k| format!("{}", 2.0 + (k % 7) as f64 * 0.1)).collect();
        format!("FLASER 180 {} {x} 0 0 {x} 0 0 {t} h {t}\n", r.join(" "))
    }

    #[test]
    fn scans_go_out_as_odometry_then_laser_with_warts_counted() {
        let dir = tempfile::tempdir().expect("tmp");
        let mut text = String::new();
        text += &flaser(1.0, 0.0);
        text += "PARAM x 1 h 1\nFLASER 3 1 2\n";
        text += &flaser(2.0, 0.5);
        text += &flaser(1.5, 0.6);
        std::fs::write(dir.path().join("a.log"), text).expect("write");
        let settings = CarmenSettings { file: "a.log".into(), add_drift: true, ..Default::default() };
        let mut s = CarmenSource::load(dir.path(), &settings).expect("load");
        let mut items = vec![];
        while let Some(i) = s.next_item().expect("item") {
            items.push(i);
        }
        assert_eq!(items.len(), 6);
        assert!(matches!(items[0], Item::PlanarOdometry { stamp_ns: 1_000_000_000, .. }));
        let Item::Laser { stamp_ns, header, ranges } = &items[1] else { panic!("{:?}", items[1]) };
        assert_eq!((*stamp_ns, ranges.len(), header.range_max_m), (1_000_000_000, 180, 80.0));
        assert!((header.angle_increment_rad - 1f64.to_radians()).abs() < 1e-12);
        let w = s.warts();
        assert_eq!(w.get("malformed_lines_skipped"), Some(&1));
        assert_eq!(w.get("other_message_lines_skipped"), Some(&1));
        assert_eq!(w.get("scans_not_after_the_previous"), Some(&1));
        let mut truth = vec![];
        s.truth(0, &mut truth);
        assert_eq!(truth.len(), 3, "the corrected poses are the reference");
        assert!(s.describe().contains("seed 7"), "{}", s.describe());
        let e = CarmenSource::load(dir.path(), &CarmenSettings { file: "none.log".into(), ..Default::default() })
            .err()
            .expect("missing file");
        assert!(e.to_string().contains("none.log"), "{e}");
    }

    #[test]
    fn odom_lines_between_scans_go_out_before_the_next_scan_drifted_like_it() {
        let dir = tempfile::tempdir().expect("tmp");
        // Scans every second, ODOM lines every 0.25 s along x (1 m/s), a reset line with stamp 0
        // after each scan as the Radish logs write them.
        let mut text = String::new();
        for k in 0..=12 {
            let t = 1.0 + k as f64 * 0.25;
            text += &format!("ODOM {} 0 0 0 0 0 {t} h {t}\n", t - 1.0);
            if k % 4 == 0 {
                text += &flaser(t, t - 1.0);
                text += &format!("ODOM {} 0 0 0 0 0 0 h 0\n", t - 1.0);
            }
        }
        std::fs::write(dir.path().join("a.log"), text).expect("write");
        let items = |add_drift: bool| {
            let settings = CarmenSettings { file: "a.log".into(), add_drift, ..Default::default() };
            let mut s = CarmenSource::load(dir.path(), &settings).expect("load");
            let mut out = vec![];
            while let Some(i) = s.next_item().expect("item") {
                out.push(match i {
                    Item::PlanarOdometry { stamp_ns, odometry } => (stamp_ns, Some(odometry.position_m[0])),
                    Item::Laser { stamp_ns, .. } => (stamp_ns, None),
                    other => panic!("{other:?}"),
                });
            }
            (out, s.warts())
        };
        let (plain, warts) = items(false);
        assert_eq!(warts.get("odom_lines_out_of_order"), Some(&4), "the resets: {warts:?}");
        let stamps: Vec<u64> = plain.iter().map(|i| i.0 / 250_000_000).collect();
        // 1 s: odometry, scan; 1.25-1.75 s: odometry; 2 s: odometry, scan; ...
        assert_eq!(stamps, vec![4, 4, 5, 6, 7, 8, 8, 9, 10, 11, 12, 12, 13, 14, 15, 16, 16]);
        for (stamp_ns, x) in &plain {
            if let Some(x) = x {
                assert!((x - (*stamp_ns as f64 * 1e-9 - 1.0)).abs() < 1e-9, "the log's own poses without drift");
            }
        }
        // With drift: the scans' odometry is what it was without the samples between, and the
        // samples between lie between their scans' (1 m/s along x, drift of a few per cent).
        let (drifted, _) = items(true);
        assert_eq!(drifted.len(), plain.len());
        let scans_only: Vec<Pose2> = (0..4).map(|k| Pose2 { x_m: k as f64, y_m: 0.0, theta_rad: 0.0 }).collect();
        let expected = DriftModel::default().apply(&scans_only);
        let at_scans: Vec<f64> = drifted.windows(2).filter(|w| w[1].1.is_none()).filter_map(|w| w[0].1).collect();
        assert_eq!(at_scans, expected.iter().map(|p| p.x_m).collect::<Vec<_>>());
        let xs: Vec<f64> = drifted.iter().filter_map(|i| i.1).collect();
        assert!(xs.windows(2).all(|w| w[1] >= w[0] && w[1] - w[0] < 0.3), "{xs:?}");
    }
}
