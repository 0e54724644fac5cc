//! `ingest_bench`: what does moving a 300k-point cloud from ingest to a consumer process cost, over
//! iceoryx2 through our runtime versus copy-based baselines (Unix stream socket with bincode, and
//! with raw bytes), measured side by side in one run?
//!
//! The parent process is the producer. For each transport it starts a consumer child (this same
//! binary, hidden `consumer` subcommand) in an isolated iceoryx2 scope, publishes `warmup + frames`
//! clouds at the configured rate, and measures per frame:
//!
//! - **producer CPU**: `CLOCK_THREAD_CPUTIME_ID` around the frame's production and send (content
//!   generation, serialisation, socket writes or the shared-memory write and notify). A
//!   `gen-only` row runs the same content generation into a `Vec` with no transport at all, so the
//!   transport's own share is `CPU − gen-only CPU`.
//! - **hop latency** (in the consumer): CLOCK_MONOTONIC when the consumer has read every point minus
//!   the publish time (iceoryx2: the header's `publish_ns`, set at send after the points were
//!   written in place; sockets: the time stamped right before serialisation/writing starts). So a
//!   copy baseline pays its serialisation, copies and deserialisation in the latency, as it would
//!   in a copy-based pipeline, and every transport pays the same final read of every point.
//! - **ready latency**: the same, but taken before the consumer's read pass (iceoryx2: at receive;
//!   sockets: after the last byte was read and, for bincode, deserialised).
//! - **consumer CPU**: thread CPU time of receiving (reading, deserialising) and reading a frame.
//!
//! The consumer sends its raw samples back as one JSON line on stdout; the parent computes exact
//! nearest-rank percentiles and prints one table row per transport (see [`report`]).

pub mod bench;
pub mod child;
pub mod cli;
pub mod consumer;
pub mod content;
pub mod cpu;
pub mod latency;
pub mod producer;
pub mod report;

pub use bench::run_bench;
pub use cli::{BenchArgs, Cli, ConsumerArgs, Role, Transport};
pub use report::{Row, Summary};
