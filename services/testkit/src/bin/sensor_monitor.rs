//! `sensor_monitor`: validates and counts every sensor message ([`testkit::monitor`]); the stage
//! is [`testkit::monitor::SensorMonitorStage`].

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<testkit::monitor::SensorMonitorStage>()
}
