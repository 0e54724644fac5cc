//! `sensor_monitor`: validates and counts every sensor message ([`sensor_monitor_stage::stage`]); the stage
//! is [`sensor_monitor_stage::stage::SensorMonitorStage`].

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<sensor_monitor_stage::stage::SensorMonitorStage>()
}
