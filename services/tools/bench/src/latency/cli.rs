//! Command line of `pipeline_bench`: the `latency` subcommand and the hidden `relay` role the
//! benchmark starts for each process of a chain.

use std::path::PathBuf;

use anyhow::ensure;

/// `pipeline_bench` command line.
#[derive(Debug, Clone, clap::Parser)]
#[command(name = "pipeline_bench", about = "Multi-process benchmarks of the pipeline's transports")]
pub struct Cli {
    /// What to run.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum Command {
    /// Latency of messages from an external producer through a chain of relay processes and back:
    /// per hop and end to end, for a sweep of payload sizes, over iceoryx2 (our runtime and bare
    /// iceoryx2) and copy-based Unix-socket baselines, side by side in one run.
    Latency(LatencyArgs),
    /// Internal: one relay process of a chain.
    #[command(hide = true)]
    Relay(RelayArgs),
}

/// A transport under test.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
pub enum LatTransport {
    /// iceoryx2 through `pipeline_runtime` (`Output::send` stamps and notifies; relays block in
    /// `Runtime::run`'s WaitSet, which also serves heartbeats and connection updates).
    Iox,
    /// iceoryx2 used directly: one publisher + notifier and one subscriber + listener per process,
    /// a WaitSet with the listener only. The reference for the runtime's own overhead.
    IoxBare,
    /// Copy baseline: a 32-byte header and the payload's bytes on a Unix stream socket, read into a
    /// reused buffer and written on.
    SocketRaw,
    /// Copy baseline: header + payload as `Vec<f32>` encoded with bincode (serde), length-prefixed
    /// on a Unix stream socket; each relay decodes and re-encodes.
    SocketBincode,
}

impl LatTransport {
    /// Name as on the command line, in the table and the CSV.
    pub fn name(self) -> &'static str {
        match self {
            LatTransport::Iox => "iox",
            LatTransport::IoxBare => "iox-bare",
            LatTransport::SocketRaw => "socket-raw",
            LatTransport::SocketBincode => "socket-bincode",
        }
    }

    /// Whether the transport is iceoryx2 shared memory.
    pub fn is_iox(self) -> bool {
        matches!(self, LatTransport::Iox | LatTransport::IoxBare)
    }
}

/// Smallest payload (the message index is written in its first and last 8 bytes).
pub const MIN_SIZE: usize = 16;
/// Largest payload, bytes (64 MiB).
pub const MAX_SIZE: usize = 64 << 20;
/// Longest chain of relay processes.
pub const MAX_CHAIN: usize = 16;

/// Options of `pipeline_bench latency`.
#[derive(Debug, Clone, clap::Args)]
pub struct LatencyArgs {
    /// Payload sizes in bytes (suffixes K/KiB and M/MiB accepted: 64,64K,1M,8M).
    #[arg(long, value_delimiter = ',', value_parser = parse_size, default_value = "64,64KiB,1MiB,8MiB")]
    pub sizes: Vec<usize>,
    /// Chain lengths: numbers of relay processes between the producer and its own receiver
    /// (a chain of n relays is n + 1 hops; 1 relay = a round trip).
    #[arg(long, value_delimiter = ',', default_value = "1,3")]
    pub chains: Vec<usize>,
    /// Transports, in this order.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "iox,iox-bare,socket-raw,socket-bincode")]
    pub transports: Vec<LatTransport>,
    /// Measured messages per case (transport × size × chain), after the warm-up.
    #[arg(long, default_value_t = 1000)]
    pub samples: u64,
    /// Warm-up messages per case, excluded from every statistic.
    #[arg(long, default_value_t = 50)]
    pub warmup: u64,
    /// Messages per second the producer starts (at most one is in flight: the next starts when it
    /// is due and the previous one is back).
    #[arg(long, default_value_t = 200.0)]
    pub rate_hz: f64,
    /// Longest a case may measure, seconds; a slow case stops early with fewer samples (noted).
    #[arg(long, default_value_t = 20.0)]
    pub max_case_seconds: f64,
    /// How long the producer waits for a message to come back before counting it as lost, ms.
    #[arg(long, default_value_t = 5000)]
    pub timeout_ms: u64,
    /// Every receiver reads every byte of the payload before it takes its receive time, and every
    /// relay's output is a full copy of its input (iceoryx2: a memcpy into the loaned sample;
    /// sockets: the kernel's copies). Without it, iceoryx2 receivers use the payload where it lies
    /// and relays write only the header and index bytes (transport cost alone).
    #[arg(long)]
    pub touch: bool,
    /// Write every row (each hop and end to end) as CSV to this file.
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// Write a PNG of the end-to-end latency histograms (one panel per payload size) to this file.
    #[arg(long)]
    pub png: Option<PathBuf>,
}

/// Parses `64`, `64K`, `64KiB`, `1M`, `8MiB` (powers of 1024).
pub fn parse_size(s: &str) -> Result<usize, String> {
    let t = s.trim();
    let lower = t.to_ascii_lowercase();
    let (digits, mult) = if let Some(d) = lower.strip_suffix("kib").or_else(|| lower.strip_suffix('k')) {
        (d, 1usize << 10)
    } else if let Some(d) = lower.strip_suffix("mib").or_else(|| lower.strip_suffix('m')) {
        (d, 1usize << 20)
    } else {
        (lower.strip_suffix('b').unwrap_or(&lower), 1)
    };
    let n: usize = digits.trim().parse().map_err(|_| format!("`{t}` is not a size (examples: 64, 64KiB, 8MiB)"))?;
    n.checked_mul(mult).ok_or_else(|| format!("`{t}` is too large"))
}

/// A size for people: `64 B`, `64 KiB`, `8 MiB`.
pub fn size_label(bytes: usize) -> String {
    if bytes >= 1 << 20 && bytes.is_multiple_of(1 << 20) {
        format!("{} MiB", bytes >> 20)
    } else if bytes >= 1 << 10 && bytes.is_multiple_of(1 << 10) {
        format!("{} KiB", bytes >> 10)
    } else {
        format!("{bytes} B")
    }
}

impl LatencyArgs {
    /// Checks the options; the error names the offending option.
    pub fn validate(&self) -> anyhow::Result<()> {
        ensure!(!self.sizes.is_empty(), "--sizes must name at least one size");
        for &s in &self.sizes {
            ensure!(
                (MIN_SIZE..=MAX_SIZE).contains(&s),
                "--sizes: {s} bytes is outside {MIN_SIZE}..={MAX_SIZE} (the message index takes 16 bytes)"
            );
            ensure!(
                s.is_multiple_of(4),
                "--sizes: {s} bytes is not a multiple of 4 (the bincode baseline sends f32 values)"
            );
        }
        ensure!(!self.chains.is_empty(), "--chains must name at least one chain length");
        for &c in &self.chains {
            ensure!((1..=MAX_CHAIN).contains(&c), "--chains: {c} is outside 1..={MAX_CHAIN}");
        }
        ensure!(!self.transports.is_empty(), "--transports must name at least one transport");
        let mut seen = std::collections::HashSet::new();
        for t in &self.transports {
            ensure!(seen.insert(*t), "--transports names `{}` twice", t.name());
        }
        ensure!(self.samples >= 1, "--samples must be at least 1");
        ensure!(
            self.rate_hz.is_finite() && self.rate_hz > 0.0 && self.rate_hz <= 100_000.0,
            "--rate-hz must be in (0, 100000], got {}",
            self.rate_hz
        );
        ensure!(
            self.max_case_seconds.is_finite() && self.max_case_seconds > 0.0,
            "--max-case-seconds must be positive, got {}",
            self.max_case_seconds
        );
        ensure!(self.timeout_ms >= 10, "--timeout-ms must be at least 10");
        Ok(())
    }
}

/// Options of the relay role (set by the benchmark).
#[derive(Debug, Clone, clap::Args)]
pub struct RelayArgs {
    /// Transport.
    #[arg(long, value_enum)]
    pub transport: LatTransport,
    /// Position in the chain, 1-based (it receives link `index − 1` and sends link `index`).
    #[arg(long)]
    pub index: usize,
    /// Name of the case (part of the service names and socket paths).
    #[arg(long)]
    pub case: String,
    /// Payload size, bytes.
    #[arg(long)]
    pub size: usize,
    /// Messages with an index below this are not recorded.
    #[arg(long)]
    pub warmup: u64,
    /// Read every byte of each input and send a full copy of it (see `latency --touch`).
    #[arg(long)]
    pub touch: bool,
    /// Directory of the socket files (socket transports).
    #[arg(long)]
    pub socket_dir: Option<PathBuf>,
    /// Pid of the benchmark: the relay exits when it is no longer its parent.
    #[arg(long)]
    pub parent_pid: i32,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_with_binary_suffixes_and_print_back() {
        assert_eq!(parse_size("64"), Ok(64));
        assert_eq!(parse_size("64KiB"), Ok(65536));
        assert_eq!(parse_size("64k"), Ok(65536));
        assert_eq!(parse_size("1M"), Ok(1 << 20));
        assert_eq!(parse_size("8MiB"), Ok(8 << 20));
        assert!(parse_size("8 furlongs").is_err());
        assert_eq!(size_label(64), "64 B");
        assert_eq!(size_label(65536), "64 KiB");
        assert_eq!(size_label(8 << 20), "8 MiB");
        assert_eq!(size_label(1000), "1000 B");
    }
}
