"""The aligned data every stage works on: illuminated samples of a scan with their flat field, and the noise model.

A scan is handled as an :class:`Observations` stack: one block per (illuminated detector row, frame)
pair, ``K`` blocks sorted by row, each holding the ``C`` selected detector columns. Per-pixel sums are
segment sums over the blocks of one row; per-frame sums are bincounts over the blocks' frames.

Observations are values: frozen, never changed after they are made. Another noise model, pixel set or
alignment is another :class:`Observations` (``dataclasses.replace``, :meth:`Observations.with_noise`),
sharing the arrays that stay the same.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import DTypeLike

from . import kernels as K
from .chunks import over_chunks, row_bounds


def lateral_coordinate(columns: np.ndarray, width: int) -> np.ndarray:
    """x = (2c + 1) / W - 1: -1 and +1 at the outer edges of the first and last column."""
    return (2.0 * np.asarray(columns, dtype=np.float64) + 1.0) / width - 1.0


def index_slice(idx: np.ndarray | None, length: int) -> slice | np.ndarray:
    """Positions ``idx`` (default all) along an axis of ``length`` as a slice where they are evenly spaced and
    ascending within [0, length) (a run of columns or rows, every n-th column of a fit's): a strided view is taken or
    copied many times faster than the same positions by an index array (13500 x 510 uint16 samples to float32: 1.4
    against 21 ms); the array otherwise (which also refuses positions beyond the axis)."""
    if idx is None:
        return slice(None)
    c = np.asarray(idx)
    if c.ndim != 1 or c.size == 0 or c[0] < 0 or c[-1] >= length:
        return c
    step = int(c[1] - c[0]) if c.size > 1 else 1
    if step > 0 and np.all(np.diff(c) == step):
        return slice(int(c[0]), int(c[-1]) + 1, step)
    return c


def quadratures(tf: np.ndarray, vf: np.ndarray, phif: np.ndarray, *,
                out: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """t^f v^f cos phi^f and t^f v^f sin phi^f (counts), each of ``tf``'s shape (K, C) and dtype (or written into
    ``out``), in chunks of rows on the kernels' threads (numpy's cos and sin release the GIL; on one thread they
    were 40 % of a scatter correction's retrieval on a binned clinical scan)."""
    # the kernels' thread count and threading layer (set_threads): numba's default layer (OpenMP), started by asking
    # numba for its thread count first, kills a process that forks later
    threads = K.set_threads()
    fc, fs = (np.empty(tf.shape, tf.dtype), np.empty(tf.shape, tf.dtype)) if out is None else out

    def rows(lo: int, hi: int) -> None:
        amp = tf[lo:hi] * vf[lo:hi]
        np.multiply(amp, np.cos(phif[lo:hi]), out=fc[lo:hi], casting="same_kind")
        np.multiply(amp, np.sin(phif[lo:hi]), out=fs[lo:hi], casting="same_kind")

    over_chunks(rows, np.linspace(0, tf.shape[0], 4 * threads + 1).astype(np.int64), (), (), ())
    return fc, fs


@dataclass(frozen=True)
class Noise:
    """The noise description of a detector: variance = f_i * gain * photons + electronic (photons: Ibar minus the
    detector's dark, :meth:`Observations.photons`).

    Attributes
    ----------
    gain : float
        Detector units per photon.
    electronic : float
        Electronic (readout) noise variance, counts^2.
    factors : ndarray, shape (H, W), or None
        Variance factor f of each detector pixel (``pixel_noise``); None: 1 everywhere.
    """

    gain: float = 1.0
    electronic: float = 0.0
    factors: np.ndarray | None = None


@dataclass(frozen=True)
class Reading:
    """Where each block reads the images when the beam paths change during the scan (``beam_path``).

    Block k sees the sample at the fractional image row ``rows[lo[k]] + frac[k]``: its expected count uses
    (1 - frac) times the images of held row ``lo`` plus frac times those of held row ``lo + 1`` (the pixel
    integrates the intensity of both: (t, t v cos phi, t v sin phi) add, not the phase).

    Attributes
    ----------
    lo : ndarray of int, shape (K,)
        Position in :attr:`Observations.rows` of the image row below the read position.
    frac : ndarray, shape (K,)
        Fraction of the way to the next held row, in [0, 1); 0 at the last held row.
    kappa : float
        The parallax that places the reads (``beam_path``): the images are those each pixel sees with the active
        area centred on it (:func:`dfxcorr.align.to_detector_rows` gives them as the detector-centred frame sees
        them).
    """

    lo: np.ndarray
    frac: np.ndarray
    kappa: float = 0.0


def displaced_reading(row: np.ndarray, rows: np.ndarray, shift: np.ndarray) -> tuple[Reading, np.ndarray]:
    """The reading of blocks that see the images ``shift`` rows off their own row.

    Parameters
    ----------
    row : ndarray of int, shape (K,)
        Detector row of each block.
    rows : ndarray of int, shape (R,)
        The held detector rows, ascending: the image rows.
    shift : ndarray, shape (K,)
        Block k reads the images at row[k] + shift[k].

    Returns
    -------
    reading : Reading
    inside : ndarray of bool, shape (K,)
        Blocks that read between two consecutive held rows (or on one); the others see the sample outside
        the images and must not be used.
    """
    at = row + np.asarray(shift, dtype=np.float64)
    base = np.floor(at)
    lo = np.searchsorted(rows, base, side="left")
    lo_c = np.clip(lo, 0, rows.size - 1)
    frac = at - base
    on_row = (lo < rows.size) & (rows[lo_c] == base)
    last = lo_c == rows.size - 1
    nxt = rows[np.minimum(lo_c + 1, rows.size - 1)]
    inside = on_row & ((~last & (nxt == base + 1)) | (frac == 0))
    frac = np.where(inside, frac, 0.0)
    return Reading(np.where(inside, lo_c, 0).astype(np.int64), frac), inside


@dataclass(frozen=True)
class Observations:
    """Illuminated samples of a scan with their flat field, as blocks of (row, frame).

    Attributes
    ----------
    counts : ndarray, shape (K, C)
        Measured counts (detector units).
    tf : ndarray, shape (K, C)
        Flat-field transmission (counts) at each sample, aligned to the frame's position.
    fc, fs : ndarray, shape (K, C)
        The flat field's fringe at each sample as its quadratures, t^f v^f cos phi^f and t^f v^f sin phi^f (counts;
        v^f its visibility, phi^f its phase in rad with the nominal phase step), aligned like ``tf``
        (:func:`quadratures`): the model turns them by the phase channel with products alone, so no sample needs a
        trigonometric call in a fit's many evaluations, and they are all a fit holds of the flat field's fringe.
        0 where the flat field carries no fringe (outside the region of interest): there the model has no
        modulation. :attr:`vf` and :attr:`phif` are made from them where asked for.
    dark : ndarray, shape (K, C)
        The additive term of each sample, unmodulated by the gratings (counts): the detector's dark signal,
        plus any known unmodulated photons the preparation put there (``offset``); the model adds it to the
        expected count.
    use : ndarray of bool, shape (K, C)
        Samples that enter the fit or the retrieval (False for masked pixels).
    row, frame : ndarray of int, shape (K,)
        Detector row and frame of each block, sorted by row.
    columns : ndarray of int, shape (C,)
        Detector columns held.
    shape : tuple
        (J, H, W) of the scan.
    gain : float
        Detector units per photon.
    electronic : float
        Electronic noise variance (counts^2); the variance of a sample is gain * photons + electronic
        (:meth:`photons`).
    noise : ndarray, shape (R, C), or None
        Variance factor f of each pixel held (``pixel_noise``): the variance is f * gain * photons
        + electronic; None: 1 everywhere.
    roi : ndarray of bool, shape (K, C), or None
        The region of interest: samples whose flat field carries a fringe. None: every sample.
    offset : ndarray, shape (K, C), or None
        The part of ``dark`` that is photons (counts): known unmodulated photons of each sample, such as Compton
        scatter (:attr:`LitStore.offset <dfxcorr.align.LitStore>`). Their shot noise is in every sample's
        variance (:meth:`photons`); the rest of ``dark`` is the detector's, without photon noise. None: none.
    reading : Reading or None
        Where each block reads the images (:class:`Reading`); None: at its own row (the paper's geometry).
    """

    counts: np.ndarray
    tf: np.ndarray
    fc: np.ndarray
    fs: np.ndarray
    dark: np.ndarray
    use: np.ndarray
    row: np.ndarray
    frame: np.ndarray
    columns: np.ndarray
    shape: tuple
    gain: float = 1.0
    electronic: float = 0.0
    noise: np.ndarray | None = None
    roi: np.ndarray | None = None
    offset: np.ndarray | None = None
    reading: Reading | None = None
    rows: np.ndarray = field(init=False)
    starts: np.ndarray = field(init=False)
    pixel: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        if np.any(np.diff(self.row) < 0):
            raise ValueError("observation blocks must be sorted by row")
        rows, starts, counts = np.unique(self.row, return_index=True, return_counts=True)
        # derived once at construction: the dataclass is frozen
        object.__setattr__(self, "rows", rows)
        object.__setattr__(self, "starts", starts)
        object.__setattr__(self, "pixel", np.repeat(np.arange(rows.size), counts))

    @property
    def x(self) -> np.ndarray:
        """Lateral coordinate of the held columns, shape (C,)."""
        return lateral_coordinate(self.columns, self.shape[2])

    @property
    def y(self) -> np.ndarray:
        """Detector-row coordinate of each block in [-1, 1], shape (K,)."""
        return (2.0 * self.row + 1.0) / self.shape[1] - 1.0

    @property
    def n_frames(self) -> int:
        return self.shape[0]

    @property
    def fringe(self) -> tuple[np.ndarray, np.ndarray]:
        """(:attr:`fc`, :attr:`fs`), the flat field's fringe at each sample, each (K, C) (counts)."""
        return self.fc, self.fs

    @property
    def vf(self) -> np.ndarray:
        """The flat field's visibility at each sample, |fc + i fs| / t^f, shape (K, C) (0 without fringe or
        transmission; its magnitude where an extrapolated v^f fell below 0). Made at each call: :attr:`fc` and
        :attr:`fs` are what is held."""
        amp = np.hypot(self.fc, self.fs)
        return np.divide(amp, self.tf, out=np.zeros_like(amp), where=self.tf != 0)

    @property
    def phif(self) -> np.ndarray:
        """The flat field's phase at each sample, arg(fc + i fs) in [-pi, pi] (rad), shape (K, C); it has no meaning
        where the sample carries no fringe (outside the region of interest). Made at each call."""
        return np.arctan2(self.fs, self.fc)

    def keep_fringe(self, where: np.ndarray) -> Observations:
        """The same samples with the flat field's fringe kept only where ``where`` (K, C) is True and 0 elsewhere
        (v^f = 0: samples outside the region of interest, which monitor dose and background but carry no
        modulation)."""
        return replace(self, fc=np.where(where, self.fc, 0).astype(self.fc.dtype, copy=False),
                       fs=np.where(where, self.fs, 0).astype(self.fs.dtype, copy=False))

    @property
    def in_roi(self) -> np.ndarray:
        """The region of interest as an array, shape (K, C)."""
        return np.ones(self.counts.shape, bool) if self.roi is None else self.roi

    def read_rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The two image rows each block reads (positions in :attr:`rows`, each (K,)) and the fraction of the way to
        the second: its own row twice and 0 without a :attr:`reading`."""
        if self.reading is None:
            return self.pixel, self.pixel, np.zeros(self.pixel.size)
        lo = self.reading.lo
        return lo, np.minimum(lo + 1, self.rows.size - 1), self.reading.frac

    def gather(self, a: np.ndarray, blocks: np.ndarray | slice = slice(None)) -> np.ndarray:
        """Per-pixel values (R, C, ...) at every sample (K, C, ...), or at those of some ``blocks``: the pixel's own, or
        where :attr:`reading` says."""
        if self.reading is None:
            return a[self.pixel[blocks]]
        lo, hi, f = (v[blocks] for v in self.read_rows())
        f = f.reshape(f.shape + (1,) * (a.ndim - 1))
        return (1.0 - f) * a[lo] + f * a[hi]

    def gather_valid(self, valid: np.ndarray) -> np.ndarray:
        """Per-pixel flags (R, C) at every sample (K, C): true where every image row the sample reads is flagged."""
        if self.reading is None:
            return valid[self.pixel]
        lo, hi, f = self.read_rows()
        return valid[lo] & (valid[hi] | (f == 0)[:, None])

    def segment_sum(self, a: np.ndarray, dtype: DTypeLike | None = None) -> np.ndarray:
        """Sum over the blocks of each row: (K, ...) -> (R, ...), R = number of rows held (in ``dtype``, e.g. to count
        booleans without a float copy)."""
        return np.add.reduceat(a, self.starts, axis=0, dtype=dtype)

    def frame_sum(self, a: np.ndarray) -> np.ndarray:
        """Sum of per-block values (K,) over the blocks of each frame -> (J,)."""
        return np.bincount(self.frame, weights=a, minlength=self.n_frames)

    def to_image(self, values: np.ndarray, *, fill: float = np.nan) -> np.ndarray:
        """Place per-pixel values (R, C) into a detector image (H, W), ``fill`` elsewhere."""
        out = np.full(self.shape[1:], fill, dtype=np.result_type(values, type(fill)))
        self.place(out, values)
        return out

    def place(self, image: np.ndarray, values: np.ndarray) -> None:
        """Write per-pixel values (R, C) into a detector image (H, W) in place (a block of a larger image)."""
        image[self._window()] = values

    def held(self, image: np.ndarray) -> np.ndarray:
        """The values (R, C) of the held pixels in a detector image (H, W)."""
        return image[self._window()]

    def _window(self) -> tuple[slice | np.ndarray, ...]:
        """The index of the held pixels in a detector image: slices where the rows and the columns are evenly spaced
        (25 times faster than the open mesh of their indices, which it is otherwise)."""
        at = tuple(index_slice(a, n) for a, n in zip((self.rows, self.columns), self.shape[1:], strict=True))
        return at if all(isinstance(a, slice) for a in at) else np.ix_(self.rows, self.columns)

    def pixel_mask(self, image: np.ndarray) -> np.ndarray:
        """A detector image of booleans (H, W) at every sample, shape (K, C)."""
        # the held columns first: every sample's full detector row was a (K, W) gather (a band of 187 of 1440
        # columns: a second of a binned clinical scan's diagnosis)
        return image[:, self.columns][self.row]

    def subset(self, columns: np.ndarray, *, copy: bool = True) -> Observations:
        """The same blocks restricted to the given positions of ``self.columns``, C-ordered.

        The column slice of a Fortran-ordered scan stays Fortran-ordered, and the compiled kernels take C-ordered
        samples: every cost evaluation of a fit on it copied them (diagnosing a 5-step stepping scan: 892 copies,
        7 GB). ``copy=False`` with evenly spaced positions (a run of consecutive ones): views of the arrays instead,
        for numpy work (the copies were a fifth of the per-pixel tests' time).
        """
        idx = np.asarray(columns)
        at = index_slice(idx, self.columns.size)

        def cut(a: np.ndarray) -> np.ndarray:
            # evenly spaced positions sliced (copied row by row), others taken: a fancy index along the columns was
            # 28x slower (12 ms against 0.43 for 390 of 1536 columns of 2560 rows)
            if isinstance(at, slice):
                view = a[:, at]
                return view if not copy else np.ascontiguousarray(view)
            return np.take(a, idx, axis=1)

        return Observations(cut(self.counts), cut(self.tf), cut(self.fc), cut(self.fs), cut(self.dark),
                            cut(self.use), self.row, self.frame, self.columns[idx], self.shape, self.gain,
                            self.electronic, None if self.noise is None else cut(self.noise),
                            None if self.roi is None else cut(self.roi),
                            None if self.offset is None else cut(self.offset), self.reading)

    def column_chunks(self, samples: float = 1e6) -> list[np.ndarray]:
        """Positions of ``self.columns`` in consecutive runs holding about ``samples`` samples each (at least one
        column): per-pixel work over every column done a run at a time holds that many samples' temporaries."""
        K, C = self.counts.shape
        step = max(int(samples // max(K, 1)), 1)
        return [np.arange(a, min(a + step, C)) for a in range(0, C, step)]

    def row_ranges(self, samples: float = 1e6) -> list[tuple[int, int]]:
        """Positions of :attr:`rows` in consecutive ranges ``(lo, hi)`` of about ``samples`` samples each (whole rows,
        at least one): the rows' counterpart of :meth:`column_chunks`, for :meth:`of_rows`."""
        K, C = self.counts.shape
        step = max(int(samples // max(C, 1)), 1)  # blocks
        edges = row_bounds(self.starts, np.arange(step, K, step))
        return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]

    def block_range(self, lo: int, hi: int) -> slice:
        """The blocks of the held rows ``lo:hi`` (positions in :attr:`rows`) along the samples' first axis (K): one run,
        the blocks being sorted by row."""
        if not 0 <= lo < hi <= self.rows.size:
            raise ValueError(f"rows {lo}:{hi} are not a range of the {self.rows.size} held rows")
        return slice(int(self.starts[lo]), int(self.starts[hi]) if hi < self.rows.size else self.frame.size)

    def of_rows(self, lo: int, hi: int) -> Observations:
        """The samples of the held rows ``lo:hi`` (positions in :attr:`rows`), without copies.

        Per-pixel work whose results add over pixels (the Fisher information where each pixel's images are its own)
        done a range of rows at a time (:meth:`row_ranges`) holds only that range's per-pixel arrays.

        Parameters
        ----------
        lo, hi : int
            First and one past the last position in :attr:`rows` (0 <= lo < hi <= R).

        Returns
        -------
        Observations
            Its per-sample arrays (K', C) are views of :meth:`block_range`'s blocks of this one's, its noise factors
            (hi - lo, C) a view of those rows'.

        Raises
        ------
        ValueError
            Where the samples read the images between rows (:attr:`reading`): a row's images then depend on its
            neighbours', and a range of rows is not a problem of its own.
        """
        if self.reading is not None:
            raise ValueError("samples that read the images between rows cannot be taken a range of rows at a time")
        at = self.block_range(lo, hi)
        return Observations(self.counts[at], self.tf[at], self.fc[at], self.fs[at], self.dark[at], self.use[at],
                            self.row[at], self.frame[at], self.columns, self.shape, self.gain, self.electronic,
                            noise=None if self.noise is None else self.noise[lo:hi],
                            roi=None if self.roi is None else self.roi[at],
                            offset=None if self.offset is None else self.offset[at])

    def with_noise(self, noise: Noise) -> Observations:
        """The same samples under another noise description (its factor map sliced to the held pixels)."""
        return replace(self, gain=noise.gain, electronic=noise.electronic,
                       noise=None if noise.factors is None else self.held(noise.factors))

    def pixel_gain(self, gain: float | None = None) -> np.ndarray:
        """The photon variance per unit of photon signal (:meth:`photons`) of each pixel held, shape (R, C).

        gain * f (``pixel_noise``): the kernels and :func:`dfxcorr.noise.variance` read this one factor per pixel.
        """
        g = self.gain if gain is None else gain
        return g * (np.ones((self.rows.size, self.columns.size)) if self.noise is None else self.noise)

    def sample_gain(self, gain: float | None = None) -> np.ndarray | float:
        """:meth:`pixel_gain` at every sample (K, C), or the one gain where no pixel has a factor of its own (a (K, C)
        array of one value was several passes of each per-sample noise evaluation)."""
        g = self.gain if gain is None else gain
        return g if self.noise is None else self.pixel_gain(gain)[self.pixel]

    @property
    def quiet(self) -> np.ndarray:
        """The part of ``dark`` without photon noise (the detector's dark signal), shape (K, C)."""
        return self.dark if self.offset is None else self.dark - self.offset

    def photons(self, ibar: np.ndarray) -> np.ndarray:
        """The photon signal of expected counts ``ibar`` (K, C) in detector units: Ibar minus :attr:`quiet`, every
        photon counted (the modulated ones and those of ``offset``)."""
        return ibar - self.quiet
