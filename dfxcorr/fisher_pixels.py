"""Compiled Fisher information where each pixel's images are solved from its own samples (numba).

The information of the channel components at known images (plain), and the share the profiled images take (the
correction): per pixel Y^T N^-1 Y with Y = X^T W F and N its 3 x 3 normal matrix, driven by a component table
(:func:`dfxcorr.model.component_table`). :func:`dfxcorr.model.fisher_matrix` is the definition; the tests hold this
kernel to it. The per-sample helpers are :mod:`dfxcorr.kernels`' (one model); :mod:`dfxcorr.fisher_between` is the
same where the samples read the images between rows.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .chunks import over_chunks, row_chunks
from .kernels import (
    BACKGROUND,
    HARMONIC,
    VISIBILITY,
    _bounds,
    _c,
    _derivatives,
    _design,
    _direction,
    _image_columns,
    _per_pixel,
    _turned,
    _turning,
    weights_dtype,
)


@njit(cache=True, inline="always")
def slot(i: int, q: int, per_frame: int, n: int) -> int:
    """The place of component ``q`` of frame (or row block) ``i`` among ``n`` of them in the Fisher matrices: per-frame
    components (q < per_frame) ordered (frame, component), the global ones after all frames."""
    return i * per_frame + q if q < per_frame else n * per_frame + q - per_frame


@njit(cache=True, error_model="numpy", nogil=True)
def _fisher_rows(tf, fc, fs, w, frame, y, bounds, first, last, cos_p, sin_p, vis, dose, harm, coef, inverse, channel,
                 power, xq, n_per_frame, n_frames, profiled, double, plain, corr):
    """Fisher information and its profiled correction of rows ``first:last`` (a chunk, :func:`over_chunks`) into the
    chunk's own plain and corr (P, P) (:func:`fisher`), with the components' column factors ``xq`` (Q, C,
    :func:`_column_factors`) and ``double`` whether the double angle is needed.

    Every loop over a row's columns is elementwise (the compiler vectorises it): the plain information is summed per
    (frame, pair of components, column) and over the columns at the end (it couples a frame only to itself and to
    the global components); the correction's X^T W F per (slot, image, column)."""
    C, Q = tf.shape[1], channel.size
    Pf, Pg = n_per_frame, Q - n_per_frame
    hc, hs = harm[0], harm[1]
    corr[:, :] = 0.0
    # the chunk's rows see a window of the frames: its sums hold those alone (every frame's, in every thread, was
    # J Q (Q + 1) / 2 C numbers per thread: 67 MB each with every effect on the paper study's 510 columns)
    lo_frame, hi_frame = n_frames, 0
    for k in range(bounds[first], bounds[last]):
        lo_frame, hi_frame = min(lo_frame, frame[k]), max(hi_frame, frame[k] + 1)
    acc = np.zeros((max(hi_frame - lo_frame, 0), Q * (Q + 1) // 2, C))
    # one 1-d array per quantity: the compiler cannot tell rows of one 2-d array apart and would keep loops scalar
    basis = (np.empty(C), np.empty(C), np.empty(C), np.empty(C), np.empty(C))
    X = (np.empty(C), np.empty(C), np.empty(C))  # the images' columns a, xc, xs
    L = (np.empty(C), np.empty(C), np.empty(C), np.empty(C), np.empty(C), np.empty(C))
    F, dirs = np.empty((Q, C)), np.empty((4, C))
    for r in range(first, last):
        lo, nb = bounds[r], bounds[r + 1] - bounds[r]
        m = nb * Pf + Pg
        idx = np.empty(m, dtype=np.int64)  # the row's slots (its frames' components, then the globals) in plain
        for b in range(nb):
            for q in range(Pf):
                idx[b * Pf + q] = frame[lo + b] * Pf + q
        for g in range(Pg):
            idx[nb * Pf + g] = n_frames * Pf + g
        Y = np.zeros((m if profiled else 0, 3, C))
        for c in range(C):
            dirs[0, c], dirs[1, c], dirs[2, c], dirs[3, c] = _direction(coef[r, c, 1], coef[r, c, 2])
        for b in range(nb):
            k = lo + b
            j, dj = frame[k], dose[frame[k]]
            for c in range(C):
                Fc, Fs = _turned(fc[k, c], fs[k, c], cos_p[j, c], sin_p[j, c])
                c2, s2, a, bc, bs, hcc, hcs = _design(Fc, Fs, dj * tf[k, c], dj * vis[j, c], hc, hs, double)
                d0, d1, d2, d3, d4 = _derivatives(coef[r, c, 0], coef[r, c, 1], coef[r, c, 2], Fc, Fs, c2, s2,
                                                  dirs[2, c], dirs[3, c], tf[k, c], dj, vis[j, c], hc, hs)
                xc, xs = _image_columns(bc, bs, hcc, hcs, dirs[0, c], dirs[1, c])
                # a sample without weight adds nothing: zeros, whatever its values
                on = w[k, c] != 0.0
                basis[0][c], basis[1][c], basis[2][c] = d0 if on else 0.0, d1 if on else 0.0, d2 if on else 0.0
                basis[3][c], basis[4][c] = d3 if on else 0.0, d4 if on else 0.0
                X[0][c], X[1][c], X[2][c] = a if on else 0.0, xc if on else 0.0, xs if on else 0.0
            for q in range(Q):
                ch, pw, Fq, xf = channel[q], power[q], F[q], xq[q]
                src = basis[min(ch, 2)] if ch <= 2 else basis[3 + pw if ch == 4 else 0]
                for c in range(C):
                    if ch == 3:
                        Fq[c] = (y[k] if pw == 2 else xf[c]) if w[k, c] != 0.0 else 0.0
                    else:
                        Fq[c] = src[c] * (xf[c] if ch <= 2 else 1.0)
            p = 0
            for q1 in range(Q):
                for q2 in range(q1, Q):
                    a12, F1, F2 = acc[j - lo_frame, p], F[q1], F[q2]
                    for c in range(C):
                        a12[c] += w[k, c] * F1[c] * F2[c]
                    p += 1
                if profiled:
                    s1 = slot(b, q1, Pf, nb)
                    for i in range(3):
                        Ys, Xi, F1 = Y[s1, i], X[i], F[q1]
                        for c in range(C):
                            Ys[c] += w[k, c] * F1[c] * Xi[c]
        if profiled:
            # sum over the row's columns of Y^T N^-1 Y = Z^T Z, Z = L^T Y with N^-1 = L L^T (each column's Cholesky
            # factor; zeros where the pixel is not solvable: its images are not profiled), then one matrix product
            for c in range(C):
                i00, i01, i02 = inverse[r, c, 0, 0], inverse[r, c, 0, 1], inverse[r, c, 0, 2]
                i11, i12, i22 = inverse[r, c, 1, 1], inverse[r, c, 1, 2], inverse[r, c, 2, 2]
                ok = i00 > 0
                l00 = np.sqrt(i00) if ok else 1.0
                l10, l20 = i01 / l00, i02 / l00
                d11 = i11 - l10 * l10
                l11 = np.sqrt(d11) if d11 > 0 else 0.0
                l21 = (i12 - l20 * l10) / l11 if l11 > 0 else 0.0
                d22 = i22 - l20 * l20 - l21 * l21
                L[0][c], L[1][c], L[2][c] = l00 if ok else 0.0, l10 if ok else 0.0, l20 if ok else 0.0
                L[3][c], L[4][c] = l11 if ok else 0.0, l21 if ok else 0.0
                L[5][c] = (np.sqrt(d22) if d22 > 0 else 0.0) if ok else 0.0
            Z = np.empty((m, 3, C))
            for s in range(m):
                y0, y1, y2, z0, z1, z2 = Y[s, 0], Y[s, 1], Y[s, 2], Z[s, 0], Z[s, 1], Z[s, 2]
                for c in range(C):
                    z0[c] = L[0][c] * y0[c] + L[1][c] * y1[c] + L[2][c] * y2[c]
                    z1[c] = L[3][c] * y1[c] + L[4][c] * y2[c]
                    z2[c] = L[5][c] * y2[c]
            Z2 = Z.reshape((m, 3 * C))
            rc = np.dot(Z2, Z2.T)
            for a1 in range(m):
                for a2 in range(m):
                    corr[idx[a1], idx[a2]] += rc[a1, a2]
    plain[:, :] = 0.0
    p = 0
    for q1 in range(Q):
        for q2 in range(q1, Q):
            for jw in range(acc.shape[0]):
                v = 0.0
                for c in range(C):
                    v += acc[jw, p, c]
                jj = jw + lo_frame
                s1, s2 = slot(jj, q1, Pf, n_frames), slot(jj, q2, Pf, n_frames)
                plain[s1, s2] += v
                if s1 != s2:
                    plain[s2, s1] += v
            p += 1
    return plain, corr


def _column_factors(channel: np.ndarray, power: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The column factor of each component, shape (Q, C): x^power (phase, visibility), x for the background's x
    term, else 1."""
    xq = np.ones((channel.size, x.size))
    for q, (c, p) in enumerate(zip(channel, power, strict=True)):
        if c <= VISIBILITY:
            xq[q] = x ** p
        elif c == BACKGROUND and p == 1:
            xq[q] = x
    return xq


def fisher(obs, ch, weights: np.ndarray, coef: np.ndarray, inverse: np.ndarray | None, table: tuple, *,
           profiled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Fisher information of channel components and its correction for profiled images.

    Parameters
    ----------
    obs : Observations
    ch : Channels
    weights : ndarray, shape (K, C)
    coef : ndarray, shape (R, C, 3)
        Images (t, c, s).
    inverse : ndarray, shape (R, C, 3, 3) or None
        Inverse normal matrices (needed when ``profiled``).
    table : tuple
        (channel ids (Q,), power or basis index (Q,), number of per-frame components; the per-frame
        ones come first), see :func:`dfxcorr.model.component_table`.
    profiled : bool
        Also compute the correction (otherwise zeros).

    Returns
    -------
    plain : ndarray, shape (P, P)
        sum w F F^T over samples, P = J * (per-frame components) + (global components), ordered (frame, component).
    correction : ndarray, shape (P, P)
        sum over pixels of Y^T N^-1 Y (Y = X^T W F): the profiled information is plain - correction.
    """
    _per_pixel(obs)
    channel, power, n_per_frame = table
    bounds = _bounds(obs)
    inv = np.zeros((0, 0, 3, 3)) if inverse is None else inverse
    # one chunk per thread: each holds (P, P) accumulators and the sums of its rows' frames, (frames, pairs, C)
    # in the samples' dtype (kernels.weights_dtype, as the cost reads them): one compiled specialisation per dtype of
    # the samples, and no float64 copy of the fit's float32 weights (215 MB at 2.7e7 samples)
    weights = _c(weights, weights_dtype(obs))
    fc, fs = obs.fringe
    channel, power = np.asarray(channel, dtype=np.int64), np.asarray(power, dtype=np.int64)
    chunks = row_chunks(bounds[:-1], obs.frame.size, per_thread=1)
    P = obs.n_frames * n_per_frame + channel.size - n_per_frame
    plain, corr = np.empty((chunks.size - 1, P, P)), np.empty((chunks.size - 1, P, P))
    over_chunks(_fisher_rows, chunks, (_c(obs.tf), fc, fs, weights, obs.frame, obs.y, bounds),
                (*_turning(obs, ch.phase), _c(ch.vis, np.float64), ch.dose, ch.harmonic, coef, inv, channel,
                 power, _column_factors(channel, power, obs.x), int(n_per_frame), int(obs.n_frames),
                 bool(profiled and inverse is not None),
                 # the double angle where the harmonic is in the model or among the components
                 bool(np.any(ch.harmonic != 0.0) or np.any(channel == HARMONIC))), (plain, corr))
    return plain.sum(axis=0), corr.sum(axis=0)
