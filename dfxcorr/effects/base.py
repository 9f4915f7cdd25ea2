"""The one interface of a catalogue effect, and the values the diagnosis passes between effects.

Every effect of ``spec/diagnosis.md`` is one object of a subclass of :class:`EffectBase`, in its own
module of this package (the model's channel effects share one, :mod:`dfxcorr.effects.channel`). It
says, for itself:

- what a configuration asks of it and how the one preparation applies that (:meth:`EffectBase.configured`,
  :meth:`EffectBase.prepare`): a correction of the counts, of the alignment, of the noise model;
- whether it applies to an acquisition and its test at the current fit (:meth:`EffectBase.test`): statistic,
  dof, identifiability, what it would explain;
- how it changes a hypothesis for the trial refit (:meth:`EffectBase.trial`);
- its report: where, the estimate, the keys of ``diagnosis.json``, the ``reconstruct`` settings that put it
  in the model, and the files it writes (:meth:`EffectBase.accepted`, :meth:`EffectBase.where`,
  :meth:`EffectBase.estimate`, :meth:`EffectBase.settings`, :meth:`EffectBase.artefacts`).

A :class:`Hypothesis` is a value: what the model holds (its channel effects), the noise model, the pixels
left out, where the flat field is read and the detector lag taken out. A trial returns a new one; a
rejected trial is dropped, never undone.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from scipy import stats

from .. import model as M
from ..catalogue import Effect
from ..observations import Noise, Observations
from ..preparation import Correctable, Prepared
from ..retrieve import Retrieval


@dataclass(frozen=True)
class Test:
    """An effect's test at the current fit.

    Attributes
    ----------
    statistic : float
        Chi-square-like statistic (what noise alone gives about ``dof`` of).
    dof : int
    p_value, log_p : float
        Its tail probability under noise alone, and the log of it (exact where the p-value underflows).
    identifiable : bool
        Whether this acquisition can determine the effect at all.
    excess : int
        Information-free directions of its parameters beyond its gauge (0 where identifiable).
    explains : float
        About how much chi-square adding it would remove (ranks candidates).
    material : bool
        Whether the change it would make matters (a gain within the practical floor does not).
    payload : mapping
        What its trial and report need (a pixel mask, a factor map, an estimate, ...).
    """

    statistic: float
    dof: int
    p_value: float
    log_p: float
    identifiable: bool = True
    excess: int = 0
    explains: float = 0.0
    material: bool = True
    payload: Mapping[str, Any] = field(default_factory=dict)


def chi2_test(statistic: float, dof: int, **kw: Any) -> Test:
    """A :class:`Test` whose statistic is chi-square with ``dof`` degrees of freedom under noise (1 where dof = 0)."""
    if dof <= 0:
        return Test(statistic, dof, 1.0, 0.0, **kw)
    log_p = float(stats.chi2.logsf(statistic, dof)) if np.isfinite(statistic) else -np.inf
    return Test(float(statistic), int(dof), float(stats.chi2.sf(statistic, dof)), log_p, **kw)


def strongest(found: Mapping[str, Test]) -> tuple[str, Test]:
    """The test of ``found`` with the least p-value, Bonferroni-corrected for how many were looked at: its key and
    the test with p (and log p) multiplied by that number (at most 1)."""
    key = min(found, key=lambda k: found[k].log_p)
    t, m = found[key], len(found)
    return key, replace(t, p_value=min(1.0, m * t.p_value), log_p=min(t.log_p + float(np.log(m)), 0.0))


def holm(log_p: list[float], alpha: float) -> list[bool]:
    """Holm's step-down verdicts at family-wise level ``alpha`` for tests with these log p-values."""
    order = sorted(range(len(log_p)), key=lambda i: log_p[i])
    out = [False] * len(log_p)
    for rank, i in enumerate(order):
        if not log_p[i] < np.log(alpha / (len(log_p) - rank)):
            break
        out[i] = True
    return out


def ranges(values: np.ndarray, limit: int = 4) -> str:
    """'3-7, 12, 40-60' for sorted integers (at most ``limit`` runs, then '...')."""
    runs, start = [], None
    for a, b in zip(values, [*list(values[1:]), None], strict=True):
        start = a if start is None else start
        if b is None or b != a + 1:
            runs.append(f"{start}-{a}" if a != start else f"{a}")
            start = None
    return ", ".join(runs[:limit]) + (", ..." if len(runs) > limit else "")


def frames_where(share: np.ndarray, n_frames: int) -> str:
    """Where a per-frame statistic sits: the fewest frames that carry half of it (``share``, shape (J,))."""
    share = np.clip(share, 0, None)
    if share.sum() <= 0:
        return "no frame in particular"
    order = np.argsort(share)[::-1]
    top = np.sort(order[: max(1, int(np.searchsorted(np.cumsum(share[order]) / share.sum(), 0.5)) + 1)])
    spread = "all frames" if top.size > 0.3 * n_frames else "few frames"
    return f"{spread}; half of the statistic in {top.size} frames, {top.min()}-{top.max()}"


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """What a fit of the diagnosis assumes beyond the prepared scan.

    Attributes
    ----------
    effects : tuple of str
        Channel effects in the model (:mod:`dfxcorr.catalogue`).
    noise : Noise
        The noise model (gain, electronic variance, per-pixel factors).
    motion : ndarray of bool, shape (H, W)
        Pixels left out (sample motion).
    shift : ndarray, shape (J,)
        Rows by which each frame reads the flat field off the prepared alignment.
    corrections : tuple of (str, setting)
        Corrections of the counts beyond the prepared (configured) ones, in order: each effect's
        :meth:`EffectBase.prepare` with that setting (e.g. a detector lag fraction).
    """

    effects: tuple[str, ...]
    noise: Noise
    motion: np.ndarray
    shift: np.ndarray
    corrections: tuple[tuple[str, Any], ...] = ()

    def but(self, **changes: Any) -> Hypothesis:
        """The same hypothesis with some fields changed."""
        return replace(self, **changes)


class State(Protocol):
    """A fitted hypothesis, as effects see it: the hypothesis, its parameters, chi-square (sum and reduced),
    residual signatures, the retrieval of the held columns (every column, or on a large scan a band of them:
    ``diagnose.max_held_samples``; images and chi-square, no per-sample arrays: a test that needs their expected
    counts makes them a run of columns at a time, :meth:`Observations.column_chunks`), the samples of the held
    columns and of the fit's columns under it, and the retrieval of the fit's columns (with the inverse normal
    matrices, expected counts and weights)."""

    @property
    def hypothesis(self) -> Hypothesis: ...
    @property
    def params(self) -> dict: ...
    @property
    def chi2(self) -> float: ...
    @property
    def reduced_chi2(self) -> float: ...
    @property
    def signatures(self) -> list: ...
    @property
    def rec(self) -> Retrieval: ...
    @property
    def obs(self) -> Observations: ...
    @property
    def fit_obs(self) -> Observations: ...
    @property
    def fit_rec(self) -> Retrieval: ...


def fit_counts(state: State) -> np.ndarray:
    """The expected counts of the fit's used, solved samples in the region of interest on the columns held for the
    per-pixel tests (``state.obs``): where bins of expected count are cut from, without every column's."""
    obs, rec = state.fit_obs, state.fit_rec
    held = obs.use & obs.in_roi & rec.images.valid[obs.pixel] & np.isin(obs.columns, state.obs.columns)[None, :]
    return rec.expected[held]


#: (observations, shift (J,) rows) -> the same samples with the flat field read that far off the prepared alignment.
Realign = Callable[[Observations, "np.ndarray | float"], Observations]


def squared_residuals(obs: Observations, params: dict, images: M.Images, exclude: np.ndarray | None = None
                       ) -> Iterator[tuple[np.ndarray, Observations, np.ndarray, np.ndarray, np.ndarray]]:
    """A run of columns at a time (:func:`dfxcorr.model.expected_by_columns`): its positions, samples, expected counts
    (from ``images`` and the model at ``params``), the samples that count (used, of solved pixels, not in
    ``exclude`` (H, W)) and their squared Pearson residuals (0 elsewhere)."""
    for cols, sub, im, _, ibar in M.expected_by_columns(obs, params, images):
        sel = sub.use & im.valid[sub.pixel]
        if exclude is not None:
            sel &= ~sub.pixel_mask(exclude)
        yield cols, sub, ibar, sel, np.where(sel, M.pearson(sub, ibar), 0.0)


def pixel_chi2(obs: Observations, params: dict, images: M.Images, *, under: Noise | None = None
               ) -> tuple[np.ndarray, np.ndarray, float]:
    """Per pixel, the Pearson chi-square of its samples under the noise model of ``obs`` and its degrees of
    freedom (samples - 3), detector images (H, W), 0 where nothing counts; and the whole chi-square of the same
    residuals under the noise model ``under`` (nan without it), in the same pass over the samples."""
    X, n = np.zeros((obs.starts.size, obs.columns.size)), np.zeros((obs.starts.size, obs.columns.size))
    total = 0.0 if under is not None else np.nan
    for cols, sub, ibar, sel, z2 in squared_residuals(obs, params, images):
        X[:, cols], n[:, cols] = sub.segment_sum(z2), sub.segment_sum(sel, dtype=np.float64)
        if under is not None:
            total += float(np.sum(M.pearson(sub.with_noise(under), ibar), where=sel))
    return obs.to_image(X, fill=0.0), obs.to_image(np.maximum(n - 3, 0.0), fill=0.0), total


def line_consistency(factors: np.ndarray, X: np.ndarray, dof: np.ndarray, *, strata: int = 6,
                     min_pixels: int = 24) -> Test | None:
    """Whether each pixel class of a factor map has one variance factor along its detector lines.

    A class of pixels whose noise differs (module boundaries, a bad readout line) has it wherever the line runs;
    a moving part of the sample, or a localised artefact, raises the variance of a patch, which the class's
    lines only cross. Per class (pixels of one factor other than 1) and per axis, its pixels in ``strata`` groups
    of equal size by detector row (and by column), a one-way analysis of variance of the per-pixel reduced
    chi-square X / dof (weights dof) at the fit with the factors in the model: F = the between-strata mean
    square over the within-strata one (the dispersion is the data's own), F(strata - 1, pixels - strata).

    Returns
    -------
    Test or None
        The strongest over classes and axes (Bonferroni, :func:`~dfxcorr.effects.base.strongest`); payload 'axis'
        'pixel', 'strata' (the strata's own factors f_s - 1 against the class's f - 1), 'spread' (their max - min),
        'factor', 'along'. None without a class to test.
    """
    found = {}
    index = np.indices(factors.shape)
    for f in np.unique(factors[(factors != 1.0) & (dof > 0)]):
        m = (factors == f) & (dof > 0)
        if m.sum() < min_pixels:
            continue
        y, w = X[m] / dof[m], dof[m]
        for name, where in (("rows", index[0][m]), ("columns", index[1][m])):
            order = np.argsort(where, kind="stable")
            group = np.empty(order.size, int)
            group[order] = np.arange(order.size) * strata // order.size
            W = np.bincount(group, weights=w, minlength=strata)
            mean = np.bincount(group, weights=w * y, minlength=strata) / W
            pooled = float(np.sum(w * y) / np.sum(w))
            between = float(np.sum(W * (mean - pooled) ** 2)) / (strata - 1)
            within = float(np.sum(w * (y - mean[group]) ** 2)) / max(order.size - strata, 1)
            F = between / within if within > 0 else 0.0
            log_p = float(stats.f.logsf(F, strata - 1, max(order.size - strata, 1)))
            sizes = (f * mean / pooled - 1.0) / (f - 1.0)
            found[f"{f:.6g} {name}"] = Test(F * (strata - 1), strata - 1, float(np.exp(log_p)), log_p,
                                            payload={"axis": "pixel", "strata": sizes.tolist(), "factor": float(f),
                                                     "along": name, "spread": float(np.ptp(sizes))})
    if not found:
        return None
    return strongest(found)[1]


class Context(Protocol):
    """What a diagnosis offers the effects it tests."""

    cfg: dict
    #: Columns of the observations that the per-frame parameters are fitted on, (C,) bool.
    fitted: np.ndarray
    #: Frames that set the gauge (:func:`dfxcorr.fit.well_determined`), (J,) bool.
    good_frames: np.ndarray
    #: A phase-stepping recording (no scan positions).
    stepping: bool
    #: Why visibility effects cannot be determined here (paper Sec. II-F), or None.
    visibility_why: str | None
    #: Results effects share within a diagnosis (computed once for the state they belong to).
    memo: dict

    def corrected(self, hypothesis: Hypothesis) -> Prepared:
        """The prepared scan with the hypothesis's corrections of the counts applied."""
        ...

    def realigner(self, hypothesis: Hypothesis) -> Realign:
        """Realignment of samples of the hypothesis's preparation."""
        ...


#: Writes one file of a report to the path given.
Writer = Callable[[Path], None]


class EffectBase:
    """An effect of the catalogue: its entry, and what it does in the preparation, the diagnosis and the report.

    Attributes
    ----------
    entry : Effect
        The catalogue entry (name, parameters, metadata).
    role : str
        'mean' (a term of the expected count), 'noise' (the noise model), 'pixels' (which pixels count),
        'alignment' (where the flat field is read), 'counts' (a correction of the data).
    tier : int
        Candidates are tried by tier, then by the chi-square they explain; noise effects by tier just
        before the first localised one ('pixels'): a global variance excess is modelled before outliers are
        judged against it, and after the mean effects that explain more.
    fresh_start : bool
        Its trial changes the data or their relative weights: the trial fit starts afresh, as the first round did.
    refinements : int
        Refits after the trial, each at the estimate its test gives on the previous refit.
    files : tuple of str
        Names of the files its report writes when it is added (:meth:`artefacts`).
    """

    entry: Effect
    role: str = "mean"
    tier: int = 2
    fresh_start: bool = False
    refinements: int = 0
    files: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        return self.entry.name

    # ---- preparation -----------------------------------------------------------------------------

    def configured(self, cfg: dict, *, n_frames: int, detector: tuple[int, int]) -> Any:
        """What the configuration asks of this effect, read and checked before any computation (None: nothing)."""
        return None

    def apply(self, data: Correctable, setting: Any) -> Correctable:
        """``data`` with the configured ``setting`` (not None) applied (default: unchanged)."""
        return data

    # ---- diagnosis -------------------------------------------------------------------------------

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test | None:
        """The effect's test at the fit ``state`` (None: does not apply to this acquisition or hypothesis).

        ``flagged`` (H, W) bool: pixels that a localised effect flagged in this round (left out of global
        variance tests: a localised misfit must not pose as a global one).
        """
        return None

    def trial(self, ctx: Context, state: State, test: Test) -> Hypothesis:
        """The hypothesis a trial refit with this effect fits."""
        raise NotImplementedError(f"{self.name} has no trial")

    def accepted(self, ctx: Context, before: State, after: State, test: Test) -> dict:
        """The keys of its ``diagnosis.json`` entry once added (beyond the common ones)."""
        return {}

    def where(self, test: Test, obs: Observations) -> str:
        """Where in the recording its signature sits."""
        return "the whole detector"

    def estimate(self, extra: dict, params: dict, good: np.ndarray) -> str:
        """One line: the estimated size of the effect."""
        return ""

    def per_frame(self, extra: dict, params: dict) -> np.ndarray | None:
        """Its per-frame estimate (J, n) for the report's picture, where it has one."""
        return None

    def judged_on(self, signature: dict) -> bool:
        """Whether a trial of this effect is judged on this residual signature (``axis``, ``kind``).

        An effect must explain the signature that its own test is about, not just any misfit. The level of
        the residuals against the stated noise model (kind 'level') is the noise model's business: a mean
        effect is never judged on it (while the noise model is off, every mean effect that takes variance out
        of the residuals would seem to make it worse, or a proxy would seem to explain it).
        """
        return self.role == "noise" or signature["kind"] != "level"

    def consistency(self, ctx: Context, before: State, state: State) -> Test | None:
        """Whether the effect, in the model of its trial fit ``state`` (from ``before``), is one effect across the
        recording: of one size wherever the count or the detector row or column differs (None: not tested).

        A detector effect in no catalogue can leave the signature of a catalogue effect (a non-linearity a
        second harmonic, a ghost of an earlier frame a change of dose) but not with one size everywhere: a
        significant test whose sizes, estimated stratum by stratum, span more than ``diagnose.proxy_spread`` times
        the shared fit's (the diagnosis's loop judges both) refuses the effect as a proxy and its signature is
        reported as unexplained. The payload holds 'axis' and 'strata' (those sizes, the shared fit's being 1).
        """
        return None

    def unexplained(self, test: Test) -> dict | None:
        """The ``unexplained`` entry of a significant test of it that was not added (a localised misfit), or None."""
        return None

    # ---- report ----------------------------------------------------------------------------------

    def settings(self, cfg: dict, final: Hypothesis, extra: dict | None, out_dir: Path) -> list[str]:
        """``--set`` options that make ``reconstruct`` use the diagnosis's final model (``extra`` None: not added)."""
        return []

    def artefacts(self, final: Hypothesis, extra: dict | None, cfg: dict) -> dict[str, Writer]:
        """Files the report writes for it: name -> writer (``extra`` None: not added)."""
        return {}
