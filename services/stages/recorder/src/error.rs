//! What recording can fail with (the MCAP sink of `record` and the ROS 2 sink of `ros2` alike).

use std::path::PathBuf;

/// What recording can fail with; each names the file or the service.
#[derive(Debug, thiserror::Error)]
pub enum RecorderError {
    /// The file or its directory cannot be created, written or synced.
    #[error("{}: {what}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What was being done.
        what: &'static str,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// The MCAP writer failed.
    #[error("{}: {source}", path.display())]
    Mcap {
        /// The file.
        path: PathBuf,
        /// The error.
        #[source]
        source: mcap::McapError,
    },
    /// The writer thread is gone (finished, stopped after an error, or panicked).
    #[error("{}: {what}", path.display())]
    Writer {
        /// The file.
        path: PathBuf,
        /// What happened.
        what: &'static str,
    },
    /// A message cannot be taken as its service's wire type.
    #[error("`{service}`: {what}")]
    Message {
        /// The service.
        service: String,
        /// What is wrong.
        what: String,
    },
    /// A port failed.
    #[error(transparent)]
    Port(#[from] pipeline_runtime::PortError),
    /// A message could not be moved in or out of shared memory.
    #[error(transparent)]
    Topic(#[from] pipeline_runtime::topics::TopicError),
    /// A schema or JSON mirror cannot be encoded.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
}

impl From<RecorderError> for pipeline_runtime::StageError {
    fn from(e: RecorderError) -> Self {
        pipeline_runtime::StageError::stage(e)
    }
}
