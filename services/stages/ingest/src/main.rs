//! `ingest`: publishes the configured source's items on the sensor services, paced on the data
//! clock, then sends end of stream. See the library docs.

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<ingest_stage::stage::IngestStage>()
}
