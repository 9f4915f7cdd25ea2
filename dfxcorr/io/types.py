"""The scan's types: the frames (in memory or left in the file), the flat-field reference and the acquisition.

A scan holds the raw frames, the per-frame geometry (position of the active area, nominal phase step)
and the reference description of the unloaded interferometer, either as maps or as a phase-stepping
series (``spec/scan-format.md``).
"""
from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import h5py
import numpy as np
from numpy.typing import DTypeLike

from ..errors import DfxcorrError

FORMAT = "dfxcorr-scan"
FORMAT_VERSION = 1
DET = "entry/instrument/detector"
FRAME_DTYPES = (np.uint16, np.uint32, np.float32, np.float64)


class ScanFormatError(DfxcorrError, ValueError):
    """The file is not a valid dfxcorr scan; the message names the offending dataset."""


class FrameSource(Protocol):
    """Frames [N, H, W] in memory (an ndarray) or read on demand (:class:`H5Frames`, the importer's counts).

    ``source[j]`` and ``source[j, r0:r1]`` give ndarrays; nothing else is asked of a source.
    """

    @property
    def shape(self) -> tuple[int, ...]: ...

    @property
    def dtype(self) -> np.dtype: ...

    def __getitem__(self, key: Any) -> Any: ...


@dataclass
class Reference:
    """Flat field of the unloaded interferometer in interferometer coordinates.

    Attributes
    ----------
    transmission, visibility, phase : ndarray, shape (A, W)
        t^f (counts per frame, dark removed), v^f in (0, 1], phi^f (rad, wrapped or unwrapped).
    """

    transmission: np.ndarray
    visibility: np.ndarray
    phase: np.ndarray


@dataclass
class SteppingReference:
    """A phase-stepping series of the unloaded interferometer, from which a :class:`Reference` is retrieved.

    Attributes
    ----------
    data : ndarray or FrameSource, shape (S, A, W)
        Counts.
    phase_step : ndarray, shape (S,)
        Nominal step phases (rad).
    dark : ndarray, shape (A, W) or None
        Dark signal per frame of that series.
    """

    data: FrameSource
    phase_step: np.ndarray
    dark: np.ndarray | None = None


class H5Frames:
    """The frames of a scan file, read on demand: ``frames[j, r0:r1]`` reads that hyperslab only.

    The file is opened for each read and closed right after, so no handle outlives a read (a scan
    can be held for hours on a cluster node without pinning the file). Anything that indexes an
    array by ``[j, rows, columns]`` accepts it in place of the (J, H, W) array.

    Attributes
    ----------
    path : Path
    dataset : str
        Path of the frames inside the file.
    shape : tuple of int
        (J, H, W).
    dtype : numpy.dtype
    """

    def __init__(self, path: str | os.PathLike, dataset: str, shape: tuple[int, ...], dtype: DTypeLike):
        self.path, self.dataset = Path(path), dataset
        self.shape, self.dtype = tuple(int(n) for n in shape), np.dtype(dtype)
        self.ndim = 3

    @contextmanager
    def open(self) -> Iterator[h5py.Dataset]:
        """The HDF5 dataset, open for several reads in a row (closed on leaving)."""
        with h5py.File(self.path, "r") as f:
            yield f[self.dataset]

    def __getitem__(self, key: Any) -> Any:
        with self.open() as dset:
            return dset[key]

    def __len__(self) -> int:
        return self.shape[0]


def frame_rows(data: FrameSource, j: int, r0: int, r1: int) -> np.ndarray:
    """Rows r0:r1 of frame j of an in-memory array or an :class:`H5Frames`, shape (r1 - r0, W)."""
    return np.asarray(data[j, r0:r1])


def lit_rows(position: np.ndarray, active_rows: int, height: int) -> np.ndarray:
    """First and last + 1 detector row lit in each frame, shape (J, 2) (r0 == r1: none), as ``spec/scan-format.md``
    says (0 <= r + 0.5 - position[j] < A); sized by the frames, never by the detector."""
    r0 = np.clip(np.ceil(position - 0.5), 0, height)
    r1 = np.clip(np.ceil(position + active_rows - 0.5), 0, height)
    return np.stack([r0, np.maximum(r1, r0)], axis=1).astype(np.int64)


@dataclass
class Scan:
    """One acquisition as in ``spec/scan-format.md``.

    Attributes
    ----------
    data : ndarray or H5Frames (any FrameSource), shape (J, H, W)
        Raw frames in acquisition order, dtype as stored; :func:`read_scan` leaves them in the file
        (:class:`H5Frames`) and the pipeline reads the lit rows of each frame once.
    position : ndarray, shape (J,)
        Detector row of the active area's top edge in each frame (rows, may be fractional/negative).
    reference : Reference or SteppingReference
        The flat field (A rows high).
    phase_step : ndarray, shape (J,)
        Nominal phase added by deliberate grating stepping (rad); zeros for a scan.
    dark : ndarray, shape (H, W)
        Dark signal per frame (counts); zeros when the file has none.
    gain : float
        Detector units per photon.
    exposure_time : ndarray, shape (J,) or None
        Seconds.
    pixel_size : tuple of float or None
        (y, x) pixel pitch in m.
    attrs : dict
        Attributes of the file's root.
    external_files : tuple of str
        Files other than the scan file that were read (only when external storage was allowed).
    """

    data: FrameSource
    position: np.ndarray
    reference: Reference | SteppingReference
    phase_step: np.ndarray | None = None
    dark: np.ndarray | None = None
    gain: float = 1.0
    exposure_time: np.ndarray | None = None
    pixel_size: tuple[float, float] | None = None
    attrs: dict = field(default_factory=dict)
    external_files: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        J, H, W = self.data.shape
        if self.phase_step is None:
            self.phase_step = np.zeros(J)
        if self.dark is None:
            self.dark = np.zeros((H, W))

    @property
    def shape(self) -> tuple[int, int, int]:
        """(J, H, W): frames, detector rows, detector columns."""
        J, H, W = self.data.shape
        return J, H, W

    @property
    def active_rows(self) -> int:
        """A, the height of the interferometer's active area in rows."""
        ref = self.reference
        return (ref.data.shape[1] if isinstance(ref, SteppingReference) else ref.transmission.shape[0])

    @property
    def is_stepping(self) -> bool:
        """True for a phase-stepping recording (A = H, all positions 0)."""
        return self.active_rows == self.data.shape[1] and bool(np.all(self.position == 0))
