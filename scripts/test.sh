#!/usr/bin/env bash
# The test command (README): builds every binary the multi-process tests start, then runs all tests.
# Whatever the tests need beyond the Rust toolchain is installed here, so a fresh machine needs
# nothing else.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --workspace --bins
cargo test --workspace "$@"
