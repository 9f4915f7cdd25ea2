#!/usr/bin/env python3
"""How close the uncertainty from standing columns comes to that of every column, where samples read between rows.

With ``geometry.parallax`` set, the fit's final uncertainty is computed on ``dfxcorr.fit.UNCERTAINTY_COLUMNS``
columns spread by their information, each standing for its stratum of all (``dfxcorr.subsets.standing_columns``):
the between-rows Fisher information costs about 100 ns per sample. For each scan below this script
reconstructs with the parallax set, takes the observations, parameters and weights of the fit's final uncertainty,
and computes it again on every column; it records, per effect, each frame's standard error from the standing
columns over every column's (median, range, RMS deviation from 1, over the frames finite in both; and how many are
finite in only one), and the seconds of each (one run each, the load average beside them). Scans: the parallax
simulation (configs/parallax-simulation.yaml, 204 columns) and the paper's study (configs/paper-simulation.yaml,
510 columns) with the same parallax in the simulation.
Writes docs/uncertainty-columns.json.

Usage: python scripts/uncertainty_columns.py [--parallax 0.02] [--out docs/]
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from dfxcorr import config as C
from dfxcorr import fit as F
from dfxcorr import pipeline
from dfxcorr.analysis.compare import machine
from dfxcorr.sim import simulate as S

ROOT = Path(__file__).resolve().parents[1]
SCANS = {"parallax simulation": "parallax-simulation.yaml", "paper study": "paper-simulation.yaml"}


def compare(scan, kappa: float) -> dict:
    """Reconstruct ``scan`` with ``geometry.parallax=kappa``; the final uncertainty from standing columns against
    every column's, per effect."""
    taken: list[tuple] = []
    uncertainty = F.uncertainty

    def keep(obs, params, weights):
        if obs.reading is not None:
            taken.append((obs, params, weights))
        return uncertainty(obs, params, weights)
    F.uncertainty = keep
    try:
        pipeline.reconstruct(scan, C.load([], [f"geometry.parallax={kappa}"]), progress=False)
    finally:
        F.uncertainty = uncertainty
    if not taken:
        raise SystemExit(f"geometry.parallax={kappa}: the fit computed no uncertainty between rows")
    obs, params, weights = taken[-1]
    t0 = time.perf_counter()
    standing = F.uncertainty(obs, params, weights)
    seconds = time.perf_counter() - t0
    most = F.UNCERTAINTY_COLUMNS
    F.UNCERTAINTY_COLUMNS = obs.columns.size
    try:
        t0 = time.perf_counter()
        every = F.uncertainty(obs, params, weights)
        every_seconds = time.perf_counter() - t0
    finally:
        F.UNCERTAINTY_COLUMNS = most
    out = {"columns": int(obs.columns.size), "standing_columns": min(most, int(obs.columns.size)),
           "seconds": {"standing": round(seconds, 3), "every column": round(every_seconds, 3)}, "ratio": {}}
    for name in params:
        a, b = np.isfinite(every[name]), np.isfinite(standing[name])
        r = standing[name][a & b] / every[name][a & b]
        out["ratio"][name] = {"median": float(np.median(r)), "min": float(r.min()), "max": float(r.max()),
                              "rms_deviation": float(np.sqrt(np.mean((r - 1) ** 2))), "frames": int(r.size),
                              "finite_in_one_only": int(np.count_nonzero(a != b))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parallax", type=float, default=0.02, help="kappa, in the simulation and the setting")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    record = {"machine": machine(), "parallax": args.parallax, "scans": {}}
    for name, config in SCANS.items():
        sim = C.load([ROOT / "configs" / config], [f"effects.parallax={args.parallax}"], schema=S.SCHEMA)
        scan, _ = S.simulate(sim)
        record["scans"][name] = {"shape": list(scan.shape), **compare(scan, args.parallax),
                                 "load_average": round(os.getloadavg()[0], 2)}
        print(name, json.dumps(record["scans"][name]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "uncertainty-columns.json").write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()
