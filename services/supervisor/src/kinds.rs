//! The process kinds the supervisor knows: which binary runs a kind and how its settings are
//! validated (and how much shared memory they will reserve) before anything starts.

use pipeline_runtime::config::{ConfigIssue, ProcessSettings, settings_for};

/// What the supervisor knows about a kind of process.
#[derive(Debug, Clone, Copy)]
pub struct Kind {
    /// Binary name, looked up next to the supervisor's own executable.
    pub binary: Option<&'static str>,
    /// Validates the settings table; returns the shared memory the process will reserve, bytes.
    pub check: fn(&str, &toml::Table) -> Result<u64, Vec<ConfigIssue>>,
    /// Gets `--config <file> --name <name>` (pipeline processes) or only its `args` (external).
    pub pipeline_args: bool,
}

fn check<T: ProcessSettings>(name: &str, table: &toml::Table) -> Result<u64, Vec<ConfigIssue>> {
    settings_for::<T>(name, table).map(|s| s.shm_estimate_bytes())
}

fn check_external(name: &str, table: &toml::Table) -> Result<u64, Vec<ConfigIssue>> {
    if table.is_empty() {
        Ok(0)
    } else {
        Err(vec![ConfigIssue {
            key: format!("processes.{name}.settings"),
            message: "an external process takes no settings table; pass its options in `args`".into(),
        }])
    }
}

/// Every kind, by name.
pub const KINDS: &[(&str, Kind)] = &[
    (
        "test_producer",
        Kind { binary: Some("pipeline-test-producer"), check: check::<testkit::ProducerSettings>, pipeline_args: true },
    ),
    (
        "test_consumer",
        Kind { binary: Some("pipeline-test-consumer"), check: check::<testkit::ConsumerSettings>, pipeline_args: true },
    ),
    (
        "sensor_monitor",
        Kind {
            binary: Some("pipeline-sensor-monitor"),
            check: check::<testkit::SensorMonitorSettings>,
            pipeline_args: true,
        },
    ),
    ("ingest", Kind { binary: Some("ingest"), check: check::<ingest::IngestSettings>, pipeline_args: true }),
    (
        "fastslam",
        Kind { binary: Some("fastslam"), check: check::<fastslam_process::FastSlamSettings>, pipeline_args: true },
    ),
    (
        "buoy_ekf",
        Kind { binary: Some("buoy_ekf"), check: check::<buoy_ekf_process::BuoyEkfSettings>, pipeline_args: true },
    ),
    (
        "synchronizer",
        Kind {
            binary: Some("synchronizer"),
            check: check::<synchronizer_process::SynchronizerSettings>,
            pipeline_args: true,
        },
    ),
    ("fusion", Kind { binary: Some("fusion"), check: check::<fusion_process::FusionSettings>, pipeline_args: true }),
    (
        "octree_mapper",
        Kind {
            binary: Some("octree_mapper"),
            check: check::<octree_mapper_process::MapperSettings>,
            pipeline_args: true,
        },
    ),
    ("recorder", Kind { binary: Some("recorder"), check: check::<recorder::RecorderSettings>, pipeline_args: true }),
    ("replayer", Kind { binary: Some("replayer"), check: check::<recorder::ReplayerSettings>, pipeline_args: true }),
    ("external", Kind { binary: None, check: check_external, pipeline_args: false }),
];

/// The kind called `name`.
pub fn kind(name: &str) -> Option<&'static Kind> {
    KINDS.iter().find(|(n, _)| *n == name).map(|(_, k)| k)
}

/// Names of every kind (for error messages).
pub fn kind_names() -> Vec<&'static str> {
    KINDS.iter().map(|(n, _)| *n).collect()
}
