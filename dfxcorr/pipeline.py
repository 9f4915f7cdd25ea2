"""The reconstruct pipeline: load -> align -> mask -> fit -> retrieve, each stage a thin wrapper.

Stages log what they did and how long it took; the numerical work is in the stage modules. Use from
Python::

    from dfxcorr import config, pipeline
    result = pipeline.reconstruct("scan.h5", config.load(["my.yaml"]))

Memory: the frames stay in the file; :func:`prepare` reads the lit rows of each frame once into a
:class:`~dfxcorr.align.LitStore` (counts in their stored dtype). The fit holds observations of its
columns only; the motion mask and the retrieval, where pixels are independent, go through the
detector in blocks of rows sized by ``retrieve.block_mb``.
"""
from __future__ import annotations

import datetime
import hashlib
import logging
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from . import __version__
from . import config as C
from . import model as M
from .align import tilt_alias_period
from .catalogue import effect
from .chunks import row_counts
from .effects import REGISTRY
from .estimators import ESTIMATORS
from .faults import MIN_KEPT_SHARE
from .fit import FitResult
from .io import Scan
from .mask import START_CHI2, motion_mask, start_misfit
from .observations import Observations
from .planning import ColumnPlan, pilot_estimate, plan_columns, resolve_effects, row_blocks
from .preparation import Prepared, prepare
from .progress import Progress, stage
from .result import Result, chi2_limits, paper_params
from .retrieve import detector_rows, image_values, per_dof, retrieve

log = logging.getLogger(__name__)


def sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def reconstruct(scan: Scan | str | Path | Prepared, cfg: dict | None = None, *, command_line: str = "",
                progress: bool | None = None) -> Result:
    """Vibration-corrected transmission, dark-field and differential-phase images of a scan.

    Parameters
    ----------
    scan : Scan, path or Prepared
        The acquisition, the path of a scan file, or a scan already prepared with the same configuration's
        ``load``, ``reference`` and ``align`` sections (:func:`prepare`).
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
    prep = scan if isinstance(scan, Prepared) else prepare(scan, cfg, effects=REGISTRY.values(), timings=timings)
    J, H, W = prep.shape
    method = cfg["fit"]["method"]
    blocks = row_blocks(prep.store, cfg["retrieve"]["block_mb"])
    log.info("retrieval and motion mask in %d block(s) of detector rows (retrieve.block_mb=%g)", len(blocks),
             cfg["retrieve"]["block_mb"])
    moving = np.zeros((H, W), bool)
    with stage("plan", timings):
        plan = plan_columns(prep, cfg) if method != "none" else None
    columns = np.zeros(0, int) if plan is None else plan.columns
    with stage("mask", timings):
        if plan is not None:
            moving = fit_motion_mask(prep, cfg, plan, blocks)
    with stage("fit", timings):
        fitted, fit_mask, effects = run_fit(prep, cfg, moving, columns=columns, progress=progress,
                                            coarse=1 if plan is None else plan.coarse,
                                            pilot=None if plan is None else plan.pilot)
    with stage("retrieve", timings):
        iterations = cfg["retrieve"]["iterations"]
        n_par = sum(np.size(p) for p in fitted.params.values())
        sets, counts = [fitted.params], [n_par]
        if cfg["retrieve"]["uncorrected"] and method != "none":
            sets, counts = [*sets, {}], [*counts, 0]
        (maps, chi2, dof), *rest = blocked_retrieval(prep, blocks, sets, iterations=iterations, n_params=counts)
        uncorrected = rest[0][0] if rest else None
        log.info("reduced chi-square of the final model: %.4f (%d degrees of freedom)", chi2, dof)
    # the paper's three parameters are always reported, at their neutral value where not estimated
    params = paper_params(fitted.params, J)
    uncertainty = {**{n: np.full_like(p, np.inf) for n, p in params.items()}, **fitted.uncertainty}
    estimated = {n: (n in effects and n in fitted.params and method != "none") for n in params}
    path = prep.path
    provenance = {"program": "dfxcorr", "version": __version__,
                  "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                  "command_line": command_line, "input_file": str(path) if path else "",
                  "input_sha256": sha256(path) if path else "",
                  "external_files": "\n".join(f"{sha256(p)}  {p}" for p in prep.scan.external_files)}
    result = Result(transmission=maps["transmission"], dark_field=maps["dark_field"],
                    differential_phase=maps["differential_phase"], params=params, estimated=estimated,
                    uncertainty=uncertainty, fit_mask=fit_mask, motion_mask=moving.astype(np.uint8),
                    cost=fitted.cost, cost_stage=fitted.stage, reduced_chi2=chi2, method=method,
                    config=cfg, provenance=provenance, uncorrected=uncorrected, timings=timings,
                    pixel_size=prep.scan.pixel_size, dof=dof)
    if result.misfit:
        lo, hi = chi2_limits(dof)
        log.warning("the reduced chi-square %.4g lies outside [%.3g, %.3g], what noise allows with %d degrees of "
                    "freedom: the model or its noise model does not fit this scan (a frame out of order or twice, "
                    "a wrong gain, a missing effect); run dfxcorr diagnose on it", chi2, lo, hi, dof)
    return result


def blocked_retrieval(prep: Prepared, blocks: list[tuple[int, int]], params: list[dict], *, iterations: int,
                      n_params: list[int]) -> list[tuple[dict[str, np.ndarray], float, int]]:
    """Images (H, W) of every pixel in its region of interest, block by block, the reduced chi-square and its degrees
    of freedom.

    One pass over the blocks serves every parameter set of ``params`` (e.g. the fitted and the neutral
    ones), so each block's observations are built once. The chi-square and its degrees of freedom are
    summed over blocks, so each result equals :func:`dfxcorr.retrieve.reduced_chi2` over the whole scan
    with that set's ``n_params`` per-frame parameters.

    The blocks are float32 observations, as the fit's, the pilot's and the motion mask's: a reconstruction
    then compiles each kernel for one dtype only (float64 variants would add about 14 s to a first run), and the
    images differ from a float64 retrieval by far less than their noise (the demo: 1e-4 of their spread).
    The expected counts and weights are not written (the images and the chi-square are all that is kept).
    """
    H, W = prep.shape[1:]
    maps = [{k: np.full((H, W), np.nan) for k in ("transmission", "dark_field", "differential_phase")}
            for _ in params]
    sums = np.zeros((len(params), 3))  # chi-square, samples, pixels
    left_out = 0
    # each parameter set's channel values at the columns of the last part: the blocks of rows share them (made for
    # every block, 0.8 s of a full-resolution retrieval)
    held: list[tuple[np.ndarray, M.Channels] | None] = [None] * len(params)
    for obs in retrieval_parts(prep, blocks):
        roi = obs.in_roi
        kept = row_counts(obs, obs.use) / np.diff(np.append(obs.starts, obs.frame.size))[:, None]
        obs = replace(obs, use=obs.use & roi & (kept >= MIN_KEPT_SHARE)[obs.pixel])
        for i, (m, p, acc) in enumerate(zip(maps, params, sums, strict=True)):
            last = held[i]
            if last is None or not np.array_equal(last[0], obs.columns):
                last = held[i] = (obs.columns, M.channels(p, x=obs.x, n_frames=obs.n_frames))
            rec = retrieve(obs, p, iterations=iterations, n_frame_params=0, keep_expected=False, channels=last[1])
            for k, v in image_values(rec.images).items():
                obs.place(m[k], v)
            acc += (rec.chi2_sum, rec.samples, int(rec.images.valid.sum()))
        left_out += int(np.count_nonzero(row_counts(obs, roi) == 0))
    if prep.store.parallax:
        maps = [detector_rows(m, prep.store.parallax) for m in maps]
    if left_out:
        log.info("region of interest: %d pixels see no fringe (reference visibility < %.3g) and are left out "
                 "of the images", left_out, prep.min_visibility)
    return [(m, per_dof(c, int(n), int(px), k, 3), max(int(n) - 3 * int(px) - k, 0))
            for m, (c, n, px), k in zip(maps, sums, n_params, strict=True)]


def retrieval_parts(prep: Prepared, blocks: list[tuple[int, int]]) -> Iterator[Observations]:
    """The float32 observations the retrieval goes through, one part at a time: the blocks of rows; or where the
    samples read the images between rows (``beam_path``: the images of a column are then one solve), as many runs
    of whole columns, each holding about a block's samples."""
    if not prep.store.parallax:
        for rows in blocks:
            yield prep.observations(rows=rows, dtype=np.float32)
        return
    for cols in column_runs(np.arange(prep.shape[2]), len(blocks)):
        yield prep.observations(columns=cols, dtype=np.float32)


def column_runs(columns: np.ndarray, parts: int) -> list[np.ndarray]:
    """``columns`` in ``parts`` runs of consecutive entries (at least one, at most one column each): where samples
    read the images between rows, the images of a column are one solve, so the stages go through whole columns."""
    return np.array_split(columns, max(1, min(parts, columns.size)))


def fit_motion_mask(prep: Prepared, cfg: dict, plan: ColumnPlan, blocks: list[tuple[int, int]]) -> np.ndarray:
    """The pixels (H, W) of the fit's columns the motion mask leaves out of the vibration fit (``mask.*``)."""
    H, W = prep.shape[1:]
    if not cfg["mask"]["enabled"]:
        return np.zeros((H, W), bool)
    m = cfg["mask"]
    pilot = pilot_estimate(prep) if plan.pilot is None else plan.pilot
    # the per-pixel statistics of the fit's columns only (the others never enter the fit), block by block: as many of
    # the retrieval's blocks of rows at once as hold a block's samples of those columns (one block each: 138 at full
    # resolution, 2 s of overheads); where the samples read between rows the images of a column are one solve: runs
    # of the fit's whole columns, as many (all of them at once, the paper study's mask took 1.32 s, now 0.53 s: its
    # temporaries of every sample, not the solve)
    per = max(W // max(plan.columns.size, 1), 1)
    if prep.store.parallax:
        parts = (prep.observations(columns=cols, dtype=np.float32)
                 for cols in column_runs(plan.columns, -(-len(blocks) // per)))
    else:
        parts = (prep.observations(columns=plan.columns, rows=(blocks[i][0], blocks[min(i + per, len(blocks)) - 1][1]),
                                   dtype=np.float32) for i in range(0, len(blocks), per))
    moving, _, thr, beyond = motion_mask(parts, pilot=pilot, threshold=m["threshold"], sigma=m["sigma"],
                                         dilate=m["dilate"], between_rows=m["between_rows"])
    log.info("motion mask: %d pixels above %.3g left out of the vibration fit", int((moving & ~beyond).sum()), thr)
    if beyond.any():
        log.info("motion mask: %d pixels where reading the images between rows misses more than %g noise standard "
                 "deviations left out of the vibration fit", int(beyond.sum()), m["between_rows"])
    return moving


def fit_observations(prep: Prepared, columns: np.ndarray, moving: np.ndarray) -> Observations:
    """The vibration fit's observations: ``columns`` in float32, the pixels ``moving`` (H, W) left out. What the
    fit and the decision which effects it can determine (:func:`dfxcorr.planning.resolve_effects`) see."""
    obs = prep.observations(columns=columns, dtype=np.float32)
    return replace(obs, use=obs.use & ~obs.pixel_mask(moving))


def pilot_start(obs: Observations, pilot: dict, *, effects: tuple[str, ...], gauge_fraction: float) -> dict:
    """The maximum-likelihood fit's options that start it at ``pilot`` where every well-determined frame fits there
    within noise (:data:`dfxcorr.mask.START_CHI2`), else none (neutral start, staged); logged.

    From the pilot the fit runs neither its stages nor a coarse first pass (``fit.coarse``): both bring a start into
    the basin of the minimum, where the pilot already is (paper study, binned and full-resolution clinical scans: the
    fit 9 %, 18 % and 24 % faster without the coarse pass, the same estimates to 5 digits).
    """
    worst = start_misfit(obs, pilot, effects=effects, gauge_fraction=gauge_fraction)
    if worst <= START_CHI2:
        log.info("vibration fit starts at the pilot estimate (largest reduced chi-square of a well-determined frame "
                 "there %.3g)", worst)
        return {"start": pilot, "staged": False, "coarse": 1}
    log.info("vibration fit starts at the neutral values: at the pilot estimate a well-determined frame's reduced "
             "chi-square is %.3g (above %g)", worst, START_CHI2)
    return {}


def run_fit(prep: Prepared, cfg: dict, moving: np.ndarray, *, columns: np.ndarray, progress: bool | None = None,
            coarse: int = 1, pilot: dict | None = None) -> tuple[FitResult, np.ndarray, tuple[str, ...]]:
    """Estimate the per-frame parameters with the configured method.

    The fit holds observations of ``columns`` only (:func:`plan_columns`), in float32; its stages run on every
    ``coarse``-th of them first (:attr:`ColumnPlan.coarse`). With ``fit.start: pilot`` the maximum-likelihood fit
    starts at ``pilot`` (the motion mask's estimate, :attr:`ColumnPlan.pilot`) where every well-determined frame fits
    there within noise (:func:`dfxcorr.mask.start_misfit`), without the stages that bring a neutral start into the
    basin of the minimum.

    Returns
    -------
    FitResult
    fit_mask : ndarray of uint8, shape (H, W)
        1 where the pixel entered the fit.
    effects : tuple of str
        The effects fitted (the configured ones this acquisition can determine).
    """
    method = cfg["fit"]["method"]
    J, H, W = prep.shape
    fit_mask = np.zeros((H, W), np.uint8)
    if method == "none":
        params = paper_params({}, J)
        unc = {k: np.full_like(v, np.inf) for k, v in params.items()}
        return FitResult(params=params, uncertainty=unc, cost=np.zeros(0), stage=[], iterations=0,
                         converged=True), fit_mask, ()
    if method not in ESTIMATORS:
        raise C.ConfigError(f"fit.method={method!r} is not available; available: {', '.join(ESTIMATORS)}, none")
    cols = columns
    fit_obs = fit_observations(prep, cols, moving)
    effects = resolve_effects(cfg, prep.scan, prep.reference, fit_obs)
    # counted compiled: a float64 copy of the mask was 216 MB beside a full-resolution fit of 2.7e7 samples
    used = row_counts(fit_obs, fit_obs.use) > 0
    fit_obs.place(fit_mask, used)
    log.info("vibration fit (%s): %s on %d columns, %d pixels, %d frames", method, ", ".join(effects),
             fit_obs.columns.size, int(used.sum()), J)
    f = cfg["fit"]
    with Progress("vibration fit", unit="iterations", enabled=progress) as bar:
        def tick(stage_name, cost):
            bar.update(1, status=f"{stage_name} cost {cost:.6g}")
        estimator = ESTIMATORS[method]
        options = estimator.options({**f, "coarse": coarse}, on_iteration=tick)
        if method == "ml" and f["start"] == "pilot" and pilot is not None:
            options.update(pilot_start(fit_obs, pilot, effects=effects, gauge_fraction=f["gauge_fraction"]))
        result = estimator.fit(fit_obs, effects=effects, **options)
    if "tilt" in result.params and result.well_determined is not None:
        step = int(cols[1] - cols[0]) if cols.size > 1 else 1
        period = tilt_alias_period(W, step)
        worst = float(np.abs(result.params["tilt"][result.well_determined]).max())
        if worst > period / 4:
            log.warning("fitted tilts reach %.2f rad, a quarter of the alias period %.2f rad of every %d-th "
                        "column: reduce fit.subsample", worst, period, step)
    log.info("vibration fit: %d iterations, %d evaluations of the cost over %d samples", result.iterations,
             result.evaluations, fit_obs.counts.size)
    if not result.converged:
        log.warning("the vibration fit stopped before converging (%s)", "; ".join(result.messages))
    for name in result.params:
        if effect(name).per_frame and result.well_determined is not None:
            good = result.well_determined
            log.info("  %s: std %.4g over %d well-determined frames, median uncertainty %.2g", name,
                     float(np.std(result.params[name][good])), int(good.sum()),
                     float(np.median(result.uncertainty[name][good])))
    return result, fit_mask, effects

