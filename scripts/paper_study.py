#!/usr/bin/env python3
"""The paper's simulation study (Sec. III-A) end to end: the numbers of docs/paper-study.json.

Simulates ``configs/paper-simulation.yaml`` (full size 209 x 450 x 510 by default), reconstructs it
with the default configuration, and measures against the truth:

- RMSE of phi0, phi1 (rad) and v^s in the median gauge over frames lighting at least half the
  active area;
- the dark-field image against the one retrieved with the true vibration parameters, relative to the
  photon-noise level (RMS of that true-parameter image minus the noise-free truth);
- a PNG of uncorrected and corrected images (docs/paper-study.png).

Usage: python scripts/paper_study.py [--pixel-mm 1.0] [--out docs/]
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from dfxcorr import config as C
from dfxcorr import pipeline, plots
from dfxcorr.align import build_observations
from dfxcorr.analysis.evaluate import frames_lighting, image_rmse, vibration_rmse
from dfxcorr.reference import resolve_reference
from dfxcorr.retrieve import image_maps, retrieve
from dfxcorr.sim import simulate as S

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pixel-mm", type=float, default=1.0, help="detector pitch (1.0 = the paper's full size)")
    ap.add_argument("--seed", type=int, default=101)
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="reconstruct option section.key=value")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    sim_cfg = C.load([ROOT / "configs" / "paper-simulation.yaml"],
                     [f"simulate.pixel_mm={args.pixel_mm}", f"simulate.seed={args.seed}"], schema=S.SCHEMA)
    t0 = time.perf_counter()
    scan, truth = S.simulate(sim_cfg)
    t_sim = time.perf_counter() - t0
    cfg = C.load([], ['retrieve.uncorrected=true', *args.sets])
    t0 = time.perf_counter()
    result = pipeline.reconstruct(scan, cfg, command_line="scripts/paper_study.py")
    t_rec = time.perf_counter() - t0
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    vib = vibration_rmse(result.params, truth, good)

    obs = build_observations(scan, resolve_reference(scan))
    true_params = {"phase_offset": truth["vib_phase_offset"][:, None], "tilt": truth["vib_tilt"][:, None],
                   "visibility_loss": truth["vib_visibility"][:, None]}
    ideal = image_maps(obs, retrieve(obs, true_params, iterations=cfg["retrieve"]["iterations"]).images)
    lit = np.isfinite(ideal["dark_field"]) & np.isfinite(result.dark_field)
    noise = float(np.sqrt(np.mean((ideal["dark_field"] - truth["image_dark_field"])[lit] ** 2)))
    close = float(np.sqrt(np.mean((result.dark_field - ideal["dark_field"])[lit] ** 2)))
    # the same comparison per pixel, each difference in units of that pixel's photon noise (estimated
    # from the scatter of the ideal image around the truth in bins of transmission)
    t = truth["image_transmission"]
    bins = np.unique(np.quantile(t[lit], np.linspace(0, 1, 21)))
    which = np.clip(np.digitize(t, bins[1:-1]), 0, bins.size - 2)
    sigma = np.array([np.std((ideal["dark_field"] - truth["image_dark_field"])[lit & (which == b)])
                      for b in range(bins.size - 1)])
    z = ((result.dark_field - ideal["dark_field"]) / sigma[which])[lit]
    # the visibility gauge: our v^s relative to the true one (1 = same normalisation)
    gauge = float(np.median(result.params["visibility_loss"][good, 0] / truth["vib_visibility"][good]))
    unc = {"uncorrected": image_rmse(result.uncorrected, truth),
           "corrected": image_rmse({k: result.image(k) for k in result.IMAGES}, truth),
           "true parameters": image_rmse(ideal, truth)}
    numbers = {
        "machine": f"{platform.processor() or platform.machine()}, {platform.system()}, "
                   f"python {platform.python_version()}",
        "size": list(scan.shape), "pixel_mm": args.pixel_mm, "seed": args.seed,
        "simulate_s": round(t_sim, 1), "reconstruct_s": round(t_rec, 1),
        "timings_s": {k: round(v, 2) for k, v in result.timings.items()},
        "iterations": int(result.cost.size), "reduced_chi2": result.reduced_chi2,
        "rmse_vibration": vib, "well_determined_frames": int(good.sum()),
        "dark_field_vs_true_parameters": {"rms_difference": close, "photon_noise_rms": noise,
                                          "ratio": close / noise, "per_pixel_rms_z": float(np.sqrt(np.mean(z ** 2))),
                                          "per_pixel_mean_z": float(np.mean(z)),
                                          "visibility_gauge_ratio": gauge},
        "image_rmse_vs_truth": unc,
    }
    stem = "paper-study" if args.pixel_mm == 1.0 else f"paper-study-{args.pixel_mm:g}mm"
    (args.out / f"{stem}.json").write_text(json.dumps(numbers, indent=2))
    plots.write_preview(args.out / f"{stem}.png", result, overwrite=True,
                         title=f"paper simulation study, {scan.shape[1]} x {scan.shape[2]} pixels, "
                               f"{scan.shape[0]} frames")
    plots.write_fit_plot(args.out / f"{stem}-fit.png", result, overwrite=True)
    print(json.dumps(numbers, indent=2))


if __name__ == "__main__":
    main()
