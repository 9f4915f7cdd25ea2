#!/usr/bin/env python3
"""The paper's evaluation (Figs. 4, 6, 7, 8, 11 and a results table), reproduced on the simulation study.

Every figure is a subcommand; ``all`` runs them in turn and shares scans and reconstructions between
them. The default pitch of 2.5 mm (180 x 204 pixels, 209 frames, 30 per pixel) runs in a few minutes
on two cores; ``--pixel-mm 1`` is the paper's full size (450 x 510 pixels). Outputs go to ``--out``
(default docs/) with the pitch in their names: PNG figures and JSON with the numbers.

    python scripts/paper_figures.py all                 # everything at 2.5 mm
    python scripts/paper_figures.py fig6 --pixel-mm 1   # one figure at full size

fig4   images before and after correction (paper Fig. 4)
fig6   cost per iteration: ML with and without preconditioning (eq. 34 and dfxcorr's profiled one), alternating
       (Fig. 6, Sec. III-C)
fig7   dark field: no correction, phase only, phase and v^s (Fig. 7, Sec. III-D.1)
fig8   the correlation method on the thorax and on a slab of constant attenuation (Fig. 8, Sec. III-D.2)
fig11  noise power spectra of blank scans for none / correlation / ml (Fig. 11, Sec. III-D.4)
table  every method against the truth (RMSE of vibration parameters and images)
"""
from __future__ import annotations

import argparse
import functools
import json
import logging
import time
from pathlib import Path

import numpy as np

from dfxcorr import config as C
from dfxcorr import pipeline, plots
from dfxcorr.align import build_observations
from dfxcorr.analysis import compare as CMP
from dfxcorr.analysis.evaluate import frames_lighting, image_rmse, vibration_rmse
from dfxcorr.baselines import fit_alternating
from dfxcorr.catalogue import neutral_params
from dfxcorr.fit import fit_vibrations, initial_weights
from dfxcorr.reference import resolve_reference
from dfxcorr.result import Result
from dfxcorr.sim import simulate as S

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "sim"
log = logging.getLogger("paper_figures")

#: Per-method options of the figures: the correlation method is cheap and meant for every column.
METHOD_SETS = {"correlation": ["fit.subsample=1"]}


# --------------------------------------------------------------------------------------------------
# Shared scans and reconstructions (cached, so that ``all`` computes each once)
# --------------------------------------------------------------------------------------------------


@functools.cache
def simulated(pixel_mm: float, seed: int, sets: tuple = ()):
    """(scan, truth) of the paper's simulation study (configs/paper-simulation.yaml) with overrides."""
    cfg = C.load([ROOT / "configs" / "paper-simulation.yaml"],
                 [f"simulate.pixel_mm={pixel_mm}", f"simulate.seed={seed}", *sets], schema=S.SCHEMA)
    return S.simulate(cfg)


@functools.cache
def reconstructed(pixel_mm: float, seed: int, sim_sets: tuple = (), sets: tuple = ()) -> tuple[Result, float]:
    """(Result, wall seconds) of :func:`simulated` reconstructed with the default configuration and ``sets``."""
    scan, _ = simulated(pixel_mm, seed, sim_sets)
    t0 = time.perf_counter()
    res = pipeline.reconstruct(scan, C.load([], ["retrieve.uncorrected=true", *sets]),
                               command_line="scripts/paper_figures.py")
    return res, time.perf_counter() - t0


def images_of(res: Result) -> dict:
    return {k: res.image(k) for k in Result.IMAGES}


def truth_images(truth: dict) -> dict:
    return {k: truth[f"image_{k}"] for k in Result.IMAGES}


def good_frames(scan) -> np.ndarray:
    return frames_lighting(scan.position, scan.active_rows, scan.shape[1])


def write_json(args, name: str, numbers: dict) -> Path:
    path = args.out / f"{name}-{args.pixel_mm:g}mm.json"
    doc = {"pixel_mm": args.pixel_mm, "seed": args.seed, "machine": CMP.machine(), **numbers}
    path.write_text(json.dumps(doc, indent=2, default=float))
    log.info("wrote %s", path)
    return path


def png(args, name: str) -> Path:
    return args.out / f"{name}-{args.pixel_mm:g}mm.png"


def size_text(scan) -> str:
    J, H, W = scan.shape
    return f"{H} x {W} pixels, {J} frames"


# --------------------------------------------------------------------------------------------------
# The figures
# --------------------------------------------------------------------------------------------------


def fig4(args) -> dict:
    """Images before and after correction (paper Fig. 4), with the truth above."""
    scan, truth = simulated(args.pixel_mm, args.seed)
    res, seconds = reconstructed(args.pixel_mm, args.seed)
    plots.plot_images(png(args, "fig4-images"), [("truth", truth_images(truth)), ("uncorrected", res.uncorrected),
                                              ("corrected (ml)", images_of(res))],
                    window_row=2, overwrite=True,
                    title=f"Fig. 4: simulation study at {args.pixel_mm:g} mm ({size_text(scan)})")
    numbers = {"size": list(scan.shape), "reconstruct_s": seconds,
               "image_rmse": {"uncorrected": image_rmse(res.uncorrected, truth), "corrected": image_rmse(
                   images_of(res), truth)},
               "vibration_rmse": vibration_rmse(res.params, truth, good_frames(scan))}
    write_json(args, "fig4", numbers)
    return numbers


def fig6(args) -> dict:
    """Cost per iteration on linear displacements only (paper Sec. III-C): ML with and without
    preconditioning and alternating optimisation, all columns, no circular-mean stage, no staging."""
    scan, truth = simulated(args.pixel_mm, args.seed, ("effects.tilt=0", "effects.visibility_loss=0"))
    obs = build_observations(scan, resolve_reference(scan))
    effects = ("phase_offset",)
    weights = initial_weights(obs, neutral_params(effects, obs.n_frames))
    # the plain estimators of the paper's comparison: no prior, no reweighting, one stage
    common = dict(effects=effects, weights=weights, reweight=0, maxiter=args.iterations, gtol=1e-7)
    runs = {"ML, preconditioned (eq. 34)": lambda: fit_vibrations(obs, **common, circmean_iterations=0, staged=False,
                                                                   prior=False, preconditioner="diagonal"),
            "ML, whitened by the profiled Fisher information (dfxcorr's default)": lambda: fit_vibrations(
                obs, **common, circmean_iterations=0, staged=False, prior=False, preconditioner="profiled"),
            "ML, not preconditioned": lambda: fit_vibrations(obs, **common, circmean_iterations=0, staged=False,
                                                             prior=False, precondition=False),
            "alternating": lambda: fit_alternating(obs, **common)}
    fits, numbers = {}, {"size": list(scan.shape), "samples": int(obs.use.sum()), "methods": {}}
    for label, run in runs.items():
        t0 = time.perf_counter()
        fits[label] = run()
        seconds = time.perf_counter() - t0
        numbers["methods"][label] = {"iterations": fits[label].iterations, "seconds": seconds,
                                     "seconds_per_iteration": seconds / max(fits[label].iterations, 1),
                                     "final_cost": float(fits[label].cost[-1]), "messages": fits[label].messages}
    best = min(float(f.cost.min()) for f in fits.values())
    good = good_frames(scan)
    for label, f in fits.items():
        excess = f.cost - best
        entry = numbers["methods"][label]
        entry["final_excess"] = float(excess[-1])
        for level in (1e3, 10.0, 1.0):
            hit = np.flatnonzero(excess <= level)
            entry[f"iterations_to_excess_{level:g}"] = int(hit[0] + 1) if hit.size else None
        entry["vibration_rmse"] = vibration_rmse(f.params, truth, good)
        ref = fits["ML, not preconditioned"].params["phase_offset"][:, 0]
        entry["frames_differing_from_unpreconditioned_ml_by_0.1_rad"] = np.flatnonzero(
            np.abs(np.angle(np.exp(1j * (f.params["phase_offset"][:, 0] - ref)))) > 0.1).tolist()
    numbers["optimum"] = best
    plots.plot_convergence(png(args, "fig6-convergence"), {k: (f.cost, f.stage) for k, f in fits.items()},
                         reference=best, whole=False, overwrite=True,
                         title=f"Fig. 6: linear displacements only (φ1 = 0, v^s = 1),\nevery column, "
                               f"{size_text(scan)}")
    write_json(args, "fig6", numbers)
    return numbers


def fig7(args) -> dict:
    """Dark field with no correction, with phases only, and with phases and v^s (paper Fig. 7)."""
    scan, truth = simulated(args.pixel_mm, args.seed)
    variants = {"no correction": ("fit.method=none",), "φ0, φ1 only": ("vibration.visibility=false",),
                "φ0, φ1 and v^s": ()}
    rows = [("truth", truth_images(truth))]
    numbers = {"size": list(scan.shape), "dark_field_rmse": {}, "dark_field_rmse_lungs": {}}
    lung = truth["image_dark_field"] < 0.9
    for label, sets in variants.items():
        res, _ = reconstructed(args.pixel_mm, args.seed, (), sets)
        rows.append((label, images_of(res)))
        numbers["dark_field_rmse"][label] = image_rmse(images_of(res), truth)["dark_field"]
        numbers["dark_field_rmse_lungs"][label] = float(np.sqrt(np.nanmean(
            (res.dark_field - truth["image_dark_field"])[lung] ** 2)))
    H, W = scan.shape[1:]
    zoom = (slice(int(0.25 * H), int(0.75 * H)), slice(int(0.05 * W), int(0.5 * W)))
    for name, crop in (("fig7-dark-field", None), ("fig7-dark-field-zoom", zoom)):
        plots.plot_images(png(args, name), rows, names=("dark_field",), window_row=3, crop=crop, overwrite=True,
                        title=f"Fig. 7: dark field{' (zoom: right lung)' if crop else ''}, {size_text(scan)}")
    write_json(args, "fig7", numbers)
    return numbers


def fig8(args) -> dict:
    """The correlation method on the thorax and on a slab of constant attenuation (paper Fig. 8).

    As in the paper, no motion-induced visibility loss is simulated and no quadratic term fitted.
    """
    sim = ("effects.visibility_loss=0",)
    fit = ("vibration.visibility=false",)
    numbers, rows = {"vibration_rmse": {}, "image_rmse": {}}, []
    for phantom, label in (("thorax", "thorax"), ("slab", "constant attenuation")):
        scan, truth = simulated(args.pixel_mm, args.seed, sim + (f"simulate.phantom={phantom}",))
        numbers["size"] = list(scan.shape)
        for method in ("none", "correlation", "ml"):
            sets = fit + (f"fit.method={method}",) + tuple(METHOD_SETS.get(method, ()))
            res, _ = reconstructed(args.pixel_mm, args.seed, sim + (f"simulate.phantom={phantom}",), sets)
            key = f"{label}, {method}"
            numbers["vibration_rmse"][key] = vibration_rmse(res.params, truth, good_frames(scan))
            numbers["image_rmse"][key] = image_rmse(images_of(res), truth)
            if (phantom, method) != ("slab", "none"):
                rows.append((f"{label}: {'uncorrected' if method == 'none' else method}", images_of(res)))
    plots.plot_images(png(args, "fig8-correlation"), rows, names=("dark_field",), window_row=2, overwrite=True,
                    title="Fig. 8: the correlation method [18] (dark field, −ln v)")
    plots.plot_images(png(args, "fig8-correlation-phase"), rows, names=("differential_phase",), window_row=2,
                    overwrite=True, title="Fig. 8 (differential phase)")
    write_json(args, "fig8", numbers)
    return numbers


def fig11(args) -> dict:
    """Noise power spectra of blank scans for none / correlation / ml (paper Fig. 11).

    Also without motion-induced visibility loss (v^s = 1 simulated, not fitted), which the correlation
    method does not model: that separates its error in the grating positions from the missing v^s.
    """
    blank = ("simulate.phantom=blank",)
    still = ("effects.visibility_loss=0",)
    cases = [(f"fig11-nps-{args.pixel_mm:g}mm", [simulated(args.pixel_mm, args.seed + k, blank)[0]
                                                 for k in range(args.scans)],
              f"{args.scans} simulated blank scans", C.defaults()),
             (f"fig11-nps-no-visibility-loss-{args.pixel_mm:g}mm",
              [simulated(args.pixel_mm, args.seed + k, blank + still)[0] for k in range(min(args.scans, 2))],
              f"{min(args.scans, 2)} blank scans without v^s", C.load([], ["vibration.visibility=false"]))]
    shared = SHARED / "blank-2.5mm.h5"
    if args.pixel_mm == 2.5 and shared.exists():
        cases.append(("fig11-nps-shared-blank-2.5mm", [shared], "shared/data/sim/blank-2.5mm.h5", C.defaults()))
    out = {}
    for name, items, what, cfg in cases:
        study = CMP.nps_study(items, cfg, methods=CMP.NPS_METHODS, method_sets=METHOD_SETS, bins=args.bins,
                              command_line="scripts/paper_figures.py")
        CMP.write_nps(args.out / name, study, overwrite=True,
                      title=f"Fig. 11: binned radial NPS of blank dark-field images,\n{what}")
        out[name] = {"fringe_frequency": study["fringe_frequency"], "bins": study["frequency"].size,
                     "power": CMP.fringe_power(study), "runtime_s": study["runtime_s"]}
    write_json(args, "fig11", out)
    return out


def table(args) -> dict:
    """Every method against the truth, on the simulation study and on the shared thorax scan."""
    from dfxcorr.io import read_scan

    cases = [("simulation study", *simulated(args.pixel_mm, args.seed), f"table-{args.pixel_mm:g}mm")]
    shared = SHARED / "thorax-2.5mm.h5"
    if args.pixel_mm == 2.5 and shared.exists():
        scan = read_scan(shared)
        cases.append(("shared/data/sim/thorax-2.5mm.h5 (independent simulator)", scan,
                      CMP.load_truth(shared.with_suffix(".truth.npz"), scan.shape), "table-shared-thorax-2.5mm"))
    out = {}
    for what, scan, truth, name in cases:
        results, runtimes = CMP.run_methods(scan, C.defaults(), methods=CMP.METHODS, method_sets=METHOD_SETS,
                                            command_line="scripts/paper_figures.py")
        CMP.write_comparison(args.out / name, scan, results, runtimes, truth=truth, source=what, result_files=False,
                             overwrite=True)
        out[name] = CMP.comparison_table(results, runtimes, scan=scan, truth=truth)
    write_json(args, "table", out)
    return out


FIGURES = {"fig4": fig4, "fig6": fig6, "fig7": fig7, "fig8": fig8, "fig11": fig11, "table": table}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("figure", choices=[*FIGURES, "all"])
    ap.add_argument("--pixel-mm", type=float, default=2.5, help="detector pitch (1 = the paper's full size)")
    ap.add_argument("--seed", type=int, default=101, help="simulation seed (fig11: the first of --scans seeds)")
    ap.add_argument("--scans", type=int, default=4, help="fig11: number of blank scans")
    ap.add_argument("--iterations", type=int, default=300, help="fig6: iterations per method")
    ap.add_argument("--bins", type=int, help="fig11: radial bins (default: rings f/4 wide, f the fringe frequency)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s", datefmt="%H:%M:%S")
    logging.getLogger("dfxcorr").setLevel(logging.WARNING)
    args.out.mkdir(parents=True, exist_ok=True)
    for name in FIGURES if args.figure == "all" else [args.figure]:
        t0 = time.perf_counter()
        numbers = FIGURES[name](args)
        log.info("%s: %.0f s\n%s", name, time.perf_counter() - t0, json.dumps(numbers, indent=1, default=float)[:3000])


if __name__ == "__main__":
    main()
