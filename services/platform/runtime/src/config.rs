//! The pipeline config: one TOML file says which processes run, each one's settings, restart
//! policy, the iceoryx2 prefix/root, the output directory and how the run ends.
//!
//! Two stages, as in ripgrep's lowargs/hiargs: [`load_pipeline_config`] parses with
//! `deny_unknown_fields` and reports the dotted key of the first type error; [`PipelineConfig::validate`]
//! then checks meaning (dependencies, cycles, ranges) and reports every problem with its key.
//! Process settings (`[processes.<name>.settings]`) are parsed into the process's own typed struct
//! with [`parse_settings`], so the supervisor validates them before anything starts.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

pub use validation::{ConfigIssue, Issues, Validate};

/// Checks a process's `remap` table: each key a data service of the contract, each name a
/// service name (chunks of `[A-Za-z0-9_.-]` joined by `/`) that is not itself a contract service
/// (it would take that service's place with another type), no two keys on one name.
fn check_remap(issues: &mut Issues, key: &str, remap: &BTreeMap<String, String>) {
    use shared_types::services;
    let chunk = |c: &str| !c.is_empty() && c.chars().all(|c| c.is_ascii_alphanumeric() || "_-.".contains(c));
    let mut seen: BTreeMap<&str, &str> = BTreeMap::new();
    for (from, to) in remap {
        let k = format!("{key}.remap.\"{from}\"");
        if services::data_service_bit(from).is_none() {
            issues.push(
                k.clone(),
                format!("`{from}` is not a data service of the contract (docs/WIRE_FORMAT.md lists them)"),
            );
        }
        if to.len() > 200 || !to.split('/').all(chunk) {
            issues.push(k.clone(), format!("`{to}` is not a service name: chunks of [A-Za-z0-9_.-] joined by /"));
        } else if services::service_spec(to).is_some()
            || ["pipeline/control/", "pipeline/stats/", "pipeline/wake/"].iter().any(|p| to.starts_with(p))
        {
            issues.push(
                k.clone(),
                format!("`{to}` is a service of the pipeline's own: remap to a name of its own (e.g. `r1/{from}`)"),
            );
        }
        if let Some(other) = seen.insert(to.as_str(), from.as_str()) {
            issues.push(k, format!("`{other}` is remapped to `{to}` too: one name per service"));
        }
    }
}

/// Errors of loading or validating a config file.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{file}: cannot read config: {source}")]
    Read {
        /// The config file.
        file: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file is not valid TOML or does not match the schema (unknown key, wrong type, ...).
    #[error("{file}:{line}: key `{key}`: {message}")]
    Parse {
        /// The config file.
        file: PathBuf,
        /// 1-based line of the error (0 when unknown).
        line: usize,
        /// Dotted key of the offending value (`.` for the document root).
        key: String,
        /// What is wrong.
        message: String,
    },
    /// The config parsed but its values are inconsistent; every problem is listed.
    #[error("{file}: invalid config:{}", .issues.iter().map(|i| format!("\n  key `{}`: {}", i.key, i.message)).collect::<String>())]
    Invalid {
        /// The config file.
        file: PathBuf,
        /// Every problem found.
        issues: Vec<ConfigIssue>,
    },
}

impl ConfigError {
    /// The keys this error names (for tests and tools).
    pub fn keys(&self) -> Vec<String> {
        match self {
            ConfigError::Read { .. } => vec![],
            ConfigError::Parse { key, .. } => vec![key.clone()],
            ConfigError::Invalid { issues, .. } => issues.iter().map(|i| i.key.clone()).collect(),
        }
    }
}

/// How the run ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum EndCondition {
    /// When every process in `end_of_stream_from` has sent end-of-stream (or `duration_s` passed).
    #[default]
    EndOfStream,
    /// After `duration_s`.
    Duration,
    /// Only on SIGINT/SIGTERM.
    Signal,
}

/// Log line format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum LogFormat {
    /// Human-readable lines.
    #[default]
    Text,
    /// One JSON object per line.
    Json,
}

/// `[run]`: settings of the whole run.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunConfig {
    /// Output directory (relative paths are relative to the working directory).
    pub out_dir: PathBuf,
    /// How the run ends.
    pub end: EndCondition,
    /// Run length in seconds for `end = "duration"`; an upper bound for `end_of_stream` (0 = none).
    pub duration_s: f64,
    /// Processes whose end-of-stream ends the run; empty: the first end-of-stream from any process.
    pub end_of_stream_from: Vec<String>,
    /// iceoryx2 file prefix of this run; every run on one machine needs its own.
    pub iceoryx_prefix: String,
    /// iceoryx2 root path (node and service files); default `/tmp/slam_pipeline/<prefix>/`.
    pub iceoryx_root: Option<PathBuf>,
    /// Optional iceoryx2 config file to start from (relative to this config file).
    pub iceoryx_config: Option<PathBuf>,
    /// Interval of the one-line status, s (0 = off).
    pub status_interval_s: f64,
    /// How long a process may take to report ready, s.
    pub ready_timeout_s: f64,
    /// A ready process that sends no heartbeat for this long is killed and handled as failed, s.
    pub heartbeat_timeout_s: f64,
    /// Time between SIGTERM and SIGKILL when stopping a process, s.
    pub stop_timeout_s: f64,
    /// Heartbeat period of every process, s.
    pub heartbeat_interval_s: f64,
    /// Period at which processes publish their latency statistics, s.
    pub stats_interval_s: f64,
    /// Log format of the supervisor and its children.
    pub log_format: LogFormat,
    /// Subscribers every service admits beyond the contract's (which already leaves room for
    /// `shared_types::services::WATCHERS` = 2 watchers, a viewer and a recorder, next to the
    /// shipped configs' consumers): for more recorders, viewers or tools on one run. Every
    /// process of the run opens every service with this many more subscribers and nodes, and
    /// the shared-memory pre-flight counts the chunks they reserve. 0-16.
    pub extra_subscribers: usize,
}

/// Largest `run.extra_subscribers`.
pub const MAX_EXTRA_SUBSCRIBERS: usize = 16;

impl Default for RunConfig {
    fn default() -> Self {
        Self {
            out_dir: PathBuf::from("out"),
            end: EndCondition::EndOfStream,
            duration_s: 0.0,
            end_of_stream_from: vec![],
            iceoryx_prefix: "slam_".into(),
            iceoryx_root: None,
            iceoryx_config: None,
            status_interval_s: 1.0,
            ready_timeout_s: 10.0,
            heartbeat_timeout_s: 3.0,
            stop_timeout_s: 2.0,
            heartbeat_interval_s: 0.25,
            stats_interval_s: 1.0,
            log_format: LogFormat::Text,
            extra_subscribers: 0,
        }
    }
}

/// Restart policy of a process.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum RestartPolicy {
    /// Never restart.
    Never,
    /// Restart when it exits with a non-zero code, dies by a signal or misses heartbeats.
    #[default]
    OnFailure,
    /// Restart whenever it exits before the run ends.
    Always,
}

/// `[processes.<name>]`: one process of the pipeline.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProcessConfig {
    /// Which program this is (e.g. `test_producer`, `external`); default: the table name.
    #[serde(default)]
    pub kind: Option<String>,
    /// Set false to keep the entry but not run it.
    #[serde(default = "yes")]
    pub enabled: bool,
    /// Path of the executable; default: the kind's binary next to the supervisor's own executable.
    #[serde(default)]
    pub binary: Option<PathBuf>,
    /// Extra command-line arguments (for `external` processes).
    #[serde(default)]
    pub args: Vec<String>,
    /// Processes that must be ready before this one starts.
    #[serde(default)]
    pub after: Vec<String>,
    /// Restart policy.
    #[serde(default)]
    pub restart: RestartPolicy,
    /// Restarts allowed before the process is given up as failed.
    #[serde(default = "default_max_restarts")]
    pub max_restarts: u32,
    /// First restart delay, s; doubles per consecutive restart.
    #[serde(default = "default_backoff_initial")]
    pub backoff_initial_s: f64,
    /// Largest restart delay, s.
    #[serde(default = "default_backoff_max")]
    pub backoff_max_s: f64,
    /// When this process fails for good (restarts exhausted), end the whole run.
    #[serde(default)]
    pub required: bool,
    /// `external` processes that do not use the runtime cannot report ready: set false to treat
    /// them as ready once spawned and to skip their heartbeat deadline.
    #[serde(default = "yes")]
    pub heartbeat: bool,
    /// Scheduling niceness of the process, 0 (default, as the supervisor) to 19 (runs only on
    /// what the others leave). Bulk work that nothing waits on at once (the octree mapper, a
    /// recorder, a monitor) at 10 lets the latency-critical chain (SLAM, synchronizer, fusion)
    /// take a core as soon as it needs one on a busy machine.
    #[serde(default)]
    pub nice: i32,
    /// Service names this process opens instead of the contract's: `contract name -> name`
    /// (e.g. `"pipeline/sensors/cloud" = "r1/pipeline/sensors/cloud"`). Every input and output of
    /// the process on a listed service uses the other name, with the contract service's type and
    /// QoS; unlisted services keep their names. This is how one host runs a stage once per robot
    /// (a mapper per robot on a base station, fed by a bridge's `local` names). A process with a
    /// remapped input must name what it ends after (its `end_after` setting): an end of stream
    /// says which contract services its process published, not the names they were remapped to.
    #[serde(default)]
    pub remap: BTreeMap<String, String>,
    /// A directory of its own for this process's output files, relative to `run.out_dir` (e.g.
    /// `"r1"`): two processes of one kind in a run (a mapper per robot) then do not write the
    /// same files. Its part of summary.json goes under `instances.<process>` instead of the top
    /// level, where a second part of the same kind would overwrite the first's keys. Its restart
    /// state and statistics stay in the run's directory. Files it reads from its output
    /// directory (ground_truth.tum, scene.json) are looked up there too.
    #[serde(default)]
    pub out_dir: Option<PathBuf>,
    /// Process-specific settings, parsed by the process's own typed settings struct.
    #[serde(default)]
    pub settings: toml::Table,
}

fn yes() -> bool {
    true
}
fn default_max_restarts() -> u32 {
    3
}
fn default_backoff_initial() -> f64 {
    0.2
}
fn default_backoff_max() -> f64 {
    5.0
}

impl ProcessConfig {
    /// The kind, defaulting to the process name.
    pub fn kind_or<'a>(&'a self, name: &'a str) -> &'a str {
        self.kind.as_deref().unwrap_or(name)
    }
}

/// The whole pipeline config file.
#[derive(Debug, Clone, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct PipelineConfig {
    /// Run settings.
    #[serde(default)]
    pub run: RunConfig,
    /// Processes by name.
    #[serde(default)]
    pub processes: BTreeMap<String, ProcessConfig>,
    /// Where the file was loaded from (not part of the file).
    #[serde(skip)]
    pub source: PathBuf,
}

/// Reads and parses a pipeline config (stage one: syntax, unknown keys, types).
///
/// A config may start from another: `extends = "default.toml"` (a file name relative to this
/// config's directory) takes that config and then this one's keys over it, tables merged key by
/// key (a process's `settings` too), any other value replaced. Relative paths in either resolve
/// against the extending config's directory: keep them in one directory.
pub fn load_pipeline_config(path: &Path) -> Result<PipelineConfig, ConfigError> {
    let text =
        std::fs::read_to_string(path).map_err(|source| ConfigError::Read { file: path.to_path_buf(), source })?;
    let table: toml::Table = parse_toml_str(&text, path)?;
    let mut cfg: PipelineConfig = if table.contains_key("extends") {
        let merged = extended(path, table, 0)?;
        serde_path_to_error::deserialize(toml::Value::Table(merged)).map_err(|e| ConfigError::Parse {
            file: path.to_path_buf(),
            line: 0,
            key: e.path().to_string(),
            message: e.into_inner().to_string(),
        })?
    } else {
        parse_toml_str(&text, path)?
    };
    cfg.source = path.to_path_buf();
    Ok(cfg)
}

/// Longest chain of configs extending one another.
const MAX_EXTENDS: usize = 4;

/// `table` (of the config at `path`) over the config it `extends`, recursively.
fn extended(path: &Path, mut table: toml::Table, depth: usize) -> Result<toml::Table, ConfigError> {
    let Some(ext) = table.remove("extends") else { return Ok(table) };
    let bad =
        |message: String| ConfigError::Parse { file: path.to_path_buf(), line: 0, key: "extends".into(), message };
    let name = ext.as_str().ok_or_else(|| bad("must name another config file".into()))?;
    if depth >= MAX_EXTENDS {
        return Err(bad(format!("more than {MAX_EXTENDS} configs extend one another (a loop?)")));
    }
    let base_path = path.parent().unwrap_or(Path::new(".")).join(name);
    let text =
        std::fs::read_to_string(&base_path).map_err(|source| ConfigError::Read { file: base_path.clone(), source })?;
    let base: toml::Table = parse_toml_str(&text, &base_path)?;
    let mut base = extended(&base_path, base, depth + 1)?;
    merge_tables(&mut base, table);
    Ok(base)
}

/// `over`'s keys into `base`: tables merged, anything else replaced.
fn merge_tables(base: &mut toml::Table, over: toml::Table) {
    for (k, v) in over {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge_tables(b, o),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

/// Parses TOML text into `T`, naming the dotted key and line of any error.
pub fn parse_toml_str<T: DeserializeOwned>(text: &str, file: &Path) -> Result<T, ConfigError> {
    let line_of = |span: Option<std::ops::Range<usize>>| {
        span.map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1).unwrap_or(0)
    };
    let de = toml::de::Deserializer::parse(text).map_err(|e| ConfigError::Parse {
        file: file.to_path_buf(),
        line: line_of(e.span()),
        key: ".".into(),
        message: e.message().to_string(),
    })?;
    serde_path_to_error::deserialize(de).map_err(|e| {
        let key = e.path().to_string();
        let inner = e.into_inner();
        ConfigError::Parse {
            file: file.to_path_buf(),
            line: line_of(inner.span()),
            key,
            message: inner.message().to_string(),
        }
    })
}

/// Parses a process's `settings` table into its typed settings, naming keys as
/// `processes.<name>.settings.<key>`.
pub fn parse_settings<T: DeserializeOwned>(name: &str, table: &toml::Table) -> Result<T, ConfigIssue> {
    let value = toml::Value::Table(table.clone());
    serde_path_to_error::deserialize(value).map_err(|e| {
        let path = e.path().to_string();
        let key = if path == "." {
            format!("processes.{name}.settings")
        } else {
            format!("processes.{name}.settings.{path}")
        };
        ConfigIssue { key, message: e.into_inner().message().to_string() }
    })
}

/// Settings of a process kind: typed, and checked by their [`Validate`] impl (keys relative to the
/// settings table; the runtime roots them at `processes.<name>.settings`).
pub trait ProcessSettings: DeserializeOwned + Validate {
    /// Shared memory the process's publishers may reserve with these settings in a run with
    /// `run.extra_subscribers = extra_subscribers`, bytes.
    fn shm_estimate_bytes(&self, extra_subscribers: usize) -> u64 {
        let _ = extra_subscribers;
        0
    }
}

/// Parses and validates a process's settings in one go.
pub fn settings_for<T: ProcessSettings>(name: &str, table: &toml::Table) -> Result<T, Vec<ConfigIssue>> {
    let settings: T = parse_settings(name, table).map_err(|i| vec![i])?;
    let mut issues = Issues::at(format!("processes.{name}.settings"));
    settings.validate(&mut issues);
    issues.into_result().map(|()| settings)
}

fn positive(issues: &mut Issues, key: &str, v: f64) {
    issues.check(v.is_finite() && v > 0.0, key, format!("must be a positive number of seconds, got {v}"));
}

impl PipelineConfig {
    /// Enabled processes by name.
    pub fn enabled(&self) -> impl Iterator<Item = (&String, &ProcessConfig)> {
        self.processes.iter().filter(|(_, p)| p.enabled)
    }

    /// Stage two: checks the meaning of the values (not the process settings, which need the
    /// kind's typed struct). Returns every problem with its key.
    pub fn validate(&self) -> Issues {
        let mut issues = Issues::default();
        let r = &self.run;
        positive(&mut issues, "run.ready_timeout_s", r.ready_timeout_s);
        if r.extra_subscribers > MAX_EXTRA_SUBSCRIBERS {
            issues.push(
                "run.extra_subscribers",
                format!("must be at most {MAX_EXTRA_SUBSCRIBERS} (got {})", r.extra_subscribers),
            );
        }
        positive(&mut issues, "run.heartbeat_timeout_s", r.heartbeat_timeout_s);
        positive(&mut issues, "run.stop_timeout_s", r.stop_timeout_s);
        positive(&mut issues, "run.heartbeat_interval_s", r.heartbeat_interval_s);
        positive(&mut issues, "run.stats_interval_s", r.stats_interval_s);
        issues.check(
            r.heartbeat_interval_s < r.heartbeat_timeout_s,
            "run.heartbeat_interval_s",
            "must be shorter than run.heartbeat_timeout_s",
        );
        issues.check(
            r.status_interval_s.is_finite() && r.status_interval_s >= 0.0,
            "run.status_interval_s",
            "must be >= 0 (0 = no status line)",
        );
        issues.check(r.duration_s.is_finite() && r.duration_s >= 0.0, "run.duration_s", "must be >= 0");
        if r.end == EndCondition::Duration {
            issues.check(r.duration_s > 0.0, "run.duration_s", "must be > 0 when run.end = \"duration\"");
        }
        let prefix_ok = !r.iceoryx_prefix.is_empty()
            && r.iceoryx_prefix.len() <= 64
            && r.iceoryx_prefix.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-' || b == b'.');
        issues.check(prefix_ok, "run.iceoryx_prefix", "must be 1-64 characters of [A-Za-z0-9_.-]");
        if let Some(root) = &r.iceoryx_root {
            issues.check(root.is_absolute(), "run.iceoryx_root", "must be an absolute path");
        }
        let enabled: BTreeSet<&str> = self.enabled().map(|(n, _)| n.as_str()).collect();
        issues.check(!enabled.is_empty(), "processes", "no enabled process: nothing to run");
        issues.check(
            enabled.len() <= shared_types::services::MAX_PROCESSES,
            "processes",
            format!("at most {} processes", shared_types::services::MAX_PROCESSES),
        );
        for name in &r.end_of_stream_from {
            issues.check(
                enabled.contains(name.as_str()),
                "run.end_of_stream_from",
                format!("names `{name}`, which is not an enabled process"),
            );
        }
        for (name, p) in self.enabled() {
            let key = format!("processes.{name}");
            let name_ok = !name.is_empty()
                && name.len() <= 32
                && name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
            issues.check(name_ok, key.clone(), "process names must be 1-32 characters of [A-Za-z0-9_-]");
            for dep in &p.after {
                if dep == name {
                    issues.push(format!("{key}.after"), "a process cannot wait for itself");
                } else if !self.processes.contains_key(dep) {
                    issues.push(format!("{key}.after"), format!("unknown process `{dep}`"));
                } else if !enabled.contains(dep.as_str()) {
                    issues.push(format!("{key}.after"), format!("process `{dep}` is disabled"));
                }
            }
            positive(&mut issues, &format!("{key}.backoff_initial_s"), p.backoff_initial_s);
            positive(&mut issues, &format!("{key}.backoff_max_s"), p.backoff_max_s);
            issues.check(
                (0..=19).contains(&p.nice),
                format!("{key}.nice"),
                "must be 0 (default) to 19 (lowest priority); raising priority needs privileges the supervisor does not ask for",
            );
            issues.check(
                p.backoff_max_s >= p.backoff_initial_s,
                format!("{key}.backoff_max_s"),
                "must be >= backoff_initial_s",
            );
            check_remap(&mut issues, &key, &p.remap);
            if let Some(dir) = &p.out_dir {
                let plain = dir.components().count() > 0
                    && dir.components().all(|c| matches!(c, std::path::Component::Normal(_)));
                issues.check(
                    plain,
                    format!("{key}.out_dir"),
                    format!("`{}` must be a relative path inside run.out_dir (no `..`, not absolute)", dir.display()),
                );
                let reserved = ["parts", "state", "stats"].iter().any(|r| dir.starts_with(r));
                issues.check(!reserved, format!("{key}.out_dir"), "parts/, state/ and stats/ are the run's own");
                // Processes of one kind write files of the same names: one directory each.
                let kind = p.kind_or(name);
                if let Some((other, _)) = self
                    .enabled()
                    .find(|(n, q)| *n < name && q.kind_or(n) == kind && q.out_dir.as_ref().is_some_and(|d| d == dir))
                {
                    issues.push(
                        format!("{key}.out_dir"),
                        format!("`{}` is `{other}`'s too, a process of the same kind ({kind})", dir.display()),
                    );
                }
            }
        }
        if let Err(cycle) = self.start_order() {
            issues.push(format!("processes.{}.after", cycle[0]), format!("dependency cycle: {}", cycle.join(" -> ")));
        }
        issues
    }

    /// Enabled processes in dependency order (every process after the ones in its `after`);
    /// ties by name. On a cycle returns the processes of one cycle, first repeated at the end.
    pub fn start_order(&self) -> Result<Vec<String>, Vec<String>> {
        let enabled: BTreeMap<&str, &ProcessConfig> = self.enabled().map(|(n, p)| (n.as_str(), p)).collect();
        let mut order: Vec<String> = Vec::new();
        let mut done: BTreeSet<&str> = BTreeSet::new();
        while done.len() < enabled.len() {
            let next = enabled.iter().find(|(n, p)| {
                !done.contains(*n)
                    && p.after.iter().all(|d| done.contains(d.as_str()) || !enabled.contains_key(d.as_str()))
            });
            match next {
                Some((n, _)) => {
                    done.insert(n);
                    order.push(n.to_string());
                }
                None => {
                    // Walk dependencies from any remaining process until a name repeats.
                    let start = *enabled.keys().find(|n| !done.contains(*n)).expect("remaining process");
                    let mut path = vec![start.to_string()];
                    let mut cur = start;
                    loop {
                        let dep = enabled[cur]
                            .after
                            .iter()
                            .find(|d| enabled.contains_key(d.as_str()) && !done.contains(d.as_str()))
                            .expect("a blocked process has an unfinished dependency");
                        if let Some(pos) = path.iter().position(|p| p == dep) {
                            let mut cycle = path[pos..].to_vec();
                            cycle.push(dep.clone());
                            return Err(cycle);
                        }
                        path.push(dep.clone());
                        cur = dep.as_str();
                    }
                }
            }
        }
        Ok(order)
    }

    /// The iceoryx2 root path of this run.
    pub fn iceoryx_root(&self) -> PathBuf {
        self.run
            .iceoryx_root
            .clone()
            .unwrap_or_else(|| PathBuf::from("/tmp/slam_pipeline").join(&self.run.iceoryx_prefix))
    }

    /// The base iceoryx2 config file, resolved against the config file's directory.
    pub fn iceoryx_config_file(&self) -> Option<PathBuf> {
        self.run
            .iceoryx_config
            .as_ref()
            .map(|p| if p.is_absolute() { p.clone() } else { self.source.parent().unwrap_or(Path::new(".")).join(p) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<PipelineConfig, ConfigError> {
        parse_toml_str(text, Path::new("test.toml"))
    }

    #[test]
    fn unknown_key_is_named_with_its_path() {
        let e = parse("[processes.a]\nkind = \"x\"\nrestrat = \"never\"\n").unwrap_err();
        assert_eq!(e.keys(), vec!["processes.a.restrat".to_string()], "{e}");
        assert!(e.to_string().contains("test.toml:3"), "{e}");
    }

    #[test]
    fn wrong_type_is_named_with_its_path() {
        let e = parse("[processes.a]\nmax_restarts = \"three\"\n").unwrap_err();
        assert_eq!(e.keys(), vec!["processes.a.max_restarts".to_string()], "{e}");
    }

    #[test]
    fn cycles_are_reported_with_the_processes_on_them() {
        let c = parse(
            "[processes.a]\nafter=[\"c\"]\n[processes.b]\nafter=[\"a\"]\n[processes.c]\nafter=[\"b\"]\n[processes.d]\n",
        )
        .unwrap();
        let cycle = c.start_order().unwrap_err();
        assert_eq!(cycle.first(), cycle.last());
        assert_eq!(cycle.len(), 4);
        let issues = c.validate();
        assert!(issues.iter().any(|i| i.key.ends_with(".after") && i.message.contains("cycle")), "{issues:?}");
    }

    #[test]
    fn start_order_puts_dependencies_first() {
        let c = parse("[processes.z]\n[processes.a]\nafter=[\"z\"]\n[processes.m]\nafter=[\"a\"]\n").unwrap();
        assert_eq!(c.start_order().unwrap(), vec!["z", "a", "m"]);
    }

    #[test]
    fn unknown_dependency_is_named() {
        let c = parse("[processes.a]\nafter=[\"ghost\"]\n").unwrap();
        let issues = c.validate();
        assert_eq!(issues.len(), 1, "{issues:?}");
        assert_eq!(issues.iter().next().unwrap().key, "processes.a.after");
        assert!(issues.iter().next().unwrap().message.contains("ghost"));
    }

    #[test]
    fn niceness_out_of_range_is_named() {
        assert!(parse("[processes.a]\nnice = 10\n").unwrap().validate().is_empty());
        for bad in ["-5", "20"] {
            let issues = parse(&format!("[processes.a]\nnice = {bad}\n")).unwrap().validate();
            assert_eq!(issues.len(), 1, "{issues:?}");
            assert_eq!(issues.iter().next().unwrap().key, "processes.a.nice");
        }
    }

    #[test]
    fn remaps_name_what_is_wrong_with_each_entry() {
        let ok = "[processes.a.remap]\n\"pipeline/sensors/cloud\" = \"r1/pipeline/sensors/cloud\"\n\
                  \"pipeline/fusion/pose\" = \"r1/pipeline/fusion/pose\"\n";
        let c = parse(ok).unwrap();
        assert!(c.validate().is_empty(), "{:?}", c.validate());
        assert_eq!(c.processes["a"].remap["pipeline/sensors/cloud"], "r1/pipeline/sensors/cloud");
        for (bad, what) in [
            ("\"pipeline/sensors/clouds\" = \"r1/x\"", "not a data service"),
            ("\"pipeline/control/heartbeat\" = \"r1/x\"", "not a data service"),
            ("\"pipeline/sensors/cloud\" = \"r1//x\"", "not a service name"),
            ("\"pipeline/sensors/cloud\" = \"r1/a b\"", "not a service name"),
            ("\"pipeline/sensors/cloud\" = \"pipeline/slam/pose\"", "of the pipeline's own"),
            ("\"pipeline/sensors/cloud\" = \"pipeline/control/x\"", "of the pipeline's own"),
            ("\"pipeline/sensors/cloud\" = \"r1/x\"\n\"pipeline/slam/pose\" = \"r1/x\"", "remapped to `r1/x` too"),
        ] {
            let issues = parse(&format!("[processes.a.remap]\n{bad}\n")).unwrap().validate();
            assert_eq!(issues.len(), 1, "{bad}: {issues:?}");
            let i = issues.iter().next().unwrap();
            assert!(i.key.starts_with("processes.a.remap.\"pipeline/"), "{bad}: {i:?}");
            assert!(i.message.contains(what), "{bad}: {i:?}");
        }
    }

    #[test]
    fn a_process_out_dir_must_be_its_own_and_inside_the_run() {
        let c = parse(
            "[processes.a]\nout_dir = \"r1\"\n[processes.b]\nout_dir = \"r2/map\"\n\
             [processes.c]\nkind = \"recorder\"\nout_dir = \"r1\"\n",
        )
        .unwrap();
        assert!(c.validate().is_empty(), "{:?}", c.validate());
        for (bad, what) in [
            ("\"../x\"", "relative path inside"),
            ("\"/tmp/x\"", "relative path inside"),
            ("\"\"", "relative path inside"),
            ("\"parts\"", "the run's own"),
            ("\"r1\"\n[processes.b]\nkind = \"a\"\nout_dir = \"r1\"", "`a`'s too, a process of the same kind (a)"),
        ] {
            let issues = parse(&format!("[processes.a]\nout_dir = {bad}\n")).unwrap().validate();
            assert_eq!(issues.len(), 1, "{bad}: {issues:?}");
            let i = issues.iter().next().unwrap();
            assert!(i.key.ends_with(".out_dir") && i.message.contains(what), "{bad}: {i:?}");
        }
    }

    #[test]
    fn extra_subscribers_beyond_the_limit_are_named() {
        assert!(parse("[run]\nextra_subscribers = 16\n[processes.a]\n").unwrap().validate().is_empty());
        let issues = parse("[run]\nextra_subscribers = 17\n[processes.a]\n").unwrap().validate();
        assert_eq!(issues.len(), 1, "{issues:?}");
        assert_eq!(issues.iter().next().unwrap().key, "run.extra_subscribers");
    }

    #[test]
    fn settings_errors_are_prefixed_with_the_process_key() {
        #[derive(Debug, Deserialize)]
        #[serde(deny_unknown_fields)]
        #[allow(dead_code)]
        struct S {
            rate_hz: f64,
        }
        let t: toml::Table = toml::from_str("rate_hz = \"fast\"").unwrap();
        let e = parse_settings::<S>("p", &t).unwrap_err();
        assert_eq!(e.key, "processes.p.settings.rate_hz");
    }

    #[test]
    fn a_config_extends_another_and_overrides_it_key_by_key() {
        let dir = tempfile::tempdir().unwrap();
        let base = "[run]\nout_dir = \"out/a\"\nduration_s = 5.0\n[processes.p]\nkind = \"k\"\n[processes.p.settings]\nx = 1\ny = 2\n";
        std::fs::write(dir.path().join("base.toml"), base).unwrap();
        let top = "extends = \"base.toml\"\n[run]\nout_dir = \"out/b\"\n[processes.p.settings]\ny = 3\n[processes.q]\nkind = \"k2\"\n";
        std::fs::write(dir.path().join("top.toml"), top).unwrap();
        let cfg = load_pipeline_config(&dir.path().join("top.toml")).unwrap();
        assert_eq!(cfg.run.out_dir, std::path::PathBuf::from("out/b"));
        assert_eq!(cfg.run.duration_s, 5.0);
        let s = &cfg.processes["p"].settings;
        assert_eq!((s["x"].as_integer(), s["y"].as_integer()), (Some(1), Some(3)));
        assert_eq!(cfg.processes["q"].kind.as_deref(), Some("k2"));
        std::fs::write(dir.path().join("loop.toml"), "extends = \"loop.toml\"\n").unwrap();
        let e = load_pipeline_config(&dir.path().join("loop.toml")).unwrap_err().to_string();
        assert!(e.contains("extends") && e.contains("loop"), "{e}");
        std::fs::write(dir.path().join("bad.toml"), "extends = \"base.toml\"\n[run]\nout_dirr = 1\n").unwrap();
        let e = load_pipeline_config(&dir.path().join("bad.toml")).unwrap_err();
        assert!(e.to_string().contains("out_dirr"), "{e}");
    }
}
