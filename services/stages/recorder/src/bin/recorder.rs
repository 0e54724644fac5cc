//! `recorder`: subscribes the configured services with the contract's QoS and writes every
//! message it receives to `<out>/<file>` (MCAP): log_time = receive time, publish_time = the
//! message's `publish_ns`, data = the user header's bytes followed by the payload's bytes. It
//! counts sequence gaps per publisher (messages it missed), ends after the `end_after` processes
//! have ended (or on SIGTERM/SIGINT, after a last drain) and always leaves a complete file.
//! The stage is [`recorder_stage::stage::RecorderStage`].

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<recorder_stage::stage::RecorderStage>()
}
