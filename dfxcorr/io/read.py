"""Reading a scan file with every check of ``spec/scan-format.md``; the frames stay in the file."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..errors import gain_problem, require_regular_file
from .types import DET as _DET
from .types import FrameSource, H5Frames, Reference, Scan, ScanFormatError, SteppingReference, lit_rows
from .validate import validate_file


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


def _open(path: str | os.PathLike) -> h5py.File:
    """The scan file opened for reading, or a refusal naming it."""
    path = Path(path)
    require_regular_file(path, "scan")
    if not path.is_file():
        raise ScanFormatError(f"{path}: no such file")
    if not h5py.is_hdf5(path):
        raise ScanFormatError(f"{path}: not an HDF5 file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise ScanFormatError(f"{path}: cannot open as HDF5 ({exc})") from None


def read_scan(path: str | os.PathLike, *, allow_external: bool = False, header_only: bool = False) -> Scan:
    """Read and validate a dfxcorr scan file.

    Parameters
    ----------
    path : str or path-like
        HDF5 file following ``spec/scan-format.md``.
    allow_external : bool
        Follow external links, external raw storage and virtual datasets (see :func:`validate_file`);
        the files followed are listed in ``Scan.external_files``.
    header_only : bool
        The geometry and reference only, in a fraction of a second (``dfxcorr check``'s look before a run):
        the frames' counts are not checked, and a phase-stepping recording's reference series is not read
        (its ``data`` is then a zero-stride view of its shape and dtype).

    Returns
    -------
    Scan
        Its ``data`` is an :class:`H5Frames`: the frames stay in the file. The lit rows of float frames are
        checked for NaN, negative and impossibly large counts here, one frame at a time (unlit rows are never
        read by the pipeline, so their declared size costs nothing).

    Raises
    ------
    ScanFormatError
        For a file that is not HDF5, is not a dfxcorr scan, or breaks a rule of the format; the message
        names the dataset.
    """
    with _open(path) as f:
        layout = validate_file(f, allow_external=allow_external)
        dset = _require(f, f"{_DET}/data")
        J, H, W = dset.shape
        data = H5Frames(path, f"{_DET}/data", dset.shape, dset.dtype)
        position = np.asarray(_require(f, "entry/scan/position")[()], dtype=np.float64)
        _check_shape("entry/scan/position", position, (J,), "one per frame of /entry/instrument/detector/data")
        _check_finite("entry/scan/position", position)
        if not header_only:
            _check_counts(f"{_DET}/data", dset, lit_rows(position, layout.A, H))
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
        problem = gain_problem(gain)
        if problem:
            raise ScanFormatError(f"/{_DET}/gain {problem}, is {gain:g}")
        px = [_optional(f, f"{_DET}/{k}") for k in ("y_pixel_size", "x_pixel_size")]
        pixel_size: tuple[float, float] | None = None
        if all(p is not None for p in px):
            size_y, size_x = (float(np.asarray(p).reshape(-1)[0]) for p in px)
            pixel_size = (size_y, size_x)
        # a phase-stepping recording's own series is resolved by the run; the header needs its shape only
        series_unread = header_only and layout.A == H and not np.any(position)
        reference = _read_reference(f, W, series_unread=series_unread)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    return Scan(data=data, position=position, reference=reference, phase_step=phase_step, dark=dark,
                gain=gain, exposure_time=exposure, pixel_size=pixel_size, attrs=attrs,
                external_files=layout.external_files)


def _read_reference(f: h5py.File, W: int, *, series_unread: bool = False) -> Reference | SteppingReference:
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
        dset = _require(f, f"{base}/data")
        data = np.broadcast_to(np.zeros((), dset.dtype), dset.shape) if series_unread else dset[()]
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
            _check_finite(f"{base}/dark", dark)
        _check_counts(f"{base}/data", data)
        return SteppingReference(data=data, phase_step=steps, dark=dark)
    missing = [f"/entry/reference/{m}" for m, h in zip(maps, have, strict=True) if not h]
    raise ScanFormatError(f"missing required dataset {missing[0]} (or /entry/reference/stepping/data)")


#: Counts above this are no detector's (uint32's maximum): float frames beyond it would overflow the float32
#: fit's squares (1e300 made every image NaN with a reduced chi-square of 0).
MAX_COUNT = 2.0 ** 32 - 1


def _check_counts(name: str, data: FrameSource, rows: np.ndarray | None = None) -> None:
    """NaN, negative or impossibly large counts in float or signed integer frames (array or HDF5 dataset), one frame
    at a time (``spec/scan-format.md``: counts are never negative, also where a signed type could hold them).

    ``rows`` (J, 2): only these rows of each frame are read (:func:`lit_rows`); default all.
    """
    if data.dtype.kind == "u":
        return
    for j in range(data.shape[0]):  # frame by frame keeps memory bounded
        r0, r1 = rows[j] if rows is not None else (0, data.shape[1])
        if r1 <= r0:
            continue
        frame = data[j, r0:r1]
        if not np.all(np.isfinite(frame)):
            raise ScanFormatError(f"/{name} frame {j} holds NaN or infinite counts")
        if np.any(frame < 0):
            raise ScanFormatError(f"/{name} frame {j} holds negative counts (down to {frame.min():.6g}); counts are "
                                  f"photons or detector units")
        if np.any(frame > MAX_COUNT):
            raise ScanFormatError(f"/{name} frame {j} holds counts above {MAX_COUNT:.0f} (up to {frame.max():.3g}), "
                                  f"more than any detector records")


def read_reference(path: str | os.PathLike, *, allow_external: bool = False) -> Reference | SteppingReference:
    """The reference of a scan file (maps or stepping series) with every check of :func:`read_scan`, frames unread.

    Raises
    ------
    ScanFormatError
        As :func:`read_scan`, for the layout of the whole file and the values of the reference.
    """
    with _open(path) as f:
        try:
            return _read_reference(f, validate_file(f, allow_external=allow_external).W)
        except ScanFormatError as exc:
            raise ScanFormatError(f"{path}: {exc}") from None
