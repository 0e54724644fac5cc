//! The small runtime every pipeline process uses: typed TOML config with validation, iceoryx2
//! node and ports with explicit QoS, a WaitSet loop that never spins and stops on SIGINT/SIGTERM,
//! heartbeats, per-hop and end-to-end latency histograms published on `pipeline/stats/<process>`,
//! and tracing logs with the process name in every line.

pub mod clock;
pub mod config;
pub mod error;
pub mod iox;
pub mod logging;
pub mod ports;
pub mod protocol;
pub mod restart;
pub mod runtime;
pub mod stage;
pub mod stats;
pub mod summary;
pub mod testing;
pub mod topics;
pub mod validate;

pub use clock::monotonic_ns;
pub use config::{ConfigError, ConfigIssue, Issues, LogFormat, PipelineConfig, ProcessSettings, Validate};
pub use error::{ContextError, StageError, error_chain};
pub use iox::IoxScope;
pub use ports::{Delivery, Input, Output, PortError};
pub use protocol::{CheckReport, process_main};
pub use restart::{Restart, StateStore};
pub use runtime::HeartbeatHold;
pub use runtime::{Flow, ProcessArgs, ProcessContext, Runtime, RuntimeOptions, StopReason, Wake, Waker};
pub use stage::{EndAfter, Ending, Stage, Step, stage_main};
pub use stats::{LatencySummary, StatsReport};

/// Maps the end of a process's `run` to an exit code: 0 for a finished run or a SIGTERM/SIGINT
/// stop (a requested stop is a success for a supervised child).
pub fn exit_code<E>(result: Result<StopReason, E>) -> std::process::ExitCode
where
    E: Into<Box<dyn std::error::Error + Send + Sync + 'static>>,
{
    match result {
        Ok(_) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            let e: Box<dyn std::error::Error + Send + Sync + 'static> = e.into();
            tracing::error!("{}", error_chain(&*e));
            std::process::ExitCode::FAILURE
        }
    }
}
