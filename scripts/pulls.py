#!/usr/bin/env python3
"""Are the reported uncertainties of phi0 and phi1 right? Pulls over noise realisations.

The pull of a frame is its error against the truth over the standard error the fit reports, the truth carried
into the estimate's gauge by the median difference over the frames lighting half the active area
(:func:`dfxcorr.analysis.evaluate.vibration_pulls`); their RMS is 1 where the error bars are right. (Each put in its
own median gauge instead, the frame at the median of both carries its error into every other: pulls of 1.16-1.38
on these scans.) The RMSE beside them is :func:`dfxcorr.analysis.evaluate.vibration_rmse`'s, each in its own median
gauge as the project's other records have it. The errors of neighbouring frames are correlated (they share
pixels), so one scan's RMS over its frames varies from one noise realisation to the next; this script simulates
each case with several seeds (into ``--dir``, never into the repository), reconstructs each at the defaults and
with every ``--set`` given, and records the per-seed RMS and the RMS pooled over all seeds' frames.
Writes docs/pulls.json.

Usage: python scripts/pulls.py --dir /tmp/dfx-bench [--cases paper binned] [--seeds 1 2 3 4 5 6]
       [--set fit.target_uncertainty=0.0025] [--out docs/]
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from dfxcorr import config as C
from dfxcorr import pipeline
from dfxcorr.analysis.compare import machine
from dfxcorr.analysis.evaluate import _aligned_errors, _gauged_errors, frames_lighting
from dfxcorr.sim import simulate as S

ROOT = Path(__file__).resolve().parents[1]
CASES = {"paper": ROOT / "configs" / "paper-simulation.yaml", "binned": ROOT / "configs" / "clinical-binned.yaml",
         "full": ROOT / "configs" / "clinical.yaml"}
EFFECTS = ("phase_offset", "tilt")


def scan_of(case: str, seed: int, folder: Path) -> tuple[Path, Path]:
    """The scan and truth of ``case`` simulated with ``seed`` (made in ``folder`` once)."""
    path, truth = folder / f"pulls-{case}-s{seed}.h5", folder / f"pulls-{case}-s{seed}.truth.npz"
    if not (path.exists() and truth.exists()):
        cfg = C.load([str(CASES[case])], [f"simulate.seed={seed}"], schema=S.SCHEMA)
        _, true = S.simulate_file(cfg, path, overwrite=True)
        np.savez_compressed(truth, **true)
    return path, truth


def pulls(path: Path, truth_path: Path, sets: list[str]) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Each effect's pulls over the gauge frames, and its RMSE, of one reconstruction."""
    from dfxcorr.io import read_scan

    scan = read_scan(path)
    t = np.load(truth_path)
    truth = {k: t[k] for k in t.files}
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    result = pipeline.reconstruct(scan, C.load([], sets), progress=False)
    err, gauged = _aligned_errors(result.params, truth, good), _gauged_errors(result.params, truth, good)
    z, rmse = {}, {}
    for name in EFFECTS:
        se = np.asarray(result.uncertainty[name])[:, 0]
        ok = good & np.isfinite(se) & (se > 0)
        z[name] = err[name][ok] / se[ok]
        rmse[name] = float(np.sqrt(np.mean(gauged[name][good] ** 2)))
    return z, rmse


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dir", type=Path, default=Path("/tmp/dfx-bench"))
    ap.add_argument("--cases", nargs="+", choices=tuple(CASES), default=["paper", "binned"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="a setting reconstructed beside the defaults (repeatable: one setting each)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    folder = args.dir.resolve()
    if folder == ROOT or ROOT in folder.parents:
        raise SystemExit(f"--dir {folder} is inside the repository; give a scratch folder such as /tmp/dfx-bench")
    folder.mkdir(parents=True, exist_ok=True)
    record: dict = {"machine": machine(), "seeds": args.seeds, "cases": {}}
    t0 = time.perf_counter()
    for case in args.cases:
        settings: dict[str, list[str]] = {"defaults": [], **{s: [s] for s in args.set}}
        out: dict = {}
        pooled: dict[str, dict[str, list[np.ndarray]]] = {k: {n: [] for n in EFFECTS} for k in settings}
        for seed in args.seeds:
            path, truth = scan_of(case, seed, folder)
            for label, sets in settings.items():
                z, rmse = pulls(path, truth, sets)
                row = {n: round(float(np.sqrt(np.mean(z[n] ** 2))), 3) for n in EFFECTS}
                out.setdefault(label, {"per_seed": [], "rmse": []})
                out[label]["per_seed"].append(row)
                out[label]["rmse"].append({n: round(v, 6) for n, v in rmse.items()})
                for n in EFFECTS:
                    pooled[label][n].append(z[n])
                print(case, seed, label, row, flush=True)
        for label in settings:
            out[label]["pooled"] = {n: round(float(np.sqrt(np.mean(np.concatenate(pooled[label][n]) ** 2))), 3)
                                    for n in EFFECTS}
        record["cases"][case] = out
        print(case, json.dumps({k: v["pooled"] for k, v in out.items()}), flush=True)
    record["seconds"] = round(time.perf_counter() - t0, 1)
    record["load_average_after"] = round(os.getloadavg()[0], 2)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "pulls.json").write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
