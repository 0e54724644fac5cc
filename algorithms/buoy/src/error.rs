//! The error types of the crate: [`BuoyError`] for the estimator and [`TrilaterationError`] for
//! the initialisation solvers. Nothing in this crate panics on bad input; every failure is one
//! of these.

/// An error of the buoy estimator ([`crate::BuoyEkf`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BuoyError {
    /// The configuration failed validation; each entry is (key, problem).
    #[error("invalid buoy configuration: {}", format_problems(.0))]
    InvalidConfig(Vec<validation::ConfigIssue>),
    /// An input was NaN or infinite.
    #[error("non-finite input: {0}")]
    NonFinite(&'static str),
    /// A standard deviation or variance was negative or zero where it must be positive.
    #[error("{what} must be positive, got {value}")]
    NonPositiveSigma {
        /// Which input.
        what: &'static str,
        /// The value given.
        value: f64,
    },
    /// A range named a buoy that is not in the configured buoy table.
    #[error("unknown buoy id {0}")]
    UnknownBuoy(u32),
    /// A time went backwards (the filter only moves forward in time).
    #[error("time {t_s} s is before the filter's time {now_s} s")]
    TimeWentBackwards {
        /// The time asked for, s.
        t_s: f64,
        /// The filter's current time, s.
        now_s: f64,
    },
    /// The estimate was asked for before the filter was initialised.
    #[error("the filter is not initialised yet")]
    NotInitialised,
    /// The measurement does not exist in this mode (a depth reading in planar mode).
    #[error("{0} is not available in planar (2-D) mode")]
    NotInPlanarMode(&'static str),
    /// A covariance that must be positive definite is not (numerical failure); the filter's
    /// state is left as it was before the call.
    #[error("{0} is not positive definite")]
    NotPositiveDefinite(&'static str),
}

/// Why a trilateration or path alignment produced no solution.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TrilaterationError {
    /// Fewer distinct buoys than the geometry needs.
    #[error("ranges to {got} distinct buoys, {needed} needed")]
    TooFewBuoys {
        /// Distinct buoys ranged.
        got: usize,
        /// Distinct buoys needed.
        needed: usize,
    },
    /// The buoys lie on one line (planar) or in one plane (spatial, without a depth constraint):
    /// the position is ambiguous (mirror solutions).
    #[error("degenerate buoy geometry: {0}")]
    DegenerateGeometry(&'static str),
    /// The normal matrix is too ill-conditioned to trust the solution.
    #[error("ill-conditioned normal matrix (condition number {condition:.3e} > {max:.3e})")]
    IllConditioned {
        /// Its condition number.
        condition: f64,
        /// The configured maximum.
        max: f64,
    },
    /// Gauss-Newton did not converge.
    #[error("Gauss-Newton did not converge in {0} iterations")]
    NotConverged(usize),
    /// The solution fits the ranges badly (normalised RMS residual too large).
    #[error("residuals too large: normalised RMS {rms:.2} > {max:.2}")]
    PoorFit {
        /// Normalised RMS residual of the inliers.
        rms: f64,
        /// The configured maximum.
        max: f64,
    },
    /// An input was NaN or infinite, or a σ not positive.
    #[error("invalid input: {0}")]
    InvalidInput(&'static str),
    /// Too few ranges in the window for a robust fix yet.
    #[error("{got} ranges in the window, {needed} needed for a robust fix")]
    TooFewRanges {
        /// Ranges in the window.
        got: usize,
        /// Ranges needed.
        needed: usize,
    },
    /// The best robust fix explains too few of the window's ranges (outliers, or the odometry
    /// does not hold over the window).
    #[error(
        "the best fix explains {inliers} of {ranges} ranges to {buoys} buoys; {needed} ranges and {min_share:.0} % needed, to >= 3 buoys"
    )]
    TooFewInliers {
        /// Ranges the best fix explains.
        inliers: usize,
        /// Ranges in the window.
        ranges: usize,
        /// Distinct buoys among the inliers.
        buoys: usize,
        /// Inliers needed.
        needed: usize,
        /// Share needed, %.
        min_share: f64,
    },
    /// The vehicle moved too far in the window to be taken as standing still, and not far
    /// enough for the heading to show.
    #[error(
        "moved {travel_m:.2} m in the window: too far to take as standing still, not far enough ({needed_m:.1} m) to solve the heading"
    )]
    Moving {
        /// Largest distance of the window's odometry positions from the newest, m.
        travel_m: f64,
        /// Distance that makes the heading observable, m.
        needed_m: f64,
    },
    /// Two distinct poses explain the window almost equally well (e.g. mirror positions, or a
    /// heading that the path so far cannot tell).
    #[error(
        "ambiguous: the best fix explains {best} ranges, a distinct one {runner_up} nearly as well (cost gap {cost_gap:.1} outliers' worth)"
    )]
    Ambiguous {
        /// Inliers of the best fix.
        best: usize,
        /// Inliers of the best distinct alternative.
        runner_up: usize,
        /// Its truncated cost above the best, in outliers' worth (k² each).
        cost_gap: f64,
    },
}

fn format_problems(problems: &[validation::ConfigIssue]) -> String {
    problems.iter().map(|i| format!("`{}` {}", i.key, i.message)).collect::<Vec<_>>().join("; ")
}
