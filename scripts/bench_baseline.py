#!/usr/bin/env python3
"""This checkout against a reference version, on the paper's simulation study, in one run.

The reference (default :data:`BASELINE`: dfxcorr's first version, the paper's method in numpy/scipy before the
compiled kernels; the speed anchor proper is ``../shared/bench/``, ``scripts/benchmark.py targets``) is exported
with ``git archive`` and installed into its own virtual environment under ``--work``; this checkout
runs from the environment that runs the script. The paper's study (209 frames of 450 x 510,
``configs/paper-simulation.yaml``) is simulated once, then both versions reconstruct it in
alternation, ``--runs`` times each, as separate processes under ``/usr/bin/time`` (wall time and
peak resident memory of the whole process, start-up included). Cases: each version at its own
defaults, and both at ``fit.subsample=20`` (the reference's default). Prints and writes medians,
ratios and the machine to ``--out``/bench-baseline.json.

Usage: python scripts/bench_baseline.py [--ref 8a55ae67a752] [--runs 3] [--work /tmp/dfx-bench] [--out docs/]
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

from dfxcorr.analysis.compare import machine

ROOT = Path(__file__).resolve().parents[1]
CASES = {"defaults": [], "fit.subsample=20": ["--set", "fit.subsample=20"]}
#: dfxcorr's first version, the paper's method in numpy/scipy: the last commit without compiled kernels, frames held in
#: memory.
BASELINE = "8a55ae67a752f7ac14bc59aa8c1bb0bdcdbba0d9"


def reference_env(ref: str, work: Path) -> Path:
    """The ``dfxcorr`` executable of ``ref``, installed into its own venv (built once, then reused)."""
    exe = work / f"venv-{ref}" / "bin" / "dfxcorr"
    if exe.exists():
        return exe
    src = work / f"src-{ref}"
    src.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
    subprocess.run([sys.executable, "-m", "venv", str(work / f"venv-{ref}")], check=True)
    subprocess.run([str(work / f"venv-{ref}" / "bin" / "pip"), "install", "-q", str(src)], check=True)
    return exe


def head_commit() -> str:
    """The commit this checkout is at (benchmark.py targets uses the ratio only if it was measured there)."""
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], check=True, capture_output=True,
                          text=True).stdout.strip()


def timed(cmd: list[str]) -> tuple[float, float]:
    """Wall seconds and peak resident MiB of one process (GNU time)."""
    fmt = "%e %M"
    proc = subprocess.run(["/usr/bin/time", "-f", fmt, *cmd], capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
    wall, rss_kib = proc.stderr.strip().splitlines()[-1].split()
    return float(wall), int(rss_kib) / 1024


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ref", default=BASELINE)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--work", type=Path, default=Path("/tmp/dfx-bench"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    current = shutil.which("dfxcorr")
    if current is None:
        sys.exit("dfxcorr is not installed in this environment (pip install -e .)")
    reference = str(reference_env(args.ref, args.work))
    scan = args.work / "paper-study.h5"
    if not scan.exists():
        subprocess.run([current, "-q", "simulate", str(ROOT / "configs" / "paper-simulation.yaml"), "-o", str(scan)],
                       check=True)
    # one untimed run each: the current version compiles its kernels into the on-disk cache here
    versions = {args.ref: reference, "this checkout": current}
    runs: dict = {case: {v: [] for v in versions} for case in CASES}
    for case, sets in CASES.items():
        for exe in versions.values():
            out = args.work / "warm.h5"
            timed([exe, "-q", "reconstruct", str(scan), "-o", str(out), "--overwrite", *sets])
        for r in range(args.runs):
            for label, exe in versions.items():
                out = args.work / f"out-{r}.h5"
                wall, rss = timed([exe, "-q", "reconstruct", str(scan), "-o", str(out), "--overwrite", *sets])
                runs[case][label].append({"seconds": wall, "peak_rss_mib": round(rss)})
                print(f"{case:>18} | {label:>14} | run {r + 1}: {wall:.1f} s, {rss:.0f} MiB", flush=True)
    summary = {}
    for case in CASES:
        med = {label: statistics.median(x["seconds"] for x in runs[case][label]) for label in versions}
        summary[case] = {"median_seconds": med, "ratio_this_over_ref": round(med["this checkout"] / med[args.ref], 3),
                         "peak_rss_mib": {label: max(x["peak_rss_mib"] for x in runs[case][label])
                                          for label in versions}}
        print(f"{case}: median {med[args.ref]:.1f} s ({args.ref}) -> {med['this checkout']:.1f} s, "
              f"ratio {summary[case]['ratio_this_over_ref']}")
    doc = {"machine": machine(), "scan": "paper study, 209 x 450 x 510 (configs/paper-simulation.yaml)",
           "reference": args.ref, "commit": head_commit(), "runs": runs, "summary": summary}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench-baseline.json").write_text(json.dumps(doc, indent=2) + "\n")


if __name__ == "__main__":
    main()
