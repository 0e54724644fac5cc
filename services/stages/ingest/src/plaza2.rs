//! `source = "plaza2"`: the Plaza2 range-only data set (odometry and beacon ranges) replayed.

use std::path::Path;

use nalgebra::Isometry3;
use shared_types::{BuoyRange, OdometryInput};

use crate::sources::*;

/// Replay of Plaza2: odometry increments as inputs (v = Δd/Δt, δθz = Δheading) and each beacon
/// range as a one-element `BuoyRange` slice, merged in time order on the data set's clock.
pub struct Plaza2Source {
    data: datasets::Plaza2,
    settings: crate::Plaza2Settings,
    next_odo: usize,
    next_range: usize,
    t_first_s: f64,
    t_last_s: f64,
    t_now_s: f64,
    skipped_odometry: u64,
    dir: std::path::PathBuf,
    /// The ground truth as body poses (Plaza2's heading is offset by π from the direction of travel).
    truth: Vec<(f64, Isometry3<f64>)>,
    /// The last item has been taken.
    exhausted: bool,
}

impl Plaza2Source {
    /// Loads the four files of `dir` (the run's prefix from the settings, else found in `dir`).
    /// Lines out of time order are sorted into place, counted and warned about once per file.
    pub fn load(dir: &Path, settings: &crate::Plaza2Settings) -> Result<Self, SourceError> {
        let data = match &settings.prefix {
            Some(prefix) => datasets::Plaza2::load_with_prefix(dir, prefix)?,
            None => datasets::Plaza2::load(dir)?,
        };
        for o in &data.out_of_order {
            tracing::warn!(file = %o.path.display(), lines = o.lines, "{o}");
        }
        let truth = data
            .ground_truth
            .iter()
            .map(|g| {
                let rot = nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, g.heading_rad + std::f64::consts::PI);
                (g.t_s, Isometry3::from_parts(nalgebra::Translation3::new(g.x_m, g.y_m, 0.0), rot))
            })
            .collect();
        let t_first_s = data
            .odometry
            .first()
            .map(|r| r.t_s)
            .unwrap_or(0.0)
            .min(data.ranges.first().map(|r| r.t_s).unwrap_or(f64::MAX));
        let t_last_s =
            data.odometry.last().map(|r| r.t_s).unwrap_or(0.0).max(data.ranges.last().map(|r| r.t_s).unwrap_or(0.0));
        Ok(Self {
            data,
            settings: settings.clone(),
            next_odo: 0,
            next_range: 0,
            t_first_s,
            t_last_s,
            t_now_s: t_first_s,
            skipped_odometry: 0,
            dir: dir.to_path_buf(),
            truth,
            exhausted: false,
        })
    }

    fn odometry_item(&mut self, i: usize) -> Option<Item> {
        let row = self.data.odometry[i];
        let dt = if i == 0 { 0.1 } else { row.t_s - self.data.odometry[i - 1].t_s };
        if dt.is_nan() || dt <= 0.0 {
            self.skipped_odometry += 1;
            tracing::warn!(row = i + 1, dt, "Plaza2 odometry: time does not advance; row skipped");
            return None;
        }
        let mut input_covariance = [0.0; 16];
        input_covariance[0] = self.settings.speed_sigma_mps.powi(2);
        for k in 1..4 {
            input_covariance[k * 5] = self.settings.turn_sigma_rad.powi(2);
        }
        Some(Item::Odometry {
            stamp_ns: stamp_from_s(row.t_s),
            input: OdometryInput {
                v_mps: row.delta_dist_m / dt,
                delta_theta_rad: [0.0, 0.0, row.delta_heading_rad],
                dt_s: dt,
                input_covariance,
            },
        })
    }
}

impl Source for Plaza2Source {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        loop {
            let t_odo = self.data.odometry.get(self.next_odo).map(|r| r.t_s);
            let t_rng = self.data.ranges.get(self.next_range).map(|r| r.t_s);
            match (t_odo, t_rng) {
                (None, None) => {
                    self.exhausted = true;
                    return Ok(None);
                }
                (Some(to), tr) if tr.is_none_or(|tr| to <= tr) => {
                    let i = self.next_odo;
                    self.next_odo += 1;
                    self.t_now_s = to;
                    if let Some(item) = self.odometry_item(i) {
                        return Ok(Some(item));
                    }
                }
                (_, Some(tr)) => {
                    let r = self.data.ranges[self.next_range];
                    self.next_range += 1;
                    self.t_now_s = tr;
                    let range = BuoyRange {
                        buoy_id: r.beacon_id,
                        _reserved: 0,
                        range_m: r.range_m,
                        sigma_m: self.settings.range_sigma_m,
                    };
                    return Ok(Some(Item::BuoyRanges { stamp_ns: stamp_from_s(r.t_s), ranges: vec![range] }));
                }
                (Some(_), None) => unreachable!("covered by the first arm"),
            }
        }
    }

    fn progress(&self) -> Option<f64> {
        Some(((self.t_now_s - self.t_first_s) / (self.t_last_s - self.t_first_s).max(1e-9)).clamp(0.0, 1.0))
    }

    /// The ground-truth rows up to the data time reached (all of them at the end), so that a run
    /// stopped early is scored on the part it replayed.
    fn truth(&self, from: usize, out: &mut Vec<(f64, Isometry3<f64>)>) {
        let known =
            if self.exhausted { self.truth.len() } else { self.truth.partition_point(|(t, _)| *t <= self.t_now_s) };
        out.extend(self.truth.iter().take(known).skip(from).copied());
    }

    fn warts(&self) -> std::collections::BTreeMap<&'static str, u64> {
        let out_of_order: usize = self.data.out_of_order.iter().map(|o| o.lines).sum();
        [("lines_out_of_time_order", out_of_order as u64), ("odometry_rows_skipped", self.skipped_odometry)]
            .into_iter()
            .filter(|(_, n)| *n > 0)
            .collect()
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        if self.skipped_odometry > 0 {
            tracing::warn!(rows = self.skipped_odometry, "Plaza2 odometry rows skipped (time not advancing)");
        }
        Ok(())
    }

    fn describe(&self) -> String {
        format!(
            "Plaza2 replay from {} ({} odometry rows, {} ranges to {} beacons, {:.0} s)",
            self.dir.display(),
            self.data.odometry.len(),
            self.data.ranges.len(),
            self.data.beacons.len(),
            self.t_last_s - self.t_first_s
        )
    }
}
