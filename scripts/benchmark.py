#!/usr/bin/env python3
"""Wall time and memory of ``reconstruct``: the paper's study, or the clinical scanner's files.

Target ``paper`` (default) simulates the paper's study (209 frames of 450 x 510) in memory once, then
reconstructs it
- with the defaults,
- with every 20th column (``fit.subsample=20``): what subsampling saves,
- with the paper's diagonal preconditioner (``fit.preconditioner=diagonal``): what whitening by the
  whole profiled Fisher information saves,
- without preconditioning (``fit.precondition=false``): what eq. 34 saves,
and reports seconds per stage, L-BFGS iterations and the ratios.

Target ``clinical`` simulates (once, into ``--dir``; never into the repository) the clinical scanner at
full resolution (configs/clinical.yaml: 195 frames of 2880 x 2880 uint16, 3.2 GB) and binned
(configs/clinical-binned.yaml: 1440 x 1440), then runs ``dfxcorr reconstruct`` on each file in a
subprocess under ``/usr/bin/time -v`` for wall time and peak resident memory, and the phi0 / phi1 /
v^s RMSE against the truth (median gauge over frames lighting half the active area). Targets: full
resolution under 60 s and 1.6 GB, binned under 15 s, RMSE within 0.004 rad.

Both print the machine and write its section of docs/benchmark.json (the other section is kept).

Target ``targets`` runs nothing: it prints every speed target of the clinical-scale work (issue 9) with
the figure measured for it and the machine, from docs/benchmark.json, docs/bench-baseline.json
(scripts/bench_baseline.py) and docs/bench-kernels.json (scripts/bench_kernels.py).

Usage: python scripts/benchmark.py [paper] [--pixel-mm 1.0] [--repeat 1] [--out docs/]
       python scripts/benchmark.py clinical --dir /tmp/dfx-bench [--cases binned full] [--set k=v ...]
       python scripts/benchmark.py targets [--out docs/]
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from dfxcorr import config as C
from dfxcorr import pipeline
from dfxcorr.analysis.compare import machine
from dfxcorr.analysis.evaluate import frames_lighting, vibration_rmse
from dfxcorr.export import SPEC_EFFECTS, read_result_h5
from dfxcorr.io import read_scan
from dfxcorr.sim import simulate as S

ROOT = Path(__file__).resolve().parents[1]

CASES = {"default": [], "every column": ["fit.subsample=1"], "every 20th column": ["fit.subsample=20"],
         "diagonal preconditioning (eq. 34)": ["fit.preconditioner=diagonal"],
         "no preconditioning": ["fit.precondition=false"]}
CLINICAL = {"binned": ROOT / "configs" / "clinical-binned.yaml", "full": ROOT / "configs" / "clinical.yaml"}


def measured(cmd: list[str]) -> tuple[float, float]:
    """Run a command; its wall time (s) and peak resident memory (MB), from /usr/bin/time -v if present."""
    t0 = time.perf_counter()
    if shutil.which("time") or Path("/usr/bin/time").exists():
        proc = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True, check=False)
        wall = time.perf_counter() - t0
        if proc.returncode:
            sys.exit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
        rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr).group(1))
        return wall, rss_kb / 1024
    import resource
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode:
        sys.exit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    # peak of the largest child so far: run one measured command per process
    return wall, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024


def clinical(args) -> dict:
    """Simulate (if missing) and reconstruct the clinical scans; wall time, peak memory and RMSE per case."""
    folder = args.dir.resolve()
    if folder == ROOT or ROOT in folder.parents:
        sys.exit(f"--dir {folder} is inside the repository; give a scratch folder such as /tmp/dfx-bench")
    folder.mkdir(parents=True, exist_ok=True)
    exe = [sys.executable, "-c", "from dfxcorr.cli import main; main()"]
    out = {}
    for case in args.cases:
        scan_path, result_path = folder / f"clinical-{case}.h5", folder / f"clinical-{case}.result.h5"
        truth_path = folder / f"clinical-{case}.truth.npz"
        entry = {}
        if not (scan_path.exists() and truth_path.exists()):
            print(f"simulating {scan_path} ...", flush=True)
            wall, rss = measured([*exe, "simulate", str(CLINICAL[case]), "-o", str(scan_path), "--truth",
                                  str(truth_path), "--overwrite"])
            entry["simulate"] = {"seconds": round(wall, 1), "peak_rss_mb": round(rss)}
        scan = read_scan(scan_path)
        entry["size"] = list(scan.shape)
        entry["file_gb"] = round(scan_path.stat().st_size / 1e9, 2)
        sets = [x for s in args.set for x in ("--set", s)]
        wall, rss = measured([*exe, "reconstruct", str(scan_path), "-o", str(result_path), "--overwrite", *sets])
        res = read_result_h5(result_path)
        # the file names effects as the results spec does (visibility), one value per frame
        params = {SPEC_EFFECTS.get(k, k): np.asarray(v).reshape(scan.shape[0], -1) for k, v in res["vibration"].items()}
        truth = dict(np.load(truth_path))
        good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
        entry.update(seconds=round(wall, 1), peak_rss_mb=round(rss),
                     stages={k: round(v, 2) for k, v in res["timings"].items()},
                     reduced_chi2=round(res["reduced_chi2"], 4),
                     rmse={k: round(v, 5) for k, v in vibration_rmse(params, truth, good).items()},
                     sets=args.set)
        out[case] = entry
        print(case, json.dumps(entry), flush=True)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("target", nargs="?", choices=("paper", "clinical", "targets"), default="paper")
    ap.add_argument("--pixel-mm", type=float, default=1.0, help="paper: pixel pitch of the simulated study (mm)")
    ap.add_argument("--repeat", type=int, default=1, help="paper: runs per case (the fastest counts)")
    ap.add_argument("--dir", type=Path, default=Path("/tmp/dfx-bench"), help="clinical: folder for the scans")
    ap.add_argument("--cases", nargs="+", choices=tuple(CLINICAL), default=list(CLINICAL), help="clinical: which")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="clinical: reconstruct option (repeatable)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    if args.target == "targets":
        targets(args.out)
        return
    info = machine()
    print(info, flush=True)
    doc_path = args.out / "benchmark.json"
    doc = json.loads(doc_path.read_text()) if doc_path.exists() else {}
    if "machine" in doc:  # the earlier layout held the paper target alone
        doc = {"paper": doc}
    if args.target == "clinical":
        doc["clinical"] = {"machine": info, "cases": clinical(args)}
    else:
        doc["paper"] = paper(args, info)
    args.out.mkdir(parents=True, exist_ok=True)
    doc_path.write_text(json.dumps(doc, indent=2))


def targets(folder: Path) -> None:
    """Print each target with its measured figure, the machine and whether it is met (from the saved JSON)."""
    def load(name):
        path = folder / name
        return json.loads(path.read_text()) if path.exists() else {}

    bench, base, kern = load("benchmark.json"), load("bench-baseline.json"), load("bench-kernels.json")
    rows = []
    clin = bench.get("clinical", {}).get("cases", {})
    if "full" in clin:
        c = clin["full"]
        worst = max(c["rmse"]["phase_offset"], c["rmse"]["tilt"])
        rows.append(("full resolution 195 x 2880 x 2880: < 60 s, <= 1.6 GB, phi0/phi1 RMSE < 0.004 rad",
                     f"{c['seconds']} s, {c['peak_rss_mb'] / 1000:.2f} GB, {worst:.4f} rad",
                     c["seconds"] < 60 and c["peak_rss_mb"] <= 1600 and worst < 0.004))
    if "binned" in clin:
        c = clin["binned"]
        rows.append(("binned 195 x 1440 x 1440: < 15 s", f"{c['seconds']} s", c["seconds"] < 15))
    for case, entry in base.get("summary", {}).items():
        sec = entry["median_seconds"]
        settings = "each at its own defaults" if case == "defaults" else case
        rows.append((f"paper study, {settings}, this / {base.get('reference')}: ratio <= 0.2",
                     f"{sec['this checkout']} / {sec[base.get('reference')]} s, ratio {entry['ratio_this_over_ref']}",
                     entry["ratio_this_over_ref"] <= 0.2))
    every = bench.get("paper", {}).get("cases", {}).get("every column")
    if every:
        rows.append(("paper study, fit.subsample=1: < 30 s", f"{every['seconds']} s (in memory)",
                     every["seconds"] < 30))
    for key, label in (("paper_every_column", "paper study, every column"), ("clinical_fit_columns", "clinical fit")):
        if key in kern:
            k = kern[key]
            rows.append((f"ns per sample, {label}: cost+gradient / retrieval (CPU) against the bandwidth floor",
                         f"{k['cost_gradient']['cpu_ns_per_sample']} / {k['retrieval']['cpu_ns_per_sample']} ns "
                         f"against {k['cost_gradient']['floor_ns_per_sample']} / "
                         f"{k['retrieval']['floor_ns_per_sample']} ns", None))
    print("machine:", bench.get("clinical", {}).get("machine") or bench.get("paper", {}).get("machine"),
          "| kernels:", kern.get("machine"))
    for what, figure, met in rows:
        print(f"{what}\n    measured {figure}: {'-' if met is None else 'met' if met else 'NOT met'}")


def paper(args, info: dict) -> dict:
    """The paper's study in memory: seconds per stage, iterations and RMSE of the cases of :data:`CASES`."""
    sim = C.load([ROOT / "configs" / "paper-simulation.yaml"], [f"simulate.pixel_mm={args.pixel_mm}"],
                 schema=S.SCHEMA)
    scan, truth = S.simulate(sim)
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    out = {"machine": info, "size": list(scan.shape), "cases": {}}
    for name, sets in CASES.items():
        best = None
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            result = pipeline.reconstruct(scan, C.load([], sets), progress=False)
            seconds = time.perf_counter() - t0
            if best is None or seconds < best["seconds"]:
                best = {"seconds": round(seconds, 2), "stages": {k: round(v, 2) for k, v in result.timings.items()},
                        "iterations": int(result.cost.size), "reduced_chi2": round(result.reduced_chi2, 4),
                        "rmse": {k: round(v, 5) for k, v in vibration_rmse(result.params, truth, good).items()}}
        out["cases"][name] = best
        print(name, json.dumps(best), flush=True)
    ref = out["cases"]["default"]
    out["ratios"] = {f"{k} / default": round(v["seconds"] / ref["seconds"], 2) for k, v in out["cases"].items()
                     if k != "default"}
    print(json.dumps(out["ratios"]))
    return out


if __name__ == "__main__":
    main()
