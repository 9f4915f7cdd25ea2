"""``scatter``: Compton scatter, photons that reach the detector without the gratings' modulation.

The model (``spec/diagnosis.md`` version 4): sample (r, c) of frame j gains the unmodulated count s S_j(r, c),
S_j the superposition of the frame's primary under the kernel, S_j(r, c) = sum over the frame's lit samples
(r', c') of P_j(r', c') K(r - r', c - c'), P = t^f t the primary on the lit rows (none elsewhere, none beyond the
detector), K a normalised Gaussian of std ``load.scatter_width_mm``. Nothing is renormalised: what the kernel
carries off the lit band or the detector is lost, so S falls towards their edges, and a band narrow against the
kernel gets much less scatter than a full field (why slot scanners reject scatter). Two ratios follow:

- s, the scatter per unit primary before the band's loss (``load.scatter``; ``"s"`` in ``diagnosis.json``): a
  pixel in the middle of a wide band under a narrow kernel gets s times its local primary;
- the measured scatter-to-primary ratio over the lit samples, sum of s S over them / sum of P
  (:meth:`ScatterField.share`; the spec's ``"value"``): smaller, by the band's loss (on the 5 mm test scan, a
  15-row band under a 10-row kernel, 0.35 s; 0.17 s at 100 mm).

The paper's Sec. V: "effects that are not included in the model must be corrected for beforehand ... Compton
scatter can be estimated". The simulator makes the field independently (:func:`dfxcorr.sim.simulate.scatter_field`:
a direct sum between rows, an FFT convolution along them, the kernel untruncated); the two agree to 1e-3 of the
field (tests/effects/test_scatter.py).

Where it enters: S couples neighbouring pixels, so it cannot be an unknown of the per-pixel closed-form
solve. It is a known field added to the model's unmodulated offset, the dark (:attr:`LitStore.offset
<dfxcorr.align.LitStore>`, then :attr:`Observations.dark <dfxcorr.observations.Observations>`), which the
compiled kernels, the numpy model and the Fisher information all read, so every stage sees the same
model. Its photons carry shot noise: each sample's variance counts them (:attr:`Observations.offset
<dfxcorr.observations.Observations>`). Counted instead as one factor per pixel (its mean share), the
variance was too low where the modulated count is low: 9.7 % above the noise near the fringe minimum at
s = 0.1, a fringe-phase signature left unexplained. The store holds S coarse (:class:`ScatterField`: each
frame's field on the blur's blocks, interpolated to the samples each stage asks for), not per sample: that
would take 2.2 GB of float32 at full clinical resolution.

The primary needs the transmission t: a retrieval at neutral per-frame parameters over every lit sample takes
the scatter for transmission; it is divided by 1 + the measured ratio, then updated with the previous t's
scatter in the offset. An update maps an error e of t to about -s L e (L the superposition over the band, of
gain at most 1), so plain updates diverge for s > 1: they are damped, each error shrinking by at least
s / (2 + s), until the change bounds the remaining error below :data:`TOLERANCE` (s = 0.1: two updates; 1.5:
seven). Where the blur's blocks are b > 1 pixels wide, t is retrieved on every b-th column only
(:func:`retrieved`).

The diagnosis tests s by its efficient score at the configured kernel width, and its trial fits s on a grid
of widths (the configured one times 1/4 ... 4, then the vertex of a parabola in log width through the best
three): for a given S the model is linear in s, so one Gauss-Newton step from s = 0 with the images profiled
is the weighted least-squares estimate. The grid uses the t of the test's estimate. It keeps the width whose
weighted least-squares cost is lowest: a wrong width misplaces the scatter (true width 100 mm fitted at 50 mm
gave s = 0.117 for 0.1). Then s, at that width, in rounds (:data:`ROUNDS`): the t behind the field at the last s,
s at it, and s again after the per-frame parameters are refitted with s S in the model (:func:`refitted`: the
base fit's parameters take up part of the scatter, 5-10 % of s). The cost is nearly flat in the width around its
minimum while s moves with it (a few % per 10 % of width), so the reported se, at the chosen width, understates
the error of s.

What identifies s: in a scan the active area moves over the detector, so a pixel's scatter (the superposition of
the frame's lit band) changes from frame to frame unlike its primary (which follows t^f at its local row); in
phase stepping every pixel sees the same primary in every step and s S is a share of the transmission.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from typing import Any

import numpy as np

from .. import engine as E
from .. import model as M
from ..align import LitStore, pixel_mm, realign
from ..catalogue import Effect
from ..errors import DfxcorrError
from ..fit import fit_vibrations
from ..io import Reference
from ..observations import Observations
from ..preparation import Correctable, Prepared
from ..retrieve import retrieve
from .base import (
    MEAN,
    Consistency,
    ConsistencyAxis,
    Context,
    EffectBase,
    Estimate,
    Finding,
    Hypothesis,
    Option,
    State,
    Test,
    chi2_test,
    dispersion,
    strongest,
)
from .channel import strata
from .superposition import Primary, ScatterField, block, unit_scatter

log = logging.getLogger(__name__)

#: Most fixed-point updates of the transmission behind the primary (see the module's text).
MAX_UPDATES = 12
#: The updates stop once the transmission's remaining error, bounded from its last change, is below this (relative
#: RMS): the field then matches the simulator's to the noise of t (0.26-0.27 % RMS at s = 0.1 and 1.5, 5 mm scan).
TOLERANCE = 5e-4
#: Kernel widths a trial fits s at, relative to the configured one (then refined between the best three).
WIDTHS = np.array([0.25, 0.5, 1.0, 2.0, 4.0])
#: Most rounds of s and the transmission behind its field in a trial (they stop once s moves by less than a quarter
#: of its standard error).
ROUNDS = 6
#: Samples per retrieval block of the transmission estimate (about 160 bytes each at the peak: 80 MB; a pixel's
#: retrieval does not depend on the blocks).
BLOCK_SAMPLES = 500_000
#: Profiled over known-image information below this share: s is a share of the transmission (not identifiable).
MIN_INFORMATION_SHARE = 1e-6


class ScatterError(DfxcorrError, ValueError):
    """A scatter correction that the scan cannot take (no pixel size to convert the kernel's width)."""


@dataclass(frozen=True)
class Setting:
    """A scatter correction: s (scatter per unit primary) and the kernel's std (mm at the detector). A hashable value
    of those two; ``measured``, the scatter-to-primary ratio over the lit samples that it makes (NaN where not
    computed), and ``start``, a transmission behind the primary at a nearby setting (H, W) where the correction's
    fixed point starts (:func:`transmission`), with its unit field where made (``start_unit``), are not compared."""

    ratio: float
    width_mm: float
    measured: float = dc_field(default=float("nan"), compare=False)
    start: np.ndarray | None = dc_field(default=None, compare=False, repr=False)
    start_unit: ScatterField | None = dc_field(default=None, compare=False, repr=False)


def kernel_pixels(width_mm: float, pixel_mm: tuple[float, float] | None) -> tuple[float, float]:
    """The kernel's std in pixels (between rows, along a row).

    Raises
    ------
    ScatterError
        If the scan file states no pixel size.
    """
    if pixel_mm is None:
        raise ScatterError("load.scatter needs the detector's pixel size (/entry/instrument/detector/"
                           "y_pixel_size and x_pixel_size) to convert load.scatter_width_mm to pixels")
    return width_mm / pixel_mm[0], width_mm / pixel_mm[1]



def retrieved(store: LitStore, reference: Reference, *, step: int = 1) -> np.ndarray:
    """Transmission from a retrieval at neutral per-frame parameters, block by block of rows, shape (H, W) (0 where
    not solvable or not lit).

    Every lit sample counts (the region of interest too: the scatter comes from wherever the primary is). With
    ``step`` > 1 only every step-th column is retrieved and stands for its strip of ``step`` columns (the last strip
    short of a retrieved column: the one before):
    enough for a primary that :func:`unit_scatter` sums on blocks of that side (:func:`block`) before a blur of 32
    of them, at a step-th of the cost (a binned clinical scan: step 5; its diagnosis with scatter retrieved every
    lit sample 13 times).
    """
    J, H, W = store.shape
    cols = np.arange(min(step // 2, W - 1), W, step) if step > 1 else None
    held = np.zeros((H, W if cols is None else cols.size))
    ref = replace(reference, phase=np.unwrap(reference.phase, axis=0))
    for r0, r1 in store.row_runs(BLOCK_SAMPLES * step):
        obs = store.observations(ref, columns=cols, rows=(r0, r1), phase_unwrapped=True)
        rec = retrieve(obs, {}, keep_expected=False)
        rows = obs.rows
        held[rows] = np.where(rec.images.valid, rec.images.t, 0.0)
    return held if cols is None else held[:, np.minimum(np.arange(W) // step, cols.size - 1)]


def field(store: LitStore, reference: Reference, t: np.ndarray, width: tuple[float, float]) -> ScatterField:
    """S of the store's samples with the primary of transmission ``t`` (H, W) and a kernel of std ``width``
    (pixels: between rows, along a row), counts per unit s: the flat field's transmission read at each block's
    position times ``t`` (:class:`Primary`)."""
    return unit_scatter(Primary(reference.transmission, store.u, t, store.row), store.row, store.frame, width)


def transmission(store: LitStore, reference: Reference, setting: Setting, pixel_mm: tuple[float, float] | None, *,
                 start: np.ndarray | None = None, start_unit: ScatterField | None = None,
                 plain: tuple[np.ndarray, ScatterField] | None = None) -> np.ndarray:
    """The sample's transmission (H, W) under the scatter of ``setting``: a retrieval without it, divided by the
    measured ratio's 1 + s share, then damped fixed-point updates with the previous transmission's scatter in the
    offset until the remaining change is below :data:`TOLERANCE` (at most :data:`MAX_UPDATES`).

    Parameters
    ----------
    store, reference
        The samples (without an offset) and their flat field.
    setting : Setting
    pixel_mm : (float, float) or None
        The detector's pixel pitch (mm).
    start : ndarray, shape (H, W), optional
        A transmission to update from instead (the one behind a nearby setting: the updates stop sooner).
    start_unit : ScatterField, optional
        The unit field of ``start`` at the setting's width (:func:`field`), where already made: the first update's.
    plain : (ndarray, ScatterField), optional
        The retrieval without the scatter (:func:`retrieved` at the kernel's :func:`block`), shape (H, W), and its
        unit field at the setting's width, where already made (:class:`Unscattered`).

    Raises
    ------
    ValueError
        If the store already holds an offset.
    """
    if store.offset is not None:
        raise ValueError("these samples already hold an unmodulated offset")
    width = kernel_pixels(setting.width_mm, pixel_mm)
    step, s = block(width), setting.ratio
    if start is None:
        if plain is None:
            t = retrieved(store, reference, step=step)
            unit = field(store, reference, t, width)
        else:
            t, unit = plain
        # the retrieval without the offset takes the scatter for transmission: t is high by about the measured ratio;
        # dividing that out leaves the error's variation across the sample, which the updates take out
        t = t / (1.0 + unit.scaled(s).share())
    else:
        t = start
    # an update maps an error e of t to about -s L e, L the superposition over the band, of gain at most 1: plain
    # updates (omega = 1) diverge for s > 1 (t falls to 0 and the field with it: no correction at all). Damped,
    # every error shrinks by at least q = s / (2 + s) a step (s = 0.1: 0.05)
    omega = 2.0 / (2.0 + s)
    for k in range(MAX_UPDATES):
        made = start_unit if k == 0 and start is not None else None  # the unit field of t, where already made
        update = retrieved(replace(store, offset=(made or field(store, reference, t, width)).scaled(s)), reference,
                           step=step)
        new = (1.0 - omega) * t + omega * update
        change = float(np.sqrt(np.mean((new - t) ** 2) / max(np.mean(t ** 2), 1e-300)))
        t = new
        # the remaining error, at most change q / (1 - q) = change s / 2
        if change * s / 2.0 < TOLERANCE:
            break
    else:
        log.warning("scatter: the transmission behind the primary changed by %.2g (relative RMS) in its last of %d "
                    "updates at s = %g", change, MAX_UPDATES, s)
    return t


def scattered(store: LitStore, reference: Reference, setting: Setting, pixel_mm: tuple[float, float] | None
              ) -> LitStore:
    """The store with the scatter of ``setting`` in its offset (see the module's text).

    Raises
    ------
    ValueError
        If the store already holds an offset.
    """
    t = transmission(store, reference, setting, pixel_mm, start=setting.start, start_unit=setting.start_unit)
    return replace(store, offset=field(store, reference, t, kernel_pixels(setting.width_mm, pixel_mm)).scaled(
        setting.ratio))


def profiler(prep: Prepared, state: State) -> Callable[[ScatterField], tuple[float, float, float]]:
    """Unit field -> s along it (a kernel width and a transmission behind the primary), at the fit's per-frame
    parameters.

    For a given field S the model is linear in s and the images are profiled per pixel: one Gauss-Newton step
    from s = 0 is the weighted least-squares estimate, exactly. The samples and the images at s = 0 are made once,
    for every width and transmission a trial tries.

    Parameters
    ----------
    prep : Prepared
        The preparation of the fit's hypothesis (without scatter).
    state : State
        The fit: its per-frame parameters and the samples of its columns (their use, noise model and alignment).

    Returns
    -------
    callable
        (the unit field, :func:`field` of a transmission behind the primary (:func:`transmission`) at a kernel
        width) -> (s, at least 0; the weighted least-squares cost at it with the fit's weights, images profiled;
        the measured ratio per unit s, :meth:`ScatterField.share`).
    """
    # the fit's weights, the same for every candidate: the Pearson chi-square's variance floors would turn a
    # candidate that over-subtracts somewhere into a huge cost (measured: 164137 at 50 mm against 118789 at
    # 100 mm, the true width, and 2e7 at 200 mm), and without the scatter in the model its variance is in t.
    # On the fit's columns, as its test: every held column's solve was (K, C) float64 arrays times seven
    weights = state.fit_rec.weights
    obs = realign(prep.store, prep.reference, state.fit_obs, state.hypothesis.shift)
    images, _ = E.solved(obs, M.channels(state.params, x=obs.x, n_frames=obs.n_frames), weights, keep_inverse=False)

    def fitted(F: ScatterField) -> tuple[float, float, float]:
        U, info, _, cost = score(obs, state.params, images, weights, F.take(columns=obs.columns).astype(np.float64))
        # no information: a field that vanishes on the fit's columns (a transmission of 0) leaves s at 0
        s = max(U / info, 0.0) if info > 0 else 0.0
        return s, cost - s * (2 * U - info * s), F.share()

    return fitted


def refitted(prep: Prepared, state: State, fit: dict[str, Any], F: ScatterField, s: float) -> tuple[float, float]:
    """s once more, after the fit's per-frame parameters are refitted with s S in the model: (s, the measured ratio
    per unit s).

    The parameters of a fit without the scatter take up part of it (the unmodulated counts change each frame's
    apparent visibility); a step of s at them falls short (on the 5 mm test scan 0.090-0.095 for 0.1, seeds
    11-15). At the refitted ones the step from s is the rest (0.096 and 0.100 on seeds 12 and 13).

    Parameters
    ----------
    prep, state
        As :func:`profiler`.
    fit : dict
        The ``fit`` section of the configuration (the refit's options, as the diagnosis's own fits).
    F : ScatterField
        The unit field (:func:`field`) of the transmission behind the primary at ``s``, at the kernel's width.
    s : float
        The scatter per unit primary of the first estimate.
    """
    weights = state.fit_rec.weights
    obs = realign(prep.store, prep.reference, state.fit_obs, state.hypothesis.shift)
    S = F.take(columns=obs.columns).astype(np.float64)
    held = replace(obs, dark=obs.dark + s * S, offset=s * S if obs.offset is None else obs.offset + s * S)
    params = state.params
    if params:
        fitted = fit_vibrations(held, effects=list(params), start=params, weights=weights, staged=False,
                                circmean_iterations=0, reweight=0, with_uncertainty=False, gtol=fit["gtol"],
                                precondition=fit["precondition"], preconditioner=fit["preconditioner"],
                                visibility_gauge=fit["visibility_gauge"],
                                visibility_quantile=fit["visibility_quantile"], gauge_fraction=fit["gauge_fraction"])
        params = {k: v for k, v in fitted.params.items() if k in params}
    images, _ = E.solved(held, M.channels(params, x=held.x, n_frames=held.n_frames), weights, keep_inverse=False)
    U, info, _, _ = score(held, params, images, weights, S)
    return (max(s + U / info, 0.0) if info > 0 else s), F.share()


def score(obs: Observations, params: dict[str, Any], images: M.Images, weights: np.ndarray, field_: np.ndarray
          ) -> tuple[float, float, float, float]:
    """Efficient score of s along ``field_`` at images fitted with ``weights``, the images profiled out.

    dIbar/ds = S at fixed images; per pixel the part of S that the image columns (A, dIbar/dc, dIbar/ds of
    :func:`dfxcorr.model.image_columns`) take up is projected out with the weights, S_perp = S - X N^-1
    X^T W S. The per-frame parameters are not profiled: their information only lowers that of s, so the
    statistic U^2 / I is conservative.

    Parameters
    ----------
    obs : Observations
    params : dict
        Per-frame parameters of the fit.
    images : Images
        Fitted with ``weights`` (so that the residuals are orthogonal to the image columns).
    weights : ndarray, shape (K, C)
        Inverse variances (counts^-2); only used samples of solved pixels count.
    field_ : ndarray, shape (K, C)
        S (counts per unit s).

    Returns
    -------
    U : float
        sum w (I - Ibar) S_perp (dimensionless per unit s).
    info : float
        sum w S_perp^2, the information of s at profiled images.
    known : float
        sum w S^2, its information at known images (``info / known`` near 0: s is a share of the images).
    cost : float
        sum w (I - Ibar)^2, the weighted least-squares cost at these images.
    """
    w = np.where(obs.use & obs.gather_valid(images.valid), weights, 0.0)
    dsg = M.design(obs, params)
    c = obs.gather(images.coef)
    cols = [dsg.A, *M.image_columns(dsg, c[..., 1], c[..., 2])]
    fitted = obs.gather(M.solve_pixels(obs, cols, field_, w)[0])
    perp = field_ - sum(fitted[..., a] * X for a, X in enumerate(cols))
    resid = obs.counts - M.expected(obs, dsg, images)
    return (float(np.sum(w * resid * perp)), float(np.sum(w * perp * perp)), float(np.sum(w * field_ * field_)),
            float(np.sum(w * resid * resid)))


@dataclass(frozen=True)
class ScatterScore:
    """A scatter test's payload: s estimated from the score (one step from 0) and its standard error, the kernel
    width it was tested at (mm), and the share of s's information left after profiling the images."""

    value: float
    se: float
    width_mm: float
    information_share: float = 0.0


@dataclass(frozen=True)
class Unscattered:
    """The transmission of a prepared scan retrieved without scatter (:func:`retrieved`, at the :func:`block` of a
    kernel of ``width_mm``) and the unit field of its primary at that width: what the test scores s along, and
    where the trial's fixed point starts (a value, so that the diagnosis makes them once per corrected scan)."""

    width_mm: float

    def __call__(self, prep: Prepared) -> tuple[np.ndarray, ScatterField]:
        width = kernel_pixels(self.width_mm, pixel_mm(prep.scan))
        t = retrieved(prep.store, prep.reference, step=block(width))
        return t, field(prep.store, prep.reference, t, width)


class Scatter(EffectBase[ScatterScore]):
    entry = Effect("scatter", None, False, ("s",), 0.0, "none",
                   "Compton scatter: unmodulated counts s times the superposition of the frame's primary under a "
                   "wide kernel")
    policy = MEAN

    def configured(self, cfg: dict[str, Any], *, n_frames: int, detector: tuple[int, int]) -> Any:
        load = cfg["load"]
        return Setting(float(load["scatter"]), float(load["scatter_width_mm"])) if load["scatter"] else None

    def apply(self, data: Correctable, setting: Any) -> Correctable:
        if data.reference is None:
            raise ValueError("the scatter correction needs the flat field")
        store = data.store.shifted(data.shift) if np.any(data.shift) else data.store
        # the shift is read again by the preparation: the store keeps its own u
        return replace(data, store=replace(data.store, offset=scattered(store, data.reference, setting,
                                                                          data.pixel_mm).offset))

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test[ScatterScore] | None:
        prep = ctx.corrected(state.hypothesis)
        if prep.store.offset is not None:
            return None  # in the model already (configured, or a correction of this hypothesis)
        width_mm = float(ctx.cfg["load"]["scatter_width_mm"])
        if pixel_mm(prep.scan) is None:
            # a kernel width in mm means nothing without the pixel pitch (an imported recording may not state it)
            return Test(0.0, 1, 1.0, 0.0, ScatterScore(0.0, np.inf, width_mm), identifiable=False)
        # measured, not assumed from the geometry: in phase stepping every step sees the same primary and the
        # share of S's information left after profiling the images is ~1e-31 (5-step simulation), in a scan ~0.1.
        # On the fit's columns, as the channel effects' tests: the score of every column would cost a fifth of the
        # paper study's tests (a stepping recording shows its ~1e-31 share of information there as well)
        obs = state.fit_obs
        # the fit's columns only (the field is held coarse): a clinical scan's field of every sample was most of its
        # diagnosis's peak memory
        S = ctx.cached(Unscattered(width_mm), state.hypothesis)[1].take(columns=obs.columns).astype(np.float64)
        U, info, known, _ = score(obs, state.params, state.fit_rec.images, state.fit_rec.weights, S)
        identifiable = info > MIN_INFORMATION_SHARE * known
        # quasi-likelihood: the dispersion of the fit, not the stated noise model, scales the score's variance
        phi = dispersion(state)
        stat = max(U, 0.0) ** 2 / (info * phi) if identifiable else 0.0
        payload = ScatterScore(U / info if identifiable else 0.0,
                               float(np.sqrt(phi / info)) if identifiable else np.inf, width_mm,
                               info / max(known, 1e-300))
        return chi2_test(stat, 1, payload, identifiable=bool(identifiable), explains=stat)

    def trial(self, ctx: Context, state: State, test: Test[ScatterScore]) -> Hypothesis:
        hyp = state.hypothesis
        prep = ctx.corrected(hyp)
        start = max(test.payload.value, 0.0)
        # the kernel's width is profiled too (a wrong one misplaces the scatter: true 100 mm fitted with 50 mm gave
        # s = 0.117 for 0.1 and a dark field 12 % low); the search's t at the test's estimate, the final one at the
        # best setting (the module's text)
        configured = float(test.payload.width_mm)
        t = transmission(prep.store, prep.reference, Setting(start, configured), pixel_mm(prep.scan),
                         plain=ctx.cached(Unscattered(configured), hyp))
        profile = profiler(prep, state)

        def unit(t: np.ndarray, width_mm: float) -> ScatterField:
            return field(prep.store, prep.reference, t, kernel_pixels(width_mm, pixel_mm(prep.scan)))

        fitted: dict[float, tuple[float, float, float]] = {}
        kept: list[ScatterField] = []  # the best width's field so far: where the first round's updates start

        def tried(w: float) -> None:
            fitted[w] = profile(F := unit(t, w))
            if min(fitted, key=lambda v: fitted[v][1]) == w:
                kept[:] = [F]

        for w in configured * WIDTHS:
            tried(w)
        widths = sorted(fitted)
        best = min(range(len(widths)), key=lambda i: fitted[widths[i]][1])
        if 0 < best < len(widths) - 1:
            x = np.log(widths[best - 1:best + 2])
            a, b, _ = np.polyfit(x, [fitted[w][1] for w in widths[best - 1:best + 2]], 2)
            if a > 0:
                tried(float(np.exp(np.clip(-b / (2 * a), x[0], x[2]))))
        width_mm = float(min(fitted, key=lambda w: fitted[w][1]))
        # s and the t behind its field, in turn: a t made at a low s is high by the scatter left in it, its field
        # too, and s comes out low again; each round shrinks the gap by about s times the measured ratio per unit s
        # (0.035 at s = 0.1 on the 5 mm test scan, one round; at s = 1.5, 0.5: 1.30 after one round for 1.5). Each
        # round's t is updated from the last one's: s moves little, so one or two updates reach the tolerance
        s, F = fitted[width_mm][0], kept[0]
        for _ in range(ROUNDS):
            t = transmission(prep.store, prep.reference, Setting(s, width_mm), pixel_mm(prep.scan), start=t,
                             start_unit=F)
            F = unit(t, width_mm)
            (s, share), moved = refitted(prep, state, ctx.cfg["fit"], F, profile(F)[0]), s
            if abs(s - moved) < 0.25 * test.payload.se:
                break
        # the correction's t starts at the last round's (s has moved little since: an update or two)
        return hyp.but(corrections=(*hyp.corrections, (self.name, Setting(s, width_mm, measured=s * share, start=t,
                                                                          start_unit=F))))

    def accepted(self, ctx: Context, before: State, after: State, test: Test[ScatterScore]) -> Finding:
        setting = dict(after.hypothesis.corrections)[self.name]
        # "value" is the spec's mean scatter-to-primary ratio over the lit samples; "s" the model's scatter per unit
        # primary (load.scatter), larger by what the kernel carries off the lit bands
        per_unit = setting.measured / setting.ratio if setting.ratio > 0 else 0.0
        se = test.payload.se
        return Finding("all frames; unmodulated counts that follow the sample (largest share behind its dense parts)",
                       f"{100 * setting.measured:.3g} % of the primary in the lit band (se {100 * se * per_unit:.2g} "
                       f"%): s = {100 * setting.ratio:.3g} % per unit primary (se {100 * se:.2g} %), kernel std "
                       f"{setting.width_mm:g} mm",
                       {"value": setting.measured, "se": se * per_unit, "s": setting.ratio, "s_se": se,
                        "width_mm": setting.width_mm},
                       options=(Option("load.scatter", f"{setting.ratio:.6g}"),
                                Option("load.scatter_width_mm", f"{setting.width_mm:g}")))

    def measure(self, ctx: Context, state: State) -> Estimate | None:
        setting = dict(state.hypothesis.corrections).get(self.name)
        if setting is None:
            return None
        # the score of s beyond the fitted one along the fitted field, at this fit: its step and standard error
        U, info, _, _ = score(state.fit_obs, state.params, state.fit_rec.images, state.fit_rec.weights,
                              self._unit_field(ctx, state))
        if info <= 0:
            return Estimate(np.asarray(setting.ratio), np.asarray(np.inf))  # no field on these columns
        return Estimate(np.asarray(setting.ratio + U / info), np.asarray(np.sqrt(dispersion(state) / info)))

    def consistency(self, ctx: Context, before: State, state: State) -> Consistency | None:
        # scatter has one ratio across the recording: s refitted on the pixels of each stratum by detector row and
        # by expected count (one step from the fitted s along the fitted field) must agree; what an effect in no
        # catalogue adds (a ghost of an earlier frame, say) follows other rows and counts than the primary's blur
        setting = dict(state.hypothesis.corrections).get(self.name)
        if setting is None or setting.ratio <= 0:
            return None
        S = self._unit_field(ctx, state)
        obs, rec = state.fit_obs, state.fit_rec
        found = {}
        axes: tuple[ConsistencyAxis, ...] = ("row", "count")
        for by in axes:
            labels = strata(obs, rec.expected, by=by)
            n = int(labels.max()) + 1
            if n < 2:
                continue
            U, info = np.zeros(n), np.zeros(n)
            for k in range(n):
                U[k], info[k], _, _ = score(obs, state.params, rec.images, np.where(labels == k, rec.weights, 0.0), S)
            ok = info > 0
            if ok.sum() < 2:
                continue
            stat = (float(np.sum(U[ok] ** 2 / info[ok])) - float(U[ok].sum()) ** 2 / float(info[ok].sum()))
            sizes = 1.0 + np.where(ok, U / np.where(ok, info, 1.0), 0.0) / setting.ratio
            found[by] = chi2_test(max(stat, 0.0) / dispersion(state), int(ok.sum()) - 1,
                                  tuple(float(s) for s in sizes))
        if not found:
            return None
        axis, t = strongest(found)
        return Consistency(t.statistic, t.dof, t.p_value, t.log_p, axis, t.payload)

    def _unit_field(self, ctx: Context, state: State) -> np.ndarray:
        """The unit scatter field in the model of ``state`` on its fit's columns: its corrected scan's offset per unit
        s (made once, by the correction: the transmission behind it is the costliest part of the diagnosis)."""
        offset = ctx.corrected(state.hypothesis).store.offset
        if not isinstance(offset, ScatterField):
            raise ValueError("the hypothesis holds no scatter correction")
        return np.asarray(replace(offset, ratio=1.0).take(columns=state.fit_obs.columns), dtype=np.float64)


EFFECT = Scatter()
