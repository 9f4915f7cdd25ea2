"""Compiled loops of the fit and the retrieval where the samples read the images between rows (numba).

Where the beam paths move during the scan (``Observations.reading``, ``beam_path``) block k's expected count uses
(1 - f_k) times the images of held row lo_k plus f_k times those of row lo_k + 1, so the images of a column are
one block-tridiagonal least-squares problem along the rows (3 x 3 blocks of the unknowns (t, c, s)). These kernels
evaluate the same quantities as :mod:`dfxcorr.kernels` for such observations: per column, one pass over the
samples accumulates the diagonal and coupling blocks of the normal equations, block Gaussian elimination over the
rows solves them (the rules of :func:`dfxcorr.banded.factor_read_between`: each row scaled by the square roots of
its diagonal, unknowns absent from a row left out, unsolvable rows held at 0), and a second pass evaluates the
expected counts, residuals and channel gradients. The numpy expressions of :mod:`dfxcorr.model` and
:mod:`dfxcorr.banded` are the definition; the tests hold these kernels to them.

Layout: the kernels run over tiles of columns in parallel (every sample of a column is read by one thread, which
owns that column's accumulators and outputs); within a tile the samples are walked block by block, the tile's
columns innermost (contiguous in the C-ordered (K, C) samples).
"""
from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from .kernels import (
    CHANNEL_IDS,
    HARMONIC_STEPS,
    _c,
    _derivatives,
    _design,
    _direction,
    _image_columns,
    _turned,
    _variance,
)

#: Position of entry (a, b) of a symmetric 3 x 3 block in its six stored entries (00, 01, 02, 11, 12, 22).
_SYM = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]], dtype=np.int64)


def _tile(n_columns: int) -> int:
    """Columns per tile: wide (each tile walks every sample's block metadata once; paper study with a parallax, 73
    columns: cost 0.18 s with tiles of 10, 0.10 s of 37), one tile per thread, at most 128 (a tile holds its weights
    and normal equations, K and R rows of it)."""
    per = -(-n_columns // numba.get_num_threads())
    return int(min(128, max(16, per)))


def _reading(obs) -> tuple[np.ndarray, np.ndarray]:
    """The image row below each block's read position and the fraction towards the next, as the kernels take them."""
    if obs.reading is None:
        raise ValueError("the observations read every sample at its own row: use dfxcorr.kernels")
    return np.ascontiguousarray(obs.reading.lo, dtype=np.int64), _c(obs.reading.frac, np.float64)


@njit(cache=True, inline="always")
def _sample(fc, fs, cos_p, sin_p, tf, vis, dose, k, c, j, hc, hs):
    """Sample (k, c) of frame j: its fringe turned by the phase channel (Fc, Fs), D tf, the double angle and the design
    columns (:func:`dfxcorr.kernels._turned`, :func:`dfxcorr.kernels._design`)."""
    Fc, Fs = _turned(np.float64(fc[k, c]), np.float64(fs[k, c]), cos_p[j, c], sin_p[j, c])
    amp = dose[j] * tf[k, c]
    c2, s2, a, bc, bs, hcc, hcs = _design(Fc, Fs, amp, dose[j] * vis[j, c], hc, hs, True)
    return Fc, Fs, amp, c2, s2, a, bc, bs, hcc, hcs


# --------------------------------------------------------------------------------------------------
# Per-column helpers: the block-tridiagonal normal equations of one column of a tile
# --------------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _add_sample(D, U, rhs, used, lo, hi, f, i, wk, a, x1, x2, target):
    """Add one sample reading rows lo and hi (share 1 - f and f) to column i of the tile's normal equations (the
    symmetric blocks' entries 00, 01, 02, 11, 12, 22)."""
    wa, w1, w2 = wk * a, wk * x1, wk * x2
    p = (wa * a, wa * x1, wa * x2, w1 * x1, w1 * x2, w2 * x2)
    r = (wa * target, w1 * target, w2 * target)
    g = 1.0 - f
    for e in range(6):
        D[lo, e, i] += g * g * p[e]
    for e in range(3):
        rhs[lo, e, i] += g * r[e]
    if wk > 0:
        used[lo, i] += 1.0
    if f != 0.0:
        for e in range(6):
            D[hi, e, i] += f * f * p[e]
            U[lo, e, i] += g * f * p[e]
        for e in range(3):
            rhs[hi, e, i] += f * r[e]
        if wk > 0:
            used[hi, i] += 1.0


@njit(cache=True, inline="always")
def _det3(M):
    """Determinant of a 3 x 3 matrix (expansion along its first column)."""
    return (M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]) + M[1, 0] * (M[0, 2] * M[2, 1] - M[0, 1] * M[2, 2])
            + M[2, 0] * (M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]))


@njit(cache=True)
def _inv3(M, out):
    """Inverse of a 3 x 3 matrix into ``out`` (cofactors)."""
    c00 = M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]
    c01 = M[0, 2] * M[2, 1] - M[0, 1] * M[2, 2]
    c02 = M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]
    det = _det3(M)
    out[0, 0] = c00 / det
    out[0, 1] = c01 / det
    out[0, 2] = c02 / det
    out[1, 0] = (M[1, 2] * M[2, 0] - M[1, 0] * M[2, 2]) / det
    out[1, 1] = (M[0, 0] * M[2, 2] - M[0, 2] * M[2, 0]) / det
    out[1, 2] = (M[0, 2] * M[1, 0] - M[0, 0] * M[1, 2]) / det
    out[2, 0] = (M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]) / det
    out[2, 1] = (M[0, 1] * M[2, 0] - M[0, 0] * M[2, 1]) / det
    out[2, 2] = (M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]) / det


@njit(cache=True)
def _factor(D, U, used, i, scale, valid, Finv, Us):
    """Scale, check and factor column i's normal matrix (:func:`dfxcorr.banded.factor_read_between`'s rules):
    ``scale`` (R, 3), ``valid`` (R,), the forward factors ``Finv`` (R, 3, 3) and the scaled couplings ``Us``."""
    R = D.shape[0]
    Ds = np.empty((R, 3, 3))
    for r in range(R):
        n_present = 0
        for a in range(3):
            d = D[r, _SYM[a, a], i]
            scale[r, a] = np.sqrt(d) if d > 0 else 1.0
            n_present += 1 if d > 0 else 0
        for a in range(3):
            for b in range(3):
                pa, pb = D[r, _SYM[a, a], i] > 0, D[r, _SYM[b, b], i] > 0
                if pa or pb:
                    Ds[r, a, b] = D[r, _SYM[a, b], i] / (scale[r, a] * scale[r, b])
                else:
                    Ds[r, a, b] = 1.0 if a == b else 0.0
        valid[r] = used[r, i] >= n_present and D[r, 0, i] > 0 and abs(_det3(Ds[r])) > 1e-10
        if not valid[r]:
            # a row that cannot be solved is held at 0, apart from its neighbours
            for a in range(3):
                for b in range(3):
                    Ds[r, a, b] = 1.0 if a == b else 0.0
    for r in range(R):
        for a in range(3):
            for b in range(3):
                Us[r, a, b] = (U[r, _SYM[a, b], i] / (scale[r, a] * scale[r + 1, b])
                               if r + 1 < R and valid[r] and valid[r + 1] else 0.0)
    S = np.empty((3, 3))
    _inv3(Ds[0], Finv[0])
    for r in range(1, R):
        # F_r = D_r - U_{r-1}^T F_{r-1}^-1 U_{r-1}
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for p in range(3):
                    for q in range(3):
                        acc += Us[r - 1, p, a] * Finv[r - 1, p, q] * Us[r - 1, q, b]
                S[a, b] = Ds[r, a, b] - acc
        _inv3(S, Finv[r])


@njit(cache=True)
def _solve(rhs, i, scale, valid, Finv, Us, out):
    """Column i's images from its :func:`_factor` factors and right-hand sides ``rhs`` (R, 3, T) into ``out``
    (R, 3, T); 0 on rows that cannot be solved."""
    R = rhs.shape[0]
    yv = np.empty((R, 3))
    for r in range(R):
        for a in range(3):
            yv[r, a] = rhs[r, a, i] / scale[r, a] if valid[r] else 0.0
        if r > 0:
            # y_r -= U_{r-1}^T F_{r-1}^-1 y_{r-1}
            for a in range(3):
                acc = 0.0
                for p in range(3):
                    z = 0.0
                    for q in range(3):
                        z += Finv[r - 1, p, q] * yv[r - 1, q]
                    acc += Us[r - 1, p, a] * z
                yv[r, a] -= acc
    xv = np.empty((R, 3))
    v = np.empty(3)
    for r in range(R - 1, -1, -1):
        for a in range(3):
            v[a] = yv[r, a]
            if r + 1 < R:
                for b in range(3):
                    v[a] -= Us[r, a, b] * xv[r + 1, b]
        for a in range(3):
            xv[r, a] = Finv[r, a, 0] * v[0] + Finv[r, a, 1] * v[1] + Finv[r, a, 2] * v[2]
    for r in range(R):
        for a in range(3):
            out[r, a, i] = xv[r, a] / scale[r, a] if valid[r] else 0.0


@njit(cache=True)
def _inverse(scale, valid, Finv, Us, diag, upper):
    """The inverse's diagonal blocks ``diag`` (R, 3, 3) and those between each row and the next ``upper``
    (:func:`dfxcorr.banded.inverse_blocks`, scaled back; zero on unsolvable rows and after the last)."""
    R = Finv.shape[0]
    T = np.empty((3, 3))
    diag[R - 1] = Finv[R - 1]
    upper[R - 1] = 0.0
    for r in range(R - 2, -1, -1):
        # upper_r = -F_r^-1 U_r diag_{r+1}; diag_r = F_r^-1 - upper_r U_r^T F_r^-1
        for a in range(3):
            for b in range(3):
                T[a, b] = Finv[r, a, 0] * Us[r, 0, b] + Finv[r, a, 1] * Us[r, 1, b] + Finv[r, a, 2] * Us[r, 2, b]
        for a in range(3):
            for b in range(3):
                upper[r, a, b] = -(T[a, 0] * diag[r + 1, 0, b] + T[a, 1] * diag[r + 1, 1, b]
                                   + T[a, 2] * diag[r + 1, 2, b])
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for p in range(3):
                    for q in range(3):
                        acc += upper[r, a, p] * Us[r, q, p] * Finv[r, q, b]
                diag[r, a, b] = Finv[r, a, b] - acc
    for r in range(R):
        for a in range(3):
            for b in range(3):
                diag[r, a, b] = diag[r, a, b] / (scale[r, a] * scale[r, b]) if valid[r] else 0.0
                if r + 1 < R:
                    upper[r, a, b] = upper[r, a, b] / (scale[r, a] * scale[r + 1, b])


@njit(cache=True, inline="always")
def _read(coef, lo, hi, f, i):
    """The images (t, c, s) a sample of column i reads: (1 - f) times row lo's plus f times row hi's."""
    g = 1.0 - f
    return (g * coef[lo, 0, i] + f * coef[hi, 0, i], g * coef[lo, 1, i] + f * coef[hi, 1, i],
            g * coef[lo, 2, i] + f * coef[hi, 2, i])


@njit(cache=True)
def _solve_tile(D, U, rhs, used, T, hold, coef, valid, keep, diag, upper):
    """Factor and solve each of the tile's T columns; ``coef`` (R, 3, T) receives (t, c, s) from the solved columns
    (x1, x2) through ``hold``, ``valid`` (R, T) the solvable rows, and with ``keep`` the inverse's blocks
    ``diag``, ``upper`` (R, T, 3, 3)."""
    R = D.shape[0]
    scale = np.empty((R, 3))
    ok = np.empty(R, dtype=np.bool_)
    Finv = np.empty((R, 3, 3))
    Us = np.empty((R, 3, 3))
    m00, m01, m10, m11 = hold[0, 0], hold[0, 1], hold[1, 0], hold[1, 1]
    for i in range(T):
        _factor(D, U, used, i, scale, ok, Finv, Us)
        _solve(rhs, i, scale, ok, Finv, Us, coef)
        for r in range(R):
            valid[r, i] = ok[r]
            u1, u2 = coef[r, 1, i], coef[r, 2, i]
            coef[r, 1, i] = m00 * u1 + m10 * u2
            coef[r, 2, i] = m01 * u1 + m11 * u2
        if keep:
            _inverse(scale, ok, Finv, Us, diag[:, i], upper[:, i])


@njit(cache=True)
def _normal(counts, tf, fc, fs, dark, w, wc0, frame, lo_, frac, y, x, cos_p, sin_p, vis, dose, bg, hc, hs,
            hold, c0, T, step, coef, D, U, rhs, used):
    """Accumulate the tile's normal equations (columns c0 to c0 + T, weights ``w[:, wc0:wc0 + T]``) over every
    sample; from the second step, the harmonic's Gauss-Newton columns at the images ``coef`` each sample reads."""
    R = D.shape[0]
    D[:, :, :T] = 0.0
    U[:, :, :T] = 0.0
    rhs[:, :, :T] = 0.0
    used[:, :T] = 0.0
    m00, m01, m10, m11 = hold[0, 0], hold[0, 1], hold[1, 0], hold[1, 1]
    for k in range(frame.size):
        j = frame[k]
        lo, f = lo_[k], frac[k]
        hi = min(lo + 1, R - 1)
        off = bg[0] + bg[2] * y[k]
        for i in range(T):
            c = c0 + i
            _, _, _, _, _, a, bc, bs, hcc, hcs = _sample(fc, fs, cos_p, sin_p, tf, vis, dose, k, c, j, hc, hs)
            if step > 0:
                _, cs, ss = _read(coef, lo, hi, f, i)
                du, dw, _, _ = _direction(cs, ss)
                bc, bs = _image_columns(bc, bs, hcc, hcs, du, dw)
            _add_sample(D, U, rhs, used, lo, hi, f, i, w[k, wc0 + i], a, m00 * bc + m01 * bs, m10 * bc + m11 * bs,
                        counts[k, c] - dark[k, c] - off - bg[1] * x[c])


@njit(cache=True, inline="always")
def _count(fc, fs, cos_p, sin_p, tf, vis, dose, dark, bg, y, x, hc, hs, harmonic, coef, k, c, j, lo, hi, f,
           i):
    """Expected count of sample (k, c) at the images it reads."""
    _, _, _, _, _, a, bc, bs, hcc, hcs = _sample(fc, fs, cos_p, sin_p, tf, vis, dose, k, c, j, hc, hs)
    tt, cs, ss = _read(coef, lo, hi, f, i)
    m = dark[k, c] + bg[0] + bg[1] * x[c] + bg[2] * y[k] + tt * a + cs * bc + ss * bs
    if harmonic:
        _, _, e, ff = _direction(cs, ss)
        m += hcc * e - hcs * ff
    return m


# --------------------------------------------------------------------------------------------------
# The fit: reduced cost and its channel gradients (or Gauss-Newton sums)
# --------------------------------------------------------------------------------------------------


@njit(cache=True, parallel=True)
def _reduced_cost(counts, tf, fc, fs, dark, w, frame, lo_, frac, y, x, cos_p, sin_p, vis, dose, bg, harm,
                  hold, square, need, R, tile):
    K, C = counts.shape
    J = vis.shape[0]
    n = -(-C // tile)
    cost = np.empty(C)
    g_phase = np.empty((J, C))
    g_vis = np.empty((J, C))
    g_dose = np.empty((J, C))
    g_bg = np.empty((3, C))
    g_harm = np.empty((2, C))
    hc, hs = harm[0], harm[1]
    harmonic = hc != 0.0 or hs != 0.0
    steps = 1 + (HARMONIC_STEPS if harmonic else 0)
    for t in prange(n):
        c0 = t * tile
        T = min(tile, C - c0)
        D = np.empty((R, 6, tile))
        U = np.empty((R, 6, tile))
        rhs = np.empty((R, 3, tile))
        used = np.empty((R, tile))
        coef = np.zeros((R, 3, tile))
        valid = np.empty((R, tile), dtype=np.bool_)
        none = np.empty((0, tile, 3, 3))
        for step in range(steps):
            _normal(counts, tf, fc, fs, dark, w, c0, frame, lo_, frac, y, x, cos_p, sin_p, vis, dose, bg, hc,
                    hs, hold, c0, T, step, coef, D, U, rhs, used)
            _solve_tile(D, U, rhs, used, T, hold, coef, valid, False, none, none)
        for i in range(T):
            c = c0 + i
            cost[c] = 0.0
            for jj in range(J):
                g_phase[jj, c] = 0.0
                g_vis[jj, c] = 0.0
                g_dose[jj, c] = 0.0
            for m in range(3):
                g_bg[m, c] = 0.0
            g_harm[0, c] = 0.0
            g_harm[1, c] = 0.0
        for k in range(K):
            j = frame[k]
            lo, f = lo_[k], frac[k]
            hi = min(lo + 1, R - 1)
            off = bg[0] + bg[2] * y[k]
            for i in range(T):
                c = c0 + i
                Fc, Fs, amp, c2, s2, a, bc, bs, hcc, hcs = _sample(fc, fs, cos_p, sin_p, tf, vis, dose, k, c, j, hc, hs)
                tt, cs, ss = _read(coef, lo, hi, f, i)
                e, ff = 0.0, 0.0
                if harmonic or need[4]:
                    _, _, e, ff = _direction(cs, ss)
                f_p, f_v, f_d, f_c, f_s = _derivatives(tt, cs, ss, Fc, Fs, c2, s2, e, ff, tf[k, c], dose[j],
                                                        vis[j, c], hc, hs)
                wk = w[k, c]
                res = counts[k, c] - dark[k, c] - off - bg[1] * x[c] - (tt * a + cs * bc + ss * bs)
                if harmonic:
                    res -= hcc * e - hcs * ff
                cost[c] += wk * res * res
                # gradient: sum (-2 w r) F; Gauss-Newton sums: sum (w F) F
                g = -2.0 * wk * res
                if need[0]:
                    g_phase[j, c] += (wk * f_p if square else g) * f_p
                if need[1]:
                    g_vis[j, c] += (wk * f_v if square else g) * f_v
                if need[2]:
                    g_dose[j, c] += (wk * f_d if square else g) * f_d
                if need[3]:
                    g_bg[0, c] += wk if square else g
                    g_bg[1, c] += (wk * x[c] if square else g) * x[c]
                    g_bg[2, c] += (wk * y[k] if square else g) * y[k]
                if need[4]:
                    g_harm[0, c] += (wk * f_c if square else g) * f_c
                    g_harm[1, c] += (wk * f_s if square else g) * f_s
    return cost, g_phase, g_vis, g_dose, g_bg, g_harm


def reduced_cost(obs, ch, weights: np.ndarray, *, phase: float | None = None, square: bool = False,
                 channels=tuple(CHANNEL_IDS)) -> tuple[float, tuple[np.ndarray, ...]]:
    """Reduced cost sum w (I - Ibar)^2 at the least-squares images and its channel gradients, where the samples read
    between rows: :func:`dfxcorr.kernels.reduced_cost`'s parameters and values.

    Parameters
    ----------
    obs : Observations
        With ``reading``.
    ch : Channels
    weights : ndarray, shape (K, C)
    phase : float, optional
        Hold the phase image at this constant: 2 unknowns per pixel.
    square : bool
        The Gauss-Newton sums sum w F^2 instead of the gradient sums -2 w r F.
    channels : sequence of str
        Channels whose sums are wanted (the others are zeros).

    Returns
    -------
    cost : float
    grads : tuple
        phase (J, C), visibility (J, C), dose (J,), background (3,), harmonic (2,).
    """
    lo, frac = _reading(obs)
    hold = np.eye(2) if phase is None else np.array([[np.cos(phase), np.sin(phase)], [0.0, 0.0]])
    need = np.isin(list(CHANNEL_IDS), list(channels))
    fc, fs = obs.fringe
    cost, g_phase, g_vis, g_dose, g_bg, g_harm = _reduced_cost(
        _c(obs.counts), _c(obs.tf), _c(fc), _c(fs), _c(obs.dark), _c(weights, np.float64), obs.frame, lo, frac,
        obs.y, obs.x, np.cos(ch.phase), np.sin(ch.phase), _c(ch.vis, np.float64), ch.dose, ch.background,
        ch.harmonic, hold, square, need, int(obs.rows.size), _tile(obs.columns.size))
    return float(cost.sum()), (g_phase, g_vis, g_dose.sum(axis=1), g_bg.sum(axis=1), g_harm.sum(axis=1))


# --------------------------------------------------------------------------------------------------
# The retrieval: images, expected counts, noise weights and Pearson chi-square
# --------------------------------------------------------------------------------------------------


@njit(cache=True, parallel=True)
def _retrieve(counts, tf, fc, fs, dark, quiet, use, start, frame, pixel, lo_, frac, y, x, cos_p, sin_p, vis,
              dose, bg, harm, gain, electronic, iterations, from_data, keep_inverse, keep_expected, next_weights, R,
              tile):
    K, C = counts.shape
    n = -(-C // tile)
    coef_out = np.empty((R, C, 3))
    valid_out = np.empty((R, C), dtype=np.bool_)
    inverse = np.empty((R if keep_inverse else 0, C, 3, 3))
    coupling = np.empty((R if keep_inverse else 0, C, 3, 3))
    ibar = np.empty((K if keep_expected else 0, C))
    w_out = np.empty((K if keep_expected else 0, C))
    chi2 = np.empty(n)
    n_sel = np.empty(n)
    hc, hs = harm[0], harm[1]
    harmonic = hc != 0.0 or hs != 0.0
    steps = 1 + (HARMONIC_STEPS if harmonic else 0)
    hold = np.eye(2)
    for t in prange(n):
        c0 = t * tile
        T = min(tile, C - c0)
        chi2[t] = 0.0
        n_sel[t] = 0.0
        D = np.empty((R, 6, tile))
        U = np.empty((R, 6, tile))
        rhs = np.empty((R, 3, tile))
        used = np.empty((R, tile))
        coef = np.zeros((R, 3, tile))
        valid = np.empty((R, tile), dtype=np.bool_)
        diag = np.empty((R if keep_inverse else 0, tile, 3, 3))
        upper = np.empty((R if keep_inverse else 0, tile, 3, 3))
        wt = np.empty((K, tile))
        for k in range(K):
            for i in range(T):
                c = c0 + i
                if not use[k, c]:
                    wt[k, i] = 0.0
                elif from_data:
                    wt[k, i] = 1.0 / _variance(gain[pixel[k], c], max(counts[k, c], 1.0), quiet[k, c], electronic)
                else:
                    wt[k, i] = start[k, c]
        for it in range(iterations):
            if it > 0:
                # weights from the previous model
                for k in range(K):
                    j = frame[k]
                    lo, f = lo_[k], frac[k]
                    hi = min(lo + 1, R - 1)
                    for i in range(T):
                        c = c0 + i
                        if use[k, c]:
                            m = _count(fc, fs, cos_p, sin_p, tf, vis, dose, dark, bg, y, x, hc, hs, harmonic,
                                       coef, k, c, j, lo, hi, f, i)
                            wt[k, i] = 1.0 / _variance(gain[pixel[k], c], m, quiet[k, c], electronic)
            coef[:, :, :T] = 0.0
            for step in range(steps):
                _normal(counts, tf, fc, fs, dark, wt, 0, frame, lo_, frac, y, x, cos_p, sin_p, vis, dose,
                        bg, hc, hs, hold, c0, T, step, coef, D, U, rhs, used)
                _solve_tile(D, U, rhs, used, T, hold, coef, valid, keep_inverse and it == iterations - 1, diag,
                            upper)
        for k in range(K):
            j = frame[k]
            lo, f = lo_[k], frac[k]
            hi = min(lo + 1, R - 1)
            for i in range(T):
                c = c0 + i
                m = _count(fc, fs, cos_p, sin_p, tf, vis, dose, dark, bg, y, x, hc, hs, harmonic, coef, k, c,
                           j, lo, hi, f, i)
                var = _variance(gain[pixel[k], c], m, quiet[k, c], electronic)
                if keep_expected:
                    ibar[k, c] = m
                    w_out[k, c] = (1.0 / var if use[k, c] else 0.0) if next_weights else wt[k, i]
                if use[k, c] and valid[lo, i] and (valid[hi, i] or f == 0.0):
                    # Pearson residual with the variance of the weights (noise.variance)
                    chi2[t] += (counts[k, c] - m) ** 2 / var
                    n_sel[t] += 1.0
        for r in range(R):
            for i in range(T):
                c = c0 + i
                valid_out[r, c] = valid[r, i]
                for a in range(3):
                    coef_out[r, c, a] = coef[r, a, i]
                if keep_inverse:
                    inverse[r, c] = diag[r, i]
                    coupling[r, c] = upper[r, i]
    return coef_out, valid_out, inverse, coupling, ibar, w_out, chi2, n_sel


def retrieve(obs, ch, *, weights: np.ndarray | None = None, iterations: int = 1, gain: float | None = None,
             keep_inverse: bool = False, keep_expected: bool = True, next_weights: bool = False) -> dict:
    """Least-squares images of every column, the expected counts and the Pearson chi-square where the samples read
    between rows: :func:`dfxcorr.kernels.retrieve`'s parameters and values.

    Parameters
    ----------
    obs : Observations
        With ``reading``.
    ch : Channels
    weights : ndarray, shape (K, C), optional
        Weights of the first solve (0 where ``obs.use`` is false); default the data's inverse noise variances.
    iterations : int
        Solves; each after the first takes the weights from the previous model.
    gain : float, optional
        Overrides ``obs.gain`` (times the pixels' variance factors ``obs.noise``).
    keep_inverse : bool
        Also return the inverse's diagonal blocks ('inverse') and those between each row and the next
        ('coupling').
    keep_expected : bool
        Return the expected counts and the weights.
    next_weights : bool
        Return as 'weights' the inverse noise variances of the last solve's model.

    Returns
    -------
    dict
        'coef' (R, C, 3), 'valid' (R, C), 'inverse' and 'coupling' (R, C, 3, 3) or None, 'expected' (K, C)
        counts, 'weights' (both (0, C) without ``keep_expected`` or ``next_weights``), 'chi2' (Pearson chi-square
        over the used samples whose rows were solved), 'samples' (their number).
    """
    lo, frac = _reading(obs)
    if iterations < 1:
        raise ValueError("iterations must be at least 1")
    g = obs.pixel_gain(gain)
    start = np.zeros((0, 0)) if weights is None else _c(weights, np.float64)
    dark = _c(obs.dark)
    quiet = dark if obs.offset is None else _c(obs.quiet)
    fc, fs = obs.fringe
    keep = keep_expected or next_weights
    coef, valid, inverse, coupling, ibar, w, chi2, n_sel = _retrieve(
        _c(obs.counts), _c(obs.tf), _c(fc), _c(fs), dark, quiet, _c(obs.use), start, obs.frame,
        np.ascontiguousarray(obs.pixel, dtype=np.int64), lo, frac, obs.y, obs.x, np.cos(ch.phase), np.sin(ch.phase),
        _c(ch.vis, np.float64), ch.dose, ch.background, ch.harmonic, _c(g, np.float64), float(obs.electronic),
        int(iterations), weights is None, keep_inverse, keep, next_weights, int(obs.rows.size),
        _tile(obs.columns.size))
    return {"coef": coef, "valid": valid, "inverse": inverse if keep_inverse else None,
            "coupling": coupling if keep_inverse else None, "expected": ibar, "weights": w,
            "chi2": float(chi2.sum()), "samples": int(n_sel.sum())}
