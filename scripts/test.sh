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
# Python test dependency: tests/tests/record_replay.rs reads the recorder's MCAP file with Python's
# `mcap` reader (the one Foxglove's tooling uses). Installed only when missing.
if ! python3 -c 'import mcap.reader' >/dev/null 2>&1; then
    python3 -m pip install --quiet mcap
fi
# Python test dependencies: tests/tests/viewer.rs connects tests/python/foxglove_ws_client.py (a
# Foxglove WebSocket client: `websockets`, decoding with the advertised schemas: `protobuf`) to the
# live viewer. Installed only when missing.
if ! python3 -c 'import websockets.sync.client, google.protobuf.message_factory' >/dev/null 2>&1; then
    python3 -m pip install --quiet 'websockets>=13' protobuf
fi
# Python test dependency: tests/tests/ros2_bags.rs writes and reads rosbag2 bags with `rosbags`
# (PyPI; with numpy), an implementation of ROS 2 bags and CDR that no one here wrote. Installed only
# when missing. (numpy is also what algorithms/navigable/tests/bench_scene.rs needs to run the
# OctoMap benchmark's ../shared/bench/octomap/gen_scene.py.)
if ! python3 -c 'import rosbags.rosbag2, rosbags.highlevel, numpy' >/dev/null 2>&1; then
    python3 -m pip install --quiet 'rosbags>=0.10'
fi
# Python test dependency: tests/tests/ros2_gateway.rs talks to the `ros2` gateway through Eclipse
# Cyclone DDS (`cyclonedds` from PyPI: a wheel with the C library inside), a DDS implementation no
# one here wrote. Installed only when missing.
if ! python3 -c 'import cyclonedds.domain, cyclonedds.idl' >/dev/null 2>&1; then
    python3 -m pip install --quiet cyclonedds
fi
# Python test dependency: tests/tests/security.rs attacks the base station with a rogue peer
# written with Eclipse Zenoh's own Python API (`eclipse-zenoh` from PyPI, the version of our zenoh
# crate). Installed only when missing.
if ! python3 -c 'import importlib.metadata as m, sys; sys.exit(m.version("eclipse-zenoh") != "1.10.2")' >/dev/null 2>&1; then
    python3 -m pip install --quiet eclipse-zenoh==1.10.2
fi
# Python test dependency: tests/tests/fusion.rs validates the main job's summary.json against
# docs/summary.schema.json with `jsonschema` (PyPI), a JSON Schema implementation no one here wrote.
# Installed only when missing.
if ! python3 -c 'import jsonschema' >/dev/null 2>&1; then
    python3 -m pip install --quiet jsonschema
fi
# Debian test dependencies: tests/tests/octree_tools.rs runs OctoMap's convert_octree and
# compare_octrees (package octomap-tools) on the .bt files of the octree crate; tests/tests/security.rs
# captures the bridge's link with tcpdump. Installed only when missing (as root, or through sudo);
# if that is impossible the tests fail naming the package.
debs=()
if ! command -v convert_octree >/dev/null 2>&1 || ! command -v compare_octrees >/dev/null 2>&1; then
    debs+=(octomap-tools)
fi
if ! command -v tcpdump >/dev/null 2>&1 && [ ! -x /usr/bin/tcpdump ] && [ ! -x /usr/sbin/tcpdump ]; then
    debs+=(tcpdump)
fi
if [ ${#debs[@]} -gt 0 ]; then
    apt=()
    if [ "$(id -u)" -eq 0 ]; then
        apt=(env DEBIAN_FRONTEND=noninteractive apt-get)
    elif command -v sudo >/dev/null 2>&1; then
        if [ -t 0 ]; then sudo_=(sudo); else sudo_=(sudo -n); fi
        apt=("${sudo_[@]}" env DEBIAN_FRONTEND=noninteractive apt-get)
    fi
    if [ ${#apt[@]} -eq 0 ]; then
        echo "test.sh: ${debs[*]} missing and cannot be installed (not root, no sudo):" \
            "run 'apt-get install -y --no-install-recommends ${debs[*]}' as root" >&2
    else
        echo "test.sh: installing ${debs[*]} (apt-get)" >&2
        # A fresh machine may have no package lists yet: update once and retry.
        if ! "${apt[@]}" install -y -qq --no-install-recommends "${debs[@]}" >/dev/null 2>&1 \
            && ! { "${apt[@]}" update -qq >/dev/null \
                && "${apt[@]}" install -y -qq --no-install-recommends "${debs[@]}" >/dev/null; }; then
            echo "test.sh: could not install ${debs[*]}: run 'apt-get install -y --no-install-recommends" \
                "${debs[*]}' as root (tests/tests/octree_tools.rs and security.rs fail without them)" >&2
        fi
    fi
fi
# Every binary the multi-process tests start and every test target, in one cargo invocation (its
# two cores stay busy across what used to be two builds). Test targets: libraries, binaries with
# `test = true`, test files; not the examples, which a plain `cargo test` compiles and links (15
# binaries no test runs; clippy --all-targets in .ci/run still checks that they build).
cargo build --workspace --bins --tests
log=$(mktemp) multi=$(mktemp) multi_rc=$(mktemp)
trap 'rm -f "$log" "$multi" "$multi_rc"' EXIT
status=0
# Three tests at once per test binary on two cores: the multi-process tests wait on other
# processes for much of their time (pipeline tests 310 s with two, 266 s with three, 254 s with
# four, one run each, 2026-12-05; docs/benchmarks.md). `--test-threads` in the arguments
# overrides it.
export RUST_TEST_THREADS="${RUST_TEST_THREADS:-3}"
if [ $# -gt 0 ] && [ "$1" != "--" ]; then
    # Cargo arguments (a package, a test target): cargo runs what they select, one binary after
    # the other.
    { cargo test --workspace --tests "$@" && cargo test --workspace --doc "$@"; } 2>&1 | tee "$log" || status=$?
else
    # The multi-process tests (one binary, pipeline_tests) run beside the other test binaries:
    # they wait on their processes much of the time, and cargo would run the binaries one after
    # the other (and holds its lock while they run, so a second cargo cannot run beside it). The
    # binary runs as cargo runs it, from its package's directory. Arguments after `--` go to every
    # test binary (a name filter, --nocapture).
    exe=$(cargo test --workspace --tests --no-run --message-format=json 2>/dev/null \
        | python3 -c 'import json, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m["target"]["name"] == "pipeline" and m.get("executable"):
        print(m["executable"])')
    [ -x "$exe" ] || { echo "test.sh: no multi-process test binary (pipeline_tests)" >&2; exit 1; }
    shift $(( $# > 0 ? 1 : 0 ))
    echo "test.sh: the multi-process tests run beside the others; their output follows at the end"
    ( cd tests || exit 1; rc=0; "$exe" "$@" > "$multi" 2>&1 || rc=$?; echo "$rc" > "$multi_rc" ) &
    { cargo test --workspace --exclude pipeline_tests --tests -- "$@" \
        && cargo test --workspace --doc -- "$@"; } 2>&1 | tee "$log" || status=$?
    wait
    echo "     Running tests/main.rs (multi-process tests, pipeline_tests)"
    cat "$multi" | tee -a "$log"
    rc=$(cat "$multi_rc")
    [ "$rc" = 0 ] || status=${rc:-1}
fi
passed=$(grep -Eo 'test result: [A-Za-z]+\. [0-9]+ passed' "$log" | awk '{s+=$4} END {print s+0}')
failed=$(grep -Eo '[0-9]+ failed' "$log" | awk '{s+=$1} END {print s+0}')
echo "tests: ${passed} passed, ${failed} failed"
exit "$status"
