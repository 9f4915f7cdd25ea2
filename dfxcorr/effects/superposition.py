"""The scatter field S: each frame's primary superposed under a Gaussian kernel, held on coarse blocks.

What :mod:`dfxcorr.effects.scatter` adds to the model's unmodulated offset (its module text: the physics and the two
ratios). Made here: the primary's sums on blocks of b x b pixels (compiled: the primary of every lit sample is read
once per field, and a diagnosis makes a dozen fields), the blur of those block grids, and the interpolation back to
the samples each stage asks for.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numba import njit
from scipy import fft as sfft

from .. import kernels as K
from ..align import reference_row
from ..chunks import over_chunks


@dataclass(frozen=True)
class Primary:
    """The unmodulated primary t^f t of a store's samples, read where a field needs it (every lit sample of a
    clinical scan at once is gigabytes): the sample of block ``k`` in column c is
    interp(maps, u[k])[c] * t[row[k], c], ``maps`` interpolated linearly between row centres as
    :func:`dfxcorr.align.interpolate_rows` does.

    Attributes
    ----------
    maps : ndarray, shape (A, W)
        The flat field's transmission at the interferometer's row centres (one row: the same for every sample).
    u : ndarray, shape (K,)
        Local interferometer row of each block of samples.
    t : ndarray, shape (R, W)
        The sample's transmission (R detector rows), or any per-row factor.
    row : ndarray of int, shape (K,)
        Row of ``t`` of each block.
    """

    maps: np.ndarray
    u: np.ndarray
    t: np.ndarray
    row: np.ndarray

    def __post_init__(self) -> None:
        # converted once: a field reads them a frame at a time
        for name, dtype in (("maps", np.float64), ("u", np.float64), ("t", np.float64), ("row", np.int64)):
            object.__setattr__(self, name, np.ascontiguousarray(getattr(self, name), dtype=dtype))
        # the compiled sums index without bounds checks
        if (self.maps.ndim != 2 or self.maps.shape[0] < 1 or self.t.ndim != 2 or self.t.shape[1] != self.maps.shape[1]
                or self.u.shape != self.row.shape or self.row.ndim != 1
                or (self.row.size and not 0 <= self.row.min() <= self.row.max() < self.t.shape[0])):
            raise ValueError(f"a primary needs maps (A, W), t (R, W) and u, row (K,) with rows in [0, R): got maps "
                             f"{self.maps.shape}, t {self.t.shape}, u {self.u.shape}, row {self.row.shape}")

    @property
    def width(self) -> int:
        """Detector columns W."""
        return int(self.maps.shape[1])

    def frame_sums(self, detector_row: np.ndarray, order: np.ndarray, bounds: np.ndarray, origin: np.ndarray, b: int,
                   frames: tuple[int, int], out: np.ndarray, totals: np.ndarray) -> None:
        """Adds the primary of frames j0 <= j < j1 (``frames``) to ``out[j - j0]`` (N, ceil(W / b)), summed on b x b
        blocks, and writes each frame's sum (counts) to ``totals[j]``.

        Frame j's blocks are ``order[bounds[j]:bounds[j + 1]]``, block k at block row
        (detector_row[k] - origin[j]) // b. In chunks of frames on the kernels' threads (each writes its own frames).
        """
        j0, j1 = frames
        n = max(1, min(j1 - j0, 2 * K.set_threads()))
        chunks = np.linspace(j0, j1, n + 1).round().astype(np.int64)
        over_chunks(_frame_sums, chunks, (self.maps, self.u, self.t, self.row, np.asarray(detector_row, np.int64),
                                          np.asarray(order, np.int64), np.asarray(bounds, np.int64),
                                          np.asarray(origin, np.int64), int(b), int(j0)), (out, totals), ())


@njit(cache=True, nogil=True, error_model="numpy")
def _frame_sums(maps: np.ndarray, u: np.ndarray, t: np.ndarray, row: np.ndarray, detector_row: np.ndarray,
                order: np.ndarray, bounds: np.ndarray, origin: np.ndarray, b: int, j0: int, lo: int, hi: int,
                out: np.ndarray, totals: np.ndarray) -> None:
    A, W = maps.shape
    for j in range(lo, hi):
        total = 0.0
        for n in range(bounds[j], bounds[j + 1]):
            k = order[n]
            k0, a = reference_row(u[k], A) if A > 1 else (0, 0.0)
            k1 = min(k0 + 1, A - 1)
            below, above, tr = maps[k0], maps[k1], t[row[k]]
            o = out[j - j0, (detector_row[k] - origin[j]) // b]
            for c in range(W):
                p = ((1.0 - a) * below[c] + a * above[c]) * tr[c]
                o[c // b] += p
                total += p
        totals[j] = total


def blur(a: np.ndarray, sigma: float, *, axis: int = -1) -> np.ndarray:
    """Gaussian blur of ``a`` along ``axis`` (std ``sigma`` pixels, kernel cut at 4 sigma), zeros beyond the edges.

    scipy.ndimage.gaussian_filter1d(mode='constant'), by FFT along an axis longer than :data:`DIRECT_BLUR`: the
    scatter's kernel spans hundreds of pixels (50 mm at 0.3 mm: sigma 167), where the direct sum took 10 s for a
    5-step 512 x 1536 scan. Along a shorter axis as a product with the kernel's band matrix: the FFT pads the axis
    to the kernel's span (a binned clinical scan's 44 block rows under a kernel of 271 blocks: 1.9 s by FFT, 0.05 s
    so, for its every frame).
    """
    radius = int(4.0 * sigma + 0.5)
    x = np.arange(-radius, radius + 1, dtype=float)
    kernel = np.exp(-0.5 * (x / max(sigma, 1e-12)) ** 2)
    kernel /= kernel.sum()
    n = a.shape[axis]
    if n <= DIRECT_BLUR:
        apart = np.arange(n)[:, None] - np.arange(n)[None, :]
        band = np.where(np.abs(apart) <= radius, kernel[np.clip(apart + radius, 0, 2 * radius)], 0.0)
        # a stack of matrix products (tensordot moved the axis to the front, a copy of the whole array each way)
        if a.ndim == 1:
            return band @ a
        return np.moveaxis(band @ np.moveaxis(a, axis, -2), -2, axis)
    # the linear convolution by real FFTs padded to the kernel's span, on the kernels' threads (scipy.signal's
    # fftconvolve on one: a binned clinical scan's field at 12.5 mm took 1.9 s, most of it there)
    m, threads = sfft.next_fast_len(n + 2 * radius, real=True), K.set_threads()
    spectrum = sfft.rfft(np.moveaxis(a, axis, -1), m, axis=-1, workers=threads) * sfft.rfft(kernel, m)
    return np.moveaxis(sfft.irfft(spectrum, m, axis=-1, workers=threads)[..., radius:radius + n], -1, axis)


@dataclass(frozen=True)
class ScatterField:
    """S of a store's samples, held coarse: each frame's primary convolved with the kernel on blocks of b x b pixels,
    interpolated to the samples asked for (:meth:`take`). S of every lit sample of a full-resolution
    clinical scan, in float32, is 2.2 GB; its blocks are about 10 MB.

    Attributes
    ----------
    grids : ndarray, shape (J, N, M), float32
        Frame j's field on blocks (rows from ``origin[j]``, its first ``rows[j]`` block rows), counts per unit s.
    rows, origin : ndarray of int, shape (J,)
        Block rows of each frame's grid, and the detector row of its first pixel row.
    b : int
        Block side (pixels).
    row, frame : ndarray of int, shape (K,)
        Detector row and frame of each block of samples.
    width : int
        Detector columns.
    lit_total, primary_total : ndarray, shape (J,)
        Per frame: the sum of the field (per unit s) over its lit samples, and that of its primary (counts).
    ratio : float
        Factor on the field (s).
    """

    grids: np.ndarray
    rows: np.ndarray
    origin: np.ndarray
    b: int
    row: np.ndarray
    frame: np.ndarray
    width: int
    lit_total: np.ndarray
    primary_total: np.ndarray
    ratio: float = 1.0

    def scaled(self, ratio: float) -> ScatterField:
        """The field times ``ratio``."""
        return replace(self, ratio=self.ratio * ratio)

    def share(self) -> float:
        """The measured scatter-to-primary ratio in the lit bands: the field's sum over every lit sample over the
        primary's (times ``ratio``). Below ``ratio`` by what the kernel carries off the bands (0 without primary)."""
        total = float(self.primary_total.sum())
        return self.ratio * float(self.lit_total.sum()) / total if total > 0 else 0.0

    def take(self, lo: int = 0, hi: int | None = None, columns: np.ndarray | None = None) -> np.ndarray:
        """The field at blocks [lo, hi) and ``columns`` (default all), shape (hi - lo, C), float32: linear
        interpolation between block centres, extended linearly over the outer half blocks (:func:`_between`); the
        grid itself where b = 1."""
        hi = self.row.size if hi is None else hi
        cols = np.arange(self.width) if columns is None else np.asarray(columns)
        c0, c1, c = _between(cols, self.grids.shape[2], self.b)
        f = self.frame[lo:hi]
        r0, r1, a = _between(self.row[lo:hi] - self.origin[f], self.rows[f], self.b)
        # compiled: numpy's gathers made temporaries of the output's size (a clinical scan's every block on a grid of
        # its every column: 1.3 GB) and took most of a diagnosis's time in fields on a scan with scatter
        out = np.empty((hi - lo, cols.size), np.float32)
        _bilinear(self.grids, f, r0, r1, a, c0, c1, c, float(self.ratio), out)
        return out


@njit(cache=True, nogil=True)
def _bilinear(grids: np.ndarray, frame: np.ndarray, r0: np.ndarray, r1: np.ndarray, a: np.ndarray, c0: np.ndarray,
              c1: np.ndarray, c: np.ndarray, ratio: float, out: np.ndarray) -> None:
    for k in range(out.shape[0]):
        g0, g1, w = grids[frame[k], r0[k]], grids[frame[k], r1[k]], a[k]
        o = out[k]
        for i in range(c0.size):
            below = (g0[c0[i]] * (1.0 - w) + g1[c0[i]] * w) * ratio
            above = (g0[c1[i]] * (1.0 - w) + g1[c1[i]] * w) * ratio
            o[i] = below * (1.0 - c[i]) + above * c[i]


def unit_scatter(primary: Primary, row: np.ndarray, frame: np.ndarray,
                 width: tuple[float, float]) -> ScatterField:
    """S of every sample: the superposition of its frame's primary under the kernel (counts per unit s).

    Parameters
    ----------
    primary : Primary
        The unmodulated primary t^f t of the blocks' samples (counts), every detector column, summed on blocks a
        frame at a time.
    row, frame : ndarray of int, shape (K,)
        Detector row and frame of each block.
    width : (float, float)
        Kernel std between rows and along a row (pixels).

    Returns
    -------
    ScatterField
        S (``take`` gives it at samples): S_j(r, c) = sum over frame j's lit samples (r', c') of P_j(r', c')
        K(r - r', c - c'), K the normalised Gaussian. Nothing is renormalised: what the kernel carries off the lit
        band (and off the detector) is lost, so S falls towards the band's edges, and a band narrow against the
        kernel gets less scatter per unit primary than a full field (:meth:`ScatterField.share`).
    """
    # the frame's lit band as an image (rows left out by alignment stay empty: no primary), summed on blocks of
    # b x b pixels: a kernel of hundreds of pixels (50 mm at 0.148 mm: 338) is blurred as well on a grid b = sigma /
    # 32 coarser and interpolated back, at about a b^2-th of the cost (a binned clinical scan, sigma 169: 7.5 ->
    # 0.8 s). The block sums hold only the band's blocks, so a kernel far wider than the detector (one block) needs
    # no more memory than a narrow one.
    b = block(width)
    J = int(frame.max(initial=-1)) + 1
    order = np.argsort(frame, kind="stable")
    bounds = np.searchsorted(frame[order], np.arange(J + 1))
    lit = np.flatnonzero(np.diff(bounds))
    origin = np.zeros(J, int)
    origin[lit] = np.minimum.reduceat(row[order], bounds[lit])
    rows = np.ones(J, int)
    rows[lit] = (np.maximum.reduceat(row[order], bounds[lit]) - origin[lit]) // b + 1
    lit_total, primary_total = np.zeros(J), np.zeros(J)
    W = primary.width
    # float32: where b = 1 the grids are every sample's field (a binned clinical scan's at 12.5 mm: 0.25 GB)
    stack = np.zeros((J, int(rows.max(initial=1)), -(-W // b)), np.float32)
    # the frames blurred together, about BLUR_VALUES block values at a time (a frame at a time, the blur's overhead on
    # grids of 44 x 288 blocks was most of the field's time on a binned clinical scan), holding only those frames'
    # block sums (all of them at once, at b = 1: 1 GB). The bands are padded to a common height with zeros, which the
    # blur assumes beyond a band's last row anyway
    j0, step = 0, 1
    while j0 < J:
        j1 = min(j0 + step, J)
        padded = np.zeros((j1 - j0, *stack.shape[1:]))
        counts: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        primary.frame_sums(row, order, bounds, origin, b, (j0, j1), padded, primary_total)
        for j in range(j0, j1):
            idx = order[bounds[j]:bounds[j + 1]]
            if idx.size == 0:
                continue
            at = (row[idx] - origin[j]) // b
            # within a frame the rows ascend: each block row's samples are one run
            first = np.flatnonzero(np.r_[True, at[1:] != at[:-1]])
            counts[j] = (at[first], np.diff(np.r_[first, at.size]))
        # the kernel on the block grid is normalised over blocks: per pixel it is b^-2 of that
        blurred = blur(blur(padded, width[0] / b, axis=1), width[1] / b, axis=2) / float(b * b)
        per_column = np.diff(np.r_[np.arange(0, W, b), W])
        for j, (held, n) in counts.items():
            grid = blurred[j - j0, :rows[j]]
            # the field's sum over the frame's lit samples: each block's value times its samples
            lit_total[j] = float(n @ grid[held] @ per_column)
            stack[j, :rows[j]] = grid
        j0, step = j1, max(int(BLUR_VALUES // stack[0].size), 1)
    return ScatterField(stack, rows, origin, b, row, frame, W, lit_total=lit_total, primary_total=primary_total)


#: unit_scatter blurs on blocks of sigma / COARSE_PER_SIGMA pixels (at least one).
COARSE_PER_SIGMA = 32
#: unit_scatter blurs the frames' block grids together, about this many values (float64) at a time.
BLUR_VALUES = 1_000_000
#: blur sums directly along an axis of at most this many values (by FFT along a longer one).
DIRECT_BLUR = 512


def block(width: tuple[float, float]) -> int:
    """The side (pixels) of the blocks on which :func:`unit_scatter` blurs, for a kernel of std ``width``."""
    return max(int(min(width) // COARSE_PER_SIGMA), 1)


def _between(pixels: np.ndarray, n: np.ndarray | int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The block centres (at (i + 1/2) b) each pixel lies between, and its weight on the second: lower and upper
    index and fraction (``n`` blocks, per pixel or one for all). Beyond the outer centres the line through the outer
    two is extended (the half block there is where the field falls fastest, towards the band's and the detector's
    edges: held constant, 1.5 % off at a kernel of 333 pixels)."""
    n = np.asarray(n)
    at = np.clip((pixels + 0.5) / b - 0.5, -0.5, n - 0.5)
    lo = np.clip(np.floor(at).astype(int), 0, np.maximum(n - 2, 0))
    return lo, np.minimum(lo + 1, n - 1), np.where(n > 1, at - lo, 0.0)
