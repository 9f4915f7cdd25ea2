#!/usr/bin/env python3
"""Wall time of ``reconstruct`` on a clinical-size scan, against references measured in the same run.

Simulates the paper's study (209 frames of 450 x 510 by default) once, then reconstructs it
- with the defaults (every 20th column, preconditioned),
- without column subsampling (``fit.subsample=1``): what subsampling saves,
- without preconditioning (``fit.precondition=false``): what eq. 34 saves,
and reports seconds per stage, L-BFGS iterations and the ratios. Writes docs/benchmark.json.

Usage: python scripts/benchmark.py [--pixel-mm 1.0] [--repeat 1] [--out docs/]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

from dfxcorr import config as C
from dfxcorr import pipeline
from dfxcorr.analysis.evaluate import frames_lighting, vibration_rmse
from dfxcorr.sim import simulate as S

ROOT = Path(__file__).resolve().parents[1]

CASES = {"default": [], "no subsampling": ["fit.subsample=1"], "no preconditioning": ["fit.precondition=false"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pixel-mm", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    sim = C.load([ROOT / "configs" / "paper-simulation.yaml"], [f"simulate.pixel_mm={args.pixel_mm}"],
                 schema=S.SCHEMA)
    scan, truth = S.simulate(sim)
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    out = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.system()}, "
                      f"python {platform.python_version()}", "size": list(scan.shape), "cases": {}}
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
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "benchmark.json").write_text(json.dumps(out, indent=2))
    print(json.dumps(out["ratios"]))


if __name__ == "__main__":
    main()
