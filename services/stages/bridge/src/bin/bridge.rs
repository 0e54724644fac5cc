//! `bridge`: forwards the configured services from this host's pipeline to Zenoh (`out`) and
//! from Zenoh into this host's pipeline (`in`), so that pipelines on several hosts work as one.
//! The stage is [`bridge_stage::stage::BridgeStage`]; the settings are
//! [`bridge_stage::BridgeSettings`].

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<bridge_stage::stage::BridgeStage>()
}
