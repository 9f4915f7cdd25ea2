"""The model evaluated on observations: the compiled kernels, or the model's own arrays beyond what they take.

Every stage that solves images, evaluates the reduced cost or the Fisher information calls these three functions
(never the kernels directly). Where every channel is a function of the frame and x they are compiled: the loops of
:mod:`dfxcorr.kernels` where each sample reads the images of its own pixel (the paper's geometry), those of
:mod:`dfxcorr.kernels_between` and :mod:`dfxcorr.fisher_between` where the beam paths move during the scan
(``Observations.reading``, ``beam_path``: the images of neighbouring rows are coupled, one block-tridiagonal solve
per column). Where a channel term depends on the detector row (``Channels.rows``, catalogue components 'x^k y^m')
the channels vary within a column: the same quantities then come from :mod:`dfxcorr.model`'s expressions, which
define what every compiled path computes. The signatures and returned values are the kernels'.
"""
from __future__ import annotations

from collections.abc import Collection, Iterator, Sequence
from dataclasses import replace

import numpy as np
from scipy import sparse

from . import fisher_between as FB
from . import fisher_pixels as FP
from . import kernels as K
from . import kernels_between as KB
from . import model as M
from .catalogue import effect
from .noise import noise_weights, variance
from .observations import Observations

#: Samples of each range of rows on which :func:`profiled_fisher` solves the images: one range's inverse matrices,
#: 72 bytes per pixel, are held at a time (a full-resolution clinical fit of 2.7e7 samples held its 1e6 pixels' 75 MB
#: at once, at the process's peak; at its 26 samples per pixel a range holds about 11 MB).
FISHER_SAMPLES = 4e6


def compiled(ch: M.Channels, names: Sequence[str] = ()) -> bool:
    """Whether compiled kernels take these channels and effects (see the module's docstring)."""
    return not ch.rows and not any(r for n in names for r in effect(n).row_powers)


def retrieve(obs: Observations, ch: M.Channels, *, weights: np.ndarray | None = None, iterations: int = 1,
             gain: float | None = None, keep_inverse: bool = False, keep_expected: bool = True,
             next_weights: bool = False, out: np.ndarray | None = None) -> dict:
    """Images, expected counts, weights and Pearson chi-square: :func:`dfxcorr.kernels.retrieve`'s values.

    Where ``obs.reading`` is set, ``inverse`` holds each row's diagonal block of the inverse and ``coupling`` the
    blocks between each row and the next (None otherwise). ``out``: where the returned weights go (it may be
    ``weights``; written in place by the per-pixel kernel, copied there by the others).
    """
    kernel = model_retrieve if not compiled(ch) else K.retrieve if obs.reading is None else KB.retrieve
    K.set_threads()
    into = {"out": out} if kernel is K.retrieve else {}
    done = {"coupling": None, **kernel(obs, ch, weights=weights, iterations=iterations, gain=gain,
                                       keep_inverse=keep_inverse, keep_expected=keep_expected,
                                       next_weights=next_weights, **into)}
    if out is not None and done["weights"] is not out:
        out[...] = done["weights"]
        done["weights"] = out
    return done


def model_retrieve(obs: Observations, ch: M.Channels, *, weights: np.ndarray | None = None, iterations: int = 1,
                   gain: float | None = None, keep_inverse: bool = False, keep_expected: bool = True,
                   next_weights: bool = False) -> dict:
    """:func:`retrieve` from the model's arrays (:func:`dfxcorr.model.solve_images`, ``expected``): what every
    compiled retrieval computes, for any observations and channels."""
    if iterations < 1:
        raise ValueError("iterations must be at least 1")
    noisy = obs if gain is None else replace(obs, gain=gain)
    dsg = M.design_channels(obs, ch)
    w = noise_weights(noisy, np.maximum(obs.counts, 1.0)) if weights is None else np.where(obs.use, weights, 0.0)
    for it in range(iterations):
        images = M.solve_images(obs, dsg, w, keep_inverse=keep_inverse and it == iterations - 1)
        ibar = M.expected(obs, dsg, images)
        if it < iterations - 1:
            w = noise_weights(noisy, ibar)
    sel = obs.use & obs.gather_valid(images.valid)
    var = variance(noisy, ibar)
    chi2 = float(np.sum(np.where(sel, (obs.counts - ibar) ** 2 / var, 0.0)))
    w_out = noise_weights(noisy, ibar) if next_weights else w
    keep = keep_expected or next_weights
    empty = np.zeros((0, obs.columns.size))
    return {"coef": images.coef, "valid": images.valid, "inverse": images.inverse if keep_inverse else None,
            "coupling": images.coupling if keep_inverse else None, "expected": ibar if keep else empty,
            "weights": w_out if keep else empty, "chi2": chi2, "samples": int(sel.sum())}


def expected_by_columns(obs: Observations, params: dict, images: M.Images, *, samples: float = 1e6
                        ) -> Iterator[tuple[np.ndarray, Observations, M.Images, np.ndarray]]:
    """The expected counts of ``obs`` at ``params`` and ``images``, a run of about ``samples`` samples' columns at a
    time (:meth:`Observations.column_chunks`): each run's column positions, samples (views, for numpy work: the
    kernel copies the few it reads), images and expected counts (K, c), from the compiled kernel where it takes the
    channels and each sample reads its own pixel (a fifth of the model's time: no design per sample), else from the
    model's design (:func:`dfxcorr.model.expected_by_columns` also yields that design)."""
    K.set_threads()
    for cols in obs.column_chunks(samples):
        sub, im = obs.subset(cols, copy=False), images.subset(cols)
        ch = M.channels(params, x=sub.x, n_frames=sub.n_frames)
        fast = compiled(ch) and sub.reading is None
        yield cols, sub, im, K.expected(sub, ch, im.coef) if fast else M.expected(sub, M.design_channels(sub, ch), im)


def reduced_cost(obs: Observations, ch: M.Channels, weights: np.ndarray, *, phase: float | None = None,
                 square: bool = False, channels: Collection[str] = tuple(K.CHANNEL_IDS)) -> tuple[float, M.Channels]:
    """Reduced cost and its channel gradients (or Gauss-Newton sums): :func:`dfxcorr.kernels.reduced_cost`'s values,
    as a :class:`~dfxcorr.model.Channels` whose ``rows`` holds those of the coefficients of powers of y."""
    if compiled(ch):
        kernel = K.reduced_cost if obs.reading is None else KB.reduced_cost
        cost, grads = kernel(obs, ch, weights, phase=phase, square=square, channels=channels)
        return cost, M.Channels(grads[0], grads[1], grads[2], grads[3], grads[4])
    return model_reduced_cost(obs, ch, weights, phase=phase, square=square, channels=channels)


def parameter_sums(obs: Observations, ch: M.Channels, weights: np.ndarray, names: Sequence[str], *,
                   phase: float | None = None, square: bool = False) -> tuple[float, dict[str, np.ndarray]]:
    """Reduced cost and its gradient in the parameters of ``names`` (``square``: the diagonal of their Gauss-Newton
    sums): :func:`reduced_cost`'s channel sums pulled back by :func:`dfxcorr.model.channel_adjoint`. At images solved
    with ``weights`` the gradient is :func:`dfxcorr.model.gradient`'s (the envelope theorem, paper eq. 25)."""
    cost, g = reduced_cost(obs, ch, weights, phase=phase, square=square,
                           channels={c for n in names if (c := effect(n).channel) is not None})
    return cost, M.channel_adjoint(names, g, x=obs.x, square=square)


def solved(obs: Observations, ch: M.Channels, weights: np.ndarray, *, keep_inverse: bool = True
           ) -> tuple[M.Images, np.ndarray]:
    """Images solved with ``weights`` (with their inverse normal matrices where ``keep_inverse``) and the residuals
    I - Ibar (K, C): :func:`dfxcorr.model.solve_images` and :func:`dfxcorr.model.expected`'s values from
    :func:`retrieve`."""
    out = retrieve(obs, ch, weights=weights, keep_inverse=keep_inverse)
    return M.Images(out["coef"], out["valid"], out["inverse"], out["coupling"]), obs.counts - out["expected"]


def model_reduced_cost(obs: Observations, ch: M.Channels, weights: np.ndarray, *, phase: float | None = None,
                       square: bool = False, channels: Collection[str] = tuple(K.CHANNEL_IDS)
                       ) -> tuple[float, M.Channels]:
    """:func:`reduced_cost` from the model's arrays (:func:`dfxcorr.model.channel_fields`): what every compiled reduced
    cost computes, for any observations and channels."""
    dsg = M.design_channels(obs, ch)
    images = M.solve_images(obs, dsg, weights, phase=phase)
    at = obs.gather(images.coef)
    resid = obs.counts - M.expected(obs, dsg, images, at=at)
    cost = float(np.sum(weights * resid ** 2))
    J, C = obs.n_frames, obs.columns.size
    out: list[np.ndarray] = [np.zeros((J, C)), np.zeros((J, C)), np.zeros(J), np.zeros(3), np.zeros(2)]
    rows: dict[tuple[int, int], np.ndarray] = {}
    g = -2.0 * weights * resid
    by_frame = sparse.csr_matrix((np.ones(obs.frame.size), (obs.frame, np.arange(obs.frame.size))),
                                 shape=(J, obs.frame.size))
    for name, cid in K.CHANNEL_IDS.items():
        if name not in channels:
            continue
        fields = M.channel_fields(obs, dsg, images, cid, at=at)
        sums = [(weights * F if square else g) * F for F in fields]
        if cid in (K.PHASE, K.VISIBILITY):
            out[cid] = by_frame @ sums[0]
            # the coefficient of y^m moves the channel by y^m: its sums carry y^m (y^2m for Gauss-Newton sums)
            for c, m in ch.rows:
                if c == cid:
                    rows[(c, m)] = by_frame @ (sums[0] * obs.y[:, None] ** (2 * m if square else m))
        elif cid == K.DOSE:
            out[cid] = obs.frame_sum(sums[0].sum(axis=1))
        else:
            out[cid] = np.array([s.sum() for s in sums])
    return cost, M.Channels(out[0], out[1], out[2], out[3], out[4], rows)


def fisher(obs: Observations, ch: M.Channels, weights: np.ndarray, coef: np.ndarray, inverse: np.ndarray | None,
           names: Sequence[str], *, profiled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Fisher information of the parameters of ``names`` and its profiled correction, in
    :func:`dfxcorr.model.fisher_index`'s order: :func:`dfxcorr.fisher_pixels.fisher`'s values.

    Where ``obs.reading`` is set, :func:`dfxcorr.fisher_between.fisher` (``inverse`` is not read); beyond the kernels
    (see :func:`compiled`), :func:`dfxcorr.model.fisher_parts`.
    """
    if not compiled(ch, names):
        images = M.Images(coef, np.ones(coef.shape[:2], bool), inverse)
        plain, corr, _ = M.fisher_parts(obs, M.design_channels(obs, ch), images, weights, names, profiled=profiled)
        return plain, corr
    K.set_threads()
    table = M.component_table(names)[:3]
    if obs.reading is not None:
        return FB.fisher(obs, ch, weights, coef, table, profiled=profiled)
    return FP.fisher(obs, ch, weights, coef, inverse, table, profiled=profiled)


def profiled_fisher(obs: Observations, ch: M.Channels, weights: np.ndarray, names: Sequence[str], *,
                    samples: float = FISHER_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fisher`'s information and profiled correction at the images solved with ``weights`` (:func:`retrieve`).

    Where each pixel's images are its own (``obs.reading`` None) both are sums over the pixels: they are summed over
    ranges of rows of about ``samples`` samples (:meth:`Observations.row_ranges`), each range's images solved on
    their own, so that only one range's inverse normal matrices are held; the same values up to the order of the
    sums. Where the samples read between rows, over all at once.

    Parameters
    ----------
    obs : Observations
        The samples, per pixel or read between rows.
    ch : Channels
        Channel values on ``obs``'s (frame, column) grid (the same for every range of rows).
    weights : ndarray, shape (K, C)
        Inverse variances (counts^-2).
    names : sequence of str
        Effects whose parameters the information is of, in :func:`dfxcorr.model.fisher_index`'s order.
    samples : float
        Samples per range of rows.

    Returns
    -------
    plain, correction : ndarray, shape (P, P)
        As :func:`fisher`'s (per parameter unit squared), in :func:`dfxcorr.model.fisher_index`'s order.
    """
    def at_images(sub: Observations, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # the between-rows information reads no inverse normal matrices
        out = retrieve(sub, ch, weights=w, keep_inverse=sub.reading is None, keep_expected=False)
        return fisher(sub, ch, w, out["coef"], out["inverse"], names)

    ranges = [] if obs.reading is not None else obs.row_ranges(samples)
    if len(ranges) <= 1:
        return at_images(obs, weights)
    parts = (at_images(obs.of_rows(lo, hi), weights[obs.block_range(lo, hi)]) for lo, hi in ranges)
    plain, corr = next(parts)
    for p, c in parts:
        plain += p
        corr += c
    return plain, corr
