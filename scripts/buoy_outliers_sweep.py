#!/usr/bin/env python3
"""Runs the heavy-outlier pipeline mission (config/buoy_outliers.toml) over simulator seeds, each
three ways, and prints the buoy EKF's ATE per seed as a Markdown table with the ratios:

  with     the config as it is (15 % gross errors of 1-10 m, either sign)
  removed  the same mission with those ranges left out (`outliers_removed = true`: every other
           range is exactly as in "with"; the reference of issue 18, "the same filter with the
           outliers removed")
  clean    `outlier_probability = 0.0`: the outliers' places taken by good ranges (stricter: it
           also charges the loss of ~15 % of the ranges)

Usage (after `cargo build --release --workspace`):
  python3 scripts/buoy_outliers_sweep.py --seeds 1-40 [--jobs 1] [--keep DIR]

Each run gets its own iceoryx2 prefix and output directory (a temporary one, removed at the end
unless --keep). Needs only the Python standard library.
"""

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor

VARIANTS = ("with", "removed", "clean")


def seeds_arg(text):
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    return out


def variant_config(base, seed, variant, out_dir):
    """The config text for one run, or raises naming the line it could not find."""

    def sub(pattern, repl, text):
        new, n = re.subn(pattern, repl, text, count=1, flags=re.M)
        if n != 1:
            raise ValueError(f"config/buoy_outliers.toml: no line matching {pattern!r}")
        return new

    c = sub(r"^seed = \d+", f"seed = {seed}", base)
    c = sub(r'^iceoryx_prefix = ".*"', f'iceoryx_prefix = "bos{os.getpid()}_{variant[0]}{seed}_"', c)
    c = sub(r'^out_dir = ".*"', f'out_dir = "{out_dir}"', c)
    if variant == "removed":
        c = sub(r"^outliers_both_signs = true.*$", "outliers_both_signs = true\noutliers_removed = true", c)
    elif variant == "clean":
        c = sub(r"^outlier_probability = [0-9.]+", "outlier_probability = 0.0", c)
    return c


def run_one(args, base, root, seed, variant):
    d = os.path.join(root, f"{variant}-{seed}")
    os.makedirs(d, exist_ok=True)
    cfg = os.path.join(d, "config.toml")
    out = os.path.join(d, "out")
    with open(cfg, "w") as f:
        f.write(variant_config(base, seed, variant, out))
    with open(os.path.join(d, "log"), "w") as log:
        p = subprocess.run([args.bin, "--config", cfg, "--out", out], stdout=log, stderr=subprocess.STDOUT)
    if p.returncode != 0:
        raise RuntimeError(f"seed {seed} {variant}: the supervisor exited with {p.returncode} (log: {d}/log)")
    with open(os.path.join(out, "summary.json")) as f:
        s = json.load(f)
    b = s.get("buoy_ekf", {})
    return {
        "ate": s["ate_m"]["buoy_ekf"],
        "restarts": b.get("reinitialisations", 0),
        "start_corrections": b.get("start_corrections", 0),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=seeds_arg, default=seeds_arg("1-10"), help="e.g. 1-40 or 1,3,5-9")
    ap.add_argument("--config", default="config/buoy_outliers.toml")
    ap.add_argument("--bin", default="target/release/supervisor")
    ap.add_argument("--jobs", type=int, default=1, help="runs at once (each is a few processes)")
    ap.add_argument("--keep", help="keep every run's config, log and outputs under this directory")
    args = ap.parse_args()
    if not os.path.exists(args.bin):
        sys.exit(f"{args.bin} not found: run `cargo build --release --workspace` first")
    with open(args.config) as f:
        base = f.read()
    root = args.keep or tempfile.mkdtemp(prefix="buoy_outliers_sweep_")
    jobs = [(s, v) for s in args.seeds for v in VARIANTS]
    results = {}
    try:
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
            futures = {ex.submit(run_one, args, base, root, s, v): (s, v) for s, v in jobs}
            for n, (fut, key) in enumerate(futures.items(), 1):
                results[key] = fut.result()
                print(f"[{n}/{len(jobs)}] seed {key[0]} {key[1]}: ATE {results[key]['ate']:.3f} m", file=sys.stderr)
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)

    print("| seed | ATE with outliers (m) | removed (m) | clean (m) | with / removed | with / clean | re-starts | start corrections |")
    print("|---|---|---|---|---|---|---|---|")
    r_rem, r_cle = [], []
    for s in args.seeds:
        w, r, c = (results[(s, v)] for v in VARIANTS)
        a, b = w["ate"] / r["ate"], w["ate"] / c["ate"]
        r_rem.append(a)
        r_cle.append(b)
        print(
            f"| {s} | {w['ate']:.3f} | {r['ate']:.3f} | {c['ate']:.3f} | {a:.2f} | {b:.2f} "
            f"| {w['restarts']} | {w['start_corrections']} |"
        )
    mean = {v: statistics.mean(results[(s, v)]["ate"] for s in args.seeds) for v in VARIANTS}
    print(
        f"| mean | {mean['with']:.3f} | {mean['removed']:.3f} | {mean['clean']:.3f} "
        f"| {statistics.mean(r_rem):.2f} | {statistics.mean(r_cle):.2f} | | |"
    )
    for name, rs in (("removed", r_rem), ("clean", r_cle)):
        miss = [s for s, x in zip(args.seeds, rs) if x > 1.2]
        print(
            f"against {name}: {len(rs) - len(miss)} of {len(rs)} seeds within 1.2x, worst {max(rs):.2f}"
            + (f" (over: seeds {', '.join(map(str, miss))})" if miss else "")
        )


if __name__ == "__main__":
    main()
