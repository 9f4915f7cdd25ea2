"""Stage 2, flat-field alignment: the reference (interferometer coordinates) onto each frame's detector rows.

Pixel (r, c) sees the interferometer at local row u = r + 0.5 - position[j] and is lit iff 0 <= u < A
(``spec/scan-format.md``). Reference maps are sampled at u = k + 0.5 and interpolated linearly between
centres, extrapolated linearly over the outer half rows. The phase is unwrapped along u first: linear
interpolation of wrapped values would put a wrong phase into every sample near a wrap.
"""
from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import nullcontext
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np
from numba import njit, prange
from numpy.typing import DTypeLike

from . import kernels as K
from .errors import DfxcorrError
from .faults import Faults, saturated
from .io import Reference, Scan, frame_rows, lit_rows
from .observations import Observations, displaced_reading, index_slice, quadratures
from .stats import ranges

#: samples whose v^f and phi^f are made at a time on the way to their fringe's quadratures (2 x 16 MB in float32)
FRINGE_CHUNK = 4_000_000

log = logging.getLogger(__name__)


class AlignmentError(DfxcorrError, ValueError):
    """No usable pixel, or a reference that cannot be aligned."""


def no_lit_rows(min_frames: int) -> AlignmentError:
    """The refusal of a scan in which no detector row is lit in ``min_frames`` frames (``dfxcorr check`` says it
    in the same words as the run)."""
    return AlignmentError(f"no detector row is lit in at least {min_frames} frames: nothing to fit "
                          f"(dataset /entry/scan/position)")


@njit(cache=True, inline="always")
def reference_row(u: float, A: int) -> tuple[int, float]:
    """The row k0 of an A-row reference map below read position ``u`` (rows; row k's centre at k + 0.5), clipped to
    [0, A - 2], and the fraction a towards row k0 + 1 (:func:`interpolate_rows`; A at least 2)."""
    f = u - 0.5
    k0 = min(max(int(np.floor(f)), 0), A - 2)
    return k0, f - k0


@njit(cache=True, parallel=True, error_model="numpy")
def _interpolate_rows(maps: np.ndarray, cols: np.ndarray, u: np.ndarray, add: np.ndarray, wrap: bool,
                      out: np.ndarray) -> None:
    A = maps.shape[0]
    n = cols.size
    # a run of consecutive columns (every column of a block of rows) read as slices: a loop the compiler vectorises,
    # where an index array makes it gather one value at a time
    run = n > 0 and cols[n - 1] - cols[0] == n - 1
    first = cols[0] if n > 0 else 0
    for k in prange(u.size):
        k0, a = reference_row(u[k], A)
        lo, hi, o = maps[k0], maps[k0 + 1], out[k]
        if run:
            lo, hi = lo[first:first + n], hi[first:first + n]
            if wrap:
                for i in range(n):
                    v = (1.0 - a) * lo[i] + a * hi[i] + add[k]
                    o[i] = v - 2.0 * np.pi * np.floor(v / (2.0 * np.pi) + 0.5)
            else:
                for i in range(n):
                    o[i] = (1.0 - a) * lo[i] + a * hi[i] + add[k]
            continue
        for i in range(n):
            c = cols[i]
            v = (1.0 - a) * lo[c] + a * hi[c] + add[k]
            if wrap:
                v -= 2.0 * np.pi * np.floor(v / (2.0 * np.pi) + 0.5)
            o[i] = v


def interpolate_rows(maps: np.ndarray, u: np.ndarray, *, columns: np.ndarray | None = None,
                     dtype: DTypeLike = np.float64, add: np.ndarray | None = None, wrap: bool = False) -> np.ndarray:
    """Linear interpolation of row-sampled maps at continuous local rows.

    With f = u - 0.5 and k0 = floor(f) clipped to [0, A - 2], the value is
    (1 - (f - k0)) maps[k0] + (f - k0) maps[k0 + 1]. Compiled: one pass per sample row, in parallel, written straight
    in ``dtype`` (the numpy expression makes four temporaries of the output's size: 3.5 s of a full-resolution
    clinical scan's retrieval); the columns are read from the whole maps (a copy of ``maps[:, columns]`` is not
    C-ordered and would be copied again: 3 s of that retrieval).

    Parameters
    ----------
    maps : ndarray, shape (A, W)
        Values at the row centres u = k + 0.5.
    u : ndarray, shape (K,)
        Local rows (0 <= u < A for lit samples); the outer half rows are extrapolated linearly.
    columns : ndarray of int, shape (C,), optional
        Only these columns of the maps (default all).
    dtype : numpy dtype
        Of the result (computed in float64).
    add : ndarray, shape (K,), optional
        Added to each sample row's values (e.g. the phase step of its frame).
    wrap : bool
        Wrap the values (rad) to [-pi, pi) before the cast to ``dtype``.

    Returns
    -------
    ndarray, shape (K, C)
    """
    if maps.shape[0] == 1:
        picked = np.asarray(maps if columns is None else maps[:, columns], dtype=np.float64)
        out = np.repeat(picked, np.size(u), axis=0)
        if add is not None:
            out += np.asarray(add, dtype=np.float64)[:, None]
        if wrap:
            out -= 2.0 * np.pi * np.floor(out / (2.0 * np.pi) + 0.5)
        return out.astype(dtype, copy=False)
    K.set_threads()
    cols = np.arange(maps.shape[1]) if columns is None else np.asarray(columns, dtype=np.int64)
    out = np.empty((np.size(u), cols.size), dtype=dtype)
    shift = np.zeros(np.size(u)) if add is None else np.asarray(add, dtype=np.float64)
    _interpolate_rows(np.ascontiguousarray(maps, np.float64), cols, np.asarray(u, np.float64), shift, bool(wrap), out)
    return out


def pixel_mm(scan: Scan) -> tuple[float, float] | None:
    """The detector's pixel pitch (mm; between rows, along a row) where the scan file states it, else None."""
    return None if scan.pixel_size is None else (1e3 * scan.pixel_size[0], 1e3 * scan.pixel_size[1])


def lit_blocks(position: np.ndarray, active_rows: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All (row, frame) pairs in which a detector row is illuminated, sorted by row.

    Returns
    -------
    row, frame : ndarray of int, shape (K,)
    u : ndarray, shape (K,)
        Local interferometer row of each pair.
    """
    position = np.asarray(position, dtype=np.float64)
    # frame by frame (a (H, J) grid of a file declaring 100000 x 100000 unlit frames asked for 74.5 GiB)
    r0, r1 = lit_rows(position, active_rows, height).T
    n = r1 - r0
    frame = np.repeat(np.arange(position.size), n)
    row = np.repeat(r0, n) + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    order = np.lexsort((frame, row))
    row, frame = row[order], frame[order]
    return row, frame, row + 0.5 - position[frame]


def gauge_frames(rows_per_frame: np.ndarray, fraction: float) -> np.ndarray:
    """The frames that set the gauge (paper eq. 22): those lighting at least ``fraction`` of the rows the best-lit
    frame lights, shape (J,) bool. Frames at the start and end of a scan light only a few rows; their
    parameters are weakly determined by the data.
    """
    rows = np.asarray(rows_per_frame)
    return rows >= fraction * rows.max(initial=0)


class OffsetField(Protocol):
    """Known unmodulated photons of a store's samples, given where asked (:class:`LitStore` ``offset``)."""

    def take(self, lo: int = 0, hi: int | None = None, columns: np.ndarray | None = None) -> np.ndarray:
        """The offsets of blocks [lo, hi) at ``columns`` (default all), shape (hi - lo, C) (counts)."""
        ...


@dataclass
class LitStore:
    """Every lit sample of a scan in the frames' own dtype, as (row, frame) blocks sorted by row.

    What the pipeline keeps of a scan: the rows of each frame that the active area lights (about
    A / H of the frames), read once. Observations of any columns or rows follow from it
    (:meth:`observations`) without touching the file again.

    Attributes
    ----------
    counts : ndarray, shape (K, W)
        Counts as stored (e.g. uint16).
    row, frame : ndarray of int, shape (K,)
        Detector row and frame of each block, sorted by row (frames ascending within a row).
    u : ndarray, shape (K,)
        Local interferometer row of each block.
    shape : tuple
        (J, H, W) of the scan.
    phase_step : ndarray, shape (J,)
    dark : ndarray, shape (H, W)
    gain : float
    left_counts : ndarray, shape (L, W)
        Counts of the pixels that the active area has just left: (row, frame) pairs lit in frame
        j - 1 but not in j. Without lag they hold the dark signal only (they measure the lag).
    left_prev : ndarray of int, shape (L,)
        Index of the block (row, j - 1) of each of them.
    lag : float
        Detector lag fraction already taken out of ``counts`` (:func:`dfxcorr.effects.detector_lag.without_lag`).
    offset : ndarray, shape (K, W), OffsetField, or None
        Known unmodulated photons of each sample beyond the dark (counts; a correction of the preparation,
        e.g. Compton scatter): the observations add them to ``dark``, the model's additive term, and count
        their shot noise (:attr:`Observations.offset <dfxcorr.observations.Observations>`). A field
        that couples neighbouring pixels cannot enter the per-pixel solve; as a known offset it enters
        every stage alike (the compiled kernels, the numpy model, the Fisher information). Held as an array, or
        as a field that gives it for the samples asked for (a smooth field, made coarse). None: none.
    good : ndarray of bool, shape (K, W), or None
        False for samples left out as detector faults (:meth:`without`); None: every sample is good.
    bad_frames : tuple of int
        Frames left out whole as detector faults.
    parallax : float
        kappa of ``beam_path`` (``geometry.parallax``): frame j sees the sample displaced by kappa (c_j - c_0) rows
        (c_j the active area's centre, c_0 the detector's). The images are those each pixel sees with the active
        area centred on it, so the samples of pixel r read them at r + kappa (c_j - r) / (1 + kappa), between rows
        (:class:`dfxcorr.observations.Reading`: within a fraction of a row of their own for the frames that light
        them, a well-posed solve); :func:`to_detector_rows` gives the images where a frame centred on the detector
        sees them. Samples that read beyond the held rows are not used. 0: every sample reads its own row.
    position : ndarray, shape (J,), or None
        The recorded position of each frame (``scan/position``: the active area's top edge, rows); None: as the
        blocks' ``u`` give it.
    active_rows : int or None
        A, the active area's height in rows (needed with ``parallax``).
    """

    counts: np.ndarray
    row: np.ndarray
    frame: np.ndarray
    u: np.ndarray
    shape: tuple
    phase_step: np.ndarray
    dark: np.ndarray
    gain: float
    left_counts: np.ndarray | None = None
    left_prev: np.ndarray | None = None
    lag: float = 0.0
    offset: np.ndarray | OffsetField | None = None
    good: np.ndarray | None = None
    bad_frames: tuple[int, ...] = ()
    parallax: float = 0.0
    position: np.ndarray | None = None
    active_rows: int | None = None

    def frame_blocks(self) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """(j, rows, counts) of each frame that lights a held row, frames ascending (rows ascending within)."""
        order = np.argsort(self.frame, kind="stable")
        bounds = np.searchsorted(self.frame[order], np.arange(self.shape[0] + 1))
        for j in range(self.shape[0]):
            idx = order[bounds[j]:bounds[j + 1]]
            if idx.size:
                yield j, self.row[idx], self.counts[idx]

    def without(self, faults: Faults, *, margin: float = 0.0) -> LitStore:
        """The same samples with the saturated ones (:func:`dfxcorr.faults.saturated`, ``margin`` counts) and
        every sample of the bad frames marked not good."""
        good = (np.ones(self.counts.shape, bool) if faults.level is None
                else ~saturated(self.counts, faults.level, margin=margin))
        bad = tuple(sorted(faults.bad_frames))
        good[np.isin(self.frame, bad)] = False
        return replace(self, good=good, bad_frames=bad)

    @property
    def rows(self) -> np.ndarray:
        """Detector rows held, ascending."""
        return np.unique(self.row)

    def shifted(self, rows: np.ndarray | float) -> LitStore:
        """The same samples with the flat field read ``rows`` off: at u - rows (scalar, or (J,) per frame).

        Which samples are lit stays as the recorded positions say; only where the flat-field maps are
        read moves (a reference offset or per-frame position errors of a fraction of a row).
        """
        delta = np.broadcast_to(np.asarray(rows, dtype=np.float64), (self.shape[0],))
        return replace(self, u=self.u - delta[self.frame])

    def centred(self) -> np.ndarray:
        """c_j - (r + 0.5) of every block (rows): how far the active area's centre lies from the block's pixel, by
        the recorded positions (the flat field's alignment, :meth:`shifted`, aside)."""
        if self.active_rows is None:
            raise ValueError("the active area's height is not known to this store")
        # u = r + 0.5 - position of every block (scan-format.md); the active area's centre at position + A / 2
        u = self.u if self.position is None else self.row + 0.5 - self.position[self.frame]
        return self.active_rows / 2.0 - u

    def with_parallax(self, kappa: float) -> LitStore:
        """The same samples seeing the sample displaced by ``kappa`` rows per row of travel (:attr:`parallax`)."""
        return replace(self, parallax=float(kappa))

    def samples_per_column(self) -> int:
        """Lit samples in one detector column (K)."""
        return int(self.row.size)

    def unmodulated(self, lo: int, hi: int, columns: np.ndarray | None = None, *, dtype: DTypeLike = np.float64
                    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The unmodulated counts of blocks [lo, hi) at ``columns`` (default all): the dark, the offset included,
        and the offset alone (None without one), each (hi - lo, C) in ``dtype``."""
        row, at = self.row[lo:hi], index_slice(columns, self.shape[2])
        # the held columns in ``dtype`` first, then whole rows by row: a 2-d fancy index of every column was most of a
        # block's own time, and a float64 gather of every sample a transient twice the result (216 MB beside the
        # samples of a full-resolution fit of 2.7e7, its peak before the fit)
        dark = np.asarray(self.dark[:, at], dtype=dtype)[row]
        offset = None
        if isinstance(self.offset, np.ndarray):
            offset = self.offset[lo:hi, at].astype(dtype, copy=False)
        elif self.offset is not None:
            offset = self.offset.take(lo, hi, columns).astype(dtype, copy=False)
        return (dark if offset is None else dark + offset), offset

    def row_runs(self, samples: float) -> list[tuple[int, int]]:
        """Runs of detector rows [r0, r1) whose blocks hold at most ``samples`` samples (at least one row each),
        covering every held row: pixels, and a pixel's frames, never straddle two of them."""
        rows, per_row = np.unique(self.row, return_counts=True)
        cap = max(int(samples / self.shape[2]), 1)  # blocks (row, frame)
        runs, start, filled = [], 0, 0
        for i, n in enumerate(per_row):
            if filled and filled + n > cap:
                runs.append((int(rows[start]), int(rows[i])))
                start, filled = i, 0
            filled += n
        runs.append((int(rows[start]), int(rows[-1]) + 1))
        return runs

    def observations(self, reference: Reference, *, columns: np.ndarray | None = None,
                     rows: tuple[int, int] | None = None, gain: float | None = None, electronic: float = 0.0,
                     noise: np.ndarray | None = None, dtype: DTypeLike = np.float64, phase_unwrapped: bool = False,
                     min_visibility: float | None = None) -> Observations:
        """Align the flat field to the held samples of some columns and rows.

        Parameters
        ----------
        reference : Reference
            Flat-field maps (A, W); the phase may be wrapped.
        columns : ndarray of int, optional
            Detector columns (default all).
        rows : (int, int), optional
            Detector rows r0 <= r < r1 (default all held).
        gain : float, optional
            Overrides the file's detector gain.
        electronic : float
            Electronic noise variance (counts^2).
        noise : ndarray, shape (H, W), optional
            Variance factor of each detector pixel (``pixel_noise``; default 1).
        dtype : numpy dtype
            Of the sample arrays: float64, or float32 to halve them (counts up to 2^24 stay exact;
            the flat field is interpolated in float64 first, its phase then wrapped to [-pi, pi)).
        phase_unwrapped : bool
            The reference's phase is already unwrapped along the scan (axis 0), so it is not done again
            (a caller aligning block after block unwraps once).
        min_visibility : float, optional
            Samples whose flat field's visibility is below it carry no fringe (v^f = 0) and are outside the region
            of interest (``roi``); None: every sample keeps its fringe, and there is no ``roi``.

        Returns
        -------
        Observations
        """
        J, H, W = self.shape
        cols = np.arange(W) if columns is None else np.asarray(columns, dtype=np.int64)
        lo, hi = (0, self.row.size) if rows is None else np.searchsorted(self.row, rows)
        row, frame, u = self.row[lo:hi], self.frame[lo:hi], self.u[lo:hi]
        phase = reference.phase if phase_unwrapped else np.unwrap(reference.phase, axis=0)
        tf = interpolate_rows(reference.transmission, u, columns=cols, dtype=dtype)
        fc, fs = np.empty_like(tf), np.empty_like(tf)
        roi = None if min_visibility is None else np.empty(tf.shape, bool)
        # v^f and phi^f a run of blocks at a time, into the fringe's quadratures: held whole they were 2 x 108 MB of
        # a full-resolution clinical fit's samples beside the quadratures
        step = max(int(FRINGE_CHUNK // max(cols.size, 1)), 1)
        for a in range(0, row.size, step):
            b = min(a + step, row.size)
            vf = interpolate_rows(reference.visibility, u[a:b], columns=cols, dtype=dtype)
            # the model takes only cos and sin of it: wrapped to [-pi, pi), float32 keeps it to 2e-7 rad (unwrapped
            # across a clinical detector's many fringes it would keep it only to |phi^f| 6e-8)
            phif = interpolate_rows(phase, u[a:b], columns=cols, dtype=dtype, add=self.phase_step[frame[a:b]],
                                    wrap=True)
            if min_visibility is not None and roi is not None:
                np.greater_equal(vf, min_visibility, out=roi[a:b])
                vf[~roi[a:b]] = 0
            quadratures(tf[a:b], vf, phif, out=(fc[a:b], fs[a:b]))
        # C order whatever the store's: the kernels walk a sample row at a time (a Fortran-ordered copy made
        # every cost evaluation about 1.7x slower)
        at = index_slice(cols, W)
        counts = self.counts[lo:hi, at].astype(dtype, order="C")
        dark, offset = self.unmodulated(lo, hi, None if columns is None else cols, dtype=dtype)
        use = np.ones(counts.shape, bool)
        held = np.ix_(np.unique(row), cols)
        if self.good is not None:
            use &= self.good[lo:hi, at]
        reading = None
        if self.parallax:
            shift = self.parallax / (1.0 + self.parallax) * self.centred()[lo:hi]
            reading, inside = displaced_reading(row, np.unique(row), shift)
            reading = replace(reading, kappa=self.parallax)
            use &= inside[:, None]
        return Observations(counts=counts, tf=tf, fc=fc, fs=fs, dark=dark, use=use,
                            row=row, frame=frame, columns=cols, shape=(J, H, W),
                            gain=self.gain if gain is None else gain, electronic=electronic,
                            noise=None if noise is None else noise[held], roi=roi,
                            offset=offset, reading=reading)


def collect_lit_rows(scan: Scan, *, active_rows: int | None = None, min_frames: int = 3) -> LitStore:
    """Read the lit rows of every frame once, frame by frame, into a :class:`LitStore`.

    Parameters
    ----------
    scan : Scan
        Its ``data`` may be an array or frames left in the file (:class:`dfxcorr.io.H5Frames`): only
        rows ``r0:r1`` lit in frame j are read, one hyperslab per frame.
    active_rows : int, optional
        A (default the scan's).
    min_frames : int
        Rows lit in fewer frames than this (the number of per-pixel unknowns) are left out with a
        warning.

    Raises
    ------
    AlignmentError
        If no row is lit in at least ``min_frames`` frames.
    """
    J, H, W = scan.shape
    A = scan.active_rows if active_rows is None else active_rows
    row, frame, u = lit_blocks(scan.position, A, H)
    n_lit = np.bincount(row, minlength=H)
    short = (n_lit > 0) & (n_lit < min_frames)
    if np.any(short):
        log.warning("%d detector rows are lit in fewer than %d frames and are left out (rows %s)",
                    int(short.sum()), min_frames, ranges(np.flatnonzero(short)))
        keep = n_lit[row] >= min_frames
        row, frame, u = row[keep], frame[keep], u[keep]
    if row.size == 0:
        raise no_lit_rows(min_frames)
    counts = np.empty((row.size, W), dtype=scan.data.dtype)
    by_frame = np.argsort(frame, kind="stable")  # within a frame, rows stay ascending
    bounds = np.searchsorted(frame[by_frame], np.arange(J + 1))
    # the pixels just left (lit in j - 1, not in j): the frame after each row's last lit frame
    left_prev = np.flatnonzero(np.r_[row[1:] != row[:-1], True] & (frame + 1 < J))
    left_frame = frame[left_prev] + 1
    left_counts = np.empty((left_prev.size, W), dtype=scan.data.dtype)
    left_order = np.argsort(left_frame, kind="stable")
    left_bounds = np.searchsorted(left_frame[left_order], np.arange(J + 1))
    opener = scan.data.open() if hasattr(scan.data, "open") else nullcontext(scan.data)
    with opener as data:
        for j in range(J):
            idx = by_frame[bounds[j]:bounds[j + 1]]
            lidx = left_order[left_bounds[j]:left_bounds[j + 1]]
            rows_j = np.r_[row[idx], row[left_prev[lidx]]]
            if rows_j.size:
                # one hyperslab per frame: the lit rows and the adjacent ones just left
                r0, r1 = int(rows_j.min()), int(rows_j.max()) + 1
                block = frame_rows(data, j, r0, r1)
                counts[idx] = block[row[idx] - r0]
                left_counts[lidx] = block[row[left_prev[lidx]] - r0]
    assert scan.dark is not None  # Scan.__post_init__ fills it
    return LitStore(counts=counts, row=row, frame=frame, u=u, shape=(J, H, W),
                    phase_step=np.asarray(scan.phase_step, dtype=np.float64), dark=scan.dark, gain=scan.gain,
                    left_counts=left_counts, left_prev=left_prev,
                    position=np.asarray(scan.position, dtype=np.float64), active_rows=int(A))


def read_position_errors(path: str | Path, n_frames: int) -> np.ndarray:
    """Per-frame position errors delta_j (rows) from a .npy file or a text file of one number per frame.

    Raises
    ------
    AlignmentError
        Naming the file, if it cannot be read or does not hold ``n_frames`` finite numbers.
    """
    path = Path(path)
    try:
        values = np.load(path, allow_pickle=False) if path.suffix == ".npy" else np.loadtxt(path, ndmin=1)
    except (OSError, ValueError) as exc:
        raise AlignmentError(f"{path}: cannot read the position errors ({exc})") from None
    values = np.asarray(values, dtype=np.float64).ravel() if np.asarray(values).dtype.kind in "fiu" else None
    if values is None or values.size != n_frames or not np.all(np.isfinite(values)):
        raise AlignmentError(f"{path}: expected {n_frames} finite position errors (rows), one per frame")
    return values


def realign(store: LitStore, reference: Reference, like: Observations, shift: np.ndarray | float, *,
            base: LitStore | None = None) -> Observations:
    """Observations of the samples of ``like`` with the flat field read at u - shift (rows; scalar or (J,)).

    ``like`` must come from ``store`` (same rows and columns); its ``use``, noise model and region of
    interest (v^f = 0 outside) are kept, so that the realigned samples are the same samples. ``base``: the store
    ``like`` was read from (with ``reference``), where known; if ``store`` shifted holds the same counts read at the
    same flat-field rows (a correction of the offset only), ``like``'s arrays are kept and only the unmodulated
    counts are made (the
    held samples of a large scan, in float32, are hundreds of megabytes each time).
    """
    rows = (int(like.row[0]), int(like.row[-1]) + 1)
    moved = store.shifted(shift)
    if (base is not None and moved.counts is base.counts and moved.good is base.good and moved.dark is base.dark
            and moved.phase_step is base.phase_step and moved.parallax == base.parallax
            and np.array_equal(moved.u, base.u)):
        lo, hi = np.searchsorted(moved.row, rows)
        dark, offset = moved.unmodulated(int(lo), int(hi), like.columns, dtype=like.counts.dtype)
        return replace(like, dark=dark, offset=offset)
    obs = moved.observations(reference, columns=like.columns, rows=rows, gain=like.gain, electronic=like.electronic,
                             dtype=like.counts.dtype)

    def own(a: np.ndarray | None) -> np.ndarray | None:
        # ``like`` may be a view of a run of columns (Observations.subset(copy=False)): the kernels read C order
        return None if a is None else np.ascontiguousarray(a)

    return replace(obs.keep_fringe(like.in_roi), noise=own(like.noise), use=np.ascontiguousarray(like.use),
                   roi=own(like.roi))


def build_observations(scan: Scan, reference: Reference, *, min_frames: int = 3, dtype: DTypeLike = np.float64
                       ) -> Observations:
    """Align the flat field to every lit sample and collect the data as :class:`Observations` (float64 unless
    ``dtype`` says otherwise, see :meth:`LitStore.observations`).

    :func:`collect_lit_rows` then :meth:`LitStore.observations`; for scans that fit in memory many
    times over. The pipeline keeps the store and builds observations of column subsets and row blocks.

    Raises
    ------
    AlignmentError
        If no row is lit in at least ``min_frames`` frames.
    """
    store = collect_lit_rows(scan, active_rows=reference.transmission.shape[0], min_frames=min_frames)
    return store.observations(reference, dtype=dtype)


def subsample_columns(width: int, n: int, *, offset: int | None = None) -> np.ndarray:
    """Every n-th detector column (paper Sec. II-D.1), starting at ``offset`` (default n // 2)."""
    start = n // 2 if offset is None else offset
    if not 0 <= start < width:
        raise ValueError(f"column offset {start} outside the detector (0..{width - 1})")
    return np.arange(start, width, n)


def tilt_alias_period(width: int, n: int) -> float:
    """Tilt change (rad) to which the cost on every n-th column is blind: pi W / n (paper Sec. II-D.1).

    On columns spaced by n the lateral coordinate steps by 2n/W, so adding pi W / n to the tilt adds
    a multiple of 2 pi at every held column up to a constant that the phase offset absorbs.
    """
    return np.pi * width / n


__all__ = ["AlignmentError", "LitStore", "build_observations", "collect_lit_rows", "interpolate_rows", "lit_blocks",
           "no_lit_rows", "read_position_errors", "subsample_columns", "tilt_alias_period"]


def to_detector_rows(images: np.ndarray, kappa: float) -> np.ndarray:
    """Images (t, c, s) seen with the active area centred on each pixel (:attr:`LitStore.parallax`), resampled to
    where a frame centred on the detector sees them: the sample's images u of ``spec/diagnosis.md``'s beam_path.

    The pixel whose centre is y (rows, edge coordinates) sees, centred, what the detector-centred frame sees at
    y + kappa (y - H / 2); row u of the result is therefore read at y = (u + 0.5 + kappa H / 2) / (1 + kappa), between
    rows (linear in (t, c, s): intensities add). Rows read beyond the images are NaN.

    Parameters
    ----------
    images : ndarray, shape (H, W, 3)
    kappa : float

    Returns
    -------
    ndarray, shape (H, W, 3)
    """
    H = images.shape[0]
    q = (np.arange(H) + 0.5 + kappa * H / 2.0) / (1.0 + kappa) - 0.5
    lo = np.floor(q).astype(np.int64)
    f = q - lo
    inside = (lo >= 0) & (lo < H - 1) | (lo == H - 1) & (f == 0)
    a, b = np.clip(lo, 0, H - 1), np.clip(lo + 1, 0, H - 1)
    # row by row into one output: the whole-array expression made five temporaries of the images' size (0.59 s of a
    # binned clinical scan's 1440 x 1440 images)
    out = np.full(images.shape, np.nan, dtype=np.result_type(images, np.float64))
    part = np.empty(images.shape[1:], dtype=out.dtype)
    for u in np.flatnonzero(inside):
        np.multiply(images[a[u]], 1 - f[u], out=out[u])
        np.multiply(images[b[u]], f[u], out=part)
        out[u] += part
    return out
