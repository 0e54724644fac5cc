#!/usr/bin/env bash
# Soak test (issue #8; not run in CI): the default pipeline (config/default.toml's processes) at
# full rate for DURATION seconds on a longer mission: the survey's first leg flown back and forth
# LEGS times over the same strip (leg spacing 0), so the mission outlasts the soak while the mapped
# area stays that of one strip (after the first legs a growing map would be a leak, not new
# ground). It samples every INTERVAL seconds the resident
# memory (VmRSS from /proc; it includes the shared-memory pages a process has touched) of every
# pipeline process and the bytes the run's files hold in /dev/shm (allocated, not apparent). Prints
# a table (start / after warm-up / max / end per process, and /dev/shm) and a verdict: bounded
# when each value at the end is within TOLERANCE % (+ 8 MiB) of its value after WARMUP seconds.
#
#   scripts/soak.sh [DURATION_S=300] [INTERVAL_S=5]
#   scripts/soak.sh --report DIR/samples.tsv     (the table again from a kept run's samples)
#   env: LEGS (40), WARMUP (120 s), TOLERANCE (25 %), KEEP=1 keeps the run directory.
#
# The table also gives each value's slope over the second half of the run (MiB/min): a process
# that keeps a history (trajectories, the fused path) grows linearly by design; a slope that does
# not level off where nothing should accumulate is a leak.
#
# The run uses its own iceoryx2 prefix and root and a temporary output directory; it is stopped
# with SIGTERM at the end (run.end = "duration") and must leave nothing in /dev/shm.
set -euo pipefail
cd "$(dirname "$0")/.."
warmup=${WARMUP:-120}
tolerance=${TOLERANCE:-25}

report() {
    awk -F'\t' -v warmup="$warmup" -v tol="$tolerance" '
        {
            t = $1; n = $2; v = $3 / 1024.0
            if (!(n in first)) { order[++k] = n; first[n] = v }
            if (t <= warmup || !(n in warm)) warm[n] = v
            if (v > max[n]) max[n] = v
            c = ++cnt[n]; ts[n, c] = t; vs[n, c] = v
            last[n] = v; last_t = t
        }
        END {
            printf "\n%-12s %10s %12s %10s %12s %14s %8s\n", "MiB", "start", "after " warmup " s", "max", \
                "end (" last_t " s)", "MiB/min 2nd half", "bounded"
            bad = 0
            for (i = 1; i <= k; i++) {
                n = order[i]
                for (j = 1; j <= cnt[n] && ts[n, j] < last_t / 2; j++) {}
                slope = (ts[n, cnt[n]] > ts[n, j]) ? (vs[n, cnt[n]] - vs[n, j]) * 60.0 / (ts[n, cnt[n]] - ts[n, j]) : 0
                ok = (last[n] <= warm[n] * (1 + tol / 100.0) + 8) ? "yes" : "NO"
                if (ok == "NO") bad++
                printf "%-12s %10.1f %12.1f %10.1f %12.1f %14.2f %8s\n", n, first[n], warm[n], max[n], last[n], slope, ok
            }
            printf "\nverdict: %s (end within %d %% + 8 MiB of the value after %d s of warm-up)\n", \
                bad ? bad " value(s) NOT bounded" : "bounded", tol, warmup
        }' "$1"
}
if [ "${1:-}" = "--report" ]; then
    report "$2"
    exit 0
fi

duration=${1:-300}
interval=${2:-5}
legs=${LEGS:-40}

cargo build --release --workspace --bins >&2
dir=$(mktemp -d /tmp/slam-soak.XXXXXX)
prefix="soak$$_"
sup_pid=""
cleanup() {
    if [ -n "$sup_pid" ] && kill -0 "$sup_pid" 2>/dev/null; then
        kill -TERM "$sup_pid" 2>/dev/null || true
        wait "$sup_pid" 2>/dev/null || true
    fi
    if [ "${KEEP:-0}" != 1 ]; then rm -rf "$dir"; else echo "run directory kept: $dir" >&2; fi
}
trap cleanup EXIT

# The default config with this run's [run] table and the longer mission.
{
    cat <<EOF
[run]
out_dir = "$dir/out"
end = "duration"
duration_s = $duration
iceoryx_prefix = "$prefix"
iceoryx_root = "$dir/iox"
status_interval_s = 5.0

EOF
    sed -n '/^\[processes\./,$p' config/default.toml
    cat <<EOF

[processes.ingest.settings.sim.mission]
legs = $legs
leg_spacing_m = 0.0
max_duration_s = 100000.0
EOF
} >"$dir/soak.toml"

./target/release/supervisor --config "$dir/soak.toml" >"$dir/supervisor.log" 2>&1 &
sup_pid=$!
echo "soak: ${duration} s, sampling every ${interval} s, mission of ${legs} legs over one strip; log $dir/supervisor.log" >&2

samples="$dir/samples.tsv" # t_s name rss_kib
t0=$(date +%s)
while kill -0 "$sup_pid" 2>/dev/null; do
    t=$(($(date +%s) - t0))
    for pid in $(pgrep -P "$sup_pid" || true); do
        name=$(tr '\0' '\n' <"/proc/$pid/cmdline" 2>/dev/null | sed -n '/^--name$/{n;p;q}' || true)
        rss=$(awk '/^VmRSS:/ {print $2}' "/proc/$pid/status" 2>/dev/null || true)
        [ -n "$name" ] && [ -n "$rss" ] && printf '%s\t%s\t%s\n' "$t" "$name" "$rss" >>"$samples"
    done
    rss=$(awk '/^VmRSS:/ {print $2}' "/proc/$sup_pid/status" 2>/dev/null || true)
    [ -n "$rss" ] && printf '%s\tsupervisor\t%s\n' "$t" "$rss" >>"$samples"
    shm=$( (du -sk /dev/shm/"$prefix"* 2>/dev/null || true) | awk '{s += $1} END {print s + 0}')
    printf '%s\t/dev/shm\t%s\n' "$t" "$shm" >>"$samples"
    sleep "$interval"
done
status=0
wait "$sup_pid" || status=$?
sup_pid=""
left=$(ls /dev/shm | grep -c "^$prefix" || true)

echo
echo "soak: supervisor exit code $status (0 = the run lasted its ${duration} s), /dev/shm files left: $left"
grep -E "ingest\] progress" "$dir/supervisor.log" | tail -1 | sed 's/.*progress/ingest progress at the end:/' || true
report "$samples"
if [ "$left" -ne 0 ]; then
    echo "soak: $left file(s) of the run left in /dev/shm" >&2
    exit 1
fi
