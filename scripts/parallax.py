#!/usr/bin/env python3
"""Beam paths that change during the scan: what beam_path finds and what its correction recovers.

For each kappa a scan is simulated with a source that travels with the gratings (the simulator evaluates the
phantom where each frame sees it, :mod:`dfxcorr.sim.simulate`) together with its twin without parallax (the same
seeds). The scan is diagnosed, then reconstructed at the defaults and with the recommended setting
(``geometry.parallax`` = the kappa found); the twin at the defaults. Each reconstruction's reduced chi-square,
transmission error, ln dark-field error (median difference removed) and differential-phase error (mean removed)
against the truth, and the seconds it took, are recorded.

The floor: images on the pixel grid describe what a pixel sees between two rows by interpolating their images.
The record gives, for displacements of a tenth and three tenths of a row, the mean squared difference between the
phantom evaluated displaced and that interpolation, in photon-noise units at the scan's flux, over the rows where
the phantom is (``interpolation_z2``; with cubic convolution between four rows ``interpolation_z2_cubic``): what
no model on the pixel grid removes; and the factor by which the
interpolation's change of the pixels under a displacement stands to the exact change (``interpolation_scale``, for
linear interpolation, the model's, and for cubic convolution): a kappa whose displacements stay within a fraction
of a row is found about that factor times the true one (whole rows of displacement the interpolation reads
exactly).
Writes docs/parallax.json.

Usage: python scripts/parallax.py [--kappas 0.02 0.05] [--pixel-mm 5] [--out docs/]
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from dfxcorr import config as C
from dfxcorr import engine as E
from dfxcorr import model as M
from dfxcorr.align import to_detector_rows
from dfxcorr.analysis.compare import machine
from dfxcorr.analysis.diagnose import diagnose
from dfxcorr.analysis.evaluate import frames_lighting, vibration_pulls, vibration_rmse
from dfxcorr.effects import REGISTRY
from dfxcorr.pipeline import prepare, reconstruct
from dfxcorr.sim import phantom
from dfxcorr.sim import simulate as S

ROOT = Path(__file__).resolve().parents[1]


def sim_config(pixel_mm: float, **overrides) -> dict:
    """The small scan (``pixel_mm`` pixels, one row per frame, edges averaged over 8 x 8 points) with ``overrides``."""
    cfg = C.defaults(S.SCHEMA)
    cfg["simulate"].update(pixel_mm=pixel_mm, step_mm=pixel_mm, supersample=8, seed=11)
    for key, value in overrides.items():
        section, name = key.split(".")
        cfg = C.merge(cfg, {section: {name: value}}, schema=S.SCHEMA)
    return cfg


def errors(result, truth: dict) -> dict[str, float]:
    """Errors of a reconstruction's images against the truth where the sample transmits more than 5 %."""
    ok = (truth["image_transmission"] > 0.05) & np.isfinite(result.transmission) & (result.dark_field > 0)
    t = result.transmission[ok] - truth["image_transmission"][ok]
    lv = np.log(result.dark_field[ok]) - np.log(truth["image_dark_field"][ok])
    dp = np.angle(np.exp(1j * (result.differential_phase[ok] - truth["image_differential_phase"][ok])))
    return {"transmission": float(np.sqrt(np.mean(t ** 2))),
            "ln_dark_field": float(np.sqrt(np.mean((lv - np.median(lv)) ** 2))),
            "differential_phase": float(np.sqrt(np.mean((dp - np.mean(dp)) ** 2)))}


def timed_reconstruct(scan, cfg, truth) -> dict:
    t0 = time.perf_counter()
    r = reconstruct(scan, cfg)
    seconds = time.perf_counter() - t0
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    return {"seconds": seconds, "reduced_chi2": float(r.reduced_chi2), "errors": errors(r, truth),
            "vibration_rmse": vibration_rmse(r.params, truth, good),
            "vibration_pulls": vibration_pulls(r.params, r.uncertainty, truth, good)}


def _cubic_convolution(x: np.ndarray) -> np.ndarray:
    """Keys' cubic convolution kernel (a = -1/2) at distances ``x`` (rows)."""
    x = np.abs(x)
    return np.where(x <= 1, 1.5 * x ** 3 - 2.5 * x ** 2 + 1,
                    np.where(x < 2, -0.5 * x ** 3 + 2.5 * x ** 2 - 4 * x + 2, 0.0))


def interpolation_floor(cfg: dict, shape: tuple[int, int]) -> tuple[dict[str, dict[str, float]], dict[str, float]]:
    """What images on the pixel grid miss of a displaced phantom (its transmission), from its exact evaluation.

    Returns
    -------
    z2 : dict
        Mean squared (exact displaced - interpolated) in photon-noise units, per displacement (0.1, 0.3), for linear
        interpolation (the model's) and for cubic convolution.
    scale : dict
        The least-squares factor between the exact change of the pixels and the change the interpolation predicts,
        over displacements of -0.3 to 0.3 rows, for linear interpolation (the model's) and for cubic convolution: a
        kappa whose displacements stay within a fraction of a row comes out about that factor times the true one.
    """
    s = cfg["simulate"]
    H, W = shape
    rows = np.arange(2, H - 2)
    kw = {"shape": (H, W), "pixel_mm": s["pixel_mm"], "magnification": s["magnification"],
          "supersample": s["supersample"]}
    still = phantom.thorax(**kw)["transmission"]
    z2: dict[str, dict[str, float]] = {"linear": {}, "cubic convolution": {}}
    for d in (0.1, 0.3):
        seen = phantom.thorax(rows=rows, shift=d, **kw)["transmission"]
        between = {"linear": (1 - d) * still[rows] + d * still[rows + 1],
                   "cubic convolution": sum(_cubic_convolution(d - m) * still[rows + m] for m in (-1, 0, 1, 2))}
        inside = seen > 0.05
        for name, x in between.items():
            z2[name][f"{d:g}"] = float(np.mean(((seen - x) ** 2 / (seen / s["flux"]))[inside]))
    sums = {"linear": [0.0, 0.0], "cubic convolution": [0.0, 0.0]}
    for d in np.linspace(-0.3, 0.3, 13):
        if d == 0:
            continue
        change = phantom.thorax(rows=rows, shift=d, **kw)["transmission"] - still[rows]
        lo, f = int(np.floor(d)), d - np.floor(d)
        predicted = {"linear": (1 - f) * still[rows + lo] + f * still[rows + lo + 1] - still[rows],
                     "cubic convolution": sum(_cubic_convolution(f - m) * still[rows + lo + m]
                                              for m in (-1, 0, 1, 2)) - still[rows]}
        for name, x in predicted.items():
            sums[name][0] += float(np.sum(x * change))
            sums[name][1] += float(np.sum(x * x))
    return z2, {name: num / den for name, (num, den) in sums.items()}


def grid_errors(scan, truth: dict, sim: dict, kappa: float) -> dict[str, float]:
    """Where the transmission error of a reconstruction at the true kappa comes from, over the pixels where the
    sample transmits more than 5 %: its images on their own grid (what each pixel sees with the active area centred
    on it, :attr:`dfxcorr.align.LitStore.parallax`) against the phantom evaluated there (``on_grid``), and that
    phantom resampled to the detector's rows as the result is (:func:`dfxcorr.align.to_detector_rows`) against the
    truth (``resampled_truth``): an error no fit on that grid avoids."""
    cfg = C.merge(C.defaults(), {"geometry": {"parallax": kappa}})
    result = reconstruct(scan, cfg)
    prep = prepare(scan, cfg, effects=REGISTRY.values())
    obs = prep.observations(columns=np.arange(prep.shape[2]))
    solved = E.retrieve(obs, M.channels(result.params, x=obs.x, n_frames=obs.n_frames), iterations=2)
    H, W = prep.shape[1:]
    s = sim["simulate"]
    kw = {"shape": (H, W), "pixel_mm": s["pixel_mm"], "magnification": s["magnification"],
          "supersample": s["supersample"]}
    # grid row r shows the sample where an undisplaced detector's row r + kappa (r - c_0) sees it
    there = np.array([phantom.thorax(rows=np.array([r]), shift=kappa * (r - (H - 1) / 2), **kw)["transmission"][0]
                      for r in range(H)])
    ok = (there > 0.05) & solved["valid"]
    back = to_detector_rows(np.repeat(there[..., None], 3, axis=-1), kappa)[..., 0]
    inside = truth["image_transmission"] > 0.05
    return {"on_grid": float(np.sqrt(np.mean((solved["coef"][..., 0] - there)[ok] ** 2))),
            "resampled_truth": float(np.sqrt(np.nanmean((back - truth["image_transmission"])[inside] ** 2)))}


def cells_floor(cfg: dict, shape: tuple[int, int], *, cells: tuple[int, ...] = (1, 2, 3, 4), every: int = 3
                ) -> dict[str, float]:
    """What images finer than the pixel grid would leave of the displaced phantom.

    An image of ``m`` cells per row, each pixel the mean of the cells under it where the frame sees it, is fitted by
    least squares to the phantom's transmission seen at displacements of -0.3 to 0.3 rows, all at once (m = 1 is the
    model's reading between rows, its images fitted to every displacement rather than taken from the undisplaced
    phantom). A second-difference ridge of 1e-6 picks one of the patterns no pixel sees (m - 1 of them, periodic over
    a row).

    Parameters
    ----------
    cfg : dict
        The simulation's configuration (:func:`sim_config`).
    shape : tuple of int
        Detector (H rows, W columns).
    cells : tuple of int
        The m tried.
    every : int
        Every ``every``-th column is fitted.

    Returns
    -------
    dict of str to float
        Per m (as a string), the mean z^2 left, photon-noise units at the scan's flux, over the rows 4 to H - 5.
    """
    s = cfg["simulate"]
    H, W = shape
    rows = np.arange(4, H - 4)
    kw = {"shape": (H, W), "pixel_mm": s["pixel_mm"], "magnification": s["magnification"],
          "supersample": s["supersample"]}
    shifts = np.linspace(-0.3, 0.3, 13)
    seen = np.concatenate([phantom.thorax(rows=rows, shift=d, **kw)["transmission"] for d in shifts])
    out = {}
    for m in cells:
        # rows: (displacement, pixel row); columns: the cells; each entry the share of the pixel a cell covers
        A = np.zeros((shifts.size * rows.size, H * m))
        for i, (d, u) in enumerate((d, u) for d in shifts for u in rows):
            lo, hi = (u + d) * m, (u + d + 1) * m
            for k in range(int(np.floor(lo)), int(np.ceil(hi))):
                A[i, k] = (min(hi, k + 1) - max(lo, k)) / m
        ridge = 1e-6 * np.diff(np.eye(H * m), 2, axis=0)
        z2 = []
        for c in range(0, W, every):
            b = seen[:, c]
            if np.all(b > 0.999):
                continue
            sw = np.sqrt(s["flux"] / np.maximum(b, 1e-6))
            x = np.linalg.lstsq(np.vstack([A * sw[:, None], ridge]), np.concatenate([b * sw, np.zeros(len(ridge))]),
                                rcond=None)[0]
            z2.append(float(np.mean(((A @ x - b) * sw) ** 2)))
        out[str(m)] = float(np.mean(z2))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kappas", type=float, nargs="+", default=[0.02, 0.05])
    ap.add_argument("--pixel-mm", type=float, default=5.0)
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    rows = []
    for kappa in args.kappas:
        scan, truth = S.simulate(sim_config(args.pixel_mm, **{"effects.parallax": kappa}))
        twin, twin_truth = S.simulate(sim_config(args.pixel_mm))
        t0 = time.perf_counter()
        diag = diagnose(scan, C.defaults())
        seconds = time.perf_counter() - t0
        found = [e for e in diag.effects if e.detected]
        beam = next((e for e in found if e.name == "beam_path"), None)
        kappa_found = beam.values["value"] if beam is not None else 0.0
        row = {"kappa": kappa, "shape": list(scan.shape),
               "diagnose": {"found": [e.name for e in found], "seconds": seconds,
                            "kappa": kappa_found, "se": beam.values["se"] if beam is not None else None,
                            "reduced_chi2": [diag.initial_chi2, diag.final_chi2],
                            "unexplained": [u.axis for u in diag.unexplained]},
               "defaults": timed_reconstruct(scan, C.defaults(), truth),
               "recommended": timed_reconstruct(scan, C.merge(C.defaults(), {"geometry": {"parallax": kappa_found}}),
                                                truth),
               "twin": timed_reconstruct(twin, C.defaults(), twin_truth),
               "transmission_at_true_kappa": grid_errors(scan, truth, sim_config(args.pixel_mm), kappa)}
        print(json.dumps(row))
        rows.append(row)
    H, W = scan.shape[1:]
    z2, scale = interpolation_floor(sim_config(args.pixel_mm), (H, W))
    record = {"machine": machine(), "load_average_after": os.getloadavg()[0], "pixel_mm": args.pixel_mm,
              "flux": sim_config(args.pixel_mm)["simulate"]["flux"],
              "interpolation_z2": z2["linear"], "interpolation_z2_cubic": z2["cubic convolution"],
              "interpolation_scale": scale, "cells_z2": cells_floor(sim_config(args.pixel_mm), (H, W)), "runs": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "parallax.json").write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()
