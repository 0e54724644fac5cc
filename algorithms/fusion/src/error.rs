//! Errors of the fusion mathematics: never a panic.

/// What went wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FusionError {
    /// A value is NaN or infinite.
    #[error("non-finite {0}")]
    NonFinite(&'static str),
    /// A covariance that must be positive definite is not.
    #[error("{0} is not positive definite")]
    NotPositiveDefinite(&'static str),
    /// Sample times must increase strictly.
    #[error("sample times must increase strictly (sample {index})")]
    TimesNotIncreasing {
        /// Index of the first offending sample.
        index: usize,
    },
    /// Too few samples or pairs for the operation.
    #[error("{what}: {got} given, {need} needed")]
    TooFew {
        /// What is counted.
        what: &'static str,
        /// How many were given.
        got: usize,
        /// How many are needed.
        need: usize,
    },
    /// A query outside the range the data covers.
    #[error("time {t_s} s outside [{from_s}, {to_s}] s")]
    OutOfRange {
        /// The query, s.
        t_s: f64,
        /// Start of the range, s.
        from_s: f64,
        /// End of the range, s.
        to_s: f64,
    },
    /// The correspondences are (nearly) collinear: the rotation about their line is unobservable.
    #[error("correspondences nearly collinear (spread ratio {ratio:.2e} below {limit:.2e})")]
    Collinear {
        /// Second to first singular value of the centred points.
        ratio: f64,
        /// The configured limit.
        limit: f64,
    },
    /// The correspondences span too small a region for the rotation to be estimated.
    #[error("correspondences span {extent_m:.3} m, below the {limit_m:.3} m needed for a rotation")]
    TooSmall {
        /// Largest extent of the local points, m.
        extent_m: f64,
        /// The configured limit, m.
        limit_m: f64,
    },
    /// An argument or setting is out of its domain (e.g. a negative gate).
    #[error("invalid argument: {0}")]
    InvalidArgument(&'static str),
    /// A linear system could not be solved.
    #[error("singular system: {0}")]
    Singular(&'static str),
    /// Writing a file failed.
    #[error("{path}: {message}")]
    Io {
        /// The file.
        path: String,
        /// The error.
        message: String,
    },
}

impl FusionError {
    /// True for the geometric degeneracies ([`FusionError::Collinear`], [`FusionError::TooSmall`])
    /// that a heading sensor resolves (see [`crate::align::align_with_heading`]).
    pub fn is_degenerate_geometry(&self) -> bool {
        matches!(self, Self::Collinear { .. } | Self::TooSmall { .. })
    }
}

impl From<geometry::gaussian::GaussianError> for FusionError {
    fn from(e: geometry::gaussian::GaussianError) -> Self {
        match e {
            geometry::gaussian::GaussianError::NonFinite(what) => FusionError::NonFinite(what),
            geometry::gaussian::GaussianError::NotPositiveDefinite(what) => FusionError::NotPositiveDefinite(what),
        }
    }
}
