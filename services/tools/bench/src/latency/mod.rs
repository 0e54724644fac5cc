//! `pipeline_bench latency`: how long does a message take from an external producer through a
//! chain of real processes, per hop and end to end, over iceoryx2 (through our runtime, and bare)
//! and over copy-based Unix-socket baselines, for payloads from 64 B to 8 MiB, in one run?
//!
//! Topology of one case (transport × payload size × chain of `n` relays): the producer (this
//! process) sends on link 0 to relay 1, relay `k` forwards on link `k`, and relay `n` sends back
//! to the producer, so a chain of 1 is a round trip and a chain of `n` is `n + 1` hops. Every
//! process blocks until its message arrives (iceoryx2: in a WaitSet on the link's event; sockets:
//! in `read`). At most one message is in flight; the producer starts one every `1/rate` s.
//!
//! Measured: each hop's latency (receiver's CLOCK_MONOTONIC when the payload is usable − the
//! sender's `publish_ns`, stamped right before send/serialisation) and end to end (back at the
//! producer − when it sent). Iceoryx2 payloads are never copied: the producer writes its payload
//! in place in shared memory (not timed) and each relay loans a new sample and writes only the
//! header and the 16 index bytes, as a stage producing its output in place would. A socket
//! relay has to copy the payload through the kernel twice per hop, and bincode also decodes and
//! re-encodes it. See [`wire`] for what travels, [`relay`] for the relay, [`report`] for the table,
//! the goals and the CSV, [`plot`] for the PNG.

pub mod cli;
pub mod links;
pub mod pacer;
pub mod plot;
pub mod relay;
pub mod report;
pub mod run;
pub mod wire;

use anyhow::Context as _;

pub use cli::{Cli, Command, LatTransport, LatencyArgs, RelayArgs};
pub use report::{CaseResult, LatencyResult};
pub use run::run_latency;

/// Runs the benchmark and prints the table and ratios to stdout; writes the CSV and PNG if asked.
pub fn run_and_print(args: &LatencyArgs) -> anyhow::Result<()> {
    let started = std::time::Instant::now();
    let result = run_latency(args)?;
    let cpus = std::thread::available_parallelism().map_or(0, |n| n.get());
    println!(
        "pipeline_bench latency: {} measured messages after {} warm-up per case at {} Hz, {cpus} CPUs, {:.0} s; \
         iceoryx2 prefix {} (removed)",
        args.samples,
        args.warmup,
        args.rate_hz,
        started.elapsed().as_secs_f64(),
        result.prefix
    );
    println!(
        "latencies in µs; e2e = producer -> every relay -> producer (chain 1 = round trip); hop p50 = median of \
         the hops' p50; wakes = WaitSet wake-ups per message (iceoryx2); vs iox = e2e p50 over the iox row"
    );
    print!("{}", report::render_table(&result.cases));
    print!("{}", report::render_ratios(&result.cases));
    for c in &result.cases {
        let name = format!("{} {} chain {}", c.transport, cli::size_label(c.size_bytes), c.chain);
        if c.cut_short {
            eprintln!(
                "note: {name}: the {} s budget ended the case after {} of {} measured messages",
                args.max_case_seconds,
                c.e2e.map_or(0, |e| e.count),
                c.samples_wanted
            );
        }
        if c.lost + c.bad > 0 {
            eprintln!("note: {name}: {} lost, {} torn or wrong-size messages", c.lost, c.bad);
        }
        // With one message in flight, a slow round trip delays the next start; say so only when
        // it changed the schedule noticeably.
        if c.late * 10 > c.samples_wanted {
            eprintln!(
                "note: {name}: {} messages started more than one period late (the chain was slower than the rate)",
                c.late
            );
        }
    }
    if let Some(path) = &args.csv {
        report::write_csv(path, &result.cases)?;
        eprintln!("pipeline_bench: wrote {}", path.display());
    }
    if let Some(path) = &args.png {
        plot::write_png(path, &result.cases).context("writing the histogram PNG")?;
        eprintln!("pipeline_bench: wrote {}", path.display());
    }
    Ok(())
}
