//! `supervisor --config <file> [--out <dir>] [--duration <s>]`: runs the pipeline;
//! `supervisor doctor [--config <file>]`: a pre-flight report of the machine.
//! Exit codes: 0 ok, 1 a process failed, 2 invalid config or machine (nothing started),
//! 128+n stopped by signal n (130 SIGINT, 143 SIGTERM).

use std::process::ExitCode;

use clap::Parser;
use supervisor::{Cli, EXIT_CONFIG, SetupError};

fn main() -> ExitCode {
    let cli = Cli::parse();
    let format = cli.log_format.unwrap_or_else(|| {
        cli.config
            .as_deref()
            .and_then(|c| pipeline_runtime::config::load_pipeline_config(c).ok())
            .map(|c| c.run.log_format)
            .unwrap_or_default()
    });
    // With the live status block the log goes to <out>/run.log once the run knows its out_dir.
    let _log = if cli.live() {
        pipeline_runtime::logging::init_redirectable("supervisor", format)
    } else {
        pipeline_runtime::logging::init("supervisor", format)
    };
    match supervisor::run(&cli) {
        Ok(code) => ExitCode::from(code),
        Err(e) => {
            eprintln!("supervisor: error: {e:#}");
            ExitCode::from(if e.is::<SetupError>() { EXIT_CONFIG } else { 1 })
        }
    }
}
