//! `replayer`: checks an MCAP recording, then publishes the recorded messages of the selected
//! topics with the contract's QoS in their original publish order, paced as recorded (times a
//! speed factor) or as fast as possible with back-pressure, and sends end of stream after the
//! last one. Payloads and user headers go out bit for bit; `seq`, `origin_ns` and `publish_ns`
//! are stamped anew by the publishing runtime (the message enters this pipeline now).
//! The stage is [`recorder_stage::replay_stage::Replayer`].

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<recorder_stage::replay_stage::Replayer>()
}
