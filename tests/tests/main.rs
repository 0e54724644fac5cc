//! The multi-process tests, one module per concern, in one test binary: real binaries started by
//! the supervisor, each run with its own iceoryx2 prefix, root and temporary directory (see the
//! `pipeline_tests` library), so that tests of different modules run side by side.
//!
//! Run one module: `cargo test --workspace --test pipeline -- bridge::` (build the binaries
//! first: `cargo build --workspace --bins`).

mod backpressure;
mod bridge;
mod buoy_sync;
mod config_errors;
mod ending;
mod external_producers;
mod fastslam;
mod fusion;
mod grid_slam;
mod in_process;
mod indoor;
mod ingest;
mod kill9;
mod layering;
mod octree_tools;
mod plugins;
mod python_producer;
mod record_replay;
mod ros2_bags;
mod ros2_gateway;
mod security;
mod stop;
mod summary_schema;
mod supervisor;
mod viewer;
mod watchers;
mod wire_roundtrip;
