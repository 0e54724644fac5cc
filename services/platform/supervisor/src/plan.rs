//! From a config file to a checked plan: every key validated, every binary found, every
//! process's settings checked by its own binary (`--check`, see [`crate::kinds`]), and the
//! machine checked (shared memory, file descriptors) before a single process starts.

use std::path::{Path, PathBuf};

use pipeline_runtime::IoxScope;
use pipeline_runtime::config::{ConfigError, Issues, PipelineConfig, ProcessConfig, load_pipeline_config};

use crate::kinds;

/// One process, ready to be started.
#[derive(Debug, Clone)]
pub struct PlannedProcess {
    /// Name (its `[processes.<name>]` table).
    pub name: String,
    /// Kind.
    pub kind: String,
    /// Absolute path of the executable.
    pub binary: PathBuf,
    /// Full argument list.
    pub args: Vec<String>,
    /// The config entry.
    pub config: ProcessConfig,
    /// Estimated shared memory its publishers reserve, bytes.
    pub shm_bytes: u64,
}

/// A validated run.
#[derive(Debug, Clone)]
pub struct Plan {
    /// The config.
    pub config: PipelineConfig,
    /// Absolute path of the config file.
    pub config_path: PathBuf,
    /// Processes in start order.
    pub processes: Vec<PlannedProcess>,
    /// iceoryx2 scope of the run.
    pub scope: IoxScope,
    /// Output directory.
    pub out_dir: PathBuf,
}

/// Shared memory budgeted per process for control services (heartbeat, stats, events), bytes.
pub const CONTROL_SHM_PER_PROCESS: u64 = 2 << 20;

/// Command-line overrides of the config.
#[derive(Debug, Clone, Default)]
pub struct Overrides {
    /// `--out`.
    pub out_dir: Option<PathBuf>,
    /// `--duration`.
    pub duration_s: Option<f64>,
    /// `--iceoryx-prefix`.
    pub iceoryx_prefix: Option<String>,
}

/// Where binaries of kinds are looked up: the directory of the running supervisor.
pub fn default_bin_dir() -> PathBuf {
    std::env::current_exe().ok().and_then(|p| p.parent().map(Path::to_path_buf)).unwrap_or_else(|| PathBuf::from("."))
}

fn is_executable(p: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(p).map(|m| m.is_file() && m.permissions().mode() & 0o111 != 0).unwrap_or(false)
}

/// Loads, overrides and validates the config; finds binaries and checks settings.
pub fn make_plan(config_path: &Path, overrides: &Overrides, bin_dir: &Path) -> Result<Plan, ConfigError> {
    let mut config = load_pipeline_config(config_path)?;
    if let Some(o) = &overrides.out_dir {
        config.run.out_dir = o.clone();
    }
    if let Some(d) = overrides.duration_s {
        config.run.duration_s = d;
        if config.run.end == pipeline_runtime::config::EndCondition::Signal {
            config.run.end = pipeline_runtime::config::EndCondition::Duration;
        }
    }
    if let Some(p) = &overrides.iceoryx_prefix {
        config.run.iceoryx_prefix = p.clone();
    }
    let mut issues: Issues = config.validate();
    let config_abs = std::path::absolute(config_path).unwrap_or_else(|_| config_path.to_path_buf());
    let order = config.start_order().unwrap_or_default();
    let mut processes = vec![];
    for name in &order {
        let p = &config.processes[name];
        let kind_name = p.kind_or(name).to_string();
        let key = format!("processes.{name}");
        let external = kind_name == kinds::EXTERNAL;
        if !external && !kinds::is_valid_kind_name(&kind_name) {
            issues.push(
                format!("{key}.kind"),
                format!("`{kind_name}` cannot name a binary: use letters, digits, `_` and `-`"),
            );
            continue;
        }
        let Some(binary) = find_binary(p, &kind_name, &key, &config_abs, bin_dir, &mut issues) else { continue };
        let shm_bytes = if external {
            issues.extend_absolute(kinds::check_external(name, &p.settings));
            0
        } else {
            match kinds::run_check(&binary, &config_abs, name, kinds::CHECK_TIMEOUT) {
                Ok(report) => {
                    issues.extend_absolute(report.issues);
                    report.shm_estimate_bytes
                }
                Err(e) => {
                    let at = if p.binary.is_some() { "binary" } else { "kind" };
                    issues.push(format!("{key}.{at}"), format!("`{}`: {e}", binary.display()));
                    0
                }
            }
        };
        let mut args = vec![];
        if !external {
            args.extend(["--config".into(), config_abs.to_string_lossy().into_owned(), "--name".into(), name.clone()]);
        }
        args.extend(p.args.iter().cloned());
        processes.push(PlannedProcess {
            name: name.clone(),
            kind: kind_name,
            binary,
            args,
            config: p.clone(),
            shm_bytes,
        });
    }
    if !issues.is_empty() {
        return Err(ConfigError::Invalid { file: config_path.to_path_buf(), issues: issues.into_vec() });
    }
    let scope = IoxScope {
        prefix: config.run.iceoryx_prefix.clone(),
        root: config.iceoryx_root(),
        base_config: config.iceoryx_config_file(),
    };
    let out_dir = std::path::absolute(&config.run.out_dir).unwrap_or_else(|_| config.run.out_dir.clone());
    Ok(Plan { config, config_path: config_abs, processes, scope, out_dir })
}

/// The executable of process `key`: its `binary` (an absolute path, a path relative to the config
/// file, or a name looked up in PATH), or the kind's binary beside the supervisor. `None`, with the
/// issue recorded, when there is none.
fn find_binary(
    p: &ProcessConfig,
    kind_name: &str,
    key: &str,
    config_abs: &Path,
    bin_dir: &Path,
    issues: &mut Issues,
) -> Option<PathBuf> {
    let external = kind_name == kinds::EXTERNAL;
    match &p.binary {
        Some(b) => {
            let config_dir = config_abs.parent().unwrap_or(Path::new("."));
            let b = if b.is_absolute() {
                b.clone()
            } else if b.components().count() > 1 {
                config_dir.join(b) // relative paths are relative to the config file
            } else {
                which(b).unwrap_or_else(|| b.clone()) // a bare name is looked up in PATH
            };
            if !is_executable(&b) {
                issues.push(format!("{key}.binary"), format!("`{}` is not an executable file", b.display()));
                return None;
            }
            Some(b)
        }
        None if external => {
            issues.push(format!("{key}.binary"), format!("kind `{kind_name}` needs `binary`"));
            None
        }
        None => {
            let b = kinds::conventional_binary(bin_dir, kind_name);
            if !is_executable(&b) {
                issues.push(
                    format!("{key}.kind"),
                    format!(
                        "unknown kind `{kind_name}`: no executable `{}` (the binary of a kind is named after it \
                         and sits next to the supervisor); build it (cargo build --release --workspace; `cargo \
                         build --release` builds only the main job's), set {key}.binary, or use kind = \
                         \"external\" for a program not built on the runtime",
                        b.display()
                    ),
                );
                return None;
            }
            Some(b)
        }
    }
}

fn which(name: &Path) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path).map(|d| d.join(name)).find(|p| is_executable(p))
}

/// Errors of the pre-flight check of the machine.
#[derive(Debug, thiserror::Error)]
pub enum PreflightError {
    /// /dev/shm is too small for the configured services.
    #[error(
        "/dev/shm has {free_mib:.1} MiB free but this pipeline may reserve {need_mib:.1} MiB ({detail}); \
         enlarge /dev/shm (containers: --shm-size, --ipc=host) or shrink the configured clouds/rates"
    )]
    SharedMemory {
        /// Free MiB.
        free_mib: f64,
        /// Needed MiB.
        need_mib: f64,
        /// Per-process estimate.
        detail: String,
    },
    /// /dev/shm cannot be inspected.
    #[error("cannot inspect /dev/shm: {0}")]
    NoShm(String),
    /// Too few file descriptors.
    #[error(
        "the open-file limit is {hard} (hard) but {need} are needed for {processes} processes; raise it (ulimit -n, LimitNOFILE=)"
    )]
    FileDescriptors {
        /// Hard limit.
        hard: u64,
        /// Needed.
        need: u64,
        /// Processes.
        processes: usize,
    },
}

/// Result of a successful pre-flight check.
#[derive(Debug, Clone)]
pub struct Preflight {
    /// Free bytes in /dev/shm.
    pub shm_free: u64,
    /// Estimated need, bytes.
    pub shm_need: u64,
    /// Soft file-descriptor limit in force after the check (raised when it was short).
    pub fd_limit: u64,
}

/// Checks that `free` bytes of /dev/shm hold what the processes reserve (`needs`: name and bytes of
/// its data services; control services are added per process). Returns the total need.
pub fn check_shm(free: u64, needs: &[(&str, u64)]) -> Result<u64, PreflightError> {
    let need: u64 = needs.iter().map(|(_, b)| b + CONTROL_SHM_PER_PROCESS).sum();
    if need <= free {
        return Ok(need);
    }
    let mib = |b: u64| b as f64 / 1048576.0;
    let detail = needs
        .iter()
        .map(|(n, b)| format!("{n}: {:.1} MiB", mib(b + CONTROL_SHM_PER_PROCESS)))
        .collect::<Vec<_>>()
        .join(", ");
    Err(PreflightError::SharedMemory { free_mib: mib(free), need_mib: mib(need), detail })
}

/// Checks /dev/shm and the file-descriptor limit against what the plan needs (raising the soft
/// fd limit up to the hard one when that suffices).
pub fn preflight(plan: &Plan) -> Result<Preflight, PreflightError> {
    let st = nix::sys::statvfs::statvfs("/dev/shm").map_err(|e| PreflightError::NoShm(e.to_string()))?;
    let shm_free = st.blocks_available() as u64 * st.fragment_size() as u64;
    let needs: Vec<(&str, u64)> = plan.processes.iter().map(|p| (p.name.as_str(), p.shm_bytes)).collect();
    let shm_need = check_shm(shm_free, &needs)?;
    use nix::sys::resource::{Resource, getrlimit, setrlimit};
    let need = 256 + 64 * plan.processes.len() as u64;
    let (soft, hard) = getrlimit(Resource::RLIMIT_NOFILE).unwrap_or((u64::MAX, u64::MAX));
    let mut fd_limit = soft;
    if soft < need {
        if hard < need {
            return Err(PreflightError::FileDescriptors { hard, need, processes: plan.processes.len() });
        }
        let target = hard.min(need * 4);
        if setrlimit(Resource::RLIMIT_NOFILE, target, hard).is_ok() {
            fd_limit = target;
        }
    }
    Ok(Preflight { shm_free, shm_need, fd_limit })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn too_little_shared_memory_is_an_error_that_names_each_process() {
        let needs = [("producer", 448u64 << 20), ("consumer", 0)];
        let e = check_shm(64 << 20, &needs).unwrap_err().to_string();
        assert!(e.contains("/dev/shm has 64.0 MiB free"), "{e}");
        assert!(e.contains("producer: 450.0 MiB") && e.contains("consumer: 2.0 MiB"), "{e}");
        assert!(e.contains("--shm-size"), "{e}");
        assert_eq!(check_shm(1 << 30, &needs).unwrap(), (448 << 20) + 2 * CONTROL_SHM_PER_PROCESS);
    }
}
