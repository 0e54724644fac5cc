//! Command line: the benchmark's options (the default role) and the hidden `consumer` role the
//! benchmark starts as its child process.

use std::path::PathBuf;

use anyhow::ensure;

/// `ingest_bench` command line.
#[derive(Debug, Clone, clap::Parser)]
#[command(
    name = "ingest_bench",
    about = "300k-point clouds from a producer to a consumer process: producer CPU per frame and hop latency, \
             iceoryx2 (our runtime) side by side with copy-based Unix-socket baselines",
    args_conflicts_with_subcommands = true
)]
pub struct Cli {
    /// A role other than the benchmark itself (internal).
    #[command(subcommand)]
    pub role: Option<Role>,
    /// Options of the benchmark.
    #[command(flatten)]
    pub bench: BenchArgs,
}

/// Roles other than the benchmark (the parent).
#[derive(Debug, Clone, clap::Subcommand)]
pub enum Role {
    /// Internal: the consumer process the benchmark starts for each transport.
    #[command(hide = true)]
    Consumer(ConsumerArgs),
}

/// A transport under test.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum Transport {
    /// iceoryx2 shared memory through `pipeline_runtime` (loan, write in place, send + notify;
    /// the consumer blocks in the runtime's WaitSet).
    Iox,
    /// Copy baseline: the cloud as `Vec<[f32; 3]>` plus a header, bincode (serde), length-prefixed
    /// on a Unix stream socket; the consumer blocks in `read` and deserialises.
    SocketBincode,
    /// Copy baseline: a fixed header and the points' raw bytes on a Unix stream socket, read into a
    /// reused buffer.
    SocketRaw,
}

impl Transport {
    /// Name as on the command line and in the table.
    pub fn name(self) -> &'static str {
        match self {
            Transport::Iox => "iox",
            Transport::SocketBincode => "socket-bincode",
            Transport::SocketRaw => "socket-raw",
        }
    }
}

/// Largest cloud the benchmark accepts (the shared-memory segment of the cloud service grows with it).
pub const MAX_POINTS: usize = 4_000_000;

/// Options of the benchmark.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchArgs {
    /// Points per cloud.
    #[arg(long, default_value_t = 300_000)]
    pub points: usize,
    /// Clouds per second (the producer is paced on an absolute schedule).
    #[arg(long, default_value_t = 30.0)]
    pub rate_hz: f64,
    /// Measured clouds per transport (after the warm-up).
    #[arg(long, default_value_t = 300)]
    pub frames: u64,
    /// Warm-up clouds per transport, sent first and excluded from every statistic.
    #[arg(long, default_value_t = 30)]
    pub warmup: u64,
    /// Also write the table as CSV to this file.
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// Transports to measure, in this order (the `gen-only` reference row always runs first).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "iox,socket-bincode,socket-raw")]
    pub transports: Vec<Transport>,
}

impl BenchArgs {
    /// Checks the options; the error names the offending option.
    pub fn validate(&self) -> anyhow::Result<()> {
        ensure!((1..=MAX_POINTS).contains(&self.points), "--points must be 1..={MAX_POINTS}, got {}", self.points);
        ensure!(
            self.rate_hz.is_finite() && self.rate_hz > 0.0 && self.rate_hz <= 10_000.0,
            "--rate-hz must be in (0, 10000], got {}",
            self.rate_hz
        );
        ensure!(self.frames >= 1, "--frames must be at least 1");
        ensure!(!self.transports.is_empty(), "--transports must name at least one transport");
        let mut seen = std::collections::HashSet::new();
        for t in &self.transports {
            ensure!(seen.insert(*t), "--transports names `{}` twice", t.name());
        }
        Ok(())
    }

    /// Clouds sent per transport (warm-up included).
    pub fn total_frames(&self) -> u64 {
        self.warmup + self.frames
    }
}

/// Options of the consumer role (set by the parent).
#[derive(Debug, Clone, clap::Args)]
pub struct ConsumerArgs {
    /// Transport to receive from.
    #[arg(long, value_enum)]
    pub transport: Transport,
    /// Points every cloud must have.
    #[arg(long)]
    pub points: usize,
    /// Clouds with a sequence number below this are not recorded.
    #[arg(long)]
    pub warmup: u64,
    /// Unix socket to connect to (socket transports).
    #[arg(long)]
    pub socket: Option<PathBuf>,
    /// Pid of the benchmark: the consumer exits when it is no longer its parent.
    #[arg(long)]
    pub parent_pid: i32,
}
