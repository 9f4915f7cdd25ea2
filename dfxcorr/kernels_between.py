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
columns innermost, each block's samples and the image rows it reads taken as contiguous rows of the tile's columns
(1-d views: loops the compiler vectorises). Weights are read in the samples' dtype, sums accumulated in float64.
"""
from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from .kernels import (
    CHANNEL_IDS,
    HARMONIC_STEPS,
    SINGULAR,
    _c,
    _derivatives,
    _design,
    _direction,
    _gradient,
    _image_columns,
    _sample_count,
    _sample_values,
    _turned,
    _variance,
    weights_dtype,
)

#: Position of entry (a, b) of a symmetric 3 x 3 block in its six stored entries (00, 01, 02, 11, 12, 22).
_SYM = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]], dtype=np.int64)


#: Bytes a tile's per-row accumulators may take (normal equations, images, the inverse's blocks: 45 float64 per image
#: row and column).
TILE_BYTES = 64e6


def _tile(n_columns: int, n_rows: int) -> int:
    """Columns per tile: wide (each tile walks every sample's block metadata once; paper study with a parallax, 510
    columns, medians of 5 alternated: tiles of 128 against 256 columns, cost 203 / 178 ms, retrieval 168 / 143 ms),
    as many tiles as threads (or a multiple of them), each at most 128 columns, or up to 256 within
    :data:`TILE_BYTES`."""
    threads = numba.get_num_threads()
    most = int(min(256, max(128, TILE_BYTES / (n_rows * 45 * 8))))
    rounds = -(-n_columns // (threads * most))
    return int(min(most, max(16, -(-n_columns // (threads * rounds)))))


def _reading(obs) -> tuple[np.ndarray, np.ndarray]:
    """The image row below each block's read position and the fraction towards the next, as the kernels take them."""
    if obs.reading is None:
        raise ValueError("the observations read every sample at its own row: use dfxcorr.kernels")
    return np.ascontiguousarray(obs.reading.lo, dtype=np.int64), _c(obs.reading.frac, np.float64)


@njit(cache=True, inline="always")
def _sample(fc, fs, cos_p, sin_p, tf, vis, dose, k, c, j, hc, hs, harm):
    """Sample (k, c) of frame j: its fringe turned by the phase channel (Fc, Fs), D tf, the double angle (zeros
    unless ``harm``) and the design columns (:func:`dfxcorr.kernels._sample_values` of its entries)."""
    return _sample_values(fc[k, c], fs[k, c], tf[k, c], cos_p[j, c], sin_p[j, c], vis[j, c], dose[j], hc, hs, harm)


# --------------------------------------------------------------------------------------------------
# Per-column helpers: the block-tridiagonal normal equations of one column of a tile
# --------------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _add_sample(D, U, rhs, used, lo, hi, f, i, wk, a, x1, x2, target):
    """Add one sample reading rows lo and hi (share 1 - f and f) to column i of the normal equations (the symmetric
    blocks' entries 00, 01, 02, 11, 12, 22): one sample at a time, where a loop walks one column (the Fisher
    information); :func:`_normal` adds a block's samples of a tile's columns together."""
    wa, w1, w2 = wk * a, wk * x1, wk * x2
    p0, p1, p2, p3, p4, p5 = wa * a, wa * x1, wa * x2, w1 * x1, w1 * x2, w2 * x2
    r0, r1, r2 = wa * target, w1 * target, w2 * target
    g = 1.0 - f
    gg = g * g
    n = 1.0 if wk > 0 else 0.0
    D[lo, 0, i] += gg * p0
    D[lo, 1, i] += gg * p1
    D[lo, 2, i] += gg * p2
    D[lo, 3, i] += gg * p3
    D[lo, 4, i] += gg * p4
    D[lo, 5, i] += gg * p5
    rhs[lo, 0, i] += g * r0
    rhs[lo, 1, i] += g * r1
    rhs[lo, 2, i] += g * r2
    used[lo, i] += n
    if f != 0.0:
        ff, gf = f * f, g * f
        D[hi, 0, i] += ff * p0
        D[hi, 1, i] += ff * p1
        D[hi, 2, i] += ff * p2
        D[hi, 3, i] += ff * p3
        D[hi, 4, i] += ff * p4
        D[hi, 5, i] += ff * p5
        U[lo, 0, i] += gf * p0
        U[lo, 1, i] += gf * p1
        U[lo, 2, i] += gf * p2
        U[lo, 3, i] += gf * p3
        U[lo, 4, i] += gf * p4
        U[lo, 5, i] += gf * p5
        rhs[hi, 0, i] += f * r0
        rhs[hi, 1, i] += f * r1
        rhs[hi, 2, i] += f * r2
        used[hi, i] += n


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
        valid[r] = used[r, i] >= n_present and D[r, 0, i] > 0 and abs(_det3(Ds[r])) > SINGULAR
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
    T = np.empty((3, 3))
    _inv3(Ds[0], Finv[0])
    for r in range(1, R):
        # F_r = D_r - U_{r-1}^T (F_{r-1}^-1 U_{r-1}): two 3 x 3 products (one sum of 81 triple products took half a
        # cost evaluation's time on the paper study)
        for p in range(3):
            for b in range(3):
                T[p, b] = Finv[r - 1, p, 0] * Us[r - 1, 0, b] + Finv[r - 1, p, 1] * Us[r - 1, 1, b] \
                    + Finv[r - 1, p, 2] * Us[r - 1, 2, b]
        for a in range(3):
            for b in range(3):
                S[a, b] = Ds[r, a, b] - (Us[r - 1, 0, a] * T[0, b] + Us[r - 1, 1, a] * T[1, b]
                                         + Us[r - 1, 2, a] * T[2, b])
        if abs(_det3(S)) <= SINGULAR:
            # what the row tells of some combination of its images is in the rows before it: held apart, at 0, as
            # banded.forward does
            valid[r] = False
            for a in range(3):
                for b in range(3):
                    S[a, b] = 1.0 if a == b else 0.0
                    Us[r - 1, a, b] = 0.0
                    Us[r, a, b] = 0.0
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


#: Where the normal equations' weights come from: the given array, the given array where the sample is used, the
#: inverse noise variance of the data, that of the model of the previous solve's images.
GIVEN, GIVEN_USED, DATA, MODEL = range(4)


@njit(cache=True)
def _normal(counts, tf, fc, fs, dark, w, source, use, quiet, gain, pixel, electronic, prev, frame, lo_, frac, y, x,
            cos_p, sin_p, vis, dose, bg, hc, hs, hold, c0, T, step, coef, D, U, rhs, used, P):
    """Accumulate the tile's normal equations (columns c0 to c0 + T) over every sample, each weighted as ``source``
    says (``w``; or the noise variance, :func:`dfxcorr.kernels._variance`, of the data or of the model at the images
    ``prev``: computed here rather than kept per sample); from the second step, the harmonic's Gauss-Newton columns
    at the images ``coef`` each sample reads.

    Block by block: the weight, the products of the design columns and the target of each of the tile's columns into
    the rows of the scratch ``P`` (10, tile), then each added to the two image rows the block reads with the block's
    shares. Loops over contiguous rows of the tile's columns, which the compiler vectorises: 3x faster per sample
    than adding each sample's products where they belong."""
    R = D.shape[0]
    D[:, :, :T] = 0.0
    U[:, :, :T] = 0.0
    rhs[:, :, :T] = 0.0
    used[:, :T] = 0.0
    m00, m01, m10, m11 = hold[0, 0], hold[0, 1], hold[1, 0], hold[1, 1]
    b0, b1, b2 = bg[0], bg[1], bg[2]
    harmonic = hc != 0.0 or hs != 0.0
    c1 = c0 + T
    xs = x[c0:c1]
    # the scratch's rows as arrays of their own: the stores below are then to contiguous memory, vectorised
    P0, P1, P2, P3, P4, P5, P6, P7, P8, wr = (P[0, :T], P[1, :T], P[2, :T], P[3, :T], P[4, :T], P[5, :T], P[6, :T],
                                              P[7, :T], P[8, :T], P[9, :T])
    for k in range(frame.size):
        j = frame[k]
        lo, f = lo_[k], frac[k]
        hi = min(lo + 1, R - 1)
        dj, off = dose[j], b0 + b2 * y[k]
        cnt, tfk, fck, fsk, dk = counts[k, c0:c1], tf[k, c0:c1], fc[k, c0:c1], fs[k, c0:c1], dark[k, c0:c1]
        cp, sp, vv = cos_p[j, c0:c1], sin_p[j, c0:c1], vis[j, c0:c1]
        # the weights, into P's last row
        if source == GIVEN:
            wk_ = w[k, c0:c1]
            for i in range(T):
                wr[i] = wk_[i]
        else:
            for i in range(T):
                c = c0 + i
                if not use[k, c]:
                    wr[i] = 0.0
                elif source == GIVEN_USED:
                    wr[i] = w[k, c]
                elif source == DATA:
                    wr[i] = 1.0 / _variance(gain[pixel[k], c], max(counts[k, c], 1.0), quiet[k, c], electronic)
                else:
                    m = _count(fc, fs, cos_p, sin_p, tf, vis, dose, dark, bg, y, x, hc, hs, harmonic, prev, k, c, j,
                               lo, hi, f, i)
                    wr[i] = 1.0 / _variance(gain[pixel[k], c], m, quiet[k, c], electronic)
        if step == 0:
            for i in range(T):
                Fc, Fs = _turned(np.float64(fck[i]), np.float64(fsk[i]), cp[i], sp[i])
                dv = dj * vv[i]
                _products(P0, P1, P2, P3, P4, P5, P6, P7, P8, i, wr[i], dj * tfk[i], dv * (m00 * Fc - m01 * Fs),
                          dv * (m10 * Fc - m11 * Fs), cnt[i] - dk[i] - off - b1 * xs[i])
        else:
            for i in range(T):
                c = c0 + i
                _, _, _, _, _, a, bc, bs, hcc, hcs = _sample(fc, fs, cos_p, sin_p, tf, vis, dose, k, c, j, hc, hs,
                                                             True)
                _, cs, ss = _read(coef, lo, hi, f, i)
                du, dw, _, _ = _direction(cs, ss)
                bc, bs = _image_columns(bc, bs, hcc, hcs, du, dw)
                _products(P0, P1, P2, P3, P4, P5, P6, P7, P8, i, wr[i], a, m00 * bc + m01 * bs, m10 * bc + m11 * bs,
                          cnt[i] - dk[i] - off - b1 * xs[i])
        _scatter(D, U, rhs, used, P, lo, hi, f, T)


@njit(cache=True, inline="always")
def _products(P0, P1, P2, P3, P4, P5, P6, P7, P8, i, wk, a, x1, x2, target):
    """One sample's entries of the normal equations (the symmetric block's 00, 01, 02, 11, 12, 22, then the right-hand
    side's three) into column i of the scratch's rows."""
    wa, w1, w2 = wk * a, wk * x1, wk * x2
    P0[i], P1[i], P2[i], P3[i], P4[i], P5[i] = wa * a, wa * x1, wa * x2, w1 * x1, w1 * x2, w2 * x2
    P6[i], P7[i], P8[i] = wa * target, w1 * target, w2 * target


@njit(cache=True)
def _scatter(D, U, rhs, used, P, lo, hi, f, T):
    """Add a block's entries ``P`` (:func:`_products`) to the rows it reads: (1 - f)^2 and f^2 of each to the diagonal
    blocks of rows lo and hi, (1 - f) f to the coupling block, (1 - f) and f of the right-hand sides; the samples
    of positive weight to each row's count."""
    g = 1.0 - f
    gg, ff, gf = g * g, f * f, g * f
    wr = P[9, :T]
    for e in range(6):
        Dl, Pe = D[lo, e, :T], P[e, :T]
        for i in range(T):
            Dl[i] += gg * Pe[i]
    for e in range(3):
        rl, Pe = rhs[lo, e, :T], P[6 + e, :T]
        for i in range(T):
            rl[i] += g * Pe[i]
    ul = used[lo, :T]
    for i in range(T):
        ul[i] += 1.0 if wr[i] > 0 else 0.0
    if f == 0.0:
        return
    for e in range(6):
        Dh, Ul, Pe = D[hi, e, :T], U[lo, e, :T], P[e, :T]
        for i in range(T):
            Dh[i] += ff * Pe[i]
        for i in range(T):
            Ul[i] += gf * Pe[i]
    for e in range(3):
        rh, Pe = rhs[hi, e, :T], P[6 + e, :T]
        for i in range(T):
            rh[i] += f * Pe[i]
    uh = used[hi, :T]
    for i in range(T):
        uh[i] += 1.0 if wr[i] > 0 else 0.0


@njit(cache=True, inline="always")
def _count(fc, fs, cos_p, sin_p, tf, vis, dose, dark, bg, y, x, hc, hs, harmonic, coef, k, c, j, lo, hi, f,
           i):
    """Expected count of sample (k, c) at the images it reads."""
    _, _, _, _, _, a, bc, bs, hcc, hcs = _sample(fc, fs, cos_p, sin_p, tf, vis, dose, k, c, j, hc, hs, harmonic)
    tt, cs, ss = _read(coef, lo, hi, f, i)
    return _sample_count(dark[k, c], bg, x[c], y[k], tt, cs, ss, a, bc, bs, hcc, hcs, harmonic)


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
    # the double angle and the images' direction where the harmonic is in the model or its sums are asked for
    double = harmonic or need[4]
    steps = 1 + (HARMONIC_STEPS if harmonic else 0)
    b0, b1, b2 = bg[0], bg[1], bg[2]
    # every sum is taken, times 0 where not asked for (a store under a condition per sample costs more)
    np_, nv, nd = 1.0 if need[0] else 0.0, 1.0 if need[1] else 0.0, 1.0 if need[2] else 0.0
    nb, nh = 1.0 if need[3] else 0.0, 1.0 if need[4] else 0.0
    no_use = np.empty((0, 0), dtype=np.bool_)
    no_gain = np.empty((0, 0))
    for t in prange(n):
        c0 = t * tile
        T = min(tile, C - c0)
        D = np.empty((R, 6, tile))
        U = np.empty((R, 6, tile))
        rhs = np.empty((R, 3, tile))
        used = np.empty((R, tile))
        P = np.empty((10, tile))
        coef = np.zeros((R, 3, tile))
        valid = np.empty((R, tile), dtype=np.bool_)
        none = np.empty((0, tile, 3, 3))
        for step in range(steps):
            _normal(counts, tf, fc, fs, dark, w, GIVEN, no_use, dark, no_gain, frame, 0.0, coef, frame, lo_, frac, y,
                    x, cos_p, sin_p, vis, dose, bg, hc, hs, hold, c0, T, step, coef, D, U, rhs, used, P)
            _solve_tile(D, U, rhs, used, T, hold, coef, valid, False, none, none)
        cost[c0:c0 + T] = 0.0
        g_phase[:, c0:c0 + T] = 0.0
        g_vis[:, c0:c0 + T] = 0.0
        g_dose[:, c0:c0 + T] = 0.0
        g_bg[:, c0:c0 + T] = 0.0
        g_harm[:, c0:c0 + T] = 0.0
        c1 = c0 + T
        xs, costs, gb0, gb1, gb2 = x[c0:c1], cost[c0:c1], g_bg[0, c0:c1], g_bg[1, c0:c1], g_bg[2, c0:c1]
        for k in range(K):
            j = frame[k]
            lo, f = lo_[k], frac[k]
            hi = min(lo + 1, R - 1)
            yk = y[k]
            dj, off = dose[j], b0 + b2 * yk
            if not double:
                # without the harmonic, on contiguous rows of the tile's columns: _design and _derivatives at
                # hc = hs = 0
                g = 1.0 - f
                cnt, tfk, fck, fsk, dk, wk_ = (counts[k, c0:c1], tf[k, c0:c1], fc[k, c0:c1], fs[k, c0:c1],
                                               dark[k, c0:c1], w[k, c0:c1])
                cp, sp, vv = cos_p[j, c0:c1], sin_p[j, c0:c1], vis[j, c0:c1]
                gp, gv, gd = g_phase[j, c0:c1], g_vis[j, c0:c1], g_dose[j, c0:c1]
                lt, lc, ls, ht, hc_, hs_ = (coef[lo, 0, :T], coef[lo, 1, :T], coef[lo, 2, :T], coef[hi, 0, :T],
                                            coef[hi, 1, :T], coef[hi, 2, :T])
                for i in range(T):
                    Fc, Fs = _turned(np.float64(fck[i]), np.float64(fsk[i]), cp[i], sp[i])
                    dv = dj * vv[i]
                    tt, cs, ss = g * lt[i] + f * ht[i], g * lc[i] + f * hc_[i], g * ls[i] + f * hs_[i]
                    q = cs * Fc - ss * Fs
                    ww = np.float64(wk_[i])
                    res = cnt[i] - dk[i] - off - b1 * xs[i] - (tt * (dj * tfk[i]) + dv * q)
                    costs[i] += ww * res * res
                    # gradient: sum (-2 w r) F; Gauss-Newton sums: sum (w F) F
                    gw = ww if square else -2.0 * ww * res
                    _gradient(gp, gv, gd, gb0, gb1, gb2, i, gw, square, np_, nv, nd, nb, -dv * (cs * Fs + ss * Fc),
                              dj * q, tfk[i] * tt + vv[i] * q, xs[i], yk)
                continue
            for i in range(T):
                c = c0 + i
                Fc, Fs, amp, c2, s2, a, bc, bs, hcc, hcs = _sample(fc, fs, cos_p, sin_p, tf, vis, dose, k, c, j, hc,
                                                                   hs, True)
                tt, cs, ss = _read(coef, lo, hi, f, i)
                _, _, e, ff = _direction(cs, ss)
                f_p, f_v, f_d, f_c, f_s = _derivatives(tt, cs, ss, Fc, Fs, c2, s2, e, ff, tf[k, c], dj, vis[j, c],
                                                        hc, hs)
                wk = np.float64(w[k, c])
                res = counts[k, c] - dark[k, c] - off - b1 * x[c] - (tt * a + cs * bc + ss * bs) - (hcc * e - hcs * ff)
                cost[c] += wk * res * res
                g = wk if square else -2.0 * wk * res
                g_phase[j, c] += np_ * g * (f_p * f_p if square else f_p)
                g_vis[j, c] += nv * g * (f_v * f_v if square else f_v)
                g_dose[j, c] += nd * g * (f_d * f_d if square else f_d)
                g_bg[0, c] += nb * g
                g_bg[1, c] += nb * g * (x[c] * x[c] if square else x[c])
                g_bg[2, c] += nb * g * (yk * yk if square else yk)
                g_harm[0, c] += nh * g * (f_c * f_c if square else f_c)
                g_harm[1, c] += nh * g * (f_s * f_s if square else f_s)
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
        Read in :func:`dfxcorr.kernels.weights_dtype` (single precision for float32 samples).
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
        _c(obs.counts), _c(obs.tf), _c(fc), _c(fs), _c(obs.dark), _c(weights, weights_dtype(obs)), obs.frame, lo, frac,
        obs.y, obs.x, np.cos(ch.phase), np.sin(ch.phase), _c(ch.vis, np.float64), ch.dose, ch.background,
        ch.harmonic, hold, square, need, int(obs.rows.size), _tile(obs.columns.size, obs.rows.size))
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
    # per-sample outputs in the samples' dtype, as dfxcorr.kernels.retrieve's
    ibar = np.empty((K if keep_expected else 0, C), tf.dtype)
    w_out = np.empty((K if keep_expected else 0, C), tf.dtype)
    chi2 = np.empty(n)
    n_sel = np.empty(n)
    hc, hs = harm[0], harm[1]
    harmonic = hc != 0.0 or hs != 0.0
    steps = 1 + (HARMONIC_STEPS if harmonic else 0)
    hold = np.eye(2)
    first = DATA if from_data else GIVEN_USED
    for t in prange(n):
        c0 = t * tile
        T = min(tile, C - c0)
        D = np.empty((R, 6, tile))
        U = np.empty((R, 6, tile))
        rhs = np.empty((R, 3, tile))
        used = np.empty((R, tile))
        P = np.empty((10, tile))
        coef = np.zeros((R, 3, tile))
        # the previous solve's images: the next solve's weights are those of their model
        prev = np.zeros((R, 3, tile))
        valid = np.empty((R, tile), dtype=np.bool_)
        diag = np.empty((R if keep_inverse else 0, tile, 3, 3))
        upper = np.empty((R if keep_inverse else 0, tile, 3, 3))
        for it in range(iterations):
            if it > 0:
                prev[:, :, :T] = coef[:, :, :T]
            source = first if it == 0 else MODEL
            for step in range(steps):
                _normal(counts, tf, fc, fs, dark, start, source, use, quiet, gain, pixel,
                        electronic, prev, frame, lo_, frac, y, x, cos_p, sin_p, vis, dose, bg, hc, hs, hold, c0, T,
                        step, coef, D, U, rhs, used, P)
                _solve_tile(D, U, rhs, used, T, hold, coef, valid, keep_inverse and it == iterations - 1, diag,
                            upper)
        b0, b1, b2 = bg[0], bg[1], bg[2]
        c1 = c0 + T
        xs = x[c0:c1]
        total, n_used = 0.0, 0.0
        for k in range(K):
            j = frame[k]
            lo, f = lo_[k], frac[k]
            hi = min(lo + 1, R - 1)
            p = pixel[k]
            g = 1.0 - f
            dj, off = dose[j], b0 + b2 * y[k]
            cnt, tfk, fck, fsk, dk, qk, uk = (counts[k, c0:c1], tf[k, c0:c1], fc[k, c0:c1], fs[k, c0:c1],
                                              dark[k, c0:c1], quiet[k, c0:c1], use[k, c0:c1])
            cp, sp, vv, gn = cos_p[j, c0:c1], sin_p[j, c0:c1], vis[j, c0:c1], gain[p, c0:c1]
            lt, lc, ls, ht, hc_, hs_ = (coef[lo, 0, :T], coef[lo, 1, :T], coef[lo, 2, :T], coef[hi, 0, :T],
                                        coef[hi, 1, :T], coef[hi, 2, :T])
            vl, vh = valid[lo, :T], valid[hi, :T]
            for i in range(T):
                Fc, Fs = _turned(np.float64(fck[i]), np.float64(fsk[i]), cp[i], sp[i])
                _, _, a, bc, bs, hcc, hcs = _design(Fc, Fs, dj * tfk[i], dj * vv[i], hc, hs, harmonic)
                tt, cs, ss = g * lt[i] + f * ht[i], g * lc[i] + f * hc_[i], g * ls[i] + f * hs_[i]
                m = dk[i] + off + b1 * xs[i] + tt * a + cs * bc + ss * bs
                if harmonic:
                    _, _, e, ff = _direction(cs, ss)
                    m += hcc * e - hcs * ff
                var = _variance(gn[i], m, qk[i], electronic)
                if keep_expected:
                    c = c0 + i
                    ibar[k, c] = m
                    if not uk[i]:
                        w_out[k, c] = 0.0
                    elif next_weights:
                        w_out[k, c] = 1.0 / var
                    elif iterations > 1:
                        # the last solve's weights: those of the model of the images before it
                        before = _count(fc, fs, cos_p, sin_p, tf, vis, dose, dark, bg, y, x, hc, hs, harmonic, prev, k,
                                        c, j, lo, hi, f, i)
                        w_out[k, c] = 1.0 / _variance(gn[i], before, qk[i], electronic)
                    elif from_data:
                        w_out[k, c] = 1.0 / _variance(gn[i], max(cnt[i], 1.0), qk[i], electronic)
                    else:
                        w_out[k, c] = start[k, c]
                if uk[i] and vl[i] and (vh[i] or f == 0.0):
                    # Pearson residual with the variance of the weights (noise.variance)
                    total += (cnt[i] - m) ** 2 / var
                    n_used += 1.0
        chi2[t] = total
        n_sel[t] = n_used
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
        Weights of the first solve (0 where ``obs.use`` is false), read in :func:`dfxcorr.kernels.weights_dtype`;
        default the data's inverse noise variances.
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
        counts, 'weights' (both in the samples' dtype; (0, C) without ``keep_expected`` or ``next_weights``), 'chi2'
        (Pearson chi-square over the used samples whose rows were solved), 'samples' (their number).
    """
    lo, frac = _reading(obs)
    if iterations < 1:
        raise ValueError("iterations must be at least 1")
    g = obs.pixel_gain(gain)
    start = np.zeros((0, 0), weights_dtype(obs)) if weights is None else _c(weights, weights_dtype(obs))
    dark = _c(obs.dark)
    quiet = dark if obs.offset is None else _c(obs.quiet)
    fc, fs = obs.fringe
    keep = keep_expected or next_weights
    coef, valid, inverse, coupling, ibar, w, chi2, n_sel = _retrieve(
        _c(obs.counts), _c(obs.tf), _c(fc), _c(fs), dark, quiet, _c(obs.use), start, obs.frame,
        np.ascontiguousarray(obs.pixel, dtype=np.int64), lo, frac, obs.y, obs.x, np.cos(ch.phase), np.sin(ch.phase),
        _c(ch.vis, np.float64), ch.dose, ch.background, ch.harmonic, _c(g, np.float64), float(obs.electronic),
        int(iterations), weights is None, keep_inverse, keep, next_weights, int(obs.rows.size),
        _tile(obs.columns.size, obs.rows.size))
    return {"coef": coef, "valid": valid, "inverse": inverse if keep_inverse else None,
            "coupling": coupling if keep_inverse else None, "expected": ibar, "weights": w,
            "chi2": float(chi2.sum()), "samples": int(n_sel.sum())}
