"""``scatter``: Compton scatter, photons that reach the detector without the gratings' modulation.

The model (``spec/diagnosis.md`` version 3): sample k of frame j gains the unmodulated count s S_k, S the
frame's primary P = t^f t on its lit rows, blurred by a Gaussian of std ``load.scatter_width_mm`` (a
normalised blur within the frame's lit rows and the detector) and scaled so that its total over the frame
is the primary's: s is the scatter-to-primary ratio of the totals, the mean ratio over the lit samples (the
paper's Sec. V: "effects that are not included in the model must be corrected for beforehand ... Compton
scatter can be estimated").

Where it enters: S couples neighbouring pixels, so it cannot be an unknown of the per-pixel closed-form
solve. It is a known field added to the model's unmodulated offset, the dark (:attr:`LitStore.offset
<dfxcorr.align.LitStore>`, then :attr:`Observations.dark <dfxcorr.observations.Observations>`), which the
compiled kernels, the numpy model and the Fisher information all read, so every stage sees the same
model. Its photons carry shot noise: each sample's variance counts them (:attr:`Observations.offset
<dfxcorr.observations.Observations>`). Counted instead as one factor per pixel (its mean share), the
variance was too low where the modulated count is low: 9.7 % above the noise near the fringe minimum at
s = 0.1, a fringe-phase signature left unexplained.

The primary needs the transmission t: a retrieval at neutral per-frame parameters over every lit sample,
then fixed-point updates with the previous t's scatter in the offset. Without the offset t comes out too
high by the local scatter share (median 23 % at s = 0.1 on the thorax, where the scatter reaches 5x the
primary behind the spine); each update shrinks that error about fivefold (measured: S off by 8.8 %, 0.86 %,
0.36 %, 0.35 % RMS after 0-3 updates; the last is the noise of t), so three are taken.

The diagnosis tests s by its efficient score at the configured kernel width, and its trial fits s by
Gauss-Newton on a grid of widths (the configured one times 1/4 ... 4, then the vertex of a parabola in log
width through the best three), keeping the width whose weighted least-squares cost is lowest: a wrong
width misplaces the scatter (measured on the 5 mm test scan: true width 100 mm fitted at 50 mm gave
s = 0.117 for 0.1). The cost is nearly flat in the width around its minimum while s moves with it (a few
% per 10 % of width), so the reported se, at the chosen width, understates the error of s.

What identifies s: in a scan the active area moves over the detector, so a pixel's scatter (a blur of the
frame's lit band) changes from frame to frame unlike its primary (which follows t^f at its local row); in
phase stepping every pixel sees the same primary in every step and s S is a share of the transmission.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal

from .. import model as M
from ..align import LitStore, interpolate_rows, pixel_mm, realign
from ..catalogue import Effect
from ..errors import DfxcorrError
from ..io import Reference
from ..observations import Observations
from ..retrieve import retrieve
from .base import Context, EffectBase, Hypothesis, Preparation, State, Test, chi2_test

#: Fixed-point updates of the transmission behind the primary (see the module's text).
UPDATES = 3
#: Gauss-Newton steps of s in a trial (the model is linear in s for a given S; S follows t).
STEPS = 2
#: Kernel widths a trial fits s at, relative to the configured one (then refined between the best three).
WIDTHS = np.array([0.25, 0.5, 1.0, 2.0, 4.0])
#: Samples per retrieval block of the transmission estimate (about 160 bytes each at the peak).
BLOCK_SAMPLES = 2_000_000
#: Profiled over known-image information below this share: s is a share of the transmission (not identifiable).
MIN_INFORMATION_SHARE = 1e-6


class ScatterError(DfxcorrError, ValueError):
    """A scatter correction that the scan cannot take (no pixel size to convert the kernel's width)."""


@dataclass(frozen=True)
class Setting:
    """A scatter correction: the ratio s and the kernel's std (mm at the detector). A hashable value."""

    ratio: float
    width_mm: float


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


def blur(a: np.ndarray, sigma: float, *, axis: int = -1) -> np.ndarray:
    """Gaussian blur of ``a`` along ``axis`` (std ``sigma`` pixels, kernel cut at 4 sigma), zeros beyond the edges.

    scipy.ndimage.gaussian_filter1d(mode='constant') by FFT: the scatter's kernel spans hundreds of pixels
    (50 mm at 0.3 mm: sigma 167), where the direct sum took 10 s for a 5-step 512 x 1536 scan.
    """
    radius = int(4.0 * sigma + 0.5)
    x = np.arange(-radius, radius + 1, dtype=float)
    kernel = np.exp(-0.5 * (x / max(sigma, 1e-12)) ** 2)
    shape = [1] * a.ndim
    shape[axis] = kernel.size
    return signal.fftconvolve(a, (kernel / kernel.sum()).reshape(shape), mode="same", axes=axis)


def primary(store: LitStore, reference: Reference, t: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """Block indices (n,) -> the unmodulated primary t^f t of those blocks' samples (counts, (n, W) float32), the
    flat field's transmission read at each block's position: what :func:`unit_scatter` blurs.

    ``t`` (H, W): the sample's transmission."""
    return lambda idx: interpolate_rows(reference.transmission, store.u[idx], dtype=np.float32) * t[store.row[idx]]


def unit_scatter(primary: Callable[[np.ndarray], np.ndarray], row: np.ndarray, frame: np.ndarray,
                 width: tuple[float, float], *, columns: np.ndarray | None = None) -> np.ndarray:
    """S of every sample: its frame's primary blurred within the frame's lit rows, scaled to the primary's total.

    Parameters
    ----------
    primary : callable
        Block indices (n,) -> the unmodulated primary t^f t of those blocks' samples (counts), shape (n, W), every
        detector column: made a frame at a time (a clinical scan's primary of every sample at once is gigabytes).
    row, frame : ndarray of int, shape (K,)
        Detector row and frame of each block.
    width : (float, float)
        Kernel std between rows and along a row (pixels).
    columns : ndarray of int, optional
        The detector columns to return (default every one); the blur still sees every column.

    Returns
    -------
    ndarray, shape (K, W) or (K, columns), float32
        S: sum over a frame's samples of S equals that of the primary, so s S has scatter-to-primary ratio s.
        The blur is normalised by the kernel's weight inside the frame's lit rows and the detector, so the
        scatter keeps its level up to the edges of the lit band.
    """
    out: np.ndarray | None = None
    order = np.argsort(frame, kind="stable")
    bounds = np.searchsorted(frame[order], np.arange(int(frame.max(initial=-1)) + 2))
    for j in range(bounds.size - 1):
        idx = order[bounds[j]:bounds[j + 1]]
        if idx.size == 0:
            continue
        p = primary(idx)
        if out is None:
            out = np.zeros((row.size, p.shape[1] if columns is None else len(columns)), np.float32)
        # the frame's lit band as an image (rows left out by alignment stay empty and get no weight), in blocks of
        # b x b pixels: a kernel of hundreds of pixels (50 mm at 0.148 mm: 338) is blurred as well on a grid
        # b = sigma / 32 coarser and interpolated back, at about a b^2-th of the cost (a binned clinical scan,
        # sigma 169: 7.5 -> 0.8 s, the field within 1e-4 of the pixel-wise blur at the median and 0.7 % at worst,
        # at the lit band's edges; sigma / 16: 0.6 s, 1.5 %)
        b = max(int(min(width) // COARSE_PER_SIGMA), 1)
        local = row[idx] - row[idx].min()
        nr, nc = -(-(int(local.max()) + 1) // b), -(-p.shape[1] // b)
        band = np.zeros((nr * b, nc * b))
        lit, across = np.zeros(nr * b), np.zeros(nc * b)
        band[local, :p.shape[1]], lit[local], across[:p.shape[1]] = p, 1.0, 1.0
        band, lit, across = band.reshape(nr, b, nc, b).sum(axis=(1, 3)), lit.reshape(nr, b).sum(1), \
            across.reshape(nc, b).sum(1)
        blurred = blur(blur(band, width[0] / b, axis=0), width[1] / b, axis=1)
        inside = np.outer(blur(lit, width[0] / b), blur(across, width[1] / b))
        spread = np.where(inside > 0, blurred / np.where(inside > 0, inside, 1.0), 0.0)
        total = float(np.sum(spread * np.outer(lit, across)))
        if total > 0:
            cols = np.arange(p.shape[1]) if columns is None else np.asarray(columns)
            out[idx] = _at_pixels(spread, local, cols, b) * (p.sum() / total)
    return np.zeros((row.size, 0), np.float32) if out is None else out


#: unit_scatter blurs on blocks of sigma / COARSE_PER_SIGMA pixels (at least one).
COARSE_PER_SIGMA = 32


def _at_pixels(grid: np.ndarray, rows: np.ndarray, cols: np.ndarray, b: int) -> np.ndarray:
    """Values of a field given on blocks of b x b pixels (centres at (i + 1/2) b) at pixel rows x columns, by
    linear interpolation between block centres (held beyond the outer ones); the grid itself where b = 1."""
    def weights(pixels: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        at = np.clip((pixels + 0.5) / b - 0.5, 0, n - 1)
        lo = np.minimum(np.floor(at).astype(int), n - 1)
        return lo, np.minimum(lo + 1, n - 1), at - lo

    r0, r1, a = weights(rows, grid.shape[0])
    c0, c1, c = weights(cols, grid.shape[1])
    by_row = grid[r0] * (1 - a)[:, None] + grid[r1] * a[:, None]
    return by_row[:, c0] * (1 - c) + by_row[:, c1] * c


def retrieved(store: LitStore, reference: Reference) -> np.ndarray:
    """Transmission from a retrieval at neutral per-frame parameters, block by block of rows, shape (H, W) (0 where
    not solvable or not lit).

    Every lit sample counts (the region of interest too: the scatter comes from wherever the primary is).
    """
    J, H, W = store.shape
    t = np.zeros((H, W))
    ref = replace(reference, phase=np.unwrap(reference.phase, axis=0))
    for r0, r1 in store.row_runs(BLOCK_SAMPLES):
        obs = store.observations(ref, rows=(r0, r1), phase_unwrapped=True)
        rec = retrieve(obs, {}, keep_expected=False)
        obs.place(t, np.where(rec.images.valid, rec.images.t, 0.0))
    return t


def scattered(store: LitStore, reference: Reference, setting: Setting, pixel_mm: tuple[float, float] | None
              ) -> LitStore:
    """The store with the scatter of ``setting`` in its offset (see the module's text).

    Raises
    ------
    ValueError
        If the store already holds an offset.
    """
    if store.offset is not None:
        raise ValueError("these samples already hold an unmodulated offset")
    width = kernel_pixels(setting.width_mm, pixel_mm)

    def with_field(t: np.ndarray) -> LitStore:
        return replace(store, offset=setting.ratio * unit_scatter(primary(store, reference, t), store.row,
                                                                  store.frame, width))

    t = retrieved(store, reference)
    for _ in range(UPDATES):
        t = retrieved(with_field(t), reference)
    return with_field(t)


def profile(prep: Any, state: State, setting: Setting) -> tuple[float, float]:
    """s by Gauss-Newton at the setting's kernel width from its ratio, at the fit's per-frame parameters.

    The model is linear in s for a given field S (the images profiled per pixel), so a step is exact for that
    S; S follows the transmission estimated under s, so :data:`STEPS` steps are taken.

    Parameters
    ----------
    prep : Prepared
        The preparation of the fit's hypothesis (without scatter).
    state : State
        The fit: its per-frame parameters and the samples of its columns (their use, noise model and alignment).
    setting : Setting
        Kernel width, and the ratio to start from.

    Returns
    -------
    s : float
        The estimate (at least 0).
    cost : float
        The weighted least-squares cost (the fit's weights) that the last step predicts at it, images profiled.
    """
    s, chi2 = setting.ratio, np.inf
    # the fit's weights, the same for every candidate: the Pearson chi-square's variance floors would turn a
    # candidate that over-subtracts somewhere into a huge cost (measured: 164137 at 50 mm against 118789 at
    # 100 mm, the true width, and 2e7 at 200 mm), and without the scatter in the model its variance is in t.
    # On the fit's columns, as its test: every held column's solve was (K, C) float64 arrays times seven
    weights = state.fit_rec.weights
    for _ in range(STEPS):
        if s <= 0:
            break
        store = scattered(prep.store, prep.reference, replace(setting, ratio=s), pixel_mm(prep.scan))
        obs = realign(store, prep.reference, state.fit_obs, state.hypothesis.shift)
        images = M.solve_images(obs, M.design(obs, state.params), weights)
        assert store.offset is not None
        U, info, _, cost = score(obs, state.params, images, weights,
                                 store.offset[:, obs.columns].astype(np.float64) / s)
        step = max(U / info, -s)
        s, chi2 = s + step, cost - info * step * (2 * U / info - step)
    return s, chi2


def score(obs: Observations, params: dict, images: M.Images, weights: np.ndarray, field_: np.ndarray
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
    w = np.where(obs.use & images.valid[obs.pixel], weights, 0.0)
    dsg = M.design(obs, params)
    c = images.coef[obs.pixel]
    cols = [dsg.A, *M.image_columns(dsg, c[..., 1], c[..., 2])]
    coef, _, _ = M.solve_pixels(obs, cols, field_, w)
    perp = field_ - sum(coef[obs.pixel, :, a] * X for a, X in enumerate(cols))
    resid = obs.counts - M.expected(obs, dsg, images)
    return (float(np.sum(w * resid * perp)), float(np.sum(w * perp * perp)), float(np.sum(w * field_ * field_)),
            float(np.sum(w * resid * resid)))


class Scatter(EffectBase):
    entry = Effect("scatter", None, False, ("s",), 0.0, "none",
                   "Compton scatter: unmodulated counts s times the frame's primary blurred by a wide kernel")
    role = "mean"

    def configured(self, cfg: dict, *, n_frames: int, detector: tuple[int, int]) -> Any:
        load = cfg["load"]
        return Setting(float(load["scatter"]), float(load["scatter_width_mm"])) if load["scatter"] else None

    def prepare(self, prep: Preparation, setting: Any) -> Preparation:
        if prep.reference is None:
            raise ValueError("the scatter correction needs the flat field")
        store = prep.store.shifted(prep.shift) if np.any(prep.shift) else prep.store
        # the shift is read again by the preparation: the store keeps its own u
        return replace(prep, store=replace(prep.store, offset=scattered(store, prep.reference, setting,
                                                                          prep.pixel_mm).offset))

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test | None:
        prep = ctx.prepared(state.hypothesis)
        if prep.store.offset is not None:
            return None  # in the model already (configured, or a correction of this hypothesis)
        width_mm = float(ctx.cfg["load"]["scatter_width_mm"])
        if pixel_mm(prep.scan) is None:
            # a kernel width in mm means nothing without the pixel pitch (an imported recording may not state it)
            return Test(0.0, 1, 1.0, 0.0, identifiable=False, payload={"value": 0.0, "se": np.inf,
                                                                          "width_mm": width_mm})
        # measured, not assumed from the geometry: in phase stepping every step sees the same primary and the
        # share of S's information left after profiling the images is ~1e-31 (5-step simulation), in a scan ~0.1
        key = ("scatter field", state.hypothesis.corrections)
        if key not in ctx.memo:
            store, ref = prep.store, prep.reference
            t = retrieved(store, ref)
            # the fit's columns only, the primary a frame at a time: a clinical scan's field of every sample was
            # most of its diagnosis's peak memory
            ctx.memo[key] = unit_scatter(primary(store, ref, t), store.row, store.frame,
                                         kernel_pixels(width_mm, pixel_mm(prep.scan)), columns=state.fit_obs.columns)
        # on the fit's columns, as the channel effects' tests: the score of every column was a fifth of the paper
        # study's tests (a stepping recording shows its ~1e-31 share of information there as well)
        obs = state.fit_obs
        U, info, known, _ = score(obs, state.params, state.fit_rec.images, state.fit_rec.weights,
                                  ctx.memo[key].astype(np.float64))
        identifiable = info > MIN_INFORMATION_SHARE * known
        # quasi-likelihood: the dispersion of the fit, not the stated noise model, scales the score's variance
        dispersion = max(state.reduced_chi2, 1.0)
        stat = max(U, 0.0) ** 2 / (info * dispersion) if identifiable else 0.0
        payload = {"value": U / info if identifiable else 0.0, "se": float(np.sqrt(dispersion / info))
                   if identifiable else np.inf, "width_mm": width_mm, "information_share": info / max(known, 1e-300)}
        return chi2_test(stat, 1, identifiable=bool(identifiable), explains=stat, payload=payload)

    def trial(self, ctx: Context, state: State, test: Test) -> Hypothesis:
        hyp = state.hypothesis
        prep = ctx.prepared(hyp)
        start = max(test.payload["value"], 0.0)
        # The kernel's width is profiled too: a wrong one misplaces the scatter (measured: true 100 mm fitted with
        # 50 mm gave s = 0.117 for 0.1 and a dark field 12 % low), so s is fitted on a grid of widths, factor 2
        # apart around the configured one, then at the vertex of a parabola in log width through the best three
        fitted = {w: profile(prep, state, Setting(start, w)) for w in test.payload["width_mm"] * WIDTHS}
        widths = sorted(fitted)
        best = min(range(len(widths)), key=lambda i: fitted[widths[i]][1])
        if 0 < best < len(widths) - 1:
            x = np.log(widths[best - 1:best + 2])
            a, b, _ = np.polyfit(x, [fitted[w][1] for w in widths[best - 1:best + 2]], 2)
            if a > 0:
                w = float(np.exp(np.clip(-b / (2 * a), x[0], x[2])))
                fitted[w] = profile(prep, state, Setting(fitted[widths[best]][0], w))
        width_mm = float(min(fitted, key=lambda w: fitted[w][1]))
        return hyp.but(corrections=(*hyp.corrections, (self.name, Setting(fitted[width_mm][0], width_mm))))

    def accepted(self, ctx: Context, before: State, after: State, test: Test) -> dict:
        setting = dict(after.hypothesis.corrections)[self.name]
        return {"value": setting.ratio, "se": test.payload["se"], "width_mm": setting.width_mm}

    def where(self, test: Test, obs: Observations) -> str:
        return "all frames; unmodulated counts that follow the sample (largest share behind its dense parts)"

    def estimate(self, extra: dict, params: dict, good: np.ndarray) -> str:
        return (f"s = {100 * extra['value']:.3g} % of the primary (se {100 * extra['se']:.2g} %), kernel std "
                f"{extra['width_mm']:g} mm")

    def settings(self, cfg: dict, final: Hypothesis, extra: dict | None, out_dir: Path) -> list[str]:
        return [f"load.scatter={extra['value']:.6g}", f"load.scatter_width_mm={extra['width_mm']:g}"] \
            if extra is not None else []


EFFECT = Scatter()
