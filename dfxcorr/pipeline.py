"""The reconstruct pipeline: load -> align -> mask -> fit -> retrieve, each stage a thin wrapper.

Stages log what they did and how long it took; the numerical work is in the stage modules. Use from
Python::

    from dfxcorr import config, pipeline
    result = pipeline.reconstruct("scan.h5", config.load(["my.yaml"]))
"""
from __future__ import annotations

import datetime
import hashlib
import logging
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from . import __version__
from . import config as C
from . import model as M
from .align import (
    auto_visibility_threshold,
    build_observations,
    resolve_reference,
    subsample_columns,
    tilt_alias_period,
)
from .analysis import identify
from .baselines import fit_alternating, fit_correlation
from .errors import DfxcorrError
from .fit import FitResult, fit_vibrations, initial_weights
from .io import Scan, read_scan
from .mask import motion_mask
from .progress import Progress
from .result import Result, paper_params
from .retrieve import image_maps, retrieve

log = logging.getLogger(__name__)


class IdentifiabilityError(DfxcorrError, ValueError):
    """An effect was asked for that the acquisition cannot determine."""


@contextmanager
def stage(name: str, timings: dict):
    """Log the start and duration of a stage and record it in ``timings``."""
    log.info("%s ...", name)
    t0 = time.perf_counter()
    yield
    timings[name] = time.perf_counter() - t0
    log.info("%s: %.2f s", name, timings[name])


def sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def separable_flat_field(reference, *, tol: float = 1e-3) -> bool:
    """True if the flat field cannot tell per-frame visibility loss from the images (paper eq. 48).

    That is the case when t^f and v^f do not change along the scan direction and the flat-field phase is
    f(column) + a * row with one slope a for all columns.
    """
    A = reference.transmission.shape[0]
    if A < 2:
        return True
    phase = np.unwrap(reference.phase, axis=0)
    u = np.arange(A) - (A - 1) / 2
    slope = np.sum(u[:, None] * (phase - phase.mean(axis=0))) / (np.sum(u ** 2) * phase.shape[1])
    resid = phase - phase.mean(axis=0) - slope * u[:, None]
    flat = [np.std(m, axis=0).max() / np.abs(m).mean() for m in (reference.transmission, reference.visibility)]
    return bool(np.sqrt(np.mean(resid ** 2)) < tol and max(flat) < tol)


def visibility_unidentifiable(scan: Scan, reference) -> str | None:
    """Why per-frame visibility loss cannot be told apart from the images here, or None (paper Sec. II-F)."""
    if scan.is_stepping:
        why = ("in a phase-stepping recording the flat field is the same in every frame, so a per-frame "
               "visibility loss trades off exactly against the transmission and dark-field images (paper Sec. II-F)")
    elif separable_flat_field(reference):
        why = ("the flat-field phase of this scan is separable (paper eq. 48) and t^f, v^f do not vary along the "
               "scan, so per-frame visibility loss cannot be told apart from the images")
    else:
        why = None
    return why


def resolve_effects(cfg: dict, scan: Scan, reference, fit_obs: M.Observations) -> tuple[str, ...]:
    """The effects to fit: the configured ones that this acquisition can determine.

    Every enabled effect is checked in turn against the Fisher information of the fit's samples
    (:mod:`dfxcorr.analysis.identify`); visibility effects in a stepping recording or over a separable flat
    field are refused with the paper's reason. An effect set to ``auto`` is dropped with a log line.

    Raises
    ------
    IdentifiabilityError
        If the configuration explicitly asks for an effect the acquisition cannot determine.
    """
    keys = {e: k for k, e in C.VIBRATION_EFFECTS.items()}

    def refuse_or_drop(name, why):
        if cfg["vibration"][keys[name]] is True:
            raise IdentifiabilityError(f"{name} is not identifiable here: {why}; set vibration.{keys[name]}=false"
                                       + (" (or auto)" if name == "visibility_loss" else ""))
        log.info("%s is not fitted: %s", name, why)

    paper_why = visibility_unidentifiable(scan, reference)
    names = []
    for name in C.effects_of(cfg):
        if paper_why and name in ("visibility_loss", "visibility_tilt"):
            refuse_or_drop(name, paper_why)
        else:
            names.append(name)
    chosen: list[str] = []
    for verdict in identify.select(fit_obs, initial_weights(fit_obs, {}), names):
        if verdict.identifiable:
            chosen.append(verdict.name)
        else:
            refuse_or_drop(verdict.name, f"the Fisher information of this acquisition has {verdict.excess} "
                                         f"direction(s) of its parameters without information beyond its gauge "
                                         f"(they trade off exactly against the images"
                                         f"{' or ' + ', '.join(chosen) if chosen else ''})")
    return tuple(chosen)


def fit_columns(width: int, cfg: dict) -> np.ndarray:
    """Columns entering the vibration fit, with the aliasing limit of paper Sec. II-D.1 checked."""
    n = cfg["fit"]["subsample"]
    cols = subsample_columns(width, n, offset=cfg["fit"]["column_offset"])
    if cols.size < 4:
        raise C.ConfigError(f"fit.subsample={n} leaves {cols.size} of {width} columns; use at most {width // 4}")
    period = tilt_alias_period(width, n)
    if period < 4 * np.pi:
        raise C.ConfigError(f"fit.subsample={n}: tilts that differ by {period:.2f} rad are indistinguishable on "
                            f"every {n}-th of {width} columns (paper Sec. II-D.1); use at most {width // 4}")
    return cols


def reconstruct(scan: Scan | str | Path, cfg: dict | None = None, *, command_line: str = "",
                progress: bool | None = None) -> Result:
    """Vibration-corrected transmission, dark-field and differential-phase images of a scan.

    Parameters
    ----------
    scan : Scan or path
        The acquisition, or the path of a scan file.
    cfg : dict, optional
        Resolved configuration (:func:`dfxcorr.config.load`); default: the defaults.
    command_line : str
        Recorded in the provenance.
    progress : bool, optional
        Force the progress display on or off (default: on a terminal only).

    Returns
    -------
    Result
    """
    cfg = C.defaults() if cfg is None else cfg
    timings: dict[str, float] = {}
    path = None
    if not isinstance(scan, Scan):
        path = Path(scan)
        with stage("load", timings):
            scan = read_scan(path, allow_external=cfg["load"]["allow_external"])
            log.info("scan %s: %d frames of %d x %d, active area %d rows%s", path.name, *scan.shape,
                     scan.active_rows, ", phase stepping" if scan.is_stepping else "")
    method = cfg["fit"]["method"]
    gain = cfg["load"]["gain"] or scan.gain
    with stage("align", timings):
        step_effects = tuple(e for e, on in (("phase_offset", cfg["reference"]["step_errors"]),
                                             ("dose", cfg["reference"]["dose"])) if on is not False)
        reference = resolve_reference(scan, effects=step_effects,
                                      optional=("dose",) if cfg["reference"]["dose"] == "auto" else ())
        obs = build_observations(scan, reference, min_frames=cfg["align"]["min_frames"], gain=gain)
        obs.electronic = cfg["load"]["electronic"]
        vmin = cfg["align"]["min_visibility"]
        vmin = auto_visibility_threshold(reference.visibility) if vmin == "auto" else vmin
        # samples without fringe carry transmission only (v^f = 0 there): no images (NaN), but in the fit
        # they monitor dose and background
        roi = obs.vf >= vmin
        obs.vf = np.where(roi, obs.vf, 0.0)
        left_out = obs.segment_sum(roi.astype(float)) == 0
        if left_out.any():
            log.info("region of interest: %d pixels see no fringe (reference visibility < %.3g) and are left out "
                     "of the images", int(left_out.sum()), vmin)
    moving = np.zeros(scan.shape[1:], bool)
    with stage("mask", timings):
        if cfg["mask"]["enabled"] and method != "none":
            moving, _, thr = motion_mask(obs, threshold=cfg["mask"]["threshold"], sigma=cfg["mask"]["sigma"],
                                         dilate=cfg["mask"]["dilate"])
            # the score assumes a fringe; pixels without one only monitor dose and background
            moving &= obs.to_image(obs.segment_sum(roi.astype(float)), fill=0.0) > 0
            log.info("motion mask: %d pixels above %.3g left out of the vibration fit", int(moving.sum()), thr)
    with stage("fit", timings):
        fitted, fit_mask, effects = run_fit(obs, scan, reference, cfg, moving, progress=progress)
    obs.use = roi
    with stage("retrieve", timings):
        rec = retrieve(obs, fitted.params, iterations=cfg["retrieve"]["iterations"])
        maps = image_maps(obs, rec.images)
        uncorrected = None
        if cfg["retrieve"]["uncorrected"] and method != "none":
            uncorrected = image_maps(obs, retrieve(obs, {}, iterations=cfg["retrieve"]["iterations"]).images)
        log.info("reduced chi-square of the final model: %.4f", rec.reduced_chi2)
    # the paper's three parameters are always reported, at their neutral value where not estimated
    params = paper_params(fitted.params, scan.shape[0])
    uncertainty = {**{n: np.full_like(p, np.inf) for n, p in params.items()}, **fitted.uncertainty}
    estimated = {n: (n in effects and n in fitted.params and method != "none") for n in params}
    provenance = {"program": "dfxcorr", "version": __version__,
                  "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                  "command_line": command_line, "input_file": str(path) if path else "",
                  "input_sha256": sha256(path) if path else "",
                  "external_files": "\n".join(f"{sha256(p)}  {p}" for p in scan.external_files)}
    return Result(transmission=maps["transmission"], dark_field=maps["dark_field"],
                  differential_phase=maps["differential_phase"], params=params, estimated=estimated,
                  uncertainty=uncertainty, fit_mask=fit_mask, motion_mask=moving.astype(np.uint8),
                  cost=fitted.cost, cost_stage=fitted.stage, reduced_chi2=rec.reduced_chi2, method=method,
                  config=cfg, provenance=provenance, uncorrected=uncorrected, timings=timings)


def run_fit(obs: M.Observations, scan: Scan, reference, cfg: dict, moving: np.ndarray, *,
            progress: bool | None = None) -> tuple[FitResult, np.ndarray, tuple[str, ...]]:
    """Estimate the per-frame parameters with the configured method.

    Returns
    -------
    FitResult
    fit_mask : ndarray of uint8, shape (H, W)
        1 where the pixel entered the fit.
    effects : tuple of str
        The effects fitted (the configured ones this acquisition can determine).
    """
    method = cfg["fit"]["method"]
    J = scan.shape[0]
    fit_mask = np.zeros(scan.shape[1:], np.uint8)
    if method == "none":
        params = paper_params({}, J)
        unc = {k: np.full_like(v, np.inf) for k, v in params.items()}
        return FitResult(params=params, uncertainty=unc, cost=np.zeros(0), stage=[], iterations=0,
                         converged=True), fit_mask, ()
    if method not in FIT_METHODS:
        raise C.ConfigError(f"fit.method={method!r} is not available; available: {', '.join(FIT_METHODS)}, none")
    cols = np.searchsorted(obs.columns, fit_columns(scan.shape[2], cfg))
    fit_obs = obs.subset(cols)
    fit_obs.use = fit_obs.use & ~moving[fit_obs.row][:, fit_obs.columns]
    effects = resolve_effects(cfg, scan, reference, fit_obs)
    used = fit_obs.segment_sum(fit_obs.use.astype(np.float64)) > 0
    fit_mask[np.ix_(fit_obs.rows, fit_obs.columns)] = used
    log.info("vibration fit (%s): %s on %d columns, %d pixels, %d frames", method, ", ".join(effects),
             fit_obs.columns.size, int(used.sum()), J)
    f = cfg["fit"]
    with Progress("vibration fit", unit="iterations", enabled=progress) as bar:
        def tick(stage_name, cost):
            bar.update(1, status=f"{stage_name} cost {cost:.6g}")
        result = FIT_METHODS[method](fit_obs, effects=effects, circmean_iterations=f["circmean_iterations"],
                                     staged=f["staged"], maxiter=f["maxiter"], gtol=f["gtol"],
                                     precondition=f["precondition"], reweight=f["reweight"],
                                     visibility_gauge=f["visibility_gauge"],
                                     visibility_quantile=f["visibility_quantile"],
                                     gauge_fraction=f["gauge_fraction"], on_iteration=tick)
    if "tilt" in result.params and result.well_determined is not None:
        period = tilt_alias_period(scan.shape[2], f["subsample"])
        worst = float(np.abs(result.params["tilt"][result.well_determined]).max())
        if worst > period / 4:
            log.warning("fitted tilts reach %.2f rad, a quarter of the alias period %.2f rad of fit.subsample=%d: "
                        "reduce fit.subsample", worst, period, f["subsample"])
    if not result.converged:
        log.warning("the vibration fit stopped before converging (%s)", "; ".join(result.messages))
    for name in result.params:
        if M.effect(name).per_frame and result.well_determined is not None:
            good = result.well_determined
            log.info("  %s: std %.4g over %d well-determined frames, median uncertainty %.2g", name,
                     float(np.std(result.params[name][good])), int(good.sum()),
                     float(np.median(result.uncertainty[name][good])))
    return result, fit_mask, effects


#: The estimator of each ``fit.method`` (:data:`dfxcorr.config.METHODS`) but 'none'.
FIT_METHODS = {"ml": fit_vibrations, "alternating": fit_alternating, "correlation": fit_correlation}
