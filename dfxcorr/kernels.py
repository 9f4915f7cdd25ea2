"""Compiled per-sample loops of the fit and the retrieval (numba).

The forward model of :mod:`dfxcorr.model` is evaluated here from its *channel values* on the (frame, column) grid: the
phase Φ (J, C), the visibility factor V (J, C), the dose D (J,), the background coefficients of (1, x, y) (3,) and the
harmonic (hc, hs) (2,). The samples' flat field is read as its transmission and fringe quadratures (``obs.tf``,
``obs.fringe``), turned by the phase channel with the cos and sin of Φ tabulated per (frame, column): no sample needs a
trigonometric call here. Every catalogue effect enters through one of these channels (:func:`dfxcorr.model.channels`
maps effect parameters to them, :func:`dfxcorr.model.channel_adjoint` maps channel gradients back), so a new effect
that enters through an existing channel needs no change here. The numpy expressions of :mod:`dfxcorr.model` are the
definition; the tests hold these kernels to them.

The second harmonic follows the sample (its term is m cos(2 psi + beta), not linear in the images): where it is
non-zero, each pixel's solve is followed by :data:`HARMONIC_STEPS` Gauss-Newton steps, each a solve with the columns
:func:`_image_columns` at the previous images (``model.solve_images``).

Layout: a pixel is (row, column); its samples are the blocks ``starts[r]:starts[r + 1]`` of one row
(:class:`dfxcorr.observations.Observations`). The kernels run over chunks of rows in parallel (the cost, and the Fisher
information of :mod:`dfxcorr.fisher_pixels`, as compiled functions of one chunk in threads, :func:`over_chunks`, which
compile in about half the time of numba's parallel loop; the retrieval in that loop); every chunk owns its
accumulators (summed afterwards), so no two threads write the same memory. Within a row the columns are handled in
tiles (:data:`TILE`) so that the second pass over a tile finds what the first left in cache. Sums are accumulated in
float64 whatever the sample dtype.
"""
from __future__ import annotations

import functools
import os

import numba
import numpy as np
from numba import njit, prange
from threadpoolctl import threadpool_limits

from .chunks import over_chunks, row_chunks

#: Channel ids of the component tables (see :func:`dfxcorr.model.component_table`).
PHASE, VISIBILITY, DOSE, BACKGROUND, HARMONIC = range(5)
CHANNEL_IDS = {"phase": PHASE, "visibility": VISIBILITY, "dose": DOSE, "background": BACKGROUND, "harmonic": HARMONIC}

#: Columns per tile (at most, in equal tiles) of the retrieval and the fit's cost: a tile's design arrays of one row
#: (about 30 blocks at clinical scale) stay in the L2 cache, and each loop over a tile's columns repays its set-up
#: (retrieval 64 -> 512 columns: 16.5 -> 11 ns CPU per sample; the cost's 256 -> 512 on the paper study: 7.0 -> 5.3)
TILE = 512

#: Gauss-Newton steps of the per-pixel solve after the first (harmonic-free) one when the second harmonic is in the
#: model (its term is not linear in the images; tests/test_model.py holds these steps to a converged solve).
HARMONIC_STEPS = 3


def set_threads() -> int:
    """Set numba's thread count from SLURM_CPUS_PER_TASK, else OMP_NUM_THREADS, else the usable cores.

    Unless NUMBA_THREADING_LAYER chooses otherwise, the kernels run on numba's own 'workqueue' pool: OpenMP's
    spin-waiting threads made every call about ten times slower on cores shared with other processes (measured: 23
    ms instead of 1.6 ms per small evaluation), and its spinning slows the optimiser between calls. This takes
    effect if no parallel kernel has run yet in the process.

    BLAS (OpenBLAS, MKL) is held to one thread for the same reason: this package's BLAS calls are small (matrices of
    the per-frame parameters, L-BFGS's vectors), and OpenBLAS's idle threads spin-wait on the cores the kernels'
    threads need (binned clinical scan: the vibration fit 8.8 -> 6.9 s, the motion mask 2.9 -> 2.4 s). Like numba's
    thread count, this holds for the process.

    Returns
    -------
    int
        The number of threads set (at most numba's pool size).
    """
    if "NUMBA_THREADING_LAYER" not in os.environ:
        # numba.config sets its options at run time from the environment, unseen by mypy
        numba.config.THREADING_LAYER = "workqueue"  # type: ignore[attr-defined]
    n = 0
    for var in ("SLURM_CPUS_PER_TASK", "OMP_NUM_THREADS"):
        first = os.environ.get(var, "").split(",")[0].strip()
        if first.isdigit() and int(first) > 0:
            n = int(first)
            break
    if n == 0:
        n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    n = max(1, min(n, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]  # set at run time, as above
    numba.set_num_threads(n)
    _single_threaded_blas()
    return n


@functools.cache
def _single_threaded_blas() -> None:
    """Hold BLAS to one thread, once per process (finding the loaded libraries takes about 2.5 ms, and
    set_threads runs for every block of a scan: 0.7 s at full resolution)."""
    threadpool_limits(limits=1, user_api="blas")


def _c(a: np.ndarray, dtype=None) -> np.ndarray:
    """``a`` C-ordered (copied only if it is not, or not of ``dtype``): numba compiles a kernel once per layout and
    dtype (a first demo run compiled the retrieval five times, about 6 s each), and walks samples a row at a time."""
    return np.ascontiguousarray(a, dtype=dtype)


def _turning(obs, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of the phase channel (J, C), each (J, C) float64, at the frames the observations hold (zeros at the
    others, which no sample reads): a block of detector rows sees a sixth of a clinical scan's frames, and the float64
    cos and sin of every frame took 17 ms per block, a serial part of the full-detector retrieval."""
    frames = np.flatnonzero(np.bincount(obs.frame, minlength=obs.n_frames))
    cos_p, sin_p = np.zeros(phase.shape), np.zeros(phase.shape)
    cos_p[frames], sin_p[frames] = np.cos(phase[frames]), np.sin(phase[frames])
    return cos_p, sin_p


def _per_pixel(obs) -> None:
    """The compiled loops solve each pixel's images from its own samples: refuse samples that read between rows."""
    if obs.reading is not None:
        raise ValueError("samples read the images between rows: evaluate them through dfxcorr.engine")


def _bounds(obs) -> np.ndarray:
    """Block boundaries of the rows, shape (R + 1,)."""
    return np.append(obs.starts, obs.frame.size).astype(np.int64)


# Per-sample helpers (inlined into the kernels)


@njit(cache=True, inline="always")
def _turned(fc, fs, cp, sp):
    """The sample's fringe turned by the phase channel: tf vf (cos θ, sin θ) from fc, fs and cos Φ, sin Φ."""
    return fc * cp - fs * sp, fs * cp + fc * sp


@njit(cache=True, inline="always")
def _design(Fc, Fs, amp, dv, hc, hs, harm):
    """tf vf (cos 2θ, sin 2θ) (model.second_harmonic; zeros unless ``harm``), the design columns A, Bc, Bs and the
    harmonic's columns Hc, Hs of one sample with turned fringe (Fc, Fs), amp = D tf and dv = D V."""
    c2, s2 = 0.0, 0.0
    if harm:
        m = np.sqrt(Fc * Fc + Fs * Fs)
        if m > 0.0:
            c2, s2 = (Fc * Fc - Fs * Fs) / m, 2.0 * Fc * Fs / m
    return c2, s2, amp, dv * Fc, -dv * Fs, dv * (hc * c2 - hs * s2), dv * (hc * s2 + hs * c2)


@njit(cache=True, inline="always")
def _sample_values(fc, fs, tf, cp, sp, vis, dose, hc, hs, harm):
    """One sample's turned fringe (Fc, Fs), D tf, double angle and design columns (:func:`_turned`, :func:`_design`)
    from its flat-field fringe (fc, fs) and transmission and its frame's cos Φ, sin Φ, V and D at its column."""
    Fc, Fs = _turned(np.float64(fc), np.float64(fs), cp, sp)
    amp = dose * tf
    c2, s2, a, bc, bs, hcc, hcs = _design(Fc, Fs, amp, dose * vis, hc, hs, harm)
    return Fc, Fs, amp, c2, s2, a, bc, bs, hcc, hcs


@njit(cache=True, inline="always")
def _direction(cs, ss):
    """cos phi, sin phi of images (c, s) (0 where c = s = 0) and the harmonic factors e = m cos 2phi, f = m sin 2phi.
    Without a branch: a loop over columns that calls it is vectorised."""
    m = np.sqrt(cs * cs + ss * ss)
    some = m != 0.0
    u, w = cs / m if some else 0.0, ss / m if some else 0.0
    return u, w, cs * u - ss * w, ss * u + cs * w


@njit(cache=True, inline="always")
def _sample_count(dark, bg, x, y, t, cs, ss, a, bc, bs, hcc, hcs, harmonic):
    """Expected count of one sample at images (t, c, s) from its dark, the background (bg at its x and y) and its
    design columns (:func:`_sample_values`)."""
    m = dark + bg[0] + bg[1] * x + bg[2] * y + t * a + cs * bc + ss * bs
    if harmonic:
        _, _, e, f = _direction(cs, ss)
        m += hcc * e - hcs * f
    return m


@njit(cache=True, inline="always")
def _image_columns(bc, bs, hcc, hcs, u, w):
    """dIbar/dc, dIbar/ds of one sample at images of direction (u, w) (model.image_columns)."""
    return (bc + hcc * u * (1.0 + 2.0 * w * w) - hcs * 2.0 * w * w * w,
            bs - hcc * w * (1.0 + 2.0 * u * u) - hcs * 2.0 * u * u * u)


@njit(cache=True, inline="always")
def _derivatives(tt, cs, ss, Fc, Fs, c2, s2, e, f, tf, dose, vis, hc, hs):
    """dIbar/d(channel) of one sample at images (t, c, s), harmonic factors (e, f), turned fringe (Fc, Fs) and its
    double angle (c2, s2): phase, visibility, dose, hc, hs (model.sample_derivatives)."""
    q = cs * Fc - ss * Fs
    g = c2 * e - s2 * f
    k = s2 * e + c2 * f
    p2 = hc * g - hs * k
    dv = dose * vis
    f_phase = -dv * (cs * Fs + ss * Fc + 2.0 * (hc * k + hs * g))
    return f_phase, dose * (q + p2), tf * tt + vis * (q + p2), dv * g, -dv * k


@njit(cache=True, inline="always")
def _variance(g, m, quiet, electronic):
    """Noise variance of a sample of expected count m, ``quiet`` its additive term without photon noise
    (noise.variance: its photon term at least one count)."""
    return g * max(m - quiet, 1.0) + electronic


#: |det| of a normal matrix scaled to a unit diagonal at or below which its unknowns count as undetermined (the pixel,
#: or the row of images read between rows, is not solved): every solve of the images uses it.
SINGULAR = 1e-10


@njit(cache=True)
def _normal(n00, n01, n02, n11, n12, n22, r0, r1, r2, n_used):
    """Closed-form solve of one pixel's 3x3 normal equations with the rules of ``model.solve_pixels``: valid, the
    coefficients (3) and the inverse normal matrix's entries i00, i01, i02, i11, i12, i22 (zeros where invalid).

    A column with zero diagonal is not an unknown; valid needs the first column, as many used samples as unknowns and
    |det| > :data:`SINGULAR` of the unit-diagonal matrix. Called where its loop over a tile's columns only keeps the
    inverse (the retrieval's ``keep_inverse``); :data:`_normal_inlined` where that loop solves the tile's pixels.
    """
    p0, p1, p2 = n00 > 0, n11 > 0, n22 > 0
    s0 = np.sqrt(n00) if p0 else 1.0
    s1 = np.sqrt(n11) if p1 else 1.0
    s2 = np.sqrt(n22) if p2 else 1.0
    a00 = n00 / (s0 * s0) if p0 else 1.0
    a11 = n11 / (s1 * s1) if p1 else 1.0
    a22 = n22 / (s2 * s2) if p2 else 1.0
    a01 = n01 / (s0 * s1) if (p0 & p1) else 0.0
    a02 = n02 / (s0 * s2) if (p0 & p2) else 0.0
    a12 = n12 / (s1 * s2) if (p1 & p2) else 0.0
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    valid = p0 & (n_used >= (1.0 * p0 + p1 + p2)) & (abs(det) > SINGULAR)
    c11, c12, c22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
    b0, b1, b2 = r0 / s0, r1 / s1, r2 / s2
    # where invalid det may be 0: the quotients are then inf or nan, never selected
    x0, x1, x2 = (c00 * b0 + c01 * b1 + c02 * b2) / det / s0, (c01 * b0 + c11 * b1 + c12 * b2) / det / s1, \
        (c02 * b0 + c12 * b1 + c22 * b2) / det / s2
    i00, i11, i22 = c00 / det / (s0 * s0), c11 / det / (s1 * s1), c22 / det / (s2 * s2)
    i01, i02, i12 = c01 / det / (s0 * s1), c02 / det / (s0 * s2), c12 / det / (s1 * s2)
    z = 0.0
    return (valid, x0 if valid else z, x1 if valid else z, x2 if valid else z, i00 if valid else z,
            i01 if valid else z, i02 if valid else z, i11 if valid else z, i12 if valid else z, i22 if valid else z)


#: :func:`_normal` inlined: the loop over a tile's columns that calls it is vectorised (the called solve took 1.9 of
#: 6.9 CPU ns per sample of a cost evaluation on the paper study, 0.2 inlined; retrieval 10.8 -> 8.3, compile +3 s)
_normal_inlined = njit(inline="always")(_normal.py_func)


# The fit: reduced cost and its gradient (or the Gauss-Newton diagonal) in one pass per pixel


@njit(cache=True, inline="always")
def _add(n00, n01, n02, n11, n12, n22, r0, r1, r2, used, i, ww, a, x1, x2, target):
    """Add one sample of weight ww, design (a, x1, x2) and target to column i of a tile's normal equations."""
    wa, w1, w2 = ww * a, ww * x1, ww * x2
    n00[i], n01[i], n02[i] = n00[i] + wa * a, n01[i] + wa * x1, n02[i] + wa * x2
    n11[i], n12[i], n22[i] = n11[i] + w1 * x1, n12[i] + w1 * x2, n22[i] + w2 * x2
    r0[i], r1[i], r2[i] = r0[i] + wa * target, r1[i] + w1 * target, r2[i] + w2 * target
    used[i] += 1.0 if ww > 0 else 0.0


@njit(cache=True, inline="always")
def _gradient(gp, gv, gd, gb0, gb1, gb2, i, g, square, np_, nv, nd, nb, f_p, f_v, f_d, x, y):
    """Add one sample to column i of the phase, visibility, dose and background sums: gradient sum (-2 w r) F with
    g = -2 w r, or Gauss-Newton diagonal sum (w F) F with g = w (``square``). Every sum is taken, times 0 (np_, ...)
    where not asked for: a store under a condition would keep the loop from being vectorised."""
    gp[i], gv[i] = gp[i] + np_ * g * (f_p * f_p if square else f_p), gv[i] + nv * g * (f_v * f_v if square else f_v)
    gd[i], gb0[i] = gd[i] + nd * g * (f_d * f_d if square else f_d), gb0[i] + nb * g
    gb1[i], gb2[i] = gb1[i] + nb * g * (x * x if square else x), gb2[i] + nb * g * (y * y if square else y)


@njit(cache=True, error_model="numpy", nogil=True)
def _cost_rows(counts, tf, fc, fs, dark, w, frame, y, x, bounds, first, last, cos_p, sin_p, vis, dose, bg, harm, hold,
               square, need, tile, cost, g_phase, g_vis, g_dose, g_bg, g_harm):
    """Reduced cost and its channel sums of rows ``first:last`` (a chunk, :func:`over_chunks`) into the chunk's own
    accumulators: cost (C,), g_phase, g_vis, g_dose (J, C), g_bg (3, C), g_harm (2, C) (:func:`reduced_cost`)."""
    C = counts.shape[1]
    hc, hs = harm[0], harm[1]
    steps = 1 + (HARMONIC_STEPS if (hc != 0.0 or hs != 0.0) else 0)
    # the double angle where the harmonic is in the model or its derivatives are asked for
    double = steps > 1 or need[4]
    m00, m01, m10, m11 = hold[0, 0], hold[0, 1], hold[1, 0], hold[1, 1]
    b0, b1, b2 = bg[0], bg[1], bg[2]
    np_, nv, nd = 1.0 if need[0] else 0.0, 1.0 if need[1] else 0.0, 1.0 if need[2] else 0.0
    nb, nh = 1.0 if need[3] else 0.0, 1.0 if need[4] else 0.0
    cost[:] = 0.0
    g_phase[:, :] = 0.0
    g_vis[:, :] = 0.0
    g_dose[:, :] = 0.0
    g_bg[:, :] = 0.0
    g_harm[:, :] = 0.0
    # one 1-d array per accumulator, each sample row's operands as 1-d slices: the column loops below are
    # elementwise over contiguous memory, which the compiler vectorises (a 2-d accumulator indexed [q, i] and
    # the samples indexed [k, c] were about eight times slower per sample)
    n00, n01, n02, n11, n12, n22 = np.empty(tile), np.empty(tile), np.empty(tile), np.empty(tile), \
        np.empty(tile), np.empty(tile)
    r0, r1, r2, used, ct, cc, cs = np.empty(tile), np.empty(tile), np.empty(tile), np.empty(tile), \
        np.empty(tile), np.empty(tile), np.empty(tile)
    du, dw, de, df = np.empty(tile), np.empty(tile), np.empty(tile), np.empty(tile)
    for r in range(first, last):
        lo, hi = bounds[r], bounds[r + 1]
        for c0 in range(0, C, tile):
            c1 = min(c0 + tile, C)
            T, xs = c1 - c0, x[c0:c1]
            for step in range(steps):
                n00[:T], n01[:T], n02[:T], n11[:T], n12[:T], n22[:T] = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
                r0[:T], r1[:T], r2[:T], used[:T] = 0.0, 0.0, 0.0, 0.0
                for k in range(lo, hi):
                    j = frame[k]
                    dj, off = dose[j], b0 + b2 * y[k]
                    cnt, tfk, fck, fsk = counts[k, c0:c1], tf[k, c0:c1], fc[k, c0:c1], fs[k, c0:c1]
                    dk, wk = dark[k, c0:c1], w[k, c0:c1]
                    cp, sp, vv = cos_p[j, c0:c1], sin_p[j, c0:c1], vis[j, c0:c1]
                    # the first solve in a loop of its own: a branch on the step kept it from being vectorised
                    if step == 0:
                        for i in range(T):
                            Fc, Fs = _turned(np.float64(fck[i]), np.float64(fsk[i]), cp[i], sp[i])
                            dv = dj * vv[i]
                            _add(n00, n01, n02, n11, n12, n22, r0, r1, r2, used, i, np.float64(wk[i]), dj * tfk[i],
                                 dv * (m00 * Fc - m01 * Fs), dv * (m10 * Fc - m11 * Fs),
                                 cnt[i] - dk[i] - off - b1 * xs[i])
                    else:
                        for i in range(T):
                            Fc, Fs = _turned(np.float64(fck[i]), np.float64(fsk[i]), cp[i], sp[i])
                            _, _, a, bc, bs, hcc, hcs = _design(Fc, Fs, dj * tfk[i], dj * vv[i], hc, hs, True)
                            # Gauss-Newton step of the harmonic: the columns at the current images
                            bc, bs = _image_columns(bc, bs, hcc, hcs, du[i], dw[i])
                            _add(n00, n01, n02, n11, n12, n22, r0, r1, r2, used, i, np.float64(wk[i]), a,
                                 m00 * bc + m01 * bs, m10 * bc + m11 * bs, cnt[i] - dk[i] - off - b1 * xs[i])
                for i in range(T):
                    _, ct[i], x1, x2, _, _, _, _, _, _ = _normal_inlined(n00[i], n01[i], n02[i], n11[i], n12[i],
                                                                         n22[i], r0[i], r1[i], r2[i], used[i])
                    # back from the solved columns (x1, x2) to (t, c, s)
                    cc[i] = m00 * x1 + m10 * x2
                    cs[i] = m01 * x1 + m11 * x2
                    du[i], dw[i], de[i], df[i] = _direction(cc[i], cs[i])
            costs, gh0, gh1 = cost[c0:c1], g_harm[0, c0:c1], g_harm[1, c0:c1]
            gb0, gb1, gb2 = g_bg[0, c0:c1], g_bg[1, c0:c1], g_bg[2, c0:c1]
            for k in range(lo, hi):
                j, yk = frame[k], y[k]
                dj, off = dose[j], b0 + b2 * yk
                cnt, tfk, fck, fsk = counts[k, c0:c1], tf[k, c0:c1], fc[k, c0:c1], fs[k, c0:c1]
                dk, wk = dark[k, c0:c1], w[k, c0:c1]
                cp, sp, vv = cos_p[j, c0:c1], sin_p[j, c0:c1], vis[j, c0:c1]
                gp, gv, gd = g_phase[j, c0:c1], g_vis[j, c0:c1], g_dose[j, c0:c1]
                if not double:
                    # without the harmonic in a loop of its own: _design and _derivatives at hc = hs = 0
                    for i in range(T):
                        Fc, Fs = _turned(np.float64(fck[i]), np.float64(fsk[i]), cp[i], sp[i])
                        dv = dj * vv[i]
                        tt, cs_, ss = ct[i], cc[i], cs[i]
                        q = cs_ * Fc - ss * Fs
                        ww = np.float64(wk[i])
                        res = cnt[i] - dk[i] - off - b1 * xs[i] - (tt * dj * tfk[i] + dv * q)
                        costs[i] += ww * res * res
                        g = ww if square else -2.0 * ww * res
                        _gradient(gp, gv, gd, gb0, gb1, gb2, i, g, square, np_, nv, nd, nb,
                                  -dv * (cs_ * Fs + ss * Fc), dj * q, tfk[i] * tt + vv[i] * q, xs[i], yk)
                    continue
                for i in range(T):
                    Fc, Fs = _turned(np.float64(fck[i]), np.float64(fsk[i]), cp[i], sp[i])
                    c2, s2, a, bc, bs, hcc, hcs = _design(Fc, Fs, dj * tfk[i], dj * vv[i], hc, hs, True)
                    tt, cs_, ss, e, f = ct[i], cc[i], cs[i], de[i], df[i]
                    f_p, f_v, f_d, f_c, f_s = _derivatives(tt, cs_, ss, Fc, Fs, c2, s2, e, f, tfk[i], dj, vv[i],
                                                            hc, hs)
                    ww = np.float64(wk[i])
                    res = cnt[i] - dk[i] - off - b1 * xs[i] - (tt * a + cs_ * bc + ss * bs) - (hcc * e - hcs * f)
                    costs[i] += ww * res * res
                    g = ww if square else -2.0 * ww * res
                    _gradient(gp, gv, gd, gb0, gb1, gb2, i, g, square, np_, nv, nd, nb, f_p, f_v, f_d, xs[i], yk)
                    gh0[i] += nh * g * (f_c * f_c if square else f_c)
                    gh1[i] += nh * g * (f_s * f_s if square else f_s)


def weights_dtype(obs) -> np.dtype:
    """The dtype of the weights the fit's cost reads: single precision unless the samples are double (rounding 6e-8
    relative, far below any noise; one compiled specialisation per dtype, 4 bytes per sample less)."""
    return np.result_type(obs.counts.dtype, np.float32)


def reduced_cost(obs, ch, weights: np.ndarray, *, phase: float | None = None, square: bool = False,
                 channels=tuple(CHANNEL_IDS)) -> tuple[float, tuple[np.ndarray, ...]]:
    """Reduced cost sum w (I - Ibar)^2 at the closed-form images and its channel gradients.

    Parameters
    ----------
    obs : Observations
    ch : Channels
        Channel values (:func:`dfxcorr.model.channels`).
    weights : ndarray, shape (K, C)
    phase : float, optional
        Hold the phase image at this constant (the circular-mean stage): 2 unknowns per pixel.
    square : bool
        Instead of the gradient sum -2 w r F, return the Gauss-Newton sums sum w F^2 (the Fisher
        diagonal, per channel value).
    channels : sequence of str
        Channels whose sums are wanted (the others are returned as zeros).

    Returns
    -------
    cost : float
        Counts^2 / variance (dimensionless).
    grads : tuple
        Per channel value: phase (J, C), visibility (J, C), dose (J,), background (3,), harmonic (2,).
    """
    _per_pixel(obs)
    hold = np.eye(2) if phase is None else np.array([[np.cos(phase), np.sin(phase)], [0.0, 0.0]])
    need = np.isin(list(CHANNEL_IDS), list(channels))
    bounds = _bounds(obs)
    weights = _c(weights, weights_dtype(obs))
    fc, fs = obs.fringe
    chunks = row_chunks(bounds[:-1], obs.frame.size)
    n, J, C = chunks.size - 1, obs.n_frames, obs.columns.size
    out = (np.empty((n, C)), np.empty((n, J, C)), np.empty((n, J, C)), np.empty((n, J, C)), np.empty((n, 3, C)),
           np.empty((n, 2, C)))
    over_chunks(_cost_rows, chunks, (_c(obs.counts), _c(obs.tf), fc, fs, _c(obs.dark), weights, obs.frame, obs.y, obs.x,
                                     bounds),
                (*_turning(obs, ch.phase), _c(ch.vis, np.float64), ch.dose, ch.background, ch.harmonic, hold, square,
                 need, TILE), out)
    cost, g_phase, g_vis, g_dose, g_bg, g_harm = (a.sum(axis=0) for a in out)
    return float(cost.sum()), (g_phase, g_vis, g_dose.sum(axis=1), g_bg.sum(axis=1), g_harm.sum(axis=1))


# The retrieval: images, expected counts, noise weights and Pearson chi-square


@njit(cache=True, inline="always")
def _count(i, off, a, bc, bs, hcc, hcs, t, c, s, e, f, harmonic):
    """Expected count of sample i of a tile row from rows (T,) of offsets, design, harmonic's columns and images."""
    m = off[i] + t[i] * a[i] + c[i] * bc[i] + s[i] * bs[i]
    if harmonic:
        m += hcc[i] * e[i] - hcs[i] * f[i]
    return m


# numba's parallel loop, not over_chunks: compiled as a function of one chunk, this loop took twice the time per sample
@njit(cache=True, parallel=True, error_model="numpy")
def _retrieve(counts, tf, fc, fs, dark, quiet, use, start, frame, y, x, bounds, chunks, cos_p, sin_p, vis, dose, bg,
              harm, gain, electronic, iterations, from_data, keep_inverse, keep_expected, keep_weights, next_weights,
              tile, w_out):
    (K, C), R, n = counts.shape, bounds.size - 1, chunks.size - 1
    # every entry is written by its chunk: np.empty (np.zeros would be a parallel region of its own)
    coef, valid = np.empty((R, C, 3)), np.empty((R, C), dtype=np.bool_)
    inverse = np.empty((R if keep_inverse else 0, C, 3, 3))
    # per-sample outputs in the samples' dtype: float32 samples need no float64 copies of their size
    ibar = np.empty((K if keep_expected else 0, C), tf.dtype)
    chi2, n_sel = np.empty(n), np.empty(n)
    b0, b1, b2 = bg[0], bg[1], bg[2]
    hc, hs = harm[0], harm[1]
    harmonic = hc != 0.0 or hs != 0.0
    steps = 1 + (HARMONIC_STEPS if harmonic else 0)
    for t in prange(n):
        # one 1-d array per accumulator and per-column value, the tile's samples as 1-d rows: every loop over a
        # tile's columns below is elementwise over memory no other operand shares, which the compiler vectorises
        n00, n01, n02, n11, n12, n22 = np.empty(tile), np.empty(tile), np.empty(tile), np.empty(tile), \
            np.empty(tile), np.empty(tile)
        r0, r1, r2, used = np.empty(tile), np.empty(tile), np.empty(tile), np.empty(tile)
        ct, cc, cs, ok = np.empty(tile), np.empty(tile), np.empty(tile), np.empty(tile, dtype=np.bool_)
        du, dw, de, df = np.empty(tile), np.empty(tile), np.empty(tile), np.empty(tile)
        # the chunk's chi-square and samples per column (a sum over columns is a serial chain). Loops, not slice
        # assignments or sums: each array expression of a parallel function is a loop nest to compile (44 -> 33 s)
        chi_t, sel_t = np.empty(tile), np.empty(tile)
        for i in range(tile):
            chi_t[i] = sel_t[i] = 0.0
        for r in range(chunks[t], chunks[t + 1]):
            lo, nb = bounds[r], bounds[r + 1] - bounds[r]
            # the tile's design, offsets and weights, computed once
            A, Bc, Bs, off, w = np.empty((nb, tile)), np.empty((nb, tile)), np.empty((nb, tile)), \
                np.empty((nb, tile)), np.empty((nb, tile))
            # the harmonic's columns only where it is in the model (one row no sample reads otherwise)
            Hc, Hs = np.empty((nb if harmonic else 1, tile)), np.empty((nb if harmonic else 1, tile))
            for c0 in range(0, C, tile):
                T, c1 = min(tile, C - c0), min(c0 + tile, C)
                xs, gr = x[c0:c1], gain[r, c0:c1]
                for it in range(iterations):
                    for step in range(steps):
                        for i in range(T):
                            n00[i] = n01[i] = n02[i] = n11[i] = n12[i] = n22[i] = r0[i] = r1[i] = r2[i] = 0.0
                            used[i] = 0.0
                        for b in range(nb):
                            k = lo + b
                            cnt, qk, uk = counts[k, c0:c1], quiet[k, c0:c1], use[k, c0:c1]
                            ab, bcb, bsb, ob, wb = A[b, :T], Bc[b, :T], Bs[b, :T], off[b, :T], w[b, :T]
                            hcb, hsb = Hc[b if harmonic else 0, :T], Hs[b if harmonic else 0, :T]
                            if it == 0 and step == 0:
                                j = frame[k]
                                dj, yk = dose[j], y[k]
                                fck, fsk, tfk, dk = fc[k, c0:c1], fs[k, c0:c1], tf[k, c0:c1], dark[k, c0:c1]
                                cp, sp, vv = cos_p[j, c0:c1], sin_p[j, c0:c1], vis[j, c0:c1]
                                if harmonic:
                                    for i in range(T):
                                        Fc, Fs = _turned(fck[i], fsk[i], cp[i], sp[i])
                                        _, _, ab[i], bcb[i], bsb[i], hcb[i], hsb[i] = _design(
                                            Fc, Fs, dj * tfk[i], dj * vv[i], hc, hs, True)
                                else:
                                    for i in range(T):
                                        Fc, Fs = _turned(fck[i], fsk[i], cp[i], sp[i])
                                        dv = dj * vv[i]
                                        ab[i], bcb[i], bsb[i] = dj * tfk[i], dv * Fc, -dv * Fs
                                for i in range(T):
                                    ob[i] = dk[i] + b0 + b1 * xs[i] + b2 * yk
                                if from_data:
                                    for i in range(T):
                                        wb[i] = 1.0 / _variance(gr[i], cnt[i], qk[i], electronic) if uk[i] else 0.0
                                else:
                                    sk = start[k, c0:c1]
                                    for i in range(T):
                                        wb[i] = sk[i]
                            elif step == 0:
                                # weights from the previous model (noise.variance: its photon term at least one count)
                                for i in range(T):
                                    m = _count(i, ob, ab, bcb, bsb, hcb, hsb, ct, cc, cs, de, df, harmonic)
                                    wb[i] = 1.0 / _variance(gr[i], m, qk[i], electronic) if uk[i] else 0.0
                            if step == 0:
                                for i in range(T):
                                    _add(n00, n01, n02, n11, n12, n22, r0, r1, r2, used, i, wb[i], ab[i], bcb[i],
                                         bsb[i], cnt[i] - ob[i])
                            else:
                                # Gauss-Newton step of the harmonic: the columns at the current images
                                for i in range(T):
                                    bc, bs = _image_columns(bcb[i], bsb[i], hcb[i], hsb[i], du[i], dw[i])
                                    _add(n00, n01, n02, n11, n12, n22, r0, r1, r2, used, i, wb[i], ab[i], bc, bs,
                                         cnt[i] - ob[i])
                        for i in range(T):
                            ok[i], ct[i], cc[i], cs[i], _, _, _, _, _, _ = _normal_inlined(
                                n00[i], n01[i], n02[i], n11[i], n12[i], n22[i], r0[i], r1[i], r2[i], used[i])
                            du[i], dw[i], de[i], df[i] = _direction(cc[i], cs[i])
                for i in range(T):
                    c = c0 + i
                    valid[r, c] = ok[i]
                    coef[r, c, 0], coef[r, c, 1], coef[r, c, 2] = ct[i], cc[i], cs[i]
                if keep_inverse:
                    for i in range(T):
                        _, _, _, _, i00, i01, i02, i11, i12, i22 = _normal(n00[i], n01[i], n02[i], n11[i], n12[i],
                                                                           n22[i], r0[i], r1[i], r2[i], used[i])
                        iv = inverse[r, c0 + i]
                        iv[0, 0], iv[0, 1], iv[0, 2], iv[1, 1], iv[1, 2], iv[2, 2] = i00, i01, i02, i11, i12, i22
                        iv[1, 0], iv[2, 0], iv[2, 1] = i01, i02, i12
                for b in range(nb):
                    k = lo + b
                    cnt, qk, uk = counts[k, c0:c1], quiet[k, c0:c1], use[k, c0:c1]
                    ab, bcb, bsb, ob, wb = A[b, :T], Bc[b, :T], Bs[b, :T], off[b, :T], w[b, :T]
                    hcb, hsb = Hc[b if harmonic else 0, :T], Hs[b if harmonic else 0, :T]
                    for i in range(T):
                        m = _count(i, ob, ab, bcb, bsb, hcb, hsb, ct, cc, cs, de, df, harmonic)
                        # Pearson residual with the variance of the weights (noise.variance)
                        sel = ok[i] & uk[i]
                        chi_t[i] += (cnt[i] - m) ** 2 / _variance(gr[i], m, qk[i], electronic) if sel else 0.0
                        sel_t[i] += 1.0 if sel else 0.0
                    for i in range(T if keep_expected or keep_weights else 0):
                        m = _count(i, ob, ab, bcb, bsb, hcb, hsb, ct, cc, cs, de, df, harmonic)
                        if keep_expected:
                            ibar[k, c0 + i] = m
                        if keep_weights:
                            # the weights of this solve, or of its model (what a further solve would use)
                            w_out[k, c0 + i] = ((1.0 / _variance(gr[i], m, qk[i], electronic) if uk[i] else 0.0)
                                                if next_weights else wb[i])
        chi2[t], n_sel[t] = 0.0, 0.0
        for i in range(tile):
            chi2[t] += chi_t[i]
            n_sel[t] += sel_t[i]
    return coef, valid, inverse, ibar, w_out, chi2, n_sel


@njit(cache=True, nogil=True, error_model="numpy")
def _expected_rows(tf, fc, fs, dark, frame, y, x, bounds, cos_p, sin_p, vis, dose, bg, harm, coef, first, last, ibar):
    """Expected counts of the samples of rows ``first`` to ``last`` into ibar (K, C): the retrieval's expected counts
    at given images."""
    hc, hs = harm[0], harm[1]
    harmonic = hc != 0.0 or hs != 0.0
    for r in range(first, last):
        for k in range(bounds[r], bounds[r + 1]):
            j = frame[k]
            dj, yk, out = dose[j], y[k], ibar[k]
            for c in range(x.size):
                _, _, _, _, _, a, bc, bs, hcc, hcs = _sample_values(fc[k, c], fs[k, c], tf[k, c], cos_p[j, c],
                                                                    sin_p[j, c], vis[j, c], dj, hc, hs, harmonic)
                out[c] = _sample_count(dark[k, c], bg, x[c], yk, coef[r, c, 0], coef[r, c, 1], coef[r, c, 2], a, bc,
                                       bs, hcc, hcs, harmonic)


def expected(obs, ch, coef: np.ndarray) -> np.ndarray:
    """Expected counts at given images, shape (K, C): :func:`dfxcorr.model.expected` of the model's design.

    Parameters
    ----------
    obs : Observations
    ch : Channels
        Channel values (:func:`dfxcorr.model.channels`) at ``obs``' columns.
    coef : ndarray, shape (R, C, 3)
        Images t, c, s of every pixel held.
    """
    _per_pixel(obs)
    bounds = _bounds(obs)
    ibar = np.empty(obs.counts.shape)
    fc, fs = obs.fringe
    samples = (_c(obs.tf), _c(fc), _c(fs), _c(obs.dark), obs.frame, obs.y, obs.x, bounds)
    over_chunks(_expected_rows, row_chunks(bounds[:-1], obs.frame.size),
                (*samples, *_turning(obs, ch.phase), _c(ch.vis, np.float64), ch.dose, ch.background, ch.harmonic,
                 _c(coef, np.float64)), (ibar,), ())
    return ibar


def retrieve(obs, ch, *, weights: np.ndarray | None = None, iterations: int = 1, gain: float | None = None,
             keep_inverse: bool = False, keep_expected: bool = True, next_weights: bool = False,
             out: np.ndarray | None = None) -> dict:
    """Closed-form images of every pixel, the expected counts and the Pearson chi-square.

    Parameters
    ----------
    obs : Observations
    ch : Channels
        Channel values (:func:`dfxcorr.model.channels`).
    weights : ndarray, shape (K, C), optional
        Weights of the first solve; default the data's inverse noise variances (paper eq. 6).
    iterations : int
        Solves; each after the first takes the weights from the previous model.
    gain : float, optional
        Overrides ``obs.gain`` in the noise weights and the chi-square (times the pixels' variance factors
        ``obs.noise``: the kernel reads one gain per pixel).
    keep_inverse : bool
        Also return the inverse normal matrices.
    keep_expected : bool
        Return the expected counts and the weights (a retrieval for the images alone writes nothing per sample).
    next_weights : bool
        Return as 'weights' the inverse noise variances of the last solve's model (the weights of a further solve,
        as ``iterations + 1`` would use them, without that solve) instead of those of the last solve, whatever
        ``keep_expected`` says.
    out : ndarray, shape (K, C), optional
        Where the returned weights are written (C-ordered, the samples' dtype); it may be ``weights`` itself: each
        pixel's weights are read before its new ones are written (a full-resolution fit's reweighting held both, 2 x
        108 MB).

    Returns
    -------
    dict
        'coef' (R, C, 3), 'valid' (R, C), 'inverse' (R, C, 3, 3) or None, 'expected' (K, C) counts ((0, C)
        without ``keep_expected``), 'weights' (K, C) of the last solve or with ``next_weights`` of its model
        ((0, C) without ``keep_expected`` or ``next_weights``), both in the samples' dtype (``obs.tf``'s),
        'chi2' (Pearson chi-square over the used samples of valid pixels), 'samples' (their number).
    """
    _per_pixel(obs)
    if iterations < 1:
        raise ValueError("iterations must be at least 1")
    g = obs.pixel_gain(gain)
    bounds = _bounds(obs)
    # weights in the samples' dtype whatever the caller's: one compiled specialisation per dtype (~6 s each)
    start = np.zeros((0, 0), obs.tf.dtype) if weights is None else _c(weights, obs.tf.dtype)
    # without known photons in it the dark is its own quiet part: one array (not a second copy of a strided one)
    dark = _c(obs.dark)
    quiet = dark if obs.offset is None else _c(obs.quiet)
    fc, fs = obs.fringe
    n_c = max(obs.columns.size, 1)
    keep_weights = keep_expected or next_weights
    shape = (obs.counts.shape[0] if keep_weights else 0, obs.columns.size)
    if out is not None and (out.shape != shape or out.dtype != obs.tf.dtype or not out.flags["C_CONTIGUOUS"]):
        raise ValueError(f"out must be a C-ordered {obs.tf.dtype} array of shape {shape}, got {out.dtype} {out.shape}")
    coef, valid, inverse, ibar, w, chi2, n_sel = _retrieve(
        _c(obs.counts), _c(obs.tf), fc, fs, dark, quiet, _c(obs.use), start,
        obs.frame, obs.y, obs.x, bounds, row_chunks(bounds[:-1], obs.frame.size), *_turning(obs, ch.phase),
        _c(ch.vis, np.float64), ch.dose, ch.background, ch.harmonic, _c(g, np.float64),
        float(obs.electronic), int(iterations), weights is None, keep_inverse, keep_expected,
        keep_weights, next_weights, -(-n_c // -(-n_c // TILE)), np.empty(shape, obs.tf.dtype) if out is None else out)
    return {"coef": coef, "valid": valid, "inverse": inverse if keep_inverse else None, "expected": ibar,
            "weights": w, "chi2": float(chi2.sum()), "samples": int(n_sel.sum())}
