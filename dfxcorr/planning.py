"""Planning a run: which configured effects a reconstruction fits (and why some cannot be), which columns its
vibration fit takes, in which blocks of rows it retrieves, and what that is predicted to cost and give.

An effect the acquisition cannot determine (its Fisher information has directions without information
beyond its gauge, :mod:`dfxcorr.identify`; visibility effects in phase stepping, paper Sec. II-F) is
dropped with a log line where the configuration leaves it to ``auto``, and refused with an
:class:`IdentifiabilityError` where the configuration asks for it explicitly. ``dfxcorr check`` plans with
the same rules, without fitting.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from . import config as C
from .align import LitStore, subsample_columns, tilt_alias_period
from .catalogue import CATALOGUE, effect
from .errors import DfxcorrError
from .fit import pilot_uncertainty
from .identify import select
from .io import Scan
from .mask import pilot_vibrations
from .observations import Observations
from .preparation import Prepared

log = logging.getLogger("dfxcorr")

#: Effects whose parameters multiply the fringe's visibility (paper Sec. II-F: not determined in phase stepping).
VISIBILITY_EFFECTS = tuple(n for n, e in CATALOGUE.items() if e.channel == "visibility")


class IdentifiabilityError(DfxcorrError, ValueError):
    """An effect was asked for that the acquisition cannot determine."""


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


def refuse_if_asked(cfg: dict, name: str, why: str) -> None:
    """Refuse an effect the acquisition cannot determine if the configuration asks for it explicitly.

    Raises
    ------
    IdentifiabilityError
        If ``vibration.<key of name>`` is true (not auto).
    """
    key = effect(name).config
    if key is not None and C.get(cfg, key) is True:
        raise IdentifiabilityError(f"{name} is not identifiable here: {why}; set {key}=false"
                                   + (" (or auto)" if C.option(key).default == "auto" else ""))


def drop_visibility(cfg: dict, effects, why: str | None) -> tuple[list[str], dict[str, str]]:
    """The effects without the visibility ones where ``why`` (paper Sec. II-F) says they cannot be determined.

    Returns
    -------
    kept : list of str
    dropped : dict
        Effect -> reason.

    Raises
    ------
    IdentifiabilityError
        If the configuration explicitly asks for a visibility effect that ``why`` rules out.
    """
    kept, dropped = [], {}
    for name in effects:
        if why and name in VISIBILITY_EFFECTS:
            refuse_if_asked(cfg, name, why)
            dropped[name] = why
        else:
            kept.append(name)
    return kept, dropped


def resolve_effects(cfg: dict, scan: Scan, reference, fit_obs: Observations) -> tuple[str, ...]:
    """The effects to fit: the configured ones that this acquisition can determine.

    Every enabled effect is checked in turn against the Fisher information of the fit's samples
    (:mod:`dfxcorr.identify`); visibility effects in a stepping recording or over a separable flat
    field are refused with the paper's reason. An effect set to ``auto`` is dropped with a log line.

    Raises
    ------
    IdentifiabilityError
        If the configuration explicitly asks for an effect the acquisition cannot determine.
    """
    def refuse_or_drop(name, why):
        refuse_if_asked(cfg, name, why)
        log.info("%s is not fitted: %s", name, why)

    names, dropped = drop_visibility(cfg, C.effects_of(cfg), visibility_unidentifiable(scan, reference))
    for name, why in dropped.items():
        log.info("%s is not fitted: %s", name, why)
    chosen: list[str] = []
    # identifiability is structural: judged on images solved per pixel also where the samples read between rows (a
    # fraction of a row off their own), as the fit's Hessian is; the block-tridiagonal solves and their Fisher
    # information took 0.8 s of the binned clinical scan with a parallax
    for verdict in select(replace(fit_obs, reading=None), names):
        if verdict.identifiable:
            chosen.append(verdict.name)
        else:
            refuse_or_drop(verdict.name, f"the Fisher information of this acquisition has {verdict.excess} "
                                         f"direction(s) of its parameters without information beyond its gauge "
                                         f"(they trade off exactly against the images"
                                         f"{' or ' + ', '.join(chosen) if chosen else ''})")
    return tuple(chosen)


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
#: time): 1.5 us on the paper study at 39 columns, idle 2-core machine with the vectorised kernels (was 2.5 on an
#: older machine under load 1.5-2.5).
FIT_SECONDS_PER_SAMPLE = 1.7e-6
#: Samples of the motion mask's pilot vibration estimate (its columns need not be the fit's).
MASK_PILOT_SAMPLES = 2_000_000
#: Samples of the coarse first pass of a fit of more columns (``fit.coarse: auto``; at least
#: :data:`COARSE_MIN_COLUMNS` columns): its estimate is far inside the basin of the minimum on all columns.
COARSE_SAMPLES = 1_000_000
COARSE_MIN_COLUMNS = 16
#: Wall seconds per sample of the fit's last stages on all its columns after a coarse pass from the neutral values
#: (the predicted time adds :data:`FIT_SECONDS_PER_SAMPLE` per sample of the coarse pass). Since the Hessian's
#: columns are spread by their information the whole fit from the neutral values takes 2.3, 2.0 and 2.7 s on the
#: paper study and the binned and full-resolution clinical scans at fit.max_samples (was 2.7, 3.0, 3.9 s); this and
#: the coarse pass's rate predict 3.0, 3.0 and 3.8 s (idle).
POLISH_SECONDS_PER_SAMPLE = 0.2e-6
#: Wall seconds per sample of a fit that starts at the pilot estimate (no stages, no coarse pass; the fit stage,
#: observations and the start's check included): 0.20 us on the paper study, 0.20 and 0.25 on the binned and
#: full-resolution clinical scans at fit.max_samples, 0.17 with 4x the samples (docs/benchmark.json, load 1.2-1.3;
#: 0.25-0.42 before the Hessian's columns were spread by their information).
PILOT_SECONDS_PER_SAMPLE = 0.22e-6
#: Wall seconds of a reconstruction's other stages (alignment, motion mask, retrieval of every pixel) per lit sample
#: of the scan: what ``fit.time_floor`` leaves to the fit (0.076 us on the binned and 0.077 on the full-resolution
#: clinical scan, 0.11 on the paper study; docs/benchmark.json, load 3.4-4.1).
REST_SECONDS_PER_SAMPLE = 0.08e-6
#: How much slower the fit runs where the samples read between rows (``geometry.parallax``: one block-tridiagonal
#: solve per column, :mod:`dfxcorr.kernels_between`): the same columns fitted, the paper study's fit stage 2.24 s
#: against 1.23 s, the binned clinical scan's 2.22 s against 1.32 s (docs/benchmark.json, load 1.1-1.7), each with 2
#: cost evaluations more (12 / 10, 11 / 9); it was 2.5 before the uncertainty between rows took standing columns.
READ_BETWEEN_SLOWDOWN = 2.0


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
        Predicted wall time of the fit (:func:`fit_seconds`) from the neutral values, through its stages.
    start_seconds : float
        Predicted wall time of the fit from the pilot estimate (``fit.start: pilot``, where it fits within noise:
        :func:`fit_seconds` with ``from_pilot``); NaN where the fit always starts at the neutral values.
    pilot : dict or None
        The pilot vibration estimate the prediction used (:func:`pilot_estimate`), for the motion mask.
    coarse : int
        From the neutral values, the fit's stages run on every ``coarse``-th of the columns first (``fit.coarse``;
        not from the pilot estimate).
    """

    columns: np.ndarray
    why: str
    uncertainty: float = float("nan")
    seconds: float = float("nan")
    start_seconds: float = float("nan")
    pilot: dict | None = None
    coarse: int = 1

    def summary(self) -> str:
        """One line: the columns, the predicted uncertainty and time, and why."""
        cols = self.columns
        every = f"every {cols[1] - cols[0]}-th column from column {cols[0]}" if cols.size > 1 else f"column {cols}"
        unc = "" if np.isnan(self.uncertainty) else f", predicted phi0/phi1 uncertainty {self.uncertainty:.2g} rad"
        first = f", its stages first on every {self.coarse}-th of them" if self.coarse > 1 else ""
        time = (f"{self.seconds:.1f} s{first}" if np.isnan(self.start_seconds) else
                f"{self.start_seconds:.1f} s from the pilot estimate ({self.seconds:.1f} s from the neutral values"
                f"{first})")
        return f"{cols.size} columns ({every}){unc}, predicted fit time {time} ({self.why})"


def coarse_step(cfg: dict, n_columns: int, samples_per_column: int, *, step: int, width: int) -> int:
    """``fit.coarse``, or for ``auto`` the spacing that leaves about :data:`COARSE_SAMPLES` samples (at least
    :data:`COARSE_MIN_COLUMNS` columns) to the first pass; never beyond the alias limit W / 4 of the detector's
    columns (``step`` apart in the fit)."""
    c = cfg["fit"]["coarse"]
    if c == "auto":
        c = min(int(round(n_columns * samples_per_column / COARSE_SAMPLES)), n_columns // COARSE_MIN_COLUMNS)
    return max(1, min(int(c), max(width // 4, 1) // max(step, 1)))


def fit_seconds(n_columns: int, samples_per_column: int, coarse: int, *, slowdown: float = 1.0,
                from_pilot: bool = False) -> float:
    """Predicted wall time (s) of a fit of ``n_columns`` columns whose stages run on every ``coarse``-th first,
    ``slowdown`` times that of the compiled kernels (:func:`slowdown`); ``from_pilot``: started at the pilot estimate,
    without stages or a coarse pass (:func:`dfxcorr.pipeline.pilot_start`; ``coarse`` then plays no part,
    :data:`PILOT_SECONDS_PER_SAMPLE`)."""
    if from_pilot:
        return slowdown * PILOT_SECONDS_PER_SAMPLE * n_columns * samples_per_column
    if coarse <= 1:
        return slowdown * FIT_SECONDS_PER_SAMPLE * n_columns * samples_per_column
    return (slowdown * (FIT_SECONDS_PER_SAMPLE * -(-n_columns // coarse) + POLISH_SECONDS_PER_SAMPLE * n_columns)
            * samples_per_column)


def start_seconds(cfg: dict, n_columns: int, samples_per_column: int) -> float:
    """The predicted fit time from the pilot estimate where the maximum-likelihood fit may start there
    (``fit.method: ml``, ``fit.start: pilot``; :func:`fit_seconds`), else NaN."""
    if cfg["fit"]["method"] != "ml" or cfg["fit"]["start"] != "pilot":
        return float("nan")
    return fit_seconds(n_columns, samples_per_column, 1, slowdown=slowdown(cfg), from_pilot=True)


def slowdown(cfg: dict) -> float:
    """How much slower than the compiled kernels the configured fit runs: :data:`READ_BETWEEN_SLOWDOWN` where the
    samples read between rows (``geometry.parallax``), else 1."""
    return READ_BETWEEN_SLOWDOWN if cfg["geometry"]["parallax"] else 1.0


def within_seconds(cfg: dict, width: int, samples_per_column: int, seconds: float) -> int:
    """The smallest column spacing whose fit is predicted (:func:`fit_seconds`) to take at most ``seconds``, from the
    neutral values (an upper bound: the pilot, which may start it sooner, is judged only after the motion mask)."""
    for n in range(1, max(width // 4, 1) + 1):
        cols = subsample_columns(width, n, offset=cfg["fit"]["column_offset"]).size
        coarse = coarse_step(cfg, cols, samples_per_column, step=n, width=width)
        if fit_seconds(cols, samples_per_column, coarse, slowdown=slowdown(cfg)) <= seconds:
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
    """Columns entering the vibration fit: ``fit.subsample``, or for ``auto`` the most the fit may hold or those a
    target precision needs, with the uncertainty and time predicted for them.

    The uncertainty is predicted from a pilot: the profiled Fisher information of :data:`PILOT_COLUMNS`
    evenly spread columns at the vibrations ``pilot`` (default :func:`pilot_estimate`) by
    :func:`dfxcorr.fit.pilot_uncertainty`; columns add information independently, so n columns give
    sigma_pilot sqrt(pilot columns / n). Without ``fit.target_uncertainty`` (the default) it takes the most evenly
    spaced columns ``fit.max_samples`` holds (the scan's Cramer-Rao level where they are all of them); with one, the
    fewest predicted to reach it, or more where the whole run is predicted to take at most ``fit.time_floor``
    seconds with them if one is set (the fit's :func:`fit_seconds` and the other stages'
    :data:`REST_SECONDS_PER_SAMPLE` per sample of the scan), or with ``fit.time_budget`` the most predicted to fit
    in that time (:func:`fit_seconds`); never more than
    ``fit.max_samples`` samples (memory) nor a spacing beyond the alias limit W / 4. Logged when ``report``.
    """
    f = cfg["fit"]
    W = prep.shape[2]
    per_column = prep.store.samples_per_column()
    n, why = f["subsample"], "fit.subsample"
    if n != "auto":
        fit_columns(W, cfg, n)  # a setting beyond the detector is refused before the pilot runs
    # the pilot's prediction at every setting: the log states what the chosen columns are expected to give
    spread = subsample_columns(W, max(W // PILOT_COLUMNS, 1))
    size = spread.size
    pilot = pilot_estimate(prep) if pilot is None else pilot
    sigma = pilot_uncertainty(prep.observations(columns=spread, dtype=np.float32), params=pilot,
                              gauge_fraction=f["gauge_fraction"])
    if n == "auto":
        cap = column_step(W, per_column, most=f["max_samples"])
        if f["time_budget"] is not None:
            n = max(within_seconds(cfg, W, per_column, f["time_budget"]), cap)
            why = f"the most columns within fit.time_budget={f['time_budget']:g} s"
        elif f["target_uncertainty"] is None:
            n, why = cap, "the most columns the fit holds (fit.target_uncertainty=null)"
        else:
            need = size * (sigma / f["target_uncertainty"]) ** 2
            # the widest spacing whose columns reach that many: from the offset, fewer than W / n of them
            n = max(W // 4, 1)
            while n > 1 and subsample_columns(W, n, offset=f["column_offset"]).size < need:
                n -= 1
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
    out = ColumnPlan(columns=cols, why=why, uncertainty=sigma * np.sqrt(size / cols.size),
                     seconds=fit_seconds(cols.size, per_column, coarse, slowdown=slowdown(cfg)),
                     start_seconds=start_seconds(cfg, cols.size, per_column), pilot=pilot, coarse=coarse)
    if report:
        log.info("vibration fit columns: %s", out.summary())
    return out
