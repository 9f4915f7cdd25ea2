"""Compiled Fisher information where the samples read the images between rows (numba).

The information of the channel components at known images, and the share the profiled images take: per column,
sum Y^T N^-1 Y with Y = X^T W F and N the column's block-tridiagonal normal matrix of the images
(:mod:`dfxcorr.kernels_between` assembles and factors it). :func:`dfxcorr.model.fisher_parts` with
:func:`dfxcorr.banded.profiled_correction` is the definition; the tests hold this kernel to it.
"""
from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from .fisher_pixels import slot
from .kernels import _derivatives, _direction, _image_columns, weights_dtype
from .kernels_between import _add_sample, _factor, _reading, _sample_values

#: Frames whose right-hand sides of the Fisher correction's Y^T N^-1 Y are one block: solved together on the rows
#: where their N^-1 Y is not negligible, then one matrix product with each block whose rows they meet. Profiled
#: Fisher information with a parallax, medians of 5 alternated: paper study (510 columns) 8: 0.85 s, 12: 0.92,
#: 16: 0.93, 24: 0.99, 32: 1.23; binned clinical scan (180 columns) 8: 1.04, 12: 0.96, 16: 1.06, 24: 1.22, 32: 1.47:
#: 8 to 16 alike within the machine's drift, 16 kept.
FRAME_GROUP = 16


#: Where a block of N^-1 Y is cut off: rows past the block's own where its largest value (in the forward sweep, times
#: the largest row sum of F^-1) has fallen below this fraction of its peak (N^-1 decays geometrically away from the
#: diagonal, by about a quarter per row where the samples read evenly between rows). What it leaves out is of this
#: order relative to the correction.
DROP = 1e-14


@njit(cache=True)
def _solve_block(Y, p0, p1, r0, r1, scale, valid, Finv, Us, M, W):
    """N^-1 Y of one column for the right-hand sides ``Y[:, :, p0:p1]`` (nonzero on rows r0..r1 only) into
    ``W`` (R, 3, p1 - p0) (``kernels_between._solve`` for many), on the rows where it is not negligible.

    Above r0 the forward sweep is exactly 0; below r1 it and above r0 the backward sweep decay, and each stops at the
    first row under :data:`DROP` of its peak (a row that cannot be solved decouples the column there: exactly 0).
    ``M`` (R, 3, 3) holds U_{r-1}^T F_{r-1}^-1. Returns the first and last row of ``W`` that hold values; the
    other rows are not written.
    """
    R = Y.shape[0]
    G = p1 - p0
    peak = 0.0
    last = R - 1
    for r in range(r0, R):
        big = 0.0
        for a in range(3):
            s = scale[r, a]
            for p in range(G):
                val = Y[r, a, p0 + p] / s if valid[r] and r <= r1 else 0.0
                if r > r0:
                    # y_r -= U_{r-1}^T F_{r-1}^-1 y_{r-1}
                    val -= M[r, a, 0] * W[r - 1, 0, p] + M[r, a, 1] * W[r - 1, 1, p] + M[r, a, 2] * W[r - 1, 2, p]
                W[r, a, p] = val
                big = max(big, abs(val))
        # judged on what the backward sweep makes of it: F_r^-1 can be large where a row is nearly undetermined
        norm = 0.0
        for a in range(3):
            norm = max(norm, abs(Finv[r, a, 0]) + abs(Finv[r, a, 1]) + abs(Finv[r, a, 2]))
        big *= norm
        peak = max(peak, big)
        if r > r1 and big <= DROP * peak:
            last = r
            break
    v = np.empty((3, G))
    peak = 0.0
    first = 0
    for r in range(last, -1, -1):
        big = 0.0
        for a in range(3):
            for p in range(G):
                v[a, p] = W[r, a, p] if r >= r0 else 0.0
        if r < last:
            for a in range(3):
                u0, u1, u2 = Us[r, a, 0], Us[r, a, 1], Us[r, a, 2]
                for p in range(G):
                    v[a, p] -= u0 * W[r + 1, 0, p] + u1 * W[r + 1, 1, p] + u2 * W[r + 1, 2, p]
        for a in range(3):
            f0, f1, f2 = Finv[r, a, 0], Finv[r, a, 1], Finv[r, a, 2]
            for p in range(G):
                val = f0 * v[0, p] + f1 * v[1, p] + f2 * v[2, p]
                W[r, a, p] = val
                big = max(big, abs(val))
        peak = max(peak, big)
        if r < r0 and big <= DROP * peak:
            first = r
            break
    for r in range(first, last + 1):
        for a in range(3):
            s = scale[r, a]
            for p in range(G):
                W[r, a, p] = W[r, a, p] / s if valid[r] else 0.0
    return first, last


@njit(cache=True, inline="always")
def _own(W, R, block, b):
    """Block b's share of the flat buffer ``W``: its N^-1 Y, (R, 3, its width), contiguous (a product reads a run
    of its rows as one matrix of exactly its columns)."""
    return W[3 * R * block[b]:3 * R * block[b + 1]].reshape(R, 3, block[b + 1] - block[b])


@njit(cache=True, parallel=True)
def _fisher(tf, fc, fs, w, frame, lo_, frac, y, x, cos_p, sin_p, vis, dose, harm, coef, channel, power,
            n_per_frame, n_frames, lead, rslot, block, slots_of, block_rows, profiled, chunks):
    # every per-sample and per-frame array column-major, (C, K), (C, J) and (C, R, 3): a column's samples are
    # contiguous
    C, K = tf.shape
    R = coef.shape[1]
    Q = channel.size
    Pf = n_per_frame
    P = n_frames * Pf + Q - n_per_frame
    Pr = block[-1]
    nb = block.size - 1
    n = chunks.size - 1
    plain = np.empty((n, P, P))
    corr = np.empty((n, P, P))
    hc, hs = harm[0], harm[1]
    for t in prange(n):
        plain[t, :, :] = 0.0
        corr[t, :, :] = 0.0
        F = np.empty(Q)
        xq = np.empty(Q)
        slots = np.empty(Q, dtype=np.int64)
        D = np.empty((R, 6, 1))
        U = np.empty((R, 6, 1))
        rhs = np.empty((R, 3, 1))
        used = np.empty((R, 1))
        # the correction's right-hand sides: a column's per-frame components of one channel differ by a factor x^k,
        # so one per (frame, channel) (``rslot``: where each component's is), then one per global component; zeroed
        # here, then after each column on the rows its blocks read (all of it per column: 4.5 MB at the paper study's
        # size)
        Y = np.zeros((R if profiled else 0, 3, Pr))
        # N^-1 Y block by block (``block``), each on the rows ``window`` where it is not negligible
        W = np.empty(R * 3 * Pr if profiled else 0)
        window = np.empty((nb, 2), dtype=np.int64)
        Mr = np.empty((R, 3, 3))
        factor = np.empty(P)
        scale = np.empty((R, 3))
        ok = np.empty(R, dtype=np.bool_)
        Finv = np.empty((R, 3, 3))
        Us = np.empty((R, 3, 3))
        for c in range(chunks[t], chunks[t + 1]):
            for q in range(Q):
                xq[q] = x[c] ** power[q]
            D[:] = 0.0
            U[:] = 0.0
            used[:] = 0.0
            for k in range(K):
                wk = w[c, k]
                if wk == 0:
                    continue
                j = frame[k]
                lo, f = lo_[k], frac[k]
                hi = min(lo + 1, R - 1)
                g = 1.0 - f
                Fc, Fs, amp, c2, s2, a, bc, bs, hcc, hcs = _sample_values(fc[c, k], fs[c, k], tf[c, k], cos_p[c, j],
                                                                          sin_p[c, j], vis[c, j], dose[j], hc, hs,
                                                                          True)
                tt = g * coef[c, lo, 0] + f * coef[c, hi, 0]
                cs = g * coef[c, lo, 1] + f * coef[c, hi, 1]
                ss = g * coef[c, lo, 2] + f * coef[c, hi, 2]
                du, dw, e, ff = _direction(cs, ss)
                basis = _derivatives(tt, cs, ss, Fc, Fs, c2, s2, e, ff, tf[c, k], dose[j], vis[c, j], hc, hs)
                for q in range(Q):
                    ch = channel[q]
                    if ch <= 1:
                        F[q] = basis[ch] * xq[q]
                    elif ch == 2:
                        F[q] = basis[2]
                    elif ch == 3:
                        F[q] = 1.0 if power[q] == 0 else (x[c] if power[q] == 1 else y[k])
                    else:
                        F[q] = basis[3 + power[q]]
                    slots[q] = slot(j, q, Pf, n_frames)
                for q1 in range(Q):
                    wf = wk * F[q1]
                    for q2 in range(Q):
                        plain[t, slots[q1], slots[q2]] += wf * F[q2]
                if profiled:
                    # the images' columns: their derivatives at the images the sample reads
                    xc, xs = _image_columns(bc, bs, hcc, hcs, du, dw)
                    _add_sample(D, U, rhs, used, lo, hi, f, 0, wk, a, xc, xs, 0.0)
                    for q in range(Q):
                        if not lead[q]:
                            continue
                        p = rslot[slots[q]]
                        wf = wk * (basis[channel[q]] if q < Pf and channel[q] <= 1 else F[q])
                        Y[lo, 0, p] += g * wf * a
                        Y[lo, 1, p] += g * wf * xc
                        Y[lo, 2, p] += g * wf * xs
                        if f != 0.0:
                            Y[hi, 0, p] += f * wf * a
                            Y[hi, 1, p] += f * wf * xc
                            Y[hi, 2, p] += f * wf * xs
            if not profiled:
                continue
            # sum Y^T N^-1 Y over the column's images: each block of N^-1 Y on the rows where it is not negligible,
            # then each pair of blocks' rows of Y^T N^-1 Y over the image rows both reach (Y is zero elsewhere), one
            # matrix product each
            _factor(D, U, used, 0, scale, ok, Finv, Us)
            for r in range(1, R):
                for a in range(3):
                    for b in range(3):
                        Mr[r, a, b] = Us[r - 1, 0, a] * Finv[r - 1, 0, b] + Us[r - 1, 1, a] * Finv[r - 1, 1, b] \
                            + Us[r - 1, 2, a] * Finv[r - 1, 2, b]
            for b in range(nb):
                r0, r1 = block_rows[b, 0], block_rows[b, 1]
                if r1 < r0 or block[b + 1] == block[b]:
                    window[b, 0], window[b, 1] = 0, -1
                    continue
                window[b, 0], window[b, 1] = _solve_block(Y, block[b], block[b + 1], r0, r1, scale, ok, Finv, Us,
                                                          Mr, _own(W, R, block, b))
            # Y^T N^-1 Y is symmetric: each pair of blocks once (the pairs whose rows meet), into the upper triangle of
            # the information's correction at once (its components: those of each (frame, channel) times x^k); the
            # lower triangle is its mirror, made once at the end
            for q in range(Q):
                f_q = xq[q] if q < Pf and channel[q] <= 1 else 1.0
                for j in range(n_frames if q < Pf else 1):
                    factor[slot(j, q, Pf, n_frames)] = f_q
            for b in range(nb):
                p0, p1 = block[b], block[b + 1]
                r0, r1 = block_rows[b, 0], block_rows[b, 1]
                if r1 < r0 or p1 == p0:
                    continue
                Yb = np.empty((3 * (r1 - r0 + 1), p1 - p0))
                for r in range(r0, r1 + 1):
                    for a in range(3):
                        for p in range(p0, p1):
                            Yb[3 * (r - r0) + a, p - p0] = Y[r, a, p]
                for q in range(b, nb):
                    lo, hi = max(r0, window[q, 0]), min(r1, window[q, 1])
                    if hi < lo:
                        continue
                    part = np.dot(Yb[3 * (lo - r0):3 * (hi - r0 + 1)].T,
                                  _own(W, R, block, q)[lo:hi + 1].reshape(3 * (hi - lo + 1), block[q + 1] - block[q]))
                    q0 = block[q]
                    for s1 in range(slots_of[b], slots_of[b + 1]):
                        f1, row = factor[s1], part[rslot[s1] - p0]
                        for s2 in range(max(s1, slots_of[q]), slots_of[q + 1]):
                            corr[t, s1, s2] += f1 * factor[s2] * row[rslot[s2] - q0]
            for b in range(nb):
                Y[block_rows[b, 0]:block_rows[b, 1] + 1, :, block[b]:block[b + 1]] = 0.0
        for p1 in range(P):
            for p2 in range(p1):
                corr[t, p1, p2] = corr[t, p2, p1]
    return plain, corr


def fisher(obs, ch, weights: np.ndarray, coef: np.ndarray, table: tuple, *, profiled: bool = True
           ) -> tuple[np.ndarray, np.ndarray]:
    """Fisher information of channel components and its correction for the profiled images where the samples read
    between rows: :func:`dfxcorr.fisher_pixels.fisher`'s values, the correction over whole columns (a pixel's images
    share samples with its neighbours', :func:`dfxcorr.banded.profiled_correction`).

    Parameters
    ----------
    obs : Observations
        With ``reading``.
    ch : Channels
    weights : ndarray, shape (K, C)
    coef : ndarray, shape (R, C, 3)
        Images (t, c, s); the images' normal matrices are assembled at them.
    table : tuple
        (channel ids (Q,), power or basis index (Q,), number of per-frame components), see
        :func:`dfxcorr.model.component_table`.
    profiled : bool
        Also compute the correction (otherwise zeros).

    Returns
    -------
    plain, correction : ndarray, shape (P, P)
        P = J * (per-frame components) + (global components), per-frame entries ordered (frame, component).
    """
    lo, frac = _reading(obs)
    channel, power, n_per_frame = table
    R, J, Pf = obs.rows.size, obs.n_frames, int(n_per_frame)
    # the correction's right-hand sides: per frame one per channel of its components (the first component of each
    # channel leads), then one per global component; each component's (``rslot``), in blocks of a frame's and the
    # global ones, with the image rows each block's samples read
    Pg = len(channel) - Pf
    chans = list(dict.fromkeys(int(ch_) for ch_ in channel[:Pf]))
    lead = np.array([q >= Pf or int(channel[q]) not in [int(v) for v in channel[:q]] for q in range(len(channel))])
    Pu = len(chans)
    own = [chans.index(int(channel[q])) for q in range(Pf)]
    rslot = np.concatenate([(np.arange(J)[:, None] * Pu + np.array(own, dtype=np.int64)[None, :]).ravel(),
                            J * Pu + np.arange(Pg)]).astype(np.int64)
    hi = np.minimum(lo + 1, R - 1)
    groups = -(-J // FRAME_GROUP)
    block_rows = np.zeros((groups + 1, 2), dtype=np.int64)
    block_rows[:groups, 0], block_rows[:groups, 1], block_rows[groups, 1] = R, -1, R - 1
    counted = np.any(weights != 0, axis=1)
    group = obs.frame[counted] // FRAME_GROUP
    np.minimum.at(block_rows[:groups, 0], group, lo[counted])
    np.maximum.at(block_rows[:groups, 1], group, np.where(frac != 0, hi, lo)[counted])
    block = np.append(np.arange(groups, dtype=np.int64) * FRAME_GROUP * Pu, [J * Pu, J * Pu + Pg])
    # the components (their slots in the information) each block's right-hand sides serve
    slots_of = np.append(np.arange(groups, dtype=np.int64) * FRAME_GROUP * Pf, [J * Pf, J * Pf + Pg])
    C = obs.columns.size
    n = max(1, min(C, numba.get_num_threads()))
    chunks = np.linspace(0, C, n + 1).round().astype(np.int64)
    fc, fs = obs.fringe

    def by_column(a: np.ndarray, dtype=None) -> np.ndarray:
        # a column's samples one after another: walked a column at a time, (K, C) arrays read a page per sample
        # (0.30 against 0.24 s for 73 columns of the paper study with a parallax)
        return np.ascontiguousarray(np.swapaxes(a, 0, 1), dtype=dtype)

    plain, corr = _fisher(by_column(obs.tf), by_column(fc), by_column(fs), by_column(weights, weights_dtype(obs)),
                          obs.frame, lo, frac, obs.y, obs.x, by_column(np.cos(ch.phase)), by_column(np.sin(ch.phase)),
                          by_column(ch.vis, np.float64), ch.dose, ch.harmonic, by_column(coef, np.float64),
                          np.asarray(channel, dtype=np.int64), np.asarray(power, dtype=np.int64), Pf, J, lead,
                          rslot, block, slots_of, block_rows, bool(profiled), chunks)
    return plain.sum(axis=0), corr.sum(axis=0)
