"""Import of phase-stepping recordings (series of .npy, TIFF or headerless raw frames) into a scan file.

A phase-stepping recording is the special case of ``spec/scan-format.md`` with A = H, all positions 0
and ``scan/phase_step`` holding the nominal step phases; the reference is stored as the stepping series
of the unloaded interferometer (``/entry/reference/stepping``). The import is lossless: counts are
written exactly as read. Frame dtypes the format does not allow are converted to the smallest allowed
type that holds every value of the source type exactly (see :func:`frame_dtype`), or refused.
"""
from __future__ import annotations

import glob
import os
import re
from pathlib import Path

import h5py
import numpy as np
import tifffile

from .errors import DfxcorrError, OutputExistsError
from .io import Scan, SteppingReference, write_scan

_NPY = {".npy"}
_TIFF = {".tif", ".tiff"}
_IMPORT_GROUP = "entry/dfxcorr_import"
# Every integer up to 2**53 is exactly representable in float64.
_FLOAT64_EXACT_INT = 2 ** 53


class StackImportError(DfxcorrError, ValueError):
    """A series cannot be imported; the message names the offending file, glob or argument."""


def _natural_key(text: str) -> list:
    # Alternating text/int parts, so that step_2 sorts before step_10.
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text)]


def _resolve_files(source) -> list[Path]:
    """Expand a glob pattern, one path or a list of paths into the list of files to read."""
    if isinstance(source, (list, tuple)):
        if not source:
            raise StackImportError("empty list of files given")
        return [Path(os.path.expanduser(os.fspath(p))) for p in source]
    text = os.path.expanduser(os.fspath(source))
    if Path(text).exists():  # a literal name may contain glob characters such as '['
        return [Path(text)]
    matches = sorted(glob.glob(text), key=_natural_key)
    if not matches:
        raise StackImportError(f"no file matches {os.fspath(source)!r}")
    return [Path(m) for m in matches]


def _read_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise StackImportError(f"{path}: cannot read as .npy ({exc})") from exc


def _read_tiff(path: Path) -> np.ndarray:
    try:
        with tifffile.TiffFile(path) as tif:
            parts = []
            # Pages appended one by one form one series each; a multi-page stack forms one series.
            for k, series in enumerate(tif.series):
                if "S" in series.axes or series.ndim not in (2, 3):
                    raise StackImportError(
                        f"{path}: image series {k} has axes {series.axes!r} and shape {series.shape}; "
                        "expected grey-value frames (2-D, or a 3-D stack of frames)")
                arr = series.asarray()
                parts.append(arr[None] if arr.ndim == 2 else arr)
    except (OSError, ValueError) as exc:
        if isinstance(exc, StackImportError):
            raise
        raise StackImportError(f"{path}: cannot read as TIFF ({exc})") from exc
    for k, arr in enumerate(parts[1:], start=1):
        if arr.shape[1:] != parts[0].shape[1:] or arr.dtype != parts[0].dtype:
            raise StackImportError(
                f"{path}: image series {k} has frames {arr.shape[1:]} {arr.dtype}, series 0 has "
                f"{parts[0].shape[1:]} {parts[0].dtype}")
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _read_raw(path: Path, shape, dtype, offset: int) -> np.ndarray:
    if shape is None or dtype is None:
        missing = " and ".join(n for n, v in (("shape", shape), ("dtype", dtype)) if v is None)
        raise StackImportError(f"{path}: headerless raw file needs {missing} (e.g. shape=(H, W), dtype='<u2')")
    try:
        dt = np.dtype(dtype)
    except TypeError as exc:
        raise StackImportError(f"{path}: invalid dtype {dtype!r} ({exc})") from exc
    try:
        h, w = (int(n) for n in shape)
    except (TypeError, ValueError) as exc:
        raise StackImportError(f"{path}: shape must be (H, W), got {shape!r}") from exc
    if h <= 0 or w <= 0:
        raise StackImportError(f"{path}: shape must be positive, got {shape!r}")
    if offset < 0:
        raise StackImportError(f"{path}: offset must be >= 0, got {offset}")
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise StackImportError(f"{path}: cannot read ({exc})") from exc
    frame_bytes = h * w * dt.itemsize
    body = size - offset
    if body <= 0 or body % frame_bytes:
        raise StackImportError(
            f"{path}: {size} bytes minus {offset} bytes of header is not a whole, non-zero number of "
            f"{h}x{w} frames of {dt} ({frame_bytes} bytes each)")
    try:
        arr = np.fromfile(path, dtype=dt, offset=offset)
    except (OSError, ValueError) as exc:
        raise StackImportError(f"{path}: cannot read ({exc})") from exc
    return arr.reshape(-1, h, w)


def _kind(path: Path) -> str:
    suffix = path.suffix.lower()
    return "npy" if suffix in _NPY else "tiff" if suffix in _TIFF else "raw"


def _read_file(path: Path, shape, dtype, offset: int) -> np.ndarray:
    if path.is_dir():
        raise StackImportError(f"{path}: is a directory, expected a file")
    kind = _kind(path)
    if kind == "npy":
        arr = _read_npy(path)
    elif kind == "tiff":
        arr = _read_tiff(path)
    else:
        arr = _read_raw(path, shape, dtype, offset)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise StackImportError(f"{path}: holds an array of shape {arr.shape}; expected a frame [H, W] "
                               "or a stack of frames [S, H, W]")
    if 0 in arr.shape:
        raise StackImportError(f"{path}: holds no data (shape {arr.shape})")
    # Native byte order: same values, and no byte-swapped types reach the scan file.
    return arr.astype(arr.dtype.newbyteorder("="), copy=False)


def read_stack(source, *, shape: tuple[int, int] | None = None, dtype: str | None = None,
               offset: int = 0) -> np.ndarray:
    """Read a series of frames.

    Parameters
    ----------
    source : str, path-like or list of them
        A glob pattern (its files are sorted in natural order: ``step_2`` before ``step_10``), one path,
        or a list of paths (read in the order given). Either several files holding one frame each, or
        one file holding a stack of frames.
    shape : (int, int), optional
        (H, W) of a frame in pixels; required for headerless raw files, ignored for other formats.
    dtype : str, optional
        Numpy dtype string of a raw file including byte order, e.g. ``'<u2'``; required for raw files.
    offset : int
        Bytes of header to skip at the start of each raw file.

    Returns
    -------
    ndarray, shape (S, H, W)
        The frames in series order, dtype as stored (in native byte order).

    Raises
    ------
    StackImportError
        A glob matching nothing, an unreadable file, raw without shape/dtype or of a size that is not a
        whole number of frames, frames of different shape or dtype (naming both files), several files of
        which one holds more than one frame, or a mixture of formats.

    Notes
    -----
    The format follows the file suffix: ``.npy`` (2-D frame or 3-D stack), ``.tif``/``.tiff`` (single
    page or multi-page stack, read with tifffile), anything else is headerless raw, whose size minus
    ``offset`` must be a whole number of frames.
    """
    return _read_series(source, shape, dtype, offset)[0]


def _read_series(source, shape, dtype, offset) -> tuple[np.ndarray, list[Path]]:
    """:func:`read_stack`, also returning the files read."""
    files = _resolve_files(source)
    first = files[0]
    for f in files[1:]:
        if _kind(f) != _kind(first):
            raise StackImportError(f"series mixes formats: {first} is {_kind(first)}, {f} is {_kind(f)}")
    if len(files) == 1:
        return _read_file(first, shape, dtype, offset), files
    stack: np.ndarray | None = None
    for s, f in enumerate(files):
        arr = _read_file(f, shape, dtype, offset)
        if arr.shape[0] != 1:
            raise StackImportError(
                f"{f}: holds {arr.shape[0]} frames; a series of {len(files)} files must hold one frame "
                "per file (give a single file for a stack)")
        if stack is None:
            stack = np.empty((len(files),) + arr.shape[1:], dtype=arr.dtype)
        elif arr.shape[1:] != stack.shape[1:]:
            raise StackImportError(
                f"frame shape {arr.shape[1:]} of {f} differs from {stack.shape[1:]} of {first}")
        elif arr.dtype != stack.dtype:
            raise StackImportError(f"dtype {arr.dtype} of {f} differs from {stack.dtype} of {first}")
        stack[s] = arr[0]
    assert stack is not None  # files holds at least two
    return stack, files


def frame_dtype(arr: np.ndarray, name: str) -> np.ndarray:
    """Convert counts losslessly to a frame dtype the scan format allows.

    Parameters
    ----------
    arr : ndarray
        Counts, any shape.
    name : str
        What to call the array in error messages (file, glob or argument).

    Returns
    -------
    ndarray
        ``arr`` itself when it is uint16, uint32, float32 or float64; otherwise a copy in the smallest of
        those types that holds every value of the source type: 8- and 16-bit integers -> uint16, 32-bit
        integers -> uint32, float16 -> float32. 64-bit integers (no allowed type holds their range) go to
        uint32 when all values are below 2**32, else float64 when all are at most 2**53; longer floats
        to float64 when that is exact.

    Raises
    ------
    StackImportError
        Negative or non-finite counts, values no allowed type holds exactly, or a non-numeric dtype.
    """
    kind, size = arr.dtype.kind, arr.dtype.itemsize
    if kind in "biu":
        if kind == "i" and arr.min() < 0:
            raise StackImportError(f"{name}: {arr.dtype} counts hold negative values (min {arr.min()})")
        if size <= 2:
            return arr.astype(np.uint16, copy=False)
        if size == 4:
            return arr.astype(np.uint32, copy=False)
        top = int(arr.max())
        if top < 2 ** 32:
            return arr.astype(np.uint32)
        if top <= _FLOAT64_EXACT_INT:
            return arr.astype(np.float64)
        raise StackImportError(f"{name}: {arr.dtype} counts up to {top} exceed uint32 and are not exact in float64")
    if kind == "f":
        if not np.all(np.isfinite(arr)):
            raise StackImportError(f"{name}: counts hold NaN or infinite values")
        if arr.min() < 0:
            raise StackImportError(f"{name}: counts hold negative values (min {arr.min()})")
        if size == 2:
            return arr.astype(np.float32)
        if size in (4, 8):
            return arr.astype(arr.dtype.newbyteorder("="), copy=False)
        out = arr.astype(np.float64)
        if not np.array_equal(out, arr):
            raise StackImportError(f"{name}: {arr.dtype} counts are not exactly representable in float64")
        return out
    raise StackImportError(f"{name}: dtype {arr.dtype} is not a numeric count type")


def nominal_steps(n: int, *, steps_per_period: float | None = None,
                  phases: list[float] | None = None) -> np.ndarray:
    """Nominal phases of a phase-stepping series.

    Parameters
    ----------
    n : int
        Number of steps (frames) in the series.
    steps_per_period : float, optional
        Equidistant steps: phase ``2*pi*k/steps_per_period`` for k = 0 .. n-1.
    phases : sequence of float, optional
        Explicit phases (rad); length n, finite.

    Exactly one of ``steps_per_period`` and ``phases`` must be given.

    Returns
    -------
    ndarray of float64, shape (n,)
        Step phases in rad.

    Raises
    ------
    StackImportError
        Both or neither option given, a non-positive ``steps_per_period``, or ``phases`` of the wrong
        length or with non-finite values.
    """
    if (steps_per_period is None) == (phases is None):
        raise StackImportError("give exactly one of steps_per_period and phases "
                               f"(got steps_per_period={steps_per_period!r}, phases={phases!r})")
    if phases is not None:
        out = np.asarray(phases, dtype=np.float64)
        if out.shape != (n,):
            raise StackImportError(f"phases has {out.size} values for {n} steps")
        if not np.all(np.isfinite(out)):
            raise StackImportError(f"phases holds values that are not finite: {list(out)}")
        return out
    if steps_per_period is None:
        raise StackImportError("give steps_per_period or phases")
    spp = float(steps_per_period)
    if not (np.isfinite(spp) and spp > 0):
        raise StackImportError(f"steps_per_period must be a positive number, got {steps_per_period!r}")
    return 2 * np.pi * np.arange(n) / spp


def _describe(source) -> str:
    if isinstance(source, (list, tuple)) and source:
        return f"{os.fspath(source[0])!r} (first of {len(source)} files)"
    return repr(os.fspath(source))


def _read_dark(source, what: str, frame_shape: tuple[int, int], **raw) -> tuple[np.ndarray, list[Path]]:
    """One dark frame as float64, the mean of all frames read from ``source``."""
    stack, files = _read_series(source, **raw)
    if stack.shape[1:] != frame_shape:
        raise StackImportError(f"{what} {_describe(source)} has frames {stack.shape[1:]}, "
                               f"expected {frame_shape} like the series it belongs to")
    if stack.dtype.kind not in "biuf":
        raise StackImportError(f"{what} {_describe(source)}: dtype {stack.dtype} is not numeric")
    # float64 holds every integer count exactly; averaging several frames needs a float anyway.
    dark = stack.astype(np.float64).mean(axis=0)
    if not np.all(np.isfinite(dark)):
        raise StackImportError(f"{what} {_describe(source)} holds values that are not finite")
    return dark, files


def _strings(paths) -> np.ndarray:
    return np.array([str(Path(p).resolve()) for p in paths], dtype=h5py.string_dtype())


def _pixel_size(pixel_size) -> tuple[float, float] | None:
    if pixel_size is None:
        return None
    values = np.atleast_1d(np.asarray(pixel_size, dtype=np.float64))
    if values.size == 1:
        values = np.repeat(values, 2)
    if values.shape != (2,) or not np.all(np.isfinite(values) & (values > 0)):
        raise StackImportError(f"pixel_size must be a positive number or (y, x) pair in m, got {pixel_size!r}")
    return float(values[0]), float(values[1])


def import_stepping(output, *, sample, reference, dark=None, reference_dark=None,
                    steps_per_period: float | None = None, phases=None, reference_phases=None,
                    shape: tuple[int, int] | None = None, dtype: str | None = None, offset: int = 0,
                    gain: float = 1.0, pixel_size=None, overwrite: bool = False) -> Scan:
    """Convert a phase-stepping recording into a dfxcorr scan file.

    Parameters
    ----------
    output : str or path-like
        Scan file to write (HDF5, written atomically).
    sample : str, path-like or list
        The sample series, J frames [H, W] of counts; a source as for :func:`read_stack`.
    reference : str, path-like or list
        The reference (flat) series of the unloaded interferometer, S frames of the same [H, W].
    dark : str, path-like or list, optional
        Dark frame(s) [H, W] of the sample series (counts per frame); several frames are averaged.
    reference_dark : str, path-like or list, optional
        The same for the reference series; default: ``dark``.
    steps_per_period : float, optional
        Equidistant nominal steps, phase ``2*pi*k/steps_per_period`` (rad) for frame k.
    phases : sequence of float, optional
        Explicit nominal phases of the sample series (rad), length J. Exactly one of ``steps_per_period``
        and ``phases`` must be given.
    reference_phases : sequence of float, optional
        Phases of the reference series (rad), length S; default: the rule used for the sample series
        (``steps_per_period``, or ``phases`` which must then have length S as well).
    shape, dtype, offset
        Frame shape (H, W), dtype string and header bytes for headerless raw files (see :func:`read_stack`).
    gain : float
        Detector units per photon (1 for photon counting).
    pixel_size : float or (float, float), optional
        Pixel pitch in m, square or (y, x).
    overwrite : bool
        Replace an existing ``output``.

    Returns
    -------
    Scan
        What was written: data [J, H, W] (dtype per :func:`frame_dtype`), positions all 0, ``phase_step``
        the nominal phases, reference a :class:`~dfxcorr.io.SteppingReference` with data [S, H, W].

    Raises
    ------
    OutputExistsError
        ``output`` exists and ``overwrite`` is false (checked before anything is read).
    StackImportError
        Any unreadable or inconsistent input; see :func:`read_stack`, :func:`frame_dtype` and
        :func:`nominal_steps`. Also sample and reference frames of different shape, or fewer than 3 steps.
    """
    output = Path(os.path.expanduser(os.fspath(output)))
    if output.exists() and not overwrite:
        raise OutputExistsError(output)
    if not output.parent.is_dir():
        raise StackImportError(f"output {output}: directory {output.parent} does not exist")
    if (steps_per_period is None) == (phases is None):
        raise StackImportError("give exactly one of steps_per_period and phases")
    raw = dict(shape=shape, dtype=dtype, offset=offset)
    try:
        gain_value = float(gain)
    except (TypeError, ValueError):
        gain_value = float("nan")
    if not (np.isfinite(gain_value) and gain_value > 0):
        raise StackImportError(f"gain must be a positive number, got {gain!r}")
    px = _pixel_size(pixel_size)

    sample_raw, sample_files = _read_series(sample, **raw)
    reference_raw, reference_files = _read_series(reference, **raw)
    data = frame_dtype(sample_raw, f"sample {_describe(sample)}")
    ref = frame_dtype(reference_raw, f"reference {_describe(reference)}")
    J, H, W = data.shape
    if ref.shape[1:] != (H, W):
        raise StackImportError(f"sample {_describe(sample)} has frames {(H, W)}, reference "
                               f"{_describe(reference)} has frames {ref.shape[1:]}; they must be equal")
    for what, source, n in (("sample", sample, J), ("reference", reference, ref.shape[0])):
        if n < 3:
            raise StackImportError(f"{what} {_describe(source)} has {n} steps; phase stepping needs at least 3")
    try:
        steps = nominal_steps(J, steps_per_period=steps_per_period, phases=phases)
    except StackImportError as exc:
        raise StackImportError(f"sample {_describe(sample)}: {exc}") from None
    try:
        if reference_phases is not None:
            ref_steps = nominal_steps(ref.shape[0], phases=reference_phases)
        else:
            ref_steps = nominal_steps(ref.shape[0], steps_per_period=steps_per_period, phases=phases)
    except StackImportError as exc:
        hint = "" if reference_phases is not None or phases is None else " (give reference_phases)"
        raise StackImportError(f"reference {_describe(reference)}: {exc}{hint}") from None

    extra = {
        f"{_IMPORT_GROUP}/source_files": _strings(sample_files),
        f"{_IMPORT_GROUP}/reference_files": _strings(reference_files),
        f"{_IMPORT_GROUP}/source_dtype": str(sample_raw.dtype),
        f"{_IMPORT_GROUP}/reference_source_dtype": str(reference_raw.dtype),
    }
    if steps_per_period is not None:
        extra[f"{_IMPORT_GROUP}/steps_per_period"] = float(steps_per_period)
    dark_frame: np.ndarray | None = None
    if dark is not None:
        dark_frame, files = _read_dark(dark, "dark", (H, W), **raw)
        extra[f"{_IMPORT_GROUP}/dark_files"] = _strings(files)
    if reference_dark is not None:
        ref_dark: np.ndarray | None
        ref_dark, files = _read_dark(reference_dark, "reference_dark", (H, W), **raw)
        extra[f"{_IMPORT_GROUP}/reference_dark_files"] = _strings(files)
    else:
        ref_dark = dark_frame

    scan = Scan(data=data, position=np.zeros(J), phase_step=steps, dark=dark_frame, gain=gain_value,
                pixel_size=px, reference=SteppingReference(data=ref, phase_step=ref_steps, dark=ref_dark))
    write_scan(output, scan, extra=extra)
    return scan
