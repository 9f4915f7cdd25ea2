"""Stage 3, motion-pixel masking (paper Sec. II-E).

Where part of the sample moves during the scan, its pixels' frames disagree with any static image and
the fit would blame the gratings. Such pixels are found before the vibration fit from the per-pixel
residual of a retrieval (eq. 35) and left out of the vibration fit only.

Vibrations raise that residual too, in proportion to how strongly a pixel's fringe responds to a phase
change (t v vf tf)^2 / Ibar; unmodelled, they dominate it in bright, modulated pixels, where they would
hide what moved and mask what did not. The retrieval therefore uses a quick pilot estimate of the
paper's per-frame terms, and the score divides the per-pixel reduced residual by 1 + gamma q_i, with
q_i that sensitivity and gamma fitted robustly over all pixels, for what the pilot leaves.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import replace

import numpy as np
from scipy import ndimage
from scipy.linalg import lstsq

from . import engine as E
from . import kernels as K
from . import model as M
from .catalogue import PAPER_MODEL, neutral_params
from .chunks import row_counts
from .fit import model_at
from .frames import well_determined
from .noise import noise_weights
from .observations import Observations
from .stats import chi2_log_tails
from .subsets import spread_columns


def motion_statistics(obs: Observations, params: dict, *, between_rows: bool = False
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel reduced residual, fringe sensitivity, degrees of freedom and what reading between rows misses: what
    :func:`motion_score`, :func:`mask_from_score` and :func:`motion_mask` need.

    Pixels are independent here, so row blocks of a scan can be evaluated separately and their
    statistics combined by :func:`score_from_statistics`.

    The residual is the Poisson deviance of the pixel's samples in photon units (scaled by the photon
    share of the variance where there is electronic noise), not the Pearson chi-square: at a few
    photons per sample the Pearson sum is biased up (the fitted mean is low exactly where the counts
    are) and heavy-tailed, so dim pixels (spine, heart) read as inconsistent; the deviance keeps
    about the chi-square mean and tail down to a few photons.

    Parameters
    ----------
    obs : Observations
    params : dict
        Effect parameters of the model to compare with (e.g. a pilot estimate of the paper's vibration model,
        :func:`pilot_vibrations`); ``{}`` compares with a model without per-frame terms (paper eq. 35).
    between_rows : bool
        Also evaluate :func:`between_rows_miss` (else ``miss`` is 0).

    Returns
    -------
    eps, q : ndarray, shape (R, C)
        Reduced weighted residual (n - 3 degrees of freedom) and the phase sensitivity
        (t v vf tf)^2 / Ibar per sample averaged over the pixel; NaN where the pixel could not be solved.
    dof : ndarray, shape (R, C)
        n - 3, the degrees of freedom of ``eps``.
    miss : ndarray, shape (R, C)
        :func:`between_rows_miss` at the model, NaN where ``eps`` is.
    """
    K.set_threads()
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    # the model's weights (a solve with the data's first): the score compares the residual with the noise the
    # model predicts, not with the data's own scatter
    solved = E.retrieve(obs, ch, iterations=2)
    weights, ibar = solved["weights"], solved["expected"]
    n = row_counts(obs, weights > 0)
    # the fringe's amplitude per unit image modulation, |(Bc, Bs)| = D tf vf V of model.design
    fringe_amp = ch.dose[obs.frame][:, None] * np.hypot(obs.fc, obs.fs) * ch.vis_at(obs)
    with np.errstate(divide="ignore", invalid="ignore"):
        eps = obs.segment_sum(np.where(weights > 0, deviance(obs, ibar), 0.0)) / (n - 3)
        amp = obs.gather(np.hypot(solved["coef"][..., 1], solved["coef"][..., 2]))
        q = obs.segment_sum(weights * (amp * fringe_amp) ** 2) / n
    ok = solved["valid"] & (n > 3) & np.isfinite(eps) & np.isfinite(q)
    miss = between_rows_miss(obs, ch, solved["coef"], solved["valid"], weights) if between_rows else np.zeros(n.shape)
    return np.where(ok, eps, np.nan), np.where(ok, q, np.nan), n - 3, np.where(ok, miss, np.nan)


def between_rows_miss(obs: Observations, ch: M.Channels, coef: np.ndarray, valid: np.ndarray, weights: np.ndarray
                      ) -> np.ndarray:
    """What reading the images linearly between rows misses at each pixel, in noise standard deviations.

    Where the samples read the images between two held rows (``obs.reading``, ``geometry.parallax``), linear
    interpolation at the fraction f misses -f (1 - f) / 2 times the images' second derivative along the rows (the
    next term of their Taylor series; exact for images quadratic along the rows). The second derivative is taken as
    the images' second difference, read where the sample reads, carried into the sample's expected count by the
    model's design and divided by the sample's noise. Large where the sample has structure finer than a row moving
    across the pixels (the edges of ribs and lungs): what no images on the pixel grid describe, and what would
    otherwise pull the per-frame estimates.

    Parameters
    ----------
    obs : Observations
    ch : Channels
        The model's channel values (:func:`dfxcorr.model.channels`).
    coef : ndarray, shape (R, C, 3)
        The images (t, c, s) of the held rows.
    valid : ndarray of bool, shape (R, C)
        The rows solved (the others are held at 0: no second difference spans them, no sample reading them counts).
    weights : ndarray, shape (K, C)
        Inverse noise variance of each sample, 0 where not used.

    Returns
    -------
    ndarray, shape (R, C)
        Root mean square over each pixel's used samples of the missed count over its noise standard deviation: 0
        where the samples read their own row (``obs.reading`` None), NaN where the pixel has no such sample. A row
        without a solved, held neighbour on each side takes the second difference of the neighbour that has them (0
        where none has).
    """
    counted = obs.gather_valid(valid) & (weights > 0)
    n = row_counts(obs, counted)
    with np.errstate(divide="ignore", invalid="ignore"):
        if obs.reading is None:
            return np.where(n > 0, 0.0, np.nan)
        rows = obs.rows
        step = np.diff(rows) == 1
        # rows whose neighbours on both sides are held next to them and solved, with them
        inner = np.zeros(valid.shape, bool)
        inner[1:-1] = (step[:-1] & step[1:])[:, None] & valid[:-2] & valid[1:-1] & valid[2:]
        d2 = np.zeros_like(coef)
        d2[1:-1] = np.where(inner[1:-1, :, None], coef[:-2] - 2.0 * coef[1:-1] + coef[2:], 0.0)
        # a row at an end (of the images or of a run of solved rows) takes its inner neighbour's
        below = np.zeros(valid.shape, bool)
        below[:-1] = ~inner[:-1] & inner[1:] & step[:, None]
        above = np.zeros(valid.shape, bool)
        above[1:] = ~inner[1:] & ~below[1:] & inner[:-1] & step[:, None]
        d2[:-1] = np.where(below[:-1, :, None], d2[1:], d2[:-1])
        d2[1:] = np.where(above[1:, :, None], d2[:-1], d2[1:])
        dsg = M.design_channels(obs, ch)
        # one image at a time: (K, C) temporaries rather than (K, C, 3)
        miss = sum(obs.gather(d2[..., a]) * X for a, X in enumerate((dsg.A, dsg.Bc, dsg.Bs)))
        _, _, f = obs.read_rows()
        miss *= (0.5 * f * (1.0 - f))[:, None]
        return np.sqrt(obs.segment_sum(np.where(counted, weights, 0.0) * miss ** 2) / n)


def score_from_statistics(eps: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Motion score eps / (1 + gamma q), gamma fitted robustly over all finite pixels (any array shape)."""
    ok = np.isfinite(eps) & np.isfinite(q)
    gamma = max(float(np.median((eps[ok] - 1.0) / np.maximum(q[ok], 1e-12))), 0.0) if np.any(ok) else 0.0
    with np.errstate(invalid="ignore"):
        return np.where(ok, eps / (1.0 + gamma * q), np.nan)


def motion_score(obs: Observations, params: dict, *, chunk: float = 1e6) -> np.ndarray:
    """Per-pixel residual relative to what noise and (unmodelled) vibrations explain.

    ``params`` as :func:`motion_statistics`'s. The statistics are taken a run of about ``chunk`` samples' columns
    at a time (the pixels are independent; :func:`score_from_statistics` fits its gamma over all of them): every
    column's temporaries at once were most of a diagnosis's peak memory.

    Returns
    -------
    ndarray, shape (R, C)
        About 1 for consistent pixels (a reduced chi-square with n - 3 degrees of freedom), NaN where
        the pixel could not be solved.
    """
    eps, q, _, _ = (np.concatenate(a, axis=1) for a in zip(*(motion_statistics(obs.subset(c), params)
                                                             for c in obs.column_chunks(chunk)), strict=True))
    return score_from_statistics(eps, q)


def deviance(obs: Observations, ibar: np.ndarray) -> np.ndarray:
    """Poisson deviance of each sample in photon units, shape (K, C); about chi-square(1) per sample.

    With electronic noise it is scaled by g mu / (g mu + sigma_e^2), the photon share of the variance; g is
    each pixel's gain (times its ``pixel_noise`` factor).
    """
    g = obs.sample_gain()
    mu = np.maximum(obs.photons(ibar), 1e-6) / g
    y = np.maximum(obs.photons(obs.counts), 0.0) / g
    with np.errstate(divide="ignore", invalid="ignore"):
        d = 2.0 * (np.where(y > 0, y * np.log(np.where(y > 0, y, 1.0) / mu), 0.0) - (y - mu))
    # no photon share without electronic noise (it is 1): the same values without (K, C) passes
    return d * (g * mu / (g * mu + obs.electronic)) if obs.electronic else d


def pilot_vibrations(obs: Observations, *, iterations: int = 8, every: int = 4, tol: float = 3e-3) -> dict:
    """A quick estimate of the paper's per-frame phase offset, tilt and visibility for the motion score.

    Gauss-Newton steps (at most ``iterations``, until the rms step is below ``tol``) on every
    ``every``-th held column with the images profiled out (the profiled Fisher information of
    :func:`dfxcorr.fisher_pixels.fisher`; its gauge directions get the minimum-norm step). Pixels whose
    mean squared residual exceeds 4 times the median pixel's are left out of each step so that a
    moving region does not steer its frames (relative to the median: early on, the vibrations
    themselves are far beyond photon noise); whole pixels, not samples, so that no frame
    loses its information (a frame that lights one row has no other). Unmodelled vibrations would
    otherwise dominate the residual of bright, modulated pixels and hide the motion among them.

    Each sample reads its own pixel's images here, also where the observations read them between rows
    (``obs.reading``, a parallax): from the neutral start, steps on images coupled between rows went astray
    (thorax on 5 mm pixels, kappa 0.1: phi0 6.7 rad rms from the truth, against 0.0072 with each pixel's own
    images).

    Returns
    -------
    dict
        'phase_offset', 'tilt', 'visibility_loss', each (J, 1).
    """
    names = PAPER_MODEL
    K.set_threads()
    sub = replace(obs.subset(np.arange(0, obs.columns.size, every)), reading=None)
    index = M.fisher_index(names, sub.n_frames)
    params = neutral_params(names, obs.n_frames)
    weights = noise_weights(sub, np.maximum(sub.counts, 1.0))
    ch = M.channels(params, x=sub.x, n_frames=sub.n_frames)
    solved = E.retrieve(sub, ch, weights=weights)
    for _ in range(iterations):
        resid = sub.counts - solved["expected"]
        z2 = sub.segment_sum(weights * resid ** 2) / np.maximum(sub.segment_sum((weights > 0) * 1.0), 1)
        # no pixel seen in more frames than its images' unknowns: nothing to compare with
        outlier = z2 > (4.0 * np.median(z2[solved["valid"]]) if solved["valid"].any() else np.inf)
        w = np.where(outlier | ~solved["valid"], 0.0, 1.0)[sub.pixel] * weights
        held = E.retrieve(sub, ch, weights=w, keep_inverse=True)
        plain, corr = E.fisher(sub, ch, w, held["coef"], held["inverse"], names)
        # the reduced cost's gradient is that at the images solved with w (envelope theorem)
        grad = M.channel_adjoint(names, E.reduced_cost(sub, ch, w, channels=("phase", "visibility"))[1],
                                 x=sub.x)
        rhs = -0.5 * np.array([grad[n][j, m] for n, j, m in index])
        # the minimum-norm step by a complete orthogonal factorisation (627 parameters: 19 ms, numpy's SVD 50 ms)
        step = lstsq(plain - corr, rhs, cond=1e-8, lapack_driver="gelsy")[0]
        for (n, j, m), d in zip(index, step, strict=True):
            params[n][j, m] += d
        if np.sqrt(np.mean(step ** 2)) < tol:
            break
        # noise weights from the model solved with the current weights; the solve with them is the next step's
        ch = M.channels(params, x=sub.x, n_frames=sub.n_frames)
        solved = E.retrieve(sub, ch, weights=weights, iterations=2)
        weights = solved["weights"]
    return params


#: The fit starts at a given estimate (the motion mask's pilot, :func:`pilot_vibrations`) only where no
#: well-determined frame's reduced chi-square there (:func:`start_misfit`) exceeds this. In the basin of the minimum a
#: frame's samples fit within noise (paper study and binned clinical scan: at most 1.09 and 1.07); a frame whose phase
#: sits in another basin leaves residuals of the order of its fringe's amplitude, many times the noise (the 11-step
#: stepping test scan, where the pilot's Gauss-Newton steps from the neutral values diverge: 199).
START_CHI2 = 1.5
#: Evenly spread columns on which :func:`start_misfit` solves the images (a few milliseconds).
START_COLUMNS = 64


def start_misfit(obs: Observations, params: dict, *, effects: Sequence[str] = PAPER_MODEL,
                 gauge_fraction: float = 0.5) -> float:
    """The largest reduced chi-square of a well-determined frame's samples at the parameters ``params`` (the other
    effects neutral): whether a start lies in the basin of the fit's minimum (:data:`START_CHI2`).

    The images are solved at ``params`` with noise weights from a first solve (as
    :func:`dfxcorr.fit.initial_weights`) on at most :data:`START_COLUMNS` evenly spread columns; each frame's sum of
    weighted squared residuals over its samples is divided by their number times the share of the samples' degrees
    of freedom the images leave (3 per solved pixel).

    Returns
    -------
    float
        inf where no frame is well determined (:func:`dfxcorr.frames.well_determined`), no pixel is solved or the
        residuals are not finite.
    """
    _, at = model_at(effects, params, obs.n_frames)
    sub = spread_columns(obs, most=START_COLUMNS)
    out = E.retrieve(sub, M.channels(at, x=sub.x, n_frames=sub.n_frames), iterations=2)
    # in the retrieval's own arrays: three temporaries of the samples' size (19 MB each at full resolution with
    # fit.max_samples=2.8e7) were then the run's peak
    w, r2 = out["weights"], out["expected"]
    w[~(sub.use & sub.gather_valid(out["valid"]))] = 0.0
    np.subtract(sub.counts, r2, out=r2)
    np.square(r2, out=r2)
    z2 = sub.frame_sum(np.sum(np.multiply(w, r2, out=r2), axis=1))
    n = sub.frame_sum(np.sum(w > 0, axis=1).astype(np.float64))
    free = n.sum() - 3.0 * np.count_nonzero(out["valid"])
    good = well_determined(sub, gauge_fraction) & (n > 0)
    worst = float(np.max(z2[good] / n[good]) * n.sum() / free) if good.any() and free > 0 else float("inf")
    # a start with non-finite parameters leaves NaN residuals: no start either
    return worst if np.isfinite(worst) else float("inf")


def robust_threshold(score: np.ndarray, *, sigma: float) -> float:
    """median + sigma * 1.4826 * MAD of the finite scores; infinite where none is finite (nothing is flagged)."""
    s = score[np.isfinite(score)]
    if not s.size:
        return float("inf")
    med = np.median(s)
    return float(med + sigma * 1.4826 * np.median(np.abs(s - med)))


def mask_from_score(image: np.ndarray, *, dof: np.ndarray | None = None, threshold: float | None = None,
                    sigma: float = 6.0, dilate: int = 1) -> tuple[np.ndarray, float]:
    """Pixels of a motion-score image (H, W) above the threshold, grown by ``dilate``; and the threshold.

    With ``dof`` (H, W), the degrees of freedom of each pixel's score, a pixel must also be as improbable
    as the threshold is at the typical number of degrees of freedom: rows lit in few frames have a long
    tail, and a score above the threshold there is no evidence of motion.
    """
    thr = robust_threshold(image, sigma=sigma) if threshold is None else float(threshold)
    score = np.nan_to_num(image, nan=0.0)
    moving = score > thr
    if dof is not None and np.isfinite(image).any():
        typical = float(np.median(dof[np.isfinite(image)]))
        # at the pixels above the threshold only (a few of a detector's millions: 0.4 s per call at full resolution)
        at = np.flatnonzero(moving)
        with np.errstate(invalid="ignore"):
            moving.flat[at] = (chi2_log_tails(score.flat[at] * dof.flat[at], np.maximum(dof.flat[at], 1))
                               <= chi2_log_tails(thr * typical, typical))
    if dilate > 0 and moving.any():
        moving = _dilated(moving, dilate)
    return moving, thr


def _dilated(moving: np.ndarray, n: int) -> np.ndarray:
    """``moving`` (H, W) grown by ``n`` pixels (binary dilation, ``n`` iterations of the cross), in the box around the
    flagged pixels widened by ``n``: the same pixels as over the whole image, where only a few are flagged."""
    rows, cols = np.flatnonzero(moving.any(axis=1)), np.flatnonzero(moving.any(axis=0))
    box = (slice(max(rows[0] - n, 0), rows[-1] + n + 1), slice(max(cols[0] - n, 0), cols[-1] + n + 1))
    out = np.zeros_like(moving)
    out[box] = ndimage.binary_dilation(moving[box], iterations=n)
    return out


def motion_mask(blocks: Iterable[Observations], *, pilot: dict, threshold: float | None = None,
                sigma: float = 6.0, dilate: int = 1, between_rows: float | None = None
                ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Pixels whose frames disagree beyond noise and vibrations (paper Sec. II-E), block by block.

    Pixels are independent here, so the observations may come in blocks of detector rows (a scan that does
    not fit in memory at once): the per-pixel statistics (:func:`motion_statistics`) come block by block
    against one per-frame ``pilot`` estimate, and are combined into one score and one threshold, equal to
    one pass over all of them. Pixels without a fringe (outside the region of interest) only monitor dose
    and background: they get no score.

    Parameters
    ----------
    blocks : iterable of Observations
        The samples (e.g. of the fit's columns), in any number of row blocks.
    pilot : dict
        Per-frame parameters to compare with (:func:`pilot_vibrations`; ``{}``: paper eq. 35 as it stands).
    threshold : float, optional
        Absolute threshold on the score; default :func:`robust_threshold` with ``sigma``.
    sigma : float
    dilate : int
        Grow the flagged region by this many pixels (its rim is partly affected too).
    between_rows : float, optional
        Where the samples read the images between rows: also leave out the pixels where that reading misses more
        than this many noise standard deviations (:func:`between_rows_miss`, at the pilot); they take no part in the
        motion score's threshold. None: none.

    Returns
    -------
    moving : ndarray of bool, shape (H, W)
        True where the pixel is left out of the vibration fit.
    score : ndarray, shape (H, W)
        The motion score (NaN where not computed).
    threshold : float
        The threshold used.
    beyond : ndarray of bool, shape (H, W)
        The pixels of ``moving`` left out for ``between_rows``.
    """
    images: dict[str, np.ndarray] = {}
    for obs in blocks:
        if not images:
            H, W = obs.shape[1:]
            images = {"eps": np.full((H, W), np.nan), "q": np.full((H, W), np.nan), "dof": np.zeros((H, W)),
                      "beyond": np.zeros((H, W), bool), "fringe": np.zeros((H, W), bool)}
        limit = np.inf if between_rows is None or obs.reading is None else between_rows
        e, qq, d, miss = motion_statistics(obs, pilot, between_rows=bool(np.isfinite(limit)))
        for key, values in (("eps", e), ("q", qq), ("dof", d), ("beyond", miss > limit),
                            ("fringe", obs.segment_sum(obs.in_roi.astype(float)) > 0)):
            obs.place(images[key], values)
    if not images:
        raise ValueError("the motion mask needs observations")
    score = np.where(images["fringe"], score_from_statistics(images["eps"], images["q"]), np.nan)
    beyond = images["beyond"] & images["fringe"]
    # a copy of the score only where pixels are left out for the reading between rows (66 MB at full resolution)
    moving, thr = mask_from_score(np.where(beyond, np.nan, score) if beyond.any() else score, dof=images["dof"],
                                  threshold=threshold, sigma=sigma, dilate=dilate)
    return moving | beyond, score, thr, beyond
