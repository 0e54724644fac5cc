//! `pipeline_bench`: multi-process benchmarks of the pipeline's transports. `pipeline_bench
//! latency` measures per-hop and end-to-end latency from an external producer through chains of
//! relay processes, iceoryx2 against copy-based socket baselines; see `pipeline_bench::latency`.

use std::process::ExitCode;

use clap::Parser;
use pipeline_bench::latency::{Cli, Command};

fn main() -> ExitCode {
    let cli = Cli::parse();
    if std::env::var_os("RUST_LOG").is_none() {
        // SAFETY: no other thread exists yet (nothing before this line starts one), so nothing can
        // read the environment concurrently. The relays inherit the setting.
        unsafe { std::env::set_var("RUST_LOG", "warn") };
    }
    let name = match &cli.command {
        Command::Latency(_) => "pipeline_bench".to_string(),
        Command::Relay(r) => format!("bench_relay{}", r.index),
    };
    let _log = pipeline_runtime::logging::init(&name, pipeline_runtime::LogFormat::Text);
    let result = match &cli.command {
        Command::Latency(args) => pipeline_bench::latency::run_and_print(args),
        Command::Relay(args) => pipeline_bench::latency::relay::run_relay(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("pipeline_bench ({name}): error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
