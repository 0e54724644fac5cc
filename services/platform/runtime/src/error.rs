//! Typed errors of a process built on the runtime: [`ContextError`] (its config and settings)
//! and [`StageError`] (what a [`Stage`](crate::Stage) and the runtime around it can fail with).
//! A stage's own failures (its maths, its data files) keep their type inside
//! [`StageError::Stage`]; [`error_chain`] renders any error with its causes for the log.

use std::path::PathBuf;

use crate::config::{ConfigError, ConfigIssue};
use crate::ports::PortError;
use crate::restart::StateError;

/// The config of a process cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ContextError {
    /// The file cannot be read or parsed.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The file has no table for this process.
    #[error("{}: no table [processes.{name}] in this config", file.display())]
    NoProcess {
        /// The config file.
        file: PathBuf,
        /// The process name.
        name: String,
    },
    /// The process's settings are invalid; every issue with its dotted key.
    #[error("{}: invalid settings:{}", file.display(), issues.iter().map(|i| format!("\n  key `{}`: {}", i.key, i.message)).collect::<String>())]
    Settings {
        /// The config file.
        file: PathBuf,
        /// What is wrong, by key.
        issues: Vec<ConfigIssue>,
    },
}

/// What a stage, or the runtime around it, failed with.
#[derive(Debug, thiserror::Error)]
pub enum StageError {
    /// The process's config or settings.
    #[error(transparent)]
    Context(#[from] ContextError),
    /// The runtime (iceoryx2 node, WaitSet, signals).
    #[error(transparent)]
    Runtime(#[from] RuntimeError),
    /// A port (open, loan, send, receive).
    #[error(transparent)]
    Port(#[from] PortError),
    /// The restart state.
    #[error(transparent)]
    State(#[from] StateError),
    /// Writing or reading a file (the summary part, an output).
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// Encoding JSON (the summary part).
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// Settings the stage refuses beyond their own validation.
    #[error("invalid settings: {0}")]
    Settings(String),
    /// The stage's own failure, with its type (downcast it to look inside).
    #[error(transparent)]
    Stage(Box<dyn std::error::Error + Send + Sync + 'static>),
}

impl From<TopicError> for StageError {
    fn from(e: TopicError) -> Self {
        match e {
            TopicError::Port(p) => StageError::Port(p),
            other => StageError::stage(other),
        }
    }
}

impl StageError {
    /// Wraps a stage's own typed error (e.g. `.map_err(StageError::stage)?`).
    pub fn stage(e: impl std::error::Error + Send + Sync + 'static) -> Self {
        StageError::Stage(Box::new(e))
    }

    /// An error with a message only, for a condition the stage names itself.
    pub fn msg(message: impl Into<String>) -> Self {
        StageError::Stage(message.into().into())
    }
}

/// `error: cause: cause ...`, for the log.
pub fn error_chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let s_text = s.to_string();
        if !text.contains(&s_text) {
            text.push_str(": ");
            text.push_str(&s_text);
        }
        source = s.source();
    }
    text
}

/// Errors of the runtime.
#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    /// iceoryx2 setup failed.
    #[error(transparent)]
    Iox(#[from] crate::iox::IoxError),
    /// A port failed.
    #[error(transparent)]
    Port(#[from] PortError),
    /// The service has no entry in the contract and no QoS was given.
    #[error("service `{0}` is not in the service contract (shared_types::services::SERVICES)")]
    UnknownService(String),
    /// The WaitSet failed.
    #[error("WaitSet: {0}")]
    WaitSet(String),
    /// Installing the signal handlers failed.
    #[error("cannot install SIGINT/SIGTERM handlers: {0}")]
    Signals(std::io::Error),
    /// An in-process runtime has no loop (drive its stage with `pipeline_runtime::testing::StageHarness`).
    #[error("an in-process runtime has no loop: drive the stage with pipeline_runtime::testing::StageHarness")]
    Local,
}

/// Why a message cannot be moved through a topic's `Tap` or `Emit` (the `topics` module).
#[derive(Debug, thiserror::Error)]
pub enum TopicError {
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
    Port(#[from] PortError),
}
