//! The protocol between the supervisor and a process kind: what makes a binary a kind.
//!
//! A kind is an executable that takes `--config <file> --name <name>` (its settings are the
//! table `[processes.<name>.settings]` of that file) and, given `--check` as well, validates its
//! settings without starting and prints one [`CheckReport`] as JSON on stdout:
//!
//! ```json
//! {"protocol": 1, "process": "odo", "issues": [{"key": "processes.odo.settings.rate_hz",
//!   "message": "must be positive"}], "shm_estimate_bytes": 0}
//! ```
//!
//! Exit code 0 means the check ran (the verdict is in `issues`); anything else means it could
//! not (the reason on stderr). The supervisor finds the binary of kind `k` next to its own
//! executable (or takes `processes.<name>.binary`), runs this check for every process in its
//! pre-flight and reports every issue with its dotted key before anything starts. A stage built
//! on this runtime gets all of it from [`process_main`]: its `main` is one line.

use std::process::ExitCode;

use clap::Parser;
use serde::{Deserialize, Serialize};

use crate::config::{ConfigIssue, ProcessSettings, load_pipeline_config, settings_for};
use crate::error::ContextError;
use crate::runtime::{ProcessArgs, StopReason};

/// Version of the `--check` protocol.
pub const CHECK_PROTOCOL: u32 = 1;

/// What `<binary> --check` prints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckReport {
    /// [`CHECK_PROTOCOL`].
    pub protocol: u32,
    /// The process checked.
    pub process: String,
    /// Every problem of its settings with its dotted key; empty when they are valid.
    pub issues: Vec<ConfigIssue>,
    /// Shared memory its publishers may reserve with these settings, bytes (0 when invalid).
    pub shm_estimate_bytes: u64,
}

/// Validates the settings of process `args.name` in `args.config` as a `T`.
pub fn check<T: ProcessSettings>(args: &ProcessArgs) -> Result<CheckReport, ContextError> {
    let config = load_pipeline_config(&args.config)?;
    let process = config
        .processes
        .get(&args.name)
        .ok_or_else(|| ContextError::NoProcess { file: args.config.clone(), name: args.name.clone() })?;
    let (issues, shm_estimate_bytes) = match settings_for::<T>(&args.name, &process.settings) {
        Ok(s) => (vec![], s.shm_estimate_bytes(config.run.extra_subscribers)),
        Err(issues) => (issues, 0),
    };
    Ok(CheckReport { protocol: CHECK_PROTOCOL, process: args.name.clone(), issues, shm_estimate_bytes })
}

/// The whole `main` of a process kind whose settings are a `T`: parses the command line,
/// answers `--check` (see the module docs), or sets up logging, calls `run` and maps its end
/// to the exit code (0 for a finished run or a requested stop, 1 for an error, logged).
pub fn process_main<T, E>(run: impl FnOnce(&ProcessArgs) -> Result<StopReason, E>) -> ExitCode
where
    T: ProcessSettings,
    E: Into<Box<dyn std::error::Error + Send + Sync + 'static>>,
{
    let args = ProcessArgs::parse();
    if args.check {
        return match check::<T>(&args) {
            Ok(report) => {
                println!("{}", serde_json::json!(report));
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("{}", crate::error::error_chain(&e));
                ExitCode::from(2)
            }
        };
    }
    let _log = crate::logging::init(&args.name, args.log_format.unwrap_or_default());
    crate::exit_code(run(&args))
}
