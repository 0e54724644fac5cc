//! `ingest_bench`: 300k-point clouds at 30 Hz from a producer to a consumer process; producer CPU
//! per frame and hop latency of iceoryx2 (our runtime) side by side with Unix-socket copy
//! baselines. See the library docs of `pipeline_bench`.

use std::process::ExitCode;

use clap::Parser;
use pipeline_bench::{Cli, Role};

fn main() -> ExitCode {
    let cli = Cli::parse();
    if std::env::var_os("RUST_LOG").is_none() {
        // SAFETY: no other thread exists yet (nothing before this line starts one), so nothing can
        // read the environment concurrently. The consumer child inherits the setting.
        unsafe { std::env::set_var("RUST_LOG", "warn") };
    }
    let name = if cli.role.is_some() { "bench_consumer" } else { "ingest_bench" };
    let _log = pipeline_runtime::logging::init(name, pipeline_runtime::LogFormat::Text);
    let result = match &cli.role {
        Some(Role::Consumer(args)) => pipeline_bench::consumer::run_consumer(args),
        None => pipeline_bench::bench::run_and_print(&cli.bench),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("ingest_bench ({name}): error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
