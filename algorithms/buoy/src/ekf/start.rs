//! How the filter starts and restarts: the ranges kept for a start, the robust window fix
//! (`buoy::window_fix`) and the stationary trilateration, the start's confirmation against later
//! ranges, and the recovery when the ranges say the filter is lost.

#![allow(non_snake_case)]

use super::*;

impl BuoyEkf {
    /// Fills the observability window from the odometry window (just after the start): the
    /// geometry of the ranges the start was made from, placed along the odometry's path
    /// through the estimate now (turned by the estimated heading once it is known).
    pub(super) fn seed_seen(&mut self) {
        let (Some(odo), Ok(e)) = (self.odo, self.estimate()) else { return };
        let window = self.model.cfg.range.observability_window_s;
        let turn = e.heading_rad.map_or(0.0, |h| h - odo[2]);
        let (sn, cs) = turn.sin_cos();
        for (t, w) in &self.window {
            if self.t_s - t > window {
                continue;
            }
            let Some(j) = self.ids.iter().position(|&id| id == w.buoy_id) else { continue };
            let (dx, dy) = (w.odom_pose[0] - odo[0], w.odom_pose[1] - odo[1]);
            let mut p = e.position_m;
            p.x += cs * dx - sn * dy;
            p.y += sn * dx + cs * dy;
            if self.model.lay.d == 3 {
                p.z = w.height_m;
            }
            self.seen.push_back(SeenRange {
                t_s: *t,
                buoy: j,
                position_m: p,
                odom_xy: Some([w.odom_pose[0], w.odom_pose[1]]),
                sigma_m: w.sigma_m,
            });
        }
    }

    /// Range `j` as seen from the current estimate (for the observability check).
    pub(super) fn seen_range(&self, j: usize, sigma_m: f64) -> Result<SeenRange, BuoyError> {
        let x = match &self.phase {
            Phase::Waiting => return Err(BuoyError::NotInitialised),
            Phase::Single(g) => g.x.clone(),
            Phase::Mixture(h) => self.model.moment_match(h).x,
        };
        let odom_xy = self.odo.map(|o| [o[0], o[1]]);
        Ok(SeenRange { t_s: self.t_s, buoy: j, position_m: self.model.position(&x), odom_xy, sigma_m })
    }

    /// The odometry path's anchor for the observability check (with odometry and a heading).
    pub(super) fn path_anchor(&self) -> Option<PathAnchor> {
        let o = self.odo?;
        let e = self.estimate().ok()?;
        let heading = e.heading_rad?;
        Some(PathAnchor { position_m: e.position_m, odom_xy: [o[0], o[1]], turn_rad: heading - o[2] })
    }

    /// The vehicle's known height now: planar mode's fixed height, or in spatial mode the
    /// latest depth reading if it is at most `init.window_s` old.
    pub(super) fn known_height(&self) -> Option<(f64, f64)> {
        match self.model.lay.d {
            2 => Some((self.model.cfg.planar_height_m, 0.0)),
            _ => self.last_depth.filter(|d| self.t_s - d.0 <= self.model.cfg.init.window_s).map(|d| (d.1, d.2)),
        }
    }

    /// Whether the odometry window is in use: `init.odometry_window`, odometry seen, and the
    /// height known (planar mode, or a recent depth reading in spatial mode).
    pub(super) fn window_enabled(&self) -> bool {
        self.model.cfg.init.odometry_window && self.odo.is_some() && self.known_height().is_some()
    }

    /// Adds a range to the odometry window (with the odometry's pose now); whether it did.
    pub(super) fn push_window(&mut self, j: usize, range_m: f64, sigma_m: f64) -> bool {
        if !self.model.cfg.init.odometry_window {
            return false;
        }
        // Before the first odometry input the vehicle is where the odometry will start.
        let o = self.odo.unwrap_or([0.0; 4]);
        // Without a known height yet (3-D before the first depth reading) the height is filled
        // in by the first reading if it comes within `init.window_s` (see `update_depth`), else
        // the range stays out of the fix (NaN).
        let height_m = self.known_height().map_or(f64::NAN, |h| h.0);
        self.window.push_back((
            self.t_s,
            WindowRange {
                odom_pose: [o[0], o[1], o[2]],
                path_m: o[3],
                height_m,
                buoy_id: self.ids[j],
                buoy_m: self.model.buoys[j],
                range_m,
                sigma_m,
            },
        ));
        true
    }

    /// Drops the window's ranges older than `init.odometry_window_s` or beyond its size.
    pub(super) fn prune_window(&mut self) {
        let i = &self.model.cfg.init;
        let (span, max) = (i.odometry_window_s, i.odometry_window_max_ranges);
        while self.window.front().is_some_and(|w| w.0 < self.t_s - span) || self.window.len() > max {
            self.window.pop_front();
        }
    }

    /// The robust fix of the window, with the ranges corrected by the calibration (scale and
    /// bias means) of `calibration`, or taken as they are.
    pub(super) fn window_fix_with(&self, calibration: Option<&Gaussian>) -> Result<WindowFix, TrilaterationError> {
        let l = &self.model.lay;
        let i = &self.model.cfg.init;
        let obs: Vec<WindowRange> = self
            .window
            .iter()
            .filter(|(_, w)| w.height_m.is_finite())
            .map(|(_, w)| {
                let mut w = *w;
                if let Some(g) = calibration {
                    let j = self.ids.iter().position(|&id| id == w.buoy_id).unwrap_or(0);
                    let s = l.scale.map_or(0.0, |k| g.x[k]);
                    let beta = l.bias_of(j).map_or(0.0, |k| g.x[k]);
                    w.range_m = ((w.range_m - beta) / (1.0 + s)).max(0.0);
                }
                w
            })
            .collect();
        let limits = WindowLimits {
            min_buoys: i.min_buoys,
            min_inliers: i.odometry_window_min_inliers,
            min_inlier_fraction: i.odometry_window_min_inlier_fraction,
            drift_fraction: i.odometry_drift_fraction,
            ambiguity_margin: i.odometry_window_ambiguity_margin,
            ..WindowLimits::default()
        };
        window_fix(&obs, &limits)
    }

    /// Waiting with the odometry window: starts from its robust fix when it has one.
    pub(super) fn try_window_init(&mut self) -> RangeOutcome {
        match self.window_fix_with(None) {
            Err(e) => RangeOutcome::Waiting(e),
            Ok(fix) => {
                self.start_from_fix(&fix, None);
                RangeOutcome::Initialised
            }
        }
    }

    /// (Re)starts the filter at a window fix: the position (and heading, when the fix has one)
    /// from the fix, the velocity at its prior; the calibration states from `keep` (a filter
    /// being re-started) or their priors.
    pub(super) fn start_from_fix(&mut self, fix: &WindowFix, keep: Option<Gaussian>) {
        let l = self.model.lay;
        let mut cov = fix.covariance_m2 * fix.normalised_rms.max(1.0).powi(2);
        if l.d == 3 {
            // z comes from the depth reading.
            cov[(2, 2)] = self.known_height().map_or(1.0, |(_, sigma)| sigma * sigma).max(1e-6);
        }
        let mut g = match keep {
            Some(mut g) => {
                self.model.reset_position(&mut g, &fix.position_m, &cov);
                let prior = self.model.prior_variances();
                for k in l.d..2 * l.d {
                    g.x[k] = 0.0;
                    g.P.row_mut(k).fill(0.0);
                    g.P.column_mut(k).fill(0.0);
                    g.P[(k, k)] = prior[k];
                }
                g
            }
            None => self.initial_gaussian(&fix.position_m, &cov),
        };
        // A re-start: the new position's error does not follow from the last fix's.
        g.cross = None;
        g.P.row_mut(l.psi).fill(0.0);
        g.P.column_mut(l.psi).fill(0.0);
        match fix.heading_rad {
            Some(h) => {
                g.x[l.psi] = h;
                // The heading's σ scaled like the position's; with their correlation.
                let scale = fix.normalised_rms.max(1.0).powi(2);
                let var = (fix.heading_sigma_rad.powi(2) * scale).max(1f64.to_radians().powi(2));
                g.P[(l.psi, l.psi)] = var;
                let c = position_heading_cov(&cov, var, &(fix.position_heading_cov_m_rad * scale));
                for a in 0..2 {
                    g.P[(a, l.psi)] = c[a];
                    g.P[(l.psi, a)] = c[a];
                }
                self.heading_known = true;
                self.phase = Phase::Single(g);
            }
            None => {
                g.P[(l.psi, l.psi)] = std::f64::consts::PI.powi(2);
                self.heading_known = false;
                self.phase = Phase::Single(g);
                self.split_if_heading_unknown();
            }
        }
        self.init_ranges.clear();
        self.recent.clear();
        self.held_nu.iter_mut().for_each(|h| *h = None);
        self.shadow = None;
        self.confirming = (self.model.cfg.recovery.confirm_checks > 0).then(Confirming::default);
    }

    /// The check of a provisional start (see `recovery.confirm_checks`), after each range:
    /// every `recovery.confirm_every_ranges` ranges the window is solved again, as at the start
    /// (raw ranges) and with the ranges corrected by the filter's calibration; when both
    /// disagree with the filter it re-starts at the first with the calibration at its prior.
    /// Returns whether it re-started.
    pub(super) fn confirm_start(&mut self) -> bool {
        let rc = &self.model.cfg.recovery;
        let (every, needed) = (rc.confirm_every_ranges, rc.confirm_checks);
        let Some(mut c) = self.confirming else { return false };
        c.ranges += 1;
        self.confirming = Some(c);
        if c.ranges < every || !self.window_enabled() {
            return false;
        }
        c.ranges = 0;
        self.confirming = Some(c);
        let g = match &self.phase {
            Phase::Single(g) => g.clone(),
            Phase::Mixture(h) => self.model.moment_match(h),
            Phase::Waiting => return false,
        };
        let Ok(fix) = self.window_fix_with(None) else { return false };
        self.counters.start_checks += 1;
        // The raw fix is off by what the calibration learned since the start (a scale, a
        // bias): a filter that agrees with the fix of the ranges corrected by its own
        // calibration holds too.
        let agrees = |f: &WindowFix| self.position_distance2(&g, f) <= self.model.gate_fix;
        if agrees(&fix) || self.window_fix_with(Some(&g)).is_ok_and(|f| agrees(&f)) {
            c.agreed += 1;
            self.confirming = (c.agreed < needed).then_some(c);
            return false;
        }
        self.start_from_fix(&fix, None);
        self.counters.start_corrections += 1;
        true
    }

    /// Squared Mahalanobis distance between the planar positions of `g` and `fix`.
    pub(super) fn position_distance2(&self, g: &Gaussian, fix: &WindowFix) -> f64 {
        let dp = nalgebra::Vector2::new(fix.position_m.x - g.x[0], fix.position_m.y - g.x[1]);
        let S = nalgebra::Matrix2::new(g.P[(0, 0)], g.P[(0, 1)], g.P[(1, 0)], g.P[(1, 1)])
            + fix.covariance_m2.fixed_view::<2, 2>(0, 0);
        S.try_inverse().map_or(f64::INFINITY, |inv| dp.dot(&(inv * dp)))
    }

    /// The lost-filter check (see `recovery.check_rejected_share`): with `forced` (a run of
    /// rejections) or too many rejections among the last ranges, asks the window for a robust
    /// fix and re-starts the filter there if the two disagree. Returns whether it re-started.
    pub(super) fn check_lost(&mut self, forced: bool) -> bool {
        if !self.window_enabled() {
            return false;
        }
        let rc = &self.model.cfg.recovery;
        let rejected = self.recent.iter().filter(|&&r| r).count();
        let due = self.recent.len() >= rc.check_ranges
            && rejected as f64 >= rc.check_rejected_share * self.recent.len() as f64;
        if !(forced || due) {
            return false;
        }
        self.recent.clear();
        let g = match &self.phase {
            Phase::Single(g) => g.clone(),
            Phase::Mixture(h) => self.model.moment_match(h),
            Phase::Waiting => return false,
        };
        let (fix, keep) = match self.window_fix_with(Some(&g)) {
            Ok(f) => (f, true),
            Err(_) => match self.window_fix_with(None) {
                Ok(f) => (f, false),
                Err(_) => {
                    self.counters.lost_checks_without_fix += 1;
                    return false;
                }
            },
        };
        if self.position_distance2(&g, &fix) <= self.model.gate_fix {
            return false;
        }
        self.start_from_fix(&fix, keep.then_some(g));
        self.counters.reinitialisations += 1;
        true
    }

    pub(super) fn inflate_after_rejections(&mut self, mean_nu2: f64, heading_sigma: f64) {
        self.shadow = None;
        let l = self.model.lay;
        let heading_known = self.heading_known;
        if let Phase::Single(g) = &mut self.phase {
            for k in 0..l.d {
                g.P[(k, k)] += mean_nu2;
            }
            if heading_known {
                g.P[(l.psi, l.psi)] += heading_sigma * heading_sigma;
            }
        }
        self.counters.recoveries += 1;
        self.counters.consecutive_rejected = 0;
        self.rejection_run_nu2 = 0.0;
    }

    pub(super) fn reset_bias(&mut self, j: usize) {
        let Some(i) = self.model.lay.bias_of(j) else { return };
        self.shadow = None;
        let var = self.model.cfg.range.bias_prior_sigma_m.powi(2);
        if let Phase::Single(g) = &mut self.phase {
            g.forget_state(i);
            g.P.row_mut(i).fill(0.0);
            g.P.column_mut(i).fill(0.0);
            g.P[(i, i)] = var;
        }
        self.counters.bias_resets += 1;
        self.counters.per_buoy[j].consecutive_rejected = 0;
    }

    /// Buffers a range for initialisation and tries a trilateration.
    pub(super) fn try_trilaterate(&mut self, r: InitRange) -> RangeOutcome {
        let window = self.model.cfg.init.window_s;
        self.init_ranges.push_back(r);
        while self.init_ranges.front().is_some_and(|o| o.t_s < self.t_s - window) {
            self.init_ranges.pop_front();
        }
        // With odometry, only the ranges taken while the vehicle was within a range σ of where
        // it is now (the trilateration takes them as taken from one place; a range from before
        // the first odometry input counts as taken where the odometry started).
        if let Some(o) = self.odo {
            self.init_ranges.retain(|r| {
                let p = r.odom_xy.unwrap_or([0.0, 0.0]);
                (p[0] - o[0]).hypot(p[1] - o[1]) <= r.sigma_m.max(0.05)
            });
        }
        let obs: Vec<RangeObs> = self
            .init_ranges
            .iter()
            .map(|o| RangeObs {
                buoy_id: self.ids[o.buoy],
                buoy_m: self.model.buoys[o.buoy],
                range_m: o.range_m,
                sigma_m: o.sigma_m,
            })
            .collect();
        let c = &self.model.cfg;
        let geometry = match c.mode {
            Mode::Planar => Geometry::Planar { height_m: c.planar_height_m },
            Mode::Spatial => Geometry::Spatial {
                z_constraint: self.last_depth.filter(|d| self.t_s - d.0 <= window).map(|d| (d.1, d.2)),
            },
        };
        let limits = Limits {
            min_buoys: c.init.min_buoys,
            max_condition: c.init.max_condition,
            max_normalised_rms: c.init.max_normalised_rms,
            huber_k: c.range.huber_k,
        };
        match trilaterate(&obs, geometry, &limits) {
            Err(e) => RangeOutcome::Waiting(e),
            Ok(sol) => {
                let mut g = self.initial_gaussian(&sol.position_m, &sol.covariance_m2);
                self.add_consider_covariance(&mut g, &sol.sensitivity, &sol.position_m);
                self.phase = Phase::Single(g);
                // The ranges it started from join the observability window (taken at the
                // solution, as the trilateration took them).
                self.seen.clear();
                for o in &self.init_ranges {
                    let (t_s, buoy, sigma_m) = (o.t_s, o.buoy, o.sigma_m);
                    let odom_xy = o.odom_xy;
                    self.seen.push_back(SeenRange { t_s, buoy, position_m: sol.position_m, odom_xy, sigma_m });
                }
                self.init_ranges.clear();
                self.split_if_heading_unknown();
                RangeOutcome::Initialised
            }
        }
    }
}
