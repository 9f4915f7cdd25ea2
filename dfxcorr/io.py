"""Stage 1, load: the dfxcorr scan file (``spec/scan-format.md``), read with every check and written atomically.

A scan holds the raw frames, the per-frame geometry (position of the active area, nominal phase step)
and the reference description of the unloaded interferometer, either as maps or as a phase-stepping
series. Reading refuses anything the format forbids with a :class:`ScanFormatError` whose message
names the dataset.
"""
from __future__ import annotations

import logging
import os
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from .errors import DfxcorrError

log = logging.getLogger(__name__)

FORMAT = "dfxcorr-scan"
FORMAT_VERSION = 1
_DET = "entry/instrument/detector"
_FRAME_DTYPES = (np.uint16, np.uint32, np.float32, np.float64)


class ScanFormatError(DfxcorrError, ValueError):
    """The file is not a valid dfxcorr scan; the message names the offending dataset."""


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
    data : ndarray, shape (S, A, W)
        Counts.
    phase_step : ndarray, shape (S,)
        Nominal step phases (rad).
    dark : ndarray, shape (A, W) or None
        Dark signal per frame of that series.
    """

    data: np.ndarray
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

    def __init__(self, path: str | os.PathLike, dataset: str, shape: tuple, dtype):
        self.path, self.dataset = Path(path), dataset
        self.shape, self.dtype = tuple(int(n) for n in shape), np.dtype(dtype)
        self.ndim = 3

    @contextmanager
    def open(self):
        """The HDF5 dataset, open for several reads in a row (closed on leaving)."""
        with h5py.File(self.path, "r") as f:
            yield f[self.dataset]

    def __getitem__(self, key):
        with self.open() as dset:
            return dset[key]

    def __len__(self) -> int:
        return self.shape[0]


def frame_rows(data, j: int, r0: int, r1: int) -> np.ndarray:
    """Rows r0:r1 of frame j of an in-memory array or an :class:`H5Frames`, shape (r1 - r0, W)."""
    return np.asarray(data[j, r0:r1])


@dataclass
class Scan:
    """One acquisition as in ``spec/scan-format.md``.

    Attributes
    ----------
    data : ndarray or H5Frames, shape (J, H, W)
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
    """

    data: np.ndarray
    position: np.ndarray
    reference: Reference | SteppingReference
    phase_step: np.ndarray = None
    dark: np.ndarray = None
    gain: float = 1.0
    exposure_time: np.ndarray | None = None
    pixel_size: tuple[float, float] | None = None
    attrs: dict = field(default_factory=dict)

    def __post_init__(self):
        J, H, W = self.data.shape
        if self.phase_step is None:
            self.phase_step = np.zeros(J)
        if self.dark is None:
            self.dark = np.zeros((H, W))

    @property
    def shape(self) -> tuple[int, int, int]:
        """(J, H, W): frames, detector rows, detector columns."""
        return tuple(self.data.shape)

    @property
    def active_rows(self) -> int:
        """A, the height of the interferometer's active area in rows."""
        ref = self.reference
        return (ref.data.shape[1] if isinstance(ref, SteppingReference) else ref.transmission.shape[0])

    @property
    def is_stepping(self) -> bool:
        """True for a phase-stepping recording (A = H, all positions 0)."""
        return self.active_rows == self.data.shape[1] and bool(np.all(self.position == 0))


def _require(f: h5py.File, path: str) -> h5py.Dataset:
    if path not in f:
        raise ScanFormatError(f"missing required dataset /{path}")
    obj = f[path]
    if not isinstance(obj, h5py.Dataset):
        raise ScanFormatError(f"/{path} must be a dataset, found a group")
    return obj


def _optional(f: h5py.File, path: str):
    obj = f.get(path)
    return obj[()] if isinstance(obj, h5py.Dataset) else None


def _check_shape(name: str, arr: np.ndarray, shape: tuple, what: str) -> None:
    if arr.shape != shape:
        raise ScanFormatError(f"/{name} has shape {arr.shape}, expected {shape} ({what})")


def _check_finite(name: str, arr: np.ndarray) -> None:
    if not np.all(np.isfinite(arr)):
        raise ScanFormatError(f"/{name} holds values that are not finite")


def read_scan(path: str | os.PathLike) -> Scan:
    """Read and validate a dfxcorr scan file.

    Parameters
    ----------
    path : str or path-like
        HDF5 file following ``spec/scan-format.md``.

    Returns
    -------
    Scan
        Its ``data`` is an :class:`H5Frames`: the frames stay in the file. Float frames are checked
        for NaN and negative counts here, one frame at a time.

    Raises
    ------
    ScanFormatError
        For a file that is not HDF5, is not a dfxcorr scan, or breaks a rule of the format; the message
        names the dataset.
    """
    path = Path(path)
    if not path.is_file():
        raise ScanFormatError(f"{path}: no such file")
    if not h5py.is_hdf5(path):
        raise ScanFormatError(f"{path}: not an HDF5 file")
    with h5py.File(path, "r") as f:
        fmt = f.attrs.get("format")
        if isinstance(fmt, bytes):
            fmt = fmt.decode()
        if fmt != FORMAT:
            raise ScanFormatError(f"/ attribute 'format' is {fmt!r}, expected {FORMAT!r}")
        version = f.attrs.get("format_version")
        if version is None or int(version) != FORMAT_VERSION:
            raise ScanFormatError(f"/ attribute 'format_version' is {version!r}, this reader knows {FORMAT_VERSION}")
        dset = _require(f, f"{_DET}/data")
        if dset.ndim != 3:
            raise ScanFormatError(f"/{_DET}/data must be 3-D [J, H, W], has shape {dset.shape}")
        if dset.dtype.type not in _FRAME_DTYPES:
            raise ScanFormatError(f"/{_DET}/data has dtype {dset.dtype}, expected uint16, uint32, float32 or float64")
        J, H, W = dset.shape
        data = H5Frames(path, f"{_DET}/data", dset.shape, dset.dtype)
        _check_counts(f"{_DET}/data", dset)
        position = np.asarray(_require(f, "entry/scan/position")[()], dtype=np.float64)
        _check_shape("entry/scan/position", position, (J,), "one per frame of /entry/instrument/detector/data")
        _check_finite("entry/scan/position", position)
        phase_step = _optional(f, "entry/scan/phase_step")
        if phase_step is not None:
            phase_step = np.asarray(phase_step, dtype=np.float64)
            _check_shape("entry/scan/phase_step", phase_step, (J,), "one per frame")
            _check_finite("entry/scan/phase_step", phase_step)
        exposure = _optional(f, "entry/scan/exposure_time")
        if exposure is not None:
            exposure = np.asarray(exposure, dtype=np.float64)
            _check_shape("entry/scan/exposure_time", exposure, (J,), "one per frame")
        dark = _optional(f, f"{_DET}/dark")
        if dark is not None:
            dark = np.asarray(dark, dtype=np.float64)
            _check_shape(f"{_DET}/dark", dark, (H, W), "one value per detector pixel")
            _check_finite(f"{_DET}/dark", dark)
        gain = _optional(f, f"{_DET}/gain")
        gain = 1.0 if gain is None else float(np.asarray(gain).reshape(-1)[0])
        if not (np.isfinite(gain) and gain > 0):
            raise ScanFormatError(f"/{_DET}/gain must be a positive number, is {gain}")
        px = [_optional(f, f"{_DET}/{k}") for k in ("y_pixel_size", "x_pixel_size")]
        pixel_size = tuple(float(p) for p in px) if all(p is not None for p in px) else None
        reference = _read_reference(f, W)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    return Scan(data=data, position=position, reference=reference, phase_step=phase_step, dark=dark,
                gain=gain, exposure_time=exposure, pixel_size=pixel_size, attrs=attrs)


def _read_reference(f: h5py.File, W: int) -> Reference | SteppingReference:
    maps = ("transmission", "visibility", "phase")
    have = [f"entry/reference/{m}" in f for m in maps]
    if all(have):
        t, v, p = (np.asarray(_require(f, f"entry/reference/{m}")[()], dtype=np.float64) for m in maps)
        if t.ndim != 2 or t.shape[1] != W:
            raise ScanFormatError(f"/entry/reference/transmission has shape {t.shape}, expected [A, {W}]")
        for m, a in zip(maps[1:], (v, p)):
            _check_shape(f"entry/reference/{m}", a, t.shape, "same as /entry/reference/transmission")
        for m, a in zip(maps, (t, v, p)):
            _check_finite(f"entry/reference/{m}", a)
        if np.any(t <= 0):
            raise ScanFormatError("/entry/reference/transmission must be positive everywhere")
        if np.any((v <= 0) | (v > 1)):
            raise ScanFormatError("/entry/reference/visibility must lie in (0, 1]")
        return Reference(t, v, p)
    if "entry/reference/stepping" in f:
        base = "entry/reference/stepping"
        data = _require(f, f"{base}/data")[()]
        if data.ndim != 3 or data.shape[2] != W:
            raise ScanFormatError(f"/{base}/data has shape {data.shape}, expected [S, A, {W}]")
        S, A, _ = data.shape
        steps = np.asarray(_require(f, f"{base}/phase_step")[()], dtype=np.float64)
        _check_shape(f"{base}/phase_step", steps, (S,), "one per frame of the stepping series")
        _check_finite(f"{base}/phase_step", steps)
        dark = _optional(f, f"{base}/dark")
        if dark is not None:
            dark = np.asarray(dark, dtype=np.float64)
            _check_shape(f"{base}/dark", dark, (A, W), "one value per pixel of the active area")
        _check_counts(f"{base}/data", data)
        return SteppingReference(data=data, phase_step=steps, dark=dark)
    missing = [f"/entry/reference/{m}" for m, h in zip(maps, have) if not h]
    raise ScanFormatError(f"missing required dataset {missing[0]} (or /entry/reference/stepping/data)")


def _check_counts(name: str, data) -> None:
    """NaN or negative counts in float frames (array or HDF5 dataset), read one frame at a time."""
    if data.dtype.kind != "f":
        return
    for j in range(data.shape[0]):  # frame by frame keeps memory bounded
        frame = data[j]
        if not np.all(np.isfinite(frame)):
            raise ScanFormatError(f"/{name} frame {j} holds NaN or infinite counts")
        if np.any(frame < 0):
            raise ScanFormatError(f"/{name} frame {j} holds negative counts")


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it to ``path`` on success, remove it on failure.

    Readers never see a half-written file, and a failed run leaves nothing behind.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.part")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


#: Detector rows per HDF5 chunk of the frames: reading a frame's lit rows decompresses little beyond them.
CHUNK_ROWS = 64


def write_scan(path: str | os.PathLike, scan: Scan, *, extra: dict[str, np.ndarray] | None = None,
               compression: str | None = "gzip", frames=None) -> None:
    """Write a scan file atomically (to a temporary name, renamed when complete), one frame at a time.

    Parameters
    ----------
    path : str or path-like
        Destination.
    scan : Scan
        What to write; ``data`` keeps its dtype.
    extra : dict, optional
        Further datasets, keyed by path inside the file (ignored by readers, per the spec).
    compression : str or None
        HDF5 filter for the frames (gzip: readable everywhere; lzf: about 7 times faster to read, h5py's).
    frames : iterable of (j, r0, ndarray (n, W)), optional
        Writes these rows r0:r0 + n of frame j instead of ``scan.data`` (rows not given stay 0); lets a
        producer hand over one frame at a time.
    """
    J, H, W = scan.shape
    chunks = (1, min(CHUNK_ROWS, H), W)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = FORMAT_VERSION
        entry = f.create_group("entry")
        entry.attrs["NX_class"] = "NXentry"
        inst = entry.create_group("instrument")
        inst.attrs["NX_class"] = "NXinstrument"
        det = inst.create_group("detector")
        det.attrs["NX_class"] = "NXdetector"
        dset = det.create_dataset("data", shape=(J, H, W), dtype=scan.data.dtype, compression=compression,
                                  chunks=chunks)
        for j, r0, block in (frames if frames is not None else ((j, 0, scan.data[j]) for j in range(J))):
            dset[j, r0:r0 + block.shape[0]] = block
        if np.any(scan.dark != 0):
            det.create_dataset("dark", data=scan.dark)
        det.create_dataset("gain", data=float(scan.gain))
        if scan.pixel_size is not None:
            det.create_dataset("y_pixel_size", data=scan.pixel_size[0]).attrs["units"] = "m"
            det.create_dataset("x_pixel_size", data=scan.pixel_size[1]).attrs["units"] = "m"
        sc = entry.create_group("scan")
        sc.create_dataset("position", data=np.asarray(scan.position, float)).attrs["units"] = "pixel"
        if np.any(scan.phase_step != 0):
            sc.create_dataset("phase_step", data=np.asarray(scan.phase_step, float)).attrs["units"] = "rad"
        if scan.exposure_time is not None:
            sc.create_dataset("exposure_time", data=scan.exposure_time).attrs["units"] = "s"
        ref = entry.create_group("reference")
        if isinstance(scan.reference, SteppingReference):
            st = ref.create_group("stepping")
            st.create_dataset("data", data=scan.reference.data, compression=compression)
            st.create_dataset("phase_step", data=scan.reference.phase_step).attrs["units"] = "rad"
            if scan.reference.dark is not None:
                st.create_dataset("dark", data=scan.reference.dark)
        else:
            ref.create_dataset("transmission", data=scan.reference.transmission)
            ref.create_dataset("visibility", data=scan.reference.visibility)
            ref.create_dataset("phase", data=scan.reference.phase).attrs["units"] = "rad"
        for key, value in (extra or {}).items():
            f.create_dataset(key, data=value)


def illumination_count(position: np.ndarray, active_rows: int, height: int) -> np.ndarray:
    """Number of frames in which each detector row is illuminated.

    Parameters
    ----------
    position : ndarray, shape (J,)
        Top edge of the active area per frame (rows).
    active_rows : int
        A.
    height : int
        H, detector rows.

    Returns
    -------
    ndarray of int, shape (H,)
        Row r is lit in frame j iff 0 <= r + 0.5 - position[j] < A.
    """
    u = np.arange(height)[:, None] + 0.5 - np.asarray(position)[None, :]
    return np.count_nonzero((u >= 0) & (u < active_rows), axis=1)
