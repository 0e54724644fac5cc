#!/usr/bin/env bash
# The test command (README): builds every binary the multi-process tests start, then runs all tests.
# Whatever the tests need beyond the Rust toolchain is installed here, so a fresh machine needs
# nothing else. Ends with one line "tests: N passed, N failed" totalled over every test binary.
set -euo pipefail
cd "$(dirname "$0")/.."
# Python test dependency: tests/tests/python_producer.rs runs examples/python/producer.py, which
# needs the iceoryx2 Python binding of the same version as the Rust crate (0.10.0, from PyPI).
# Installed only when missing.
if ! python3 -c 'import importlib.metadata as m, sys; sys.exit(m.version("iceoryx2") != "0.10.0")' >/dev/null 2>&1; then
    python3 -m pip install --quiet iceoryx2==0.10.0
fi
cargo build --workspace --bins
log=$(mktemp)
trap 'rm -f "$log"' EXIT
status=0
cargo test --workspace "$@" 2>&1 | tee "$log" || status=$?
passed=$(grep -Eo 'test result: [A-Za-z]+\. [0-9]+ passed' "$log" | awk '{s+=$4} END {print s+0}')
failed=$(grep -Eo '[0-9]+ failed' "$log" | awk '{s+=$1} END {print s+0}')
echo "tests: ${passed} passed, ${failed} failed"
exit "$status"
