//! `ros2`: the ROS 2 gateway, a native ROS 2 node that feeds ROS 2 topics into the pipeline and
//! publishes its outputs as ROS 2 topics. The stage is [`ros2_stage::stage::Ros2Stage`];
//! the settings are [`ros2_stage::Ros2Settings`].

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<ros2_stage::stage::Ros2Stage>()
}
