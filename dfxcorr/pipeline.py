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
import functools
import hashlib
import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from . import __version__
from . import config as C
from . import model as M
from .align import FringeMaps, LitStore, collect_lit_rows, fringe_maps, pixel_mm, subsample_columns, tilt_alias_period
from .effects import REGISTRY
from .effects.base import Preparation
from .estimators import ESTIMATORS
from .faults import MIN_KEPT_SHARE, find_faults, saturation_level
from .fit import FitResult, pilot_uncertainty
from .io import Reference, Scan, read_scan
from .mask import motion_mask, pilot_vibrations
from .observations import Noise
from .planning import resolve_effects
from .progress import Progress
from .reference import auto_visibility_threshold, resolve_reference
from .result import Result, paper_params
from .retrieve import image_values, per_dof, retrieve

log = logging.getLogger(__name__)


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


@dataclass(frozen=True)
class Prepared:
    """A scan made ready for any analysis: flat field resolved and aligned, lit samples held, region of interest.

    Every consumer (reconstruct, diagnose, compare) gets its observations from here, so that they see
    the same data for the same scan and configuration.

    Attributes
    ----------
    scan : Scan
        The acquisition (its frames may stay in the file; the store holds what is needed).
    name : str
        File name, or 'scan' for an in-memory scan.
    path : Path or None
    reference : Reference
        Flat-field maps (retrieved from the scan's stepping series with the ``reference.*`` options).
    store : LitStore
    min_visibility : float
        Samples whose aligned reference visibility is below this carry no fringe (region of interest).
    noise : Noise
        Noise model of the configuration (``load.*``: gain, electronic noise, per-pixel factors).
    """

    scan: Scan
    name: str
    path: Path | None
    reference: Reference
    store: LitStore
    min_visibility: float
    noise: Noise

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.scan.shape

    @functools.cached_property
    def _fringe_maps(self) -> FringeMaps:
        """The reference's maps as the alignment reads them, made once for every block aligned."""
        return fringe_maps(self.reference)

    def observations(self, *, columns: np.ndarray | None = None, rows: tuple[int, int] | None = None,
                     dtype=np.float64) -> M.Observations:
        """Observations of some columns and detector rows, with the region of interest of their samples.

        Samples without fringe (outside the region of interest, ``obs.roi`` False) get v^f = 0: they yield
        no images, but in the fit they still monitor dose and background. ``use`` is False for the detector
        faults only (saturated samples, bad frames: :mod:`dfxcorr.faults`).
        """
        obs = self.store.observations(self.reference, columns=columns, rows=rows, gain=self.noise.gain,
                                      electronic=self.noise.electronic, noise=self.noise.factors, dtype=dtype,
                                      maps=self._fringe_maps)
        roi = obs.vf >= self.min_visibility
        return replace(obs.fringe_within(roi), roi=roi)


def prepare(scan: Scan | str | Path, cfg: dict, *, timings: dict | None = None) -> Prepared:
    """Load, resolve the reference, align and collect the lit samples: the one preparation of every analysis.

    Parameters
    ----------
    scan : Scan or path
    cfg : dict
        Resolved configuration: ``load``, ``reference`` and ``align`` sections.
    timings : dict, optional
        Receives the seconds of the load and align stages.

    Returns
    -------
    Prepared
    """
    timings = {} if timings is None else timings
    path = None
    if not isinstance(scan, Scan):
        path = Path(scan)
        with stage("load", timings):
            scan = read_scan(path, allow_external=cfg["load"]["allow_external"])
            log.info("scan %s: %d frames of %d x %d, active area %d rows%s", path.name, *scan.shape,
                     scan.active_rows, ", phase stepping" if scan.is_stepping else "")
    # what the configuration asks of each effect (files it names included) is read and checked before any computation
    settings = {e.name: e.configured(cfg, n_frames=scan.shape[0], detector=scan.shape[1:]) for e in REGISTRY.values()}
    with stage("align", timings):
        step_effects, optional = C.reference_effects(cfg)
        reference = resolve_reference(scan, effects=step_effects, optional=optional)
        store = collect_lit_rows(scan, active_rows=reference.transmission.shape[0],
                                 min_frames=cfg["align"]["min_frames"])
        faults = find_faults(store.frame_blocks(), shape=scan.shape, dark=store.dark,
                             level=saturation_level(store.counts.dtype, cfg["load"]["saturation"]))
        faults.require_data()
        if faults.any:
            log.warning("%s", faults.summary())
            # noise of a sample at the level: what a neighbour's count may differ by from its own expectation
            gain = cfg["load"]["gain"] or scan.gain
            store = store.without(faults, margin=SATURATION_SIGMAS * np.sqrt(gain * (faults.level or 0.0)
                                                                           + cfg["load"]["electronic"]))
        made = Preparation(store=store, shift=np.zeros(scan.shape[0]),
                           noise=Noise(cfg["load"]["gain"] or scan.gain, cfg["load"]["electronic"]),
                           reference=reference, pixel_mm=pixel_mm(scan))
        for name, setting in settings.items():
            if setting is not None:
                made = REGISTRY[name].prepare(made, setting)
                log.info("%s: the configured correction is applied", name)
        store = made.store.shifted(made.shift) if np.any(made.shift != 0) else made.store
        log.info("lit samples: %d rows x frames of %d columns (%.0f MB as %s)", store.row.size, scan.shape[2],
                 store.counts.nbytes / 1e6, store.counts.dtype)
        vmin = cfg["align"]["min_visibility"]
        vmin = auto_visibility_threshold(reference.visibility) if vmin == "auto" else float(vmin)
    return Prepared(scan=scan, name=path.name if path else "scan", path=path, reference=reference, store=store,
                    min_visibility=vmin, noise=made.noise)


#: Noise standard deviations below the saturation level within which a neighbour's count leaves a sample out.
SATURATION_SIGMAS = 3.0


#: Bytes per (pixel, frame) sample at the peak of a block's retrieval or motion statistics in float64: 153
#: measured with tracemalloc on the numpy model (observations, design, weights, expected counts, temporaries).
BYTES_PER_SAMPLE = 160


def row_blocks(store: LitStore, budget_mb: float) -> list[tuple[int, int]]:
    """Detector-row ranges [r0, r1) whose samples fit the memory budget, covering every held row
    (:meth:`LitStore.row_runs`)."""
    return store.row_runs(budget_mb * 1e6 / BYTES_PER_SAMPLE)


#: Evenly spread columns of the pilot that predicts the fit's uncertainty (``fit.subsample: auto``): its profiled
#: Fisher information costs a fraction of a second even at full resolution.
PILOT_COLUMNS = 16
#: Wall seconds of the vibration fit per sample it holds, all stages and the uncertainty included (the predicted
#: time): 1.7 us on the paper study at every column, 2.2 on a binned and 3.2 on a full-resolution clinical scan
#: (the Hessians' share grows with the rows), on the 2-core machine under load 1.5-2.5.
FIT_SECONDS_PER_SAMPLE = 2.5e-6
#: Samples of the motion mask's pilot vibration estimate (its columns need not be the fit's).
MASK_PILOT_SAMPLES = 2_000_000
#: Samples of the coarse first pass of a fit of more columns (``fit.coarse: auto``; at least
#: :data:`COARSE_MIN_COLUMNS` columns): its estimate is far inside the basin of the minimum on all columns.
COARSE_SAMPLES = 1_000_000
COARSE_MIN_COLUMNS = 16
#: Wall seconds per sample of the fit's last stages on all its columns after a coarse pass (the predicted time
#: adds :data:`FIT_SECONDS_PER_SAMPLE` per sample of the coarse pass): 0.53 us on the paper study at every column
#: with both cores free (fit 5.7 s, its coarse pass on every 7th column about 2 s; 0.6 before its intermediate
#: stages stopped at :data:`dfxcorr.fit.STAGE_GTOL`).
POLISH_SECONDS_PER_SAMPLE = 0.5e-6
#: Wall seconds of a reconstruction's other stages (alignment, motion mask, retrieval of every pixel) per lit sample
#: of the scan: what ``fit.time_floor`` leaves to the fit (0.076 us on the binned and 0.077 on the full-resolution
#: clinical scan, 0.11 on the paper study; docs/benchmark.json, load 3.4-4.1).
REST_SECONDS_PER_SAMPLE = 0.08e-6


@dataclass(frozen=True)
class ColumnPlan:
    """The columns of the vibration fit and what they are predicted to give.

    Attributes
    ----------
    columns : ndarray of int
    why : str
        How they were chosen.
    uncertainty : float
        Predicted median one-sigma uncertainty of the phase effects (phi0, phi1; rad) over the well-determined
        frames, from the pilot's Fisher information at the neutral model (NaN without a pilot).
    seconds : float
        Predicted wall time of the fit (:func:`fit_seconds`).
    pilot : dict or None
        The pilot vibration estimate the prediction used (:func:`pilot_estimate`), for the motion mask.
    coarse : int
        The fit's stages run on every ``coarse``-th of the columns first (``fit.coarse``).
    """

    columns: np.ndarray
    why: str
    uncertainty: float = float("nan")
    seconds: float = float("nan")
    pilot: dict | None = None
    coarse: int = 1

    def summary(self) -> str:
        """One line: the columns, the predicted uncertainty and time, and why."""
        cols = self.columns
        every = f"every {cols[1] - cols[0]}-th column from column {cols[0]}" if cols.size > 1 else f"column {cols}"
        unc = "" if np.isnan(self.uncertainty) else f", predicted phi0/phi1 uncertainty {self.uncertainty:.2g} rad"
        first = f", its stages first on every {self.coarse}-th of them" if self.coarse > 1 else ""
        return f"{cols.size} columns ({every}){unc}, predicted fit time {self.seconds:.1f} s{first} ({self.why})"


def coarse_step(cfg: dict, n_columns: int, samples_per_column: int, *, step: int, width: int) -> int:
    """``fit.coarse``, or for ``auto`` the spacing that leaves about :data:`COARSE_SAMPLES` samples (at least
    :data:`COARSE_MIN_COLUMNS` columns) to the first pass; never beyond the alias limit W / 4 of the detector's
    columns (``step`` apart in the fit)."""
    c = cfg["fit"]["coarse"]
    if c == "auto":
        c = min(int(round(n_columns * samples_per_column / COARSE_SAMPLES)), n_columns // COARSE_MIN_COLUMNS)
    return max(1, min(int(c), max(width // 4, 1) // max(step, 1)))


def fit_seconds(n_columns: int, samples_per_column: int, coarse: int) -> float:
    """Predicted wall time (s) of a fit of ``n_columns`` columns whose stages run on every ``coarse``-th first."""
    if coarse <= 1:
        return FIT_SECONDS_PER_SAMPLE * n_columns * samples_per_column
    return (FIT_SECONDS_PER_SAMPLE * -(-n_columns // coarse) + POLISH_SECONDS_PER_SAMPLE * n_columns) \
        * samples_per_column


def within_seconds(cfg: dict, width: int, samples_per_column: int, seconds: float) -> int:
    """The smallest column spacing whose fit is predicted (:func:`fit_seconds`) to take at most ``seconds``."""
    for n in range(1, max(width // 4, 1) + 1):
        cols = subsample_columns(width, n, offset=cfg["fit"]["column_offset"]).size
        coarse = coarse_step(cfg, cols, samples_per_column, step=n, width=width)
        if fit_seconds(cols, samples_per_column, coarse) <= seconds:
            return n
    return max(width // 4, 1)


def column_step(width: int, samples_per_column: int, *, most: float) -> int:
    """The smallest column spacing n whose columns hold at most ``most`` lit samples, at most W / 4."""
    return min(max(int(np.ceil(samples_per_column * width / most)), 1), max(width // 4, 1))


def fit_columns(width: int, cfg: dict, n: int) -> np.ndarray:
    """Every ``n``-th column from ``fit.column_offset``, with the aliasing limit of paper Sec. II-D.1 checked."""
    cols = subsample_columns(width, n, offset=cfg["fit"]["column_offset"])
    if cols.size < 4:
        raise C.ConfigError(f"fit.subsample={n} leaves {cols.size} of {width} columns; use at most {width // 4}")
    period = tilt_alias_period(width, n)
    if period < 4 * np.pi:
        raise C.ConfigError(f"fit.subsample={n}: tilts that differ by {period:.2f} rad are indistinguishable on "
                            f"every {n}-th of {width} columns (paper Sec. II-D.1); use at most {width // 4}")
    return cols


def pilot_estimate(prep: Prepared) -> dict:
    """A quick estimate of the paper's vibrations (:func:`dfxcorr.mask.pilot_vibrations`) on evenly spread columns
    holding at most :data:`MASK_PILOT_SAMPLES` samples: what the motion mask compares with and the column plan
    predicts at. In float32, as every observation of a reconstruction (:func:`blocked_retrieval`)."""
    W = prep.shape[2]
    cols = subsample_columns(W, column_step(W, prep.store.samples_per_column(), most=MASK_PILOT_SAMPLES))
    return pilot_vibrations(prep.observations(columns=cols, dtype=np.float32))


def plan_columns(prep: Prepared, cfg: dict, *, pilot: dict | None = None, report: bool = True) -> ColumnPlan:
    """Columns entering the vibration fit: ``fit.subsample``, or for ``auto`` those a target precision needs.

    ``auto`` predicts the uncertainty from a pilot: the profiled Fisher information of :data:`PILOT_COLUMNS`
    evenly spread columns at the vibrations ``pilot`` (default :func:`pilot_estimate`) by
    :func:`dfxcorr.fit.pilot_uncertainty`; columns add information independently, so n columns give
    sigma_pilot sqrt(pilot columns / n). It takes the fewest evenly spaced columns predicted to reach
    ``fit.target_uncertainty``, or more where the whole run is predicted to take at most ``fit.time_floor``
    seconds with them (the fit's :func:`fit_seconds` and the other stages' :data:`REST_SECONDS_PER_SAMPLE` per
    sample of the scan: a small scan's run is short, and its fit takes every column, the paper study's too), or
    with ``fit.time_budget`` the most predicted to fit in that time (:func:`fit_seconds`); never more than
    ``fit.max_samples`` samples (memory) nor a spacing beyond the alias limit W / 4. Logged when ``report``.
    """
    f = cfg["fit"]
    W = prep.shape[2]
    per_column = prep.store.samples_per_column()
    n, why = f["subsample"], "fit.subsample"
    sigma, size = float("nan"), 0
    if n == "auto":
        spread = subsample_columns(W, max(W // PILOT_COLUMNS, 1))
        size = spread.size
        pilot = pilot_estimate(prep) if pilot is None else pilot
        sigma = pilot_uncertainty(prep.observations(columns=spread, dtype=np.float32), params=pilot,
                                  gauge_fraction=f["gauge_fraction"])
        cap = column_step(W, per_column, most=f["max_samples"])
        if f["time_budget"] is not None:
            n = max(within_seconds(cfg, W, per_column, f["time_budget"]), cap)
            why = f"the most columns within fit.time_budget={f['time_budget']:g} s"
        else:
            need = size * (sigma / f["target_uncertainty"]) ** 2
            n = min(max(int(W / max(need, 1.0)), 1), max(W // 4, 1))
            why = f"fit.target_uncertainty={f['target_uncertainty']:g} rad"
            rest = REST_SECONDS_PER_SAMPLE * per_column * W
            floor = W if f["time_floor"] is None else within_seconds(cfg, W, per_column, f["time_floor"] - rest)
            if floor < n:
                n, why = floor, (f"the most columns within fit.time_floor={f['time_floor']:g} s for the whole run, "
                                 f"its other stages predicted {rest:.1f} s")
            n = max(n, cap)
        why += f"; pilot of {size} columns {sigma:.2g} rad"
        if n == cap and cap > 1:
            why += f"; held at fit.max_samples={f['max_samples']:g}"
    cols = fit_columns(W, cfg, n)
    coarse = coarse_step(cfg, cols.size, per_column, step=n, width=W)
    out = ColumnPlan(columns=cols, why=why,
                     uncertainty=sigma * np.sqrt(size / cols.size) if size else float("nan"),
                     seconds=fit_seconds(cols.size, per_column, coarse), pilot=pilot, coarse=coarse)
    if report:
        log.info("vibration fit columns: %s", out.summary())
    return out


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
    prep = scan if isinstance(scan, Prepared) else prepare(scan, cfg, timings=timings)
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
        if cfg["mask"]["enabled"] and plan is not None:
            m = cfg["mask"]
            pilot = pilot_estimate(prep) if plan.pilot is None else plan.pilot
            # the per-pixel statistics of the fit's columns only (the others never enter the fit), block by block
            moving, _, thr = motion_mask((prep.observations(columns=columns, rows=rows, dtype=np.float32)
                                          for rows in blocks),
                                         pilot=pilot, threshold=m["threshold"], sigma=m["sigma"], dilate=m["dilate"])
            log.info("motion mask: %d pixels above %.3g left out of the vibration fit", int(moving.sum()), thr)
    with stage("fit", timings):
        fitted, fit_mask, effects = run_fit(prep, cfg, moving, columns=columns, progress=progress,
                                            coarse=1 if plan is None else plan.coarse)
    with stage("retrieve", timings):
        iterations = cfg["retrieve"]["iterations"]
        n_par = sum(np.size(p) for p in fitted.params.values())
        sets, counts = [fitted.params], [n_par]
        if cfg["retrieve"]["uncorrected"] and method != "none":
            sets, counts = [*sets, {}], [*counts, 0]
        (maps, chi2), *rest = blocked_retrieval(prep, blocks, sets, iterations=iterations, n_params=counts)
        uncorrected = rest[0][0] if rest else None
        log.info("reduced chi-square of the final model: %.4f", chi2)
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
    return Result(transmission=maps["transmission"], dark_field=maps["dark_field"],
                  differential_phase=maps["differential_phase"], params=params, estimated=estimated,
                  uncertainty=uncertainty, fit_mask=fit_mask, motion_mask=moving.astype(np.uint8),
                  cost=fitted.cost, cost_stage=fitted.stage, reduced_chi2=chi2, method=method,
                  config=cfg, provenance=provenance, uncorrected=uncorrected, timings=timings)


def blocked_retrieval(prep: Prepared, blocks: list[tuple[int, int]], params: list[dict], *, iterations: int,
                      n_params: list[int]) -> list[tuple[dict[str, np.ndarray], float]]:
    """Images (H, W) of every pixel in its region of interest, block by block, and the reduced chi-square.

    One pass over the blocks serves every parameter set of ``params`` (e.g. the fitted and the neutral
    ones), so each block's observations are built once. The chi-square and its degrees of freedom are
    summed over blocks, so each result equals :func:`dfxcorr.retrieve.reduced_chi2` over the whole scan
    with that set's ``n_params`` per-frame parameters.

    The blocks are float32 observations, as the fit's, the pilot's and the motion mask's: a reconstruction
    then compiles each kernel for one dtype only (the float64 variants were about 14 s of a first run), and the
    images differ from a float64 retrieval by far less than their noise (the demo: 1e-4 of their spread).
    The expected counts and weights are not written (the images and the chi-square are all that is kept).
    """
    H, W = prep.shape[1:]
    maps = [{k: np.full((H, W), np.nan) for k in ("transmission", "dark_field", "differential_phase")}
            for _ in params]
    sums = np.zeros((len(params), 3))  # chi-square, samples, pixels
    left_out = 0
    for rows in blocks:
        obs = prep.observations(rows=rows, dtype=np.float32)
        roi = obs.in_roi
        with np.errstate(invalid="ignore"):
            kept = obs.segment_sum(obs.use.astype(np.float64)) / obs.segment_sum(np.ones(obs.use.shape))
        obs = replace(obs, use=obs.use & roi & (kept >= MIN_KEPT_SHARE)[obs.pixel])
        for m, p, acc in zip(maps, params, sums, strict=True):
            rec = retrieve(obs, p, iterations=iterations, n_frame_params=0, keep_expected=False)
            for k, v in image_values(rec.images).items():
                obs.place(m[k], v)
            acc += (rec.chi2_sum, rec.samples, int(rec.images.valid.sum()))
        left_out += int(np.count_nonzero(obs.segment_sum(roi.astype(np.float64)) == 0))
    if left_out:
        log.info("region of interest: %d pixels see no fringe (reference visibility < %.3g) and are left out "
                 "of the images", left_out, prep.min_visibility)
    return [(m, per_dof(c, int(n), int(px), k, 3)) for m, (c, n, px), k in zip(maps, sums, n_params, strict=True)]


def run_fit(prep: Prepared, cfg: dict, moving: np.ndarray, *, columns: np.ndarray, progress: bool | None = None,
            coarse: int = 1) -> tuple[FitResult, np.ndarray, tuple[str, ...]]:
    """Estimate the per-frame parameters with the configured method.

    The fit holds observations of ``columns`` only (:func:`plan_columns`), in float32; its stages run on every
    ``coarse``-th of them first (:attr:`ColumnPlan.coarse`).

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
    fit_obs = prep.observations(columns=cols, dtype=np.float32)
    fit_obs = replace(fit_obs, use=fit_obs.use & ~fit_obs.pixel_mask(moving))
    effects = resolve_effects(cfg, prep.scan, prep.reference, fit_obs)
    used = fit_obs.segment_sum(fit_obs.use.astype(np.float64)) > 0
    fit_obs.place(fit_mask, used)
    log.info("vibration fit (%s): %s on %d columns, %d pixels, %d frames", method, ", ".join(effects),
             fit_obs.columns.size, int(used.sum()), J)
    f = cfg["fit"]
    with Progress("vibration fit", unit="iterations", enabled=progress) as bar:
        def tick(stage_name, cost):
            bar.update(1, status=f"{stage_name} cost {cost:.6g}")
        estimator = ESTIMATORS[method]
        result = estimator.fit(fit_obs, effects=effects, **estimator.options({**f, "coarse": coarse},
                                                                             on_iteration=tick))
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
        if M.effect(name).per_frame and result.well_determined is not None:
            good = result.well_determined
            log.info("  %s: std %.4g over %d well-determined frames, median uncertainty %.2g", name,
                     float(np.std(result.params[name][good])), int(good.sum()),
                     float(np.median(result.uncertainty[name][good])))
    return result, fit_mask, effects

