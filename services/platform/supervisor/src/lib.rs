//! The supervisor: validates a pipeline config, checks the machine, starts the processes in
//! dependency order, watches and restarts them, ends the run, stops everything in reverse order,
//! removes the run's iceoryx2 resources and writes `summary.json`.

pub mod certs;
pub mod doctor;
pub mod kinds;
pub mod live;
pub mod outcome;
pub mod plan;
pub mod report;
pub mod status;
pub mod supervise;

use std::io::Write as _;
use std::path::PathBuf;

use anyhow::Context as _;
use pipeline_runtime::{LogFormat, Runtime};

/// Command line of `supervisor`.
#[derive(Debug, clap::Parser)]
#[command(version, about = "Runs the SLAM pipeline: starts, watches, restarts and stops its processes.")]
#[command(args_conflicts_with_subcommands = true)]
pub struct Cli {
    /// What else to do instead of running the pipeline.
    #[command(subcommand)]
    pub command: Option<Command>,
    /// Pipeline config (TOML), e.g. config/default.toml.
    #[arg(long, required = true)]
    pub config: Option<PathBuf>,
    /// Output directory (overrides run.out_dir).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// End the run after this many seconds (overrides run.duration_s).
    #[arg(long)]
    pub duration: Option<f64>,
    /// iceoryx2 prefix of this run (overrides run.iceoryx_prefix).
    #[arg(long)]
    pub iceoryx_prefix: Option<String>,
    /// Log format (overrides run.log_format).
    #[arg(long, value_enum)]
    pub log_format: Option<LogFormat>,
    /// Only validate the config and check the machine; start nothing.
    #[arg(long)]
    pub check: bool,
    /// No live status block even when stdout is a terminal: the log on stderr with a status line
    /// every `run.status_interval_s`, as when stdout is a pipe or a file.
    #[arg(long)]
    pub no_live: bool,
}

impl Cli {
    /// Whether this invocation runs a pipeline with the live status block ([`live`]): a run
    /// (not a subcommand, not `--check`) whose stdout is a terminal, without `--no-live`.
    pub fn live(&self) -> bool {
        self.command.is_none() && !self.check && live::wanted(self.no_live)
    }
}

/// Subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// Pre-flight report of this machine (cores, iceoryx2 version, /dev/shm against a config's
    /// needs, open-file limits, files of other runs in /dev/shm); exit code 2 on a problem.
    Doctor {
        /// Also check this config's processes, binaries and needs.
        #[arg(long)]
        config: Option<PathBuf>,
    },
    /// The state of the pipeline that runs (or ran) this config: per process state, restarts,
    /// message rate and latency; exit code 0 running, 1 not running, 2 no status.
    Status {
        /// The pipeline's config (its `run.out_dir` holds `status.json`).
        #[arg(long)]
        config: PathBuf,
        /// Output directory, when the run overrode it with `--out`.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Makes the certificates of the bridge's mutual TLS (docs/security.md): a CA in `--dir`
    /// (made on the first call, reused after) and one certificate per `--name`; `--revoke` adds
    /// a host to the revocation list (`<dir>/revoked.txt`), which running bridges apply at once.
    Certs {
        /// Directory of `ca.pem`/`ca.key` and the `<name>.pem`/`<name>.key` pairs.
        #[arg(long, default_value = "certs")]
        dir: PathBuf,
        /// A host's name: a robot's `robot`, or the base station's (repeat for several).
        #[arg(long = "name", required_unless_present_any = ["revoke", "viewer_token"])]
        names: Vec<String>,
        /// Revoke this host's certificates (repeat for several): bridges refuse everything from
        /// it and send it nothing, from the moment the list changes (they restart to apply it).
        #[arg(long = "revoke")]
        revoke: Vec<String>,
        /// Also make a token for the live view (`<dir>/viewer.token`, mode 0600; a viewer's
        /// `token_file`): clients connect with `wss://<host>:<port>/?token=<token>`.
        #[arg(long)]
        viewer_token: bool,
        /// An address or DNS name other hosts dial this host by (repeat; 127.0.0.1, ::1 and
        /// localhost are always in).
        #[arg(long = "san")]
        sans: Vec<String>,
        /// Validity of the certificates, days.
        #[arg(long, default_value_t = 365.0)]
        days: f64,
        /// Validity of a new CA, days.
        #[arg(long, default_value_t = 3650.0)]
        ca_days: f64,
    },
}

/// Exit code for an invalid config or a failed pre-flight check (nothing was started).
pub const EXIT_CONFIG: u8 = 2;

/// An error before anything started (config or machine): exit code [`EXIT_CONFIG`].
#[derive(Debug, thiserror::Error)]
#[error(transparent)]
pub struct SetupError(#[from] anyhow::Error);

/// Runs the supervisor; returns the process exit code.
pub fn run(cli: &Cli) -> anyhow::Result<u8> {
    if let Some(command) = &cli.command {
        return run_command(command);
    }
    let config = cli.config.as_deref().ok_or_else(|| SetupError(anyhow::anyhow!("--config is required")))?;
    let overrides = plan::Overrides {
        out_dir: cli.out.clone(),
        duration_s: cli.duration,
        iceoryx_prefix: cli.iceoryx_prefix.clone(),
    };
    let mut plan = plan::make_plan(config, &overrides, &plan::default_bin_dir()).map_err(|e| SetupError(e.into()))?;
    if let Some(f) = cli.log_format {
        plan.config.run.log_format = f;
    }
    let pre = plan::preflight(&plan).map_err(|e| SetupError(e.into()))?;
    tracing::info!(
        "pre-flight ok: /dev/shm {:.0} MiB free, ~{:.0} MiB needed; fd limit {}",
        pre.shm_free as f64 / 1048576.0,
        pre.shm_need as f64 / 1048576.0,
        pre.fd_limit
    );
    if cli.check {
        println!(
            "config ok: {} process(es) in order {:?}",
            plan.processes.len(),
            plan.processes.iter().map(|p| &p.name).collect::<Vec<_>>()
        );
        return Ok(0);
    }
    prepare_run(&plan)?;
    let scope = plan.scope.clone();
    let out_dir = plan.out_dir.clone();
    // The supervisor opens the control services like every process of the run.
    let options = supervise::Supervisor::runtime_options(plan.config.run.extra_subscribers);
    let live = if cli.live() {
        let names: Vec<String> = plan.processes.iter().map(|p| p.name.clone()).collect();
        let view = live::Live::start(&out_dir, &names)
            .with_context(|| format!("opening {}", out_dir.join("run.log").display()))?;
        Some(view)
    } else {
        None
    };
    let log_path = live.as_ref().map(|l| l.log_path().to_path_buf());
    let outcome = {
        let mut rt = Runtime::new("supervisor", &scope, options)?;
        let mut sup = supervise::Supervisor::new(plan, &mut rt)?;
        if let Some(l) = live {
            sup.set_live(l);
        }
        sup.run(&mut rt)?
    };
    // Every child is reaped and our own node is dropped: nothing of the run may remain.
    let _ = scope.cleanup_dead_nodes();
    match scope.remove_all_resources() {
        Ok(n) if n > 0 => tracing::debug!("removed {n} remaining iceoryx2 file(s)"),
        Ok(_) => {}
        Err(e) => tracing::warn!("removing the run's iceoryx2 resources: {e}"),
    }
    report::write(&out_dir, &outcome.summary)
        .with_context(|| format!("writing {}", out_dir.join("summary.json").display()))?;
    print_report(&outcome.summary, &out_dir, log_path.as_deref());
    Ok(outcome.exit_code)
}

/// `doctor`, `certs` and `status`: the subcommands that run no pipeline.
fn run_command(command: &Command) -> anyhow::Result<u8> {
    match command {
        Command::Doctor { config } => {
            let r = doctor::report(config.as_deref());
            print!("{}", r.render());
            Ok(r.exit_code())
        }
        Command::Certs { dir, names, revoke, viewer_token, sans, days, ca_days } => {
            let req = certs::CertsRequest {
                dir: dir.clone(),
                names: names.clone(),
                revoke: revoke.clone(),
                viewer_token: *viewer_token,
                sans: sans.clone(),
                days: *days,
                ca_days: *ca_days,
            };
            let r = certs::make(&req).map_err(SetupError)?;
            print!("{}", r.render());
            Ok(0)
        }
        Command::Status { config, out } => {
            let out_dir = match out {
                Some(o) => o.clone(),
                None => {
                    let c = pipeline_runtime::config::load_pipeline_config(config).map_err(|e| SetupError(e.into()))?;
                    // As the run resolves it: relative to the current directory.
                    std::path::absolute(&c.run.out_dir).unwrap_or(c.run.out_dir)
                }
            };
            let v = status::view(&out_dir);
            print!("{}", v.text);
            Ok(v.exit_code)
        }
    }
}

/// Refuses a run while another pipeline lives under the same iceoryx2 prefix, removes what dead
/// runs left there, and clears the output directory's `parts/` and `stats/`.
fn prepare_run(plan: &plan::Plan) -> anyhow::Result<()> {
    let census = plan.scope.node_census().map_err(|e| SetupError(e.into()))?;
    if !census.alive.is_empty() {
        return Err(SetupError(anyhow::anyhow!(
            "another pipeline is running with iceoryx2 prefix `{}` (live nodes: {}); stop it or choose another run.iceoryx_prefix / --iceoryx-prefix",
            plan.scope.prefix,
            census.alive.join(", ")
        ))
        .into());
    }
    let removed = plan
        .scope
        .remove_all_resources()
        .with_context(|| format!("removing stale resources under {}", plan.scope.root.display()))?;
    if removed > 0 || census.dead > 0 {
        tracing::info!("removed {removed} stale iceoryx2 file(s) of {} dead node(s) from an earlier run", census.dead);
    }
    std::fs::create_dir_all(&plan.out_dir).with_context(|| format!("creating {}", plan.out_dir.display()))?;
    for sub in ["parts", "stats"] {
        let dir = plan.out_dir.join(sub);
        if dir.exists() {
            std::fs::remove_dir_all(&dir).with_context(|| format!("clearing {}", dir.display()))?;
        }
    }
    Ok(())
}

/// Prints the report: in a terminal the short summary (the whole report goes to `run.log`, at
/// `log_path`), else the whole report. A closed stdout (piped into `head`) changes nothing.
fn print_report(summary: &serde_json::Value, out_dir: &std::path::Path, log_path: Option<&std::path::Path>) {
    let mut out = std::io::stdout().lock();
    let _ = match log_path {
        // In a terminal: the short summary; the whole report goes to run.log.
        Some(p) => {
            let text = std::fs::read_to_string(p).unwrap_or_default();
            let warnings = text.lines().filter(|l| l.contains(" WARN ")).count();
            let report = report::render(summary);
            let _ = std::fs::OpenOptions::new().append(true).open(p).and_then(|mut f| write!(f, "{report}"));
            write!(out, "{}", report::render_short(summary, out_dir, warnings))
                .and_then(|()| writeln!(out, "full log in {} (with the latency tables)", p.display()))
        }
        None => {
            write!(out, "{}", report::render(summary)).and_then(|()| writeln!(out, "outputs in {}", out_dir.display()))
        }
    }
    .and_then(|()| out.flush());
}
