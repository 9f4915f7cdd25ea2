"""Stage 1, load: the dfxcorr scan file (``spec/scan-format.md``), read with every check and written atomically.

A scan holds the raw frames, the per-frame geometry (position of the active area, nominal phase step)
and the reference description of the unloaded interferometer, either as maps or as a phase-stepping
series. Reading refuses anything the format forbids with a :class:`ScanFormatError` whose message
names the dataset.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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


@dataclass
class Scan:
    """One acquisition as in ``spec/scan-format.md``.

    Attributes
    ----------
    data : ndarray, shape (J, H, W)
        Raw frames in acquisition order, dtype as stored.
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
    phase_step: np.ndarray | None = None
    dark: np.ndarray | None = None
    gain: float = 1.0
    exposure_time: np.ndarray | None = None
    pixel_size: tuple[float, float] | None = None
    attrs: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
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


def _optional(f: h5py.File, path: str) -> Any:
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
        data = dset[()]
        J, H, W = data.shape
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
        pixel_size = (float(px[0]), float(px[1])) if px[0] is not None and px[1] is not None else None
        reference = _read_reference(f, W)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    _check_counts(f"{_DET}/data", data)
    return Scan(data=data, position=position, reference=reference, phase_step=phase_step, dark=dark,
                gain=gain, exposure_time=exposure, pixel_size=pixel_size, attrs=attrs)


def _read_reference(f: h5py.File, W: int) -> Reference | SteppingReference:
    maps = ("transmission", "visibility", "phase")
    have = [f"entry/reference/{m}" in f for m in maps]
    if all(have):
        t, v, p = (np.asarray(_require(f, f"entry/reference/{m}")[()], dtype=np.float64) for m in maps)
        if t.ndim != 2 or t.shape[1] != W:
            raise ScanFormatError(f"/entry/reference/transmission has shape {t.shape}, expected [A, {W}]")
        for m, a in zip(maps[1:], (v, p), strict=True):
            _check_shape(f"entry/reference/{m}", a, t.shape, "same as /entry/reference/transmission")
        for m, a in zip(maps, (t, v, p), strict=True):
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
    missing = [f"/entry/reference/{m}" for m, h in zip(maps, have, strict=True) if not h]
    raise ScanFormatError(f"missing required dataset {missing[0]} (or /entry/reference/stepping/data)")


def _check_counts(name: str, data: np.ndarray) -> None:
    if data.dtype.kind != "f":
        return
    for j in range(data.shape[0]):  # frame by frame keeps temporaries small
        frame = data[j]
        if not np.all(np.isfinite(frame)):
            raise ScanFormatError(f"/{name} frame {j} holds NaN or infinite counts")
        if np.any(frame < 0):
            raise ScanFormatError(f"/{name} frame {j} holds negative counts")


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
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


def write_scan(path: str | os.PathLike, scan: Scan, *, extra: dict[str, Any] | None = None,
               compression: str | None = "gzip") -> None:
    """Write a scan file atomically (to a temporary name, renamed when complete).

    Parameters
    ----------
    path : str or path-like
        Destination.
    scan : Scan
        What to write; ``data`` keeps its dtype.
    extra : dict, optional
        Further datasets, keyed by path inside the file (ignored by readers, per the spec).
    compression : str or None
        HDF5 filter for the frames.
    """
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = FORMAT_VERSION
        entry = f.create_group("entry")
        entry.attrs["NX_class"] = "NXentry"
        inst = entry.create_group("instrument")
        inst.attrs["NX_class"] = "NXinstrument"
        det = inst.create_group("detector")
        det.attrs["NX_class"] = "NXdetector"
        J, H, W = scan.data.shape
        det.create_dataset("data", data=scan.data, compression=compression, chunks=(1, H, W))
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
