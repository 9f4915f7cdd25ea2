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
from .align import build_observations, resolve_reference, subsample_columns, tilt_alias_period
from .fit import FitResult, fit_vibrations
from .io import Scan, read_scan
from .mask import motion_mask
from .progress import Progress
from .result import Result
from .retrieve import image_maps, retrieve

log = logging.getLogger("dfxcorr")


class IdentifiabilityError(ValueError):
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


def check_identifiable(scan: Scan, reference, effects) -> None:
    """Refuse effects the acquisition cannot determine (paper Sec. II-F).

    Raises
    ------
    IdentifiabilityError
    """
    asks = [e for e in effects if e in ("visibility_loss", "visibility_tilt")]
    if not asks:
        return
    if scan.is_stepping:
        why = ("in a phase-stepping recording the flat field is the same in every frame, so a per-frame "
               "visibility loss trades off exactly against the transmission and dark-field images (paper Sec. II-F)")
    elif separable_flat_field(reference):
        why = ("the flat-field phase of this scan is separable (paper eq. 48) and t^f, v^f do not vary along the "
               "scan, so per-frame visibility loss cannot be told apart from the images")
    else:
        return
    raise IdentifiabilityError(f"{', '.join(asks)} is not identifiable here: {why}; "
                               f"set vibration.visibility=false (and vibration.visibility_tilt=false)")


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


def region_of_interest(reference, scan: Scan, min_visibility: float) -> np.ndarray | None:
    """Pixels whose reference visibility reaches ``min_visibility`` (stepping recordings: the grating area)."""
    if min_visibility <= 0:
        return None
    if not scan.is_stepping:
        cols = reference.visibility.max(axis=0) >= min_visibility
        return np.broadcast_to(cols, scan.shape[1:]).copy()
    return reference.visibility >= min_visibility


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
            scan = read_scan(path)
            log.info("scan %s: %d frames of %d x %d, active area %d rows%s", path.name, *scan.shape,
                     scan.active_rows, ", phase stepping" if scan.is_stepping else "")
    effects = C.effects_of(cfg)
    method = cfg["fit"]["method"]
    gain = cfg["load"]["gain"] or scan.gain
    with stage("align", timings):
        reference = resolve_reference(scan)
        if method != "none":
            check_identifiable(scan, reference, effects)
        roi = region_of_interest(reference, scan, cfg["align"]["min_visibility"])
        if roi is not None:
            log.info("region of interest: %d of %d pixels have reference visibility >= %g", int(roi.sum()), roi.size,
                     cfg["align"]["min_visibility"])
        obs = build_observations(scan, reference, min_frames=cfg["align"]["min_frames"], pixel_mask=roi, gain=gain)
        if roi is not None:
            obs = _drop_unused(obs)
    moving = np.zeros(scan.shape[1:], bool)
    with stage("mask", timings):
        if cfg["mask"]["enabled"] and method != "none":
            moving, _, thr = motion_mask(obs, threshold=cfg["mask"]["threshold"], sigma=cfg["mask"]["sigma"],
                                         dilate=cfg["mask"]["dilate"])
            log.info("motion mask: %d pixels above %.3g left out of the vibration fit", int(moving.sum()), thr)
    with stage("fit", timings):
        fitted, fit_mask = run_fit(obs, scan, cfg, effects, moving, progress=progress)
    with stage("retrieve", timings):
        rec = retrieve(obs, fitted.params, iterations=cfg["retrieve"]["iterations"])
        maps = image_maps(obs, rec.images)
        uncorrected = None
        if cfg["retrieve"]["uncorrected"] and method != "none":
            uncorrected = image_maps(obs, retrieve(obs, {}, iterations=cfg["retrieve"]["iterations"]).images)
        log.info("reduced chi-square of the final model: %.4f", rec.reduced_chi2)
    estimated = {n: (n in effects and method != "none") for n in fitted.params}
    provenance = {"program": "dfxcorr", "version": __version__,
                  "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                  "command_line": command_line, "input_file": str(path) if path else "",
                  "input_sha256": sha256(path) if path else ""}
    return Result(transmission=maps["transmission"], dark_field=maps["dark_field"],
                  differential_phase=maps["differential_phase"], params=fitted.params, estimated=estimated,
                  uncertainty=fitted.uncertainty, fit_mask=fit_mask, motion_mask=moving.astype(np.uint8),
                  cost=fitted.cost, cost_stage=fitted.stage, reduced_chi2=rec.reduced_chi2, method=method,
                  config=cfg, provenance=provenance, uncorrected=uncorrected, timings=timings)


def _drop_unused(obs: M.Observations) -> M.Observations:
    """Keep only the columns with at least one usable sample (outside a region of interest nothing is solved)."""
    keep = np.flatnonzero(obs.use.any(axis=0))
    sub = obs.subset(keep)
    sub.counts = np.where(sub.use, sub.counts, 0.0)
    return sub


def run_fit(obs: M.Observations, scan: Scan, cfg: dict, effects, moving: np.ndarray, *,
            progress: bool | None = None) -> tuple[FitResult, np.ndarray]:
    """Estimate the per-frame parameters with the configured method.

    Returns
    -------
    FitResult
    fit_mask : ndarray of uint8, shape (H, W)
        1 where the pixel entered the fit.
    """
    method = cfg["fit"]["method"]
    J = scan.shape[0]
    fit_mask = np.zeros(scan.shape[1:], np.uint8)
    if method == "none":
        params = M.neutral_params(M.PAPER_MODEL, J)
        unc = {k: np.full_like(v, np.inf) for k, v in params.items()}
        return FitResult(params=params, uncertainty=unc, cost=np.zeros(0), stage=[], iterations=0,
                         converged=True), fit_mask
    if method not in FIT_METHODS:
        raise C.ConfigError(f"fit.method={method!r} is not available; available: {', '.join(FIT_METHODS)}, none")
    cols = np.searchsorted(obs.columns, fit_columns(scan.shape[2], cfg))
    fit_obs = obs.subset(cols)
    fit_obs.use = fit_obs.use & ~moving[fit_obs.row][:, fit_obs.columns]
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
    return result, fit_mask


#: Vibration estimators selectable by ``fit.method``.
FIT_METHODS = {"ml": fit_vibrations}
