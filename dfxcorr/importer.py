"""Import of recordings (series of .npy, TIFF or headerless raw frames) into a scan file.

Two layouts: a phase-stepping recording (:func:`import_stepping`), the special case of
``spec/scan-format.md`` with A = H, all positions 0 and ``scan/phase_step`` holding the nominal step phases,
its reference stored as the stepping series of the unloaded interferometer (``/entry/reference/stepping``);
and a scanning acquisition (:func:`import_scanning`): frames plus a motor log of the interferometer position,
with a reference stepping series cropped to the active area or the reference of another scan file. The import
is lossless: counts are written exactly as read. Frame dtypes the format does not allow are converted to the
smallest allowed type that holds every value of the source type exactly (see :func:`frame_dtype`), or refused.
Every file's size is checked from its header before its data is read.
"""
from __future__ import annotations

import contextlib
import glob
import logging
import math
import os
import re
from pathlib import Path
from typing import TypedDict

import h5py
import numpy as np
import tifffile
from scipy import ndimage

from .errors import DfxcorrError, OutputExistsError
from .io import Scan, SteppingReference, read_reference, write_scan

_NPY = {".npy"}
_TIFF = {".tif", ".tiff"}
_IMPORT_GROUP = "entry/dfxcorr_import"
log = logging.getLogger(__name__)
# Every integer up to 2**53 is exactly representable in float64.
_FLOAT64_EXACT_INT = 2 ** 53


class StackImportError(DfxcorrError, ValueError):
    """A series cannot be imported; the message names the offending file, glob or argument."""


def _natural_key(text: str) -> list:
    # Alternating text/int parts, so that step_2 sorts before step_10; ASCII digits only (str.isdigit() is also
    # true of superscripts, which int() refuses)
    return [int(part) if k % 2 else part for k, part in enumerate(re.split(r"([0-9]+)", text))]


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


class _Frames:
    """The frames of one file, sized from its header and read one at a time.

    Attributes
    ----------
    path : Path
    shape : (int, int, int)
        (frames, H, W) as declared by the file and checked against its size.
    dtype : numpy.dtype
        As stored (byte order included).
    """

    def __init__(self, path: Path, shape: tuple[int, int, int], dtype: np.dtype, read, close=lambda: None):
        self.path, self.shape, self.dtype = path, shape, dtype
        self._read, self.close = read, close

    def frame(self, k: int) -> np.ndarray:
        """Frame ``k`` [H, W] in native byte order."""
        try:
            arr = np.asarray(self._read(k))
        except (OSError, ValueError, EOFError, MemoryError) as exc:
            raise StackImportError(f"{self.path}: cannot read frame {k} ({exc})") from exc
        if arr.shape != self.shape[1:]:
            raise StackImportError(f"{self.path}: frame {k} has shape {arr.shape}, its header declares "
                                   f"{self.shape[1:]}")
        # Native byte order: same values, and no byte-swapped types reach the scan file.
        return arr.astype(arr.dtype.newbyteorder("="), copy=False)


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError as exc:
        raise StackImportError(f"{path}: cannot read ({exc})") from exc


def _frames_shape(path: Path, shape: tuple) -> tuple[int, int, int]:
    if len(shape) == 2:
        shape = (1, *shape)
    if len(shape) != 3:
        raise StackImportError(f"{path}: holds an array of shape {shape}; expected a frame [H, W] "
                               "or a stack of frames [S, H, W]")
    if 0 in shape:
        raise StackImportError(f"{path}: holds no data (shape {shape})")
    n, h, w = shape
    return int(n), int(h), int(w)


def _open_npy(path: Path) -> _Frames:
    try:
        with open(path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, _, dt = read_header(fh)
            header = fh.tell()
    except (OSError, ValueError, EOFError) as exc:
        raise StackImportError(f"{path}: cannot read as .npy ({exc})") from exc
    if dt.hasobject:
        raise StackImportError(f"{path}: holds Python objects (dtype {dt}); expected counts")
    declared = math.prod(shape) * dt.itemsize
    if _size(path) - header != declared:
        raise StackImportError(f"{path}: header declares {shape} {dt} ({declared} bytes) but the file holds "
                               f"{_size(path) - header} bytes of data")
    frames = _frames_shape(path, shape)

    def read(k):
        # a memory map, opened per frame, reads only that frame and holds no file or mapping in between
        return np.array(np.load(path, mmap_mode="r", allow_pickle=False).reshape(frames)[k])

    return _Frames(path, frames, dt, read)


def _open_tiff(path: Path) -> _Frames:
    try:
        tif = tifffile.TiffFile(path)
    except (OSError, ValueError, tifffile.TiffFileError) as exc:
        raise StackImportError(f"{path}: cannot read as TIFF ({exc})") from exc
    try:
        return _tiff_frames(path, tif)
    except BaseException:
        tif.close()
        raise


def _tiff_frames(path: Path, tif) -> _Frames:
    size = _size(path)
    index = []  # (series, key within the series) of each frame
    first = None
    try:
        # Pages appended one by one form one series each; a multi-page stack forms one series.
        for k, series in enumerate(tif.series):
            if "S" in series.axes or series.ndim not in (2, 3):
                raise StackImportError(
                    f"{path}: image series {k} has axes {series.axes!r} and shape {series.shape}; "
                    "expected grey-value frames (2-D, or a 3-D stack of frames)")
            frames = _frames_shape(path, series.shape)
            if first is None:
                first = (frames[1:], series.dtype)
            elif (frames[1:], series.dtype) != first:
                raise StackImportError(f"{path}: image series {k} has frames {frames[1:]} {series.dtype}, "
                                       f"series 0 has {first[0]} {first[1]}")
            index += [(k, j) for j in range(frames[0])]
        _check_tiff_storage(path, tif, size)
    except StackImportError:
        raise
    except (OSError, ValueError, IndexError, tifffile.TiffFileError) as exc:
        raise StackImportError(f"{path}: cannot read as TIFF ({exc})") from exc
    if first is None:
        raise StackImportError(f"{path}: holds no image")

    if len(index) == 1:
        # one frame per file: reopen to read it, so that a series of many files keeps none open
        tif.close()
        return _Frames(path, (1, *first[0]), np.dtype(first[1]), lambda k: tifffile.imread(path, series=0, key=0))

    def read(k):
        s, j = index[k]
        return tif.asarray(series=s, key=j)

    return _Frames(path, (len(index), *first[0]), np.dtype(first[1]), read, tif.close)


# Deflate cannot compress more than 1032:1 and LZW not much more; a page claiming more is not what it says.
_MAX_TIFF_COMPRESSION = 4096


def _check_tiff_storage(path: Path, tif, size: int) -> None:
    """Refuse pages whose declared size the file cannot hold (uncompressed) or could not expand to (compressed)."""
    for n, page in enumerate(tif.pages):
        declared = math.prod(page.shape) * np.dtype(page.dtype).itemsize
        stored = sum(page.databytecounts)
        if any(o + c > size for o, c in zip(page.dataoffsets, page.databytecounts, strict=True)):
            raise StackImportError(f"{path}: page {n} points beyond the end of the file ({size} bytes)")
        limit = stored if page.compression == 1 else stored * _MAX_TIFF_COMPRESSION
        if declared > limit:
            raise StackImportError(f"{path}: page {n} declares {page.shape} {page.dtype} ({declared} bytes) but "
                                   f"stores {stored} bytes{'' if page.compression == 1 else ' compressed'}")


def _open_raw(path: Path, shape, dtype, offset: int) -> _Frames:
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
    size = _size(path)
    frame_bytes = h * w * dt.itemsize
    body = size - offset
    if body <= 0 or body % frame_bytes:
        raise StackImportError(
            f"{path}: {size} bytes minus {offset} bytes of header is not a whole, non-zero number of "
            f"{h}x{w} frames of {dt} ({frame_bytes} bytes each)")

    def read(k):
        return np.fromfile(path, dtype=dt, count=h * w, offset=offset + k * frame_bytes).reshape(h, w)

    return _Frames(path, (body // frame_bytes, h, w), dt, read)


def _kind(path: Path) -> str:
    suffix = path.suffix.lower()
    return "npy" if suffix in _NPY else "tiff" if suffix in _TIFF else "raw"


def _open_file(path: Path, shape, dtype, offset: int) -> _Frames:
    if path.is_dir():
        raise StackImportError(f"{path}: is a directory, expected a file")
    kind = _kind(path)
    if kind == "npy":
        return _open_npy(path)
    if kind == "tiff":
        return _open_tiff(path)
    return _open_raw(path, shape, dtype, offset)


class _RawLayout(TypedDict):
    """How to read raw files: the ``shape``, ``dtype`` and ``offset`` options of :class:`Series`."""

    shape: tuple[int, int] | None
    dtype: str | None
    offset: int


class Series:
    """A series of frames from one stack file or one file per frame, checked from the headers, read lazily.

    Use as a context manager (it closes the files). ``series[k]`` reads frame k [H, W] in native byte order;
    ``shape`` is (frames, H, W) and ``dtype`` the stored type (native order).
    """

    def __init__(self, source, shape: tuple[int, int] | None = None, dtype: str | None = None, offset: int = 0):
        files = _resolve_files(source)
        first = files[0]
        for f in files[1:]:
            if _kind(f) != _kind(first):
                raise StackImportError(f"series mixes formats: {first} is {_kind(first)}, {f} is {_kind(f)}")
        self.files = files
        self._parts: list[_Frames] = []
        try:
            for f in files:
                part = _open_file(f, shape, dtype, offset)
                self._parts.append(part)
                if len(files) > 1 and part.shape[0] != 1:
                    raise StackImportError(
                        f"{f}: holds {part.shape[0]} frames; a series of {len(files)} files must hold one frame "
                        "per file (give a single file for a stack)")
                ref = self._parts[0]
                if part.shape[1:] != ref.shape[1:]:
                    raise StackImportError(f"frame shape {part.shape[1:]} of {f} differs from {ref.shape[1:]} "
                                           f"of {first}")
                if part.dtype.newbyteorder("=") != ref.dtype.newbyteorder("="):
                    raise StackImportError(f"dtype {part.dtype} of {f} differs from {ref.dtype} of {first}")
        except BaseException:
            self.close()
            raise
        self.shape = (sum(p.shape[0] for p in self._parts), *self._parts[0].shape[1:])
        self.dtype = self._parts[0].dtype.newbyteorder("=")

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, k: int) -> np.ndarray:
        if len(self._parts) == 1:
            return self._parts[0].frame(k)
        return self._parts[k].frame(0)

    def __iter__(self):
        return (self[k] for k in range(len(self)))

    def close(self) -> None:
        for p in self._parts:
            p.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


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
        A glob matching nothing, an unreadable file, a header that declares more data than the file holds,
        raw without shape/dtype or of a size that is not a whole number of frames, frames of different shape
        or dtype (naming both files), several files of which one holds more than one frame, or a mixture of
        formats.

    Notes
    -----
    The format follows the file suffix: ``.npy`` (2-D frame or 3-D stack), ``.tif``/``.tiff`` (single
    page or multi-page stack, read with tifffile), anything else is headerless raw, whose size minus
    ``offset`` must be a whole number of frames. Sizes are checked from the headers before any data is read.
    """
    return _read_series(source, shape, dtype, offset)[0]


def _read_series(source, shape, dtype, offset) -> tuple[np.ndarray, list[Path]]:
    """:func:`read_stack`, also returning the files read."""
    with Series(source, shape, dtype, offset) as series:
        stack = np.empty(series.shape, dtype=series.dtype)
        for k in range(len(series)):
            stack[k] = series[k]
        return stack, series.files


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
        Both or neither option given, a non-positive ``steps_per_period`` or one so small that the phases
        overflow, or ``phases`` of the wrong length or with non-finite values.
    """
    if (steps_per_period is None) == (phases is None):
        raise StackImportError("give exactly one of steps_per_period and phases "
                               f"(got steps_per_period={steps_per_period!r}, phases={phases!r})")
    if phases is not None:
        out: np.ndarray = np.asarray(phases, dtype=np.float64)
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
    with np.errstate(over="ignore"):
        out = 2 * np.pi * np.arange(n) / spp
    if not np.all(np.isfinite(out)):
        raise StackImportError(f"steps_per_period={steps_per_period!r} makes the phase steps 2 pi k / n infinite")
    return out


def _describe(source) -> str:
    if isinstance(source, (list, tuple)) and source:
        return f"{os.fspath(source[0])!r} (first of {len(source)} files)"
    return repr(os.fspath(source))


def _read_dark(source, what: str, frame_shape: tuple[int, int], **raw) -> tuple[np.ndarray, list[Path]]:
    """One dark frame as float64, the mean of all frames read from ``source`` (one at a time)."""
    with Series(source, **raw) as series:
        if series.shape[1:] != frame_shape:
            raise StackImportError(f"{what} {_describe(source)} has frames {series.shape[1:]}, "
                                   f"expected {frame_shape} like the series it belongs to")
        if series.dtype.kind not in "biuf":
            raise StackImportError(f"{what} {_describe(source)}: dtype {series.dtype} is not numeric")
        # float64 holds every integer count exactly; averaging several frames needs a float anyway.
        total = np.zeros(frame_shape)
        for frame in series:
            total += frame
        dark = total / len(series)
        files = series.files
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


def _gain(gain) -> float:
    try:
        value = float(gain)
    except (TypeError, ValueError):
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise StackImportError(f"gain must be a positive number, got {gain!r}")
    return value


def input_files(*sources) -> list[Path]:
    """Every file the given sources (globs, paths or lists; None skipped) name: what an import reads."""
    return [f for source in sources if source is not None for f in _resolve_files(source)]


def _checked_output(output, overwrite: bool, *sources) -> Path:
    """The output path of an import, refused before anything is read if it exists (without ``overwrite``), its
    folder is missing, or it is one of the files the ``sources`` name (:func:`dfxcorr.check.check_outputs`)."""
    from .check import check_outputs

    output = Path(os.path.expanduser(os.fspath(output)))
    if output.exists() and not overwrite:
        raise OutputExistsError(output)
    if not output.parent.is_dir():
        raise StackImportError(f"output {output}: directory {output.parent} does not exist")
    check_outputs([output], inputs=input_files(*sources), overwrite=overwrite)
    return output


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
    OutputError
        ``output`` is one of the input files (any spelling or link), or cannot be written; see
        :func:`dfxcorr.check.check_outputs`.
    StackImportError
        Any unreadable or inconsistent input; see :func:`read_stack`, :func:`frame_dtype` and
        :func:`nominal_steps`. Also sample and reference frames of different shape, or fewer than 3 steps.
    """
    output = _checked_output(output, overwrite, sample, reference, dark, reference_dark)
    if (steps_per_period is None) == (phases is None):
        raise StackImportError("give exactly one of steps_per_period and phases")
    raw = dict(shape=shape, dtype=dtype, offset=offset)
    gain_value = _gain(gain)
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
    write_scan(output, scan, extra=extra, overwrite=overwrite)
    return scan


class _Counts:
    """Frames of a :class:`Series` converted losslessly (:func:`frame_dtype`) as they are read, optionally cropped
    to rows ``rows``; ``shape``, ``dtype`` and ``[k]`` as :func:`dfxcorr.io.write_scan` expects of frames."""

    def __init__(self, series: Series, name: str, rows: slice | None = None):
        self.series, self.name, self.rows = series, name, rows or slice(None)
        n, h, w = series.shape
        self.shape = (n, len(range(h)[self.rows]), w)
        src = series.dtype
        if (src.kind in "iu" and src.itemsize == 8) or (src.kind == "f" and src.itemsize > 8):
            # the lossless type depends on the values: one pass over the frames, one at a time
            self.dtype = np.result_type(*(frame_dtype(frame, name).dtype for frame in series))
        else:
            self.dtype = frame_dtype(np.zeros(1, src), name).dtype

    def __getitem__(self, k: int) -> np.ndarray:
        # the whole frame is checked: counts outside the crop also tell whether the file holds counts at all
        return frame_dtype(self.series[k], f"{self.name} frame {k}")[self.rows].astype(self.dtype, copy=False)


#: Largest position log read (a number per frame per line: tens of millions of frames).
_MAX_LOG_BYTES = 256 << 20


def read_positions(path, n: int, *, column: str | None = None) -> np.ndarray:
    """Positions from a motor log: one number per frame per line, or a CSV table with a header row.

    Parameters
    ----------
    path : str or path-like
        Text file. Blank lines and lines starting with ``#`` are skipped. A first line that is not a number is
        a header; columns are separated by semicolons, tabs, commas or blanks (the first of these the first line
        holds separates every line). With semicolons or tabs a decimal comma is read as a decimal point
        (``0;-14,0``).
    n : int
        Number of frames: the log must hold exactly one value per frame.
    column : str, optional
        Header name of the column to take (required when the table has several columns).

    Returns
    -------
    ndarray of float64, shape (n,)

    Raises
    ------
    StackImportError
        Unreadable or oversized file, unknown or repeated column, a value that is not a finite number (naming
        the line), or a count other than ``n``.
    """
    path = Path(os.path.expanduser(os.fspath(path)))
    if not path.is_file():
        raise StackImportError(f"position log {path}: no such file")
    if _size(path) > _MAX_LOG_BYTES:
        raise StackImportError(f"position log {path}: {_size(path)} bytes, more than a log of {n} frames needs")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise StackImportError(f"position log {path}: cannot read as text ({exc})") from exc
    lines = [(k, ln.strip()) for k, ln in enumerate(text.splitlines(), start=1)
             if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise StackImportError(f"position log {path}: holds no values")

    # one separator for the whole file: a semicolon file's decimal commas must not split its cells
    sep = next((s for s in (";", "\t", ",") if s in lines[0][1]), None)

    def split(line):
        return line.split() if sep is None else [c.strip() for c in line.split(sep)]

    def number(text, k):
        if sep in (";", "\t") and text.count(",") == 1 and "." not in text:
            text = text.replace(",", ".")
        try:
            value = float(text)
        except ValueError:
            raise StackImportError(f"position log {path} line {k}: {text!r} is not a number") from None
        if not np.isfinite(value):
            raise StackImportError(f"position log {path} line {k}: {text!r} is not finite")
        return value

    head = split(lines[0][1])
    try:
        number(head[0], lines[0][0])
        names = None
    except StackImportError:
        names = head
        lines = lines[1:]
    if names is None:
        if column is not None:
            raise StackImportError(f"position log {path}: has no header, so no column {column!r}")
        index = 0
    elif len(set(names)) != len(names):
        twice = sorted({c for c in names if names.count(c) > 1})
        raise StackImportError(f"position log {path}: the header names column(s) {twice} more than once; "
                               f"which one is meant is ambiguous")
    elif column is None:
        if len(names) != 1:
            raise StackImportError(f"position log {path}: has columns {names}; name one (--position-column)")
        index = 0
    elif column in names:
        index = names.index(column)
    else:
        raise StackImportError(f"position log {path}: no column {column!r}; it has {names}")
    values = []
    for k, line in lines:
        cells = split(line)
        if names is None and len(cells) != 1:
            raise StackImportError(f"position log {path} line {k}: {line!r} is not one number")
        if names is not None and len(cells) != len(names):
            raise StackImportError(f"position log {path} line {k}: {len(cells)} columns, the header has {len(names)}")
        values.append(number(cells[index], k))
    if len(values) != n:
        raise StackImportError(f"position log {path}: {len(values)} positions for {n} frames")
    return np.asarray(values)


def active_area(profile: np.ndarray) -> tuple[int, int]:
    """First row and height of the interferometer's active area from the mean flux per detector row.

    Parameters
    ----------
    profile : ndarray, shape (H,)
        Mean counts of each detector row over the reference frames (dark removed).

    Returns
    -------
    first, rows : int
        The longest run of rows whose flux (median over 3 rows, so a hot or dead row neither splits nor
        makes the area) is above half-way between the darkest and the brightest row.
    """
    smooth = ndimage.median_filter(np.asarray(profile, float), size=3, mode="nearest")
    lit = smooth > (smooth.min() + smooth.max()) / 2
    best = (0, 0)
    start = None
    for r, on in enumerate(np.append(lit, False)):
        if on and start is None:
            start = r
        elif not on and start is not None:
            best = max(best, (r - start, start))
            start = None
    rows, first = best
    return first, rows


def import_scanning(output, *, frames, positions, position_units: str = "pixel", position_column: str | None = None,
                    reference_stepping=None, steps_per_period: float | None = None, reference_phases=None,
                    reference=None, dark=None, reference_dark=None, active_first_row: int | None = None,
                    active_rows: int | None = None, shape: tuple[int, int] | None = None, dtype: str | None = None,
                    offset: int = 0, gain: float = 1.0, pixel_size=None, overwrite: bool = False) -> Scan:
    """Convert a scanning acquisition (frames and a motor log of the interferometer position) into a scan file.

    Frames are read, checked and written one at a time, so memory stays at a few frames.

    Parameters
    ----------
    output : str or path-like
        Scan file to write (HDF5, written atomically).
    frames : str, path-like or list
        The J frames [H, W] of counts in acquisition order; a source as for :func:`read_stack`.
    positions : str or path-like
        Motor log: the top edge of the active area per frame (see :func:`read_positions`).
    position_units : {'pixel', 'mm'}
        Units of the log: detector rows, or mm along the detector columns (needs ``pixel_size``).
    position_column : str, optional
        Column of a CSV log.
    reference_stepping : str, path-like or list, optional
        A phase-stepping series [S, H, W] of the unloaded interferometer recorded on the detector; cropped to
        the active area and stored as ``/entry/reference/stepping``.
    steps_per_period, reference_phases
        Nominal steps of that series (exactly one; see :func:`nominal_steps`).
    reference : str or path-like, optional
        Another scan file whose ``/entry/reference`` is taken as it is (instead of ``reference_stepping``).
    dark, reference_dark : optional
        Dark frame(s) [H, W] of the frames and of the reference series (default: ``dark``), averaged.
    active_first_row, active_rows : int, optional
        The active area in the reference frames; default: found from the flux (:func:`active_area`).
    shape, dtype, offset
        Raw files only (see :func:`read_stack`).
    gain : float
        Detector units per photon.
    pixel_size : float or (float, float), optional
        Pixel pitch in m, square or (y, x).
    overwrite : bool
        Replace an existing ``output``.

    Returns
    -------
    Scan
        What was written; its ``data`` (and a stepping reference's ``data``) only describe the frames written
        (``shape``, ``dtype``), the files are closed.

    Raises
    ------
    OutputExistsError, StackImportError, dfxcorr.io.ScanFormatError
        Before anything is written: existing output, bad options, unreadable or inconsistent inputs.
    """
    output = _checked_output(output, overwrite, frames, positions, reference_stepping, reference, dark,
                             reference_dark)
    if (reference is None) == (reference_stepping is None):
        raise StackImportError("give exactly one of reference (a scan file) and reference_stepping (a series)")
    if position_units not in ("pixel", "mm"):
        raise StackImportError(f"position_units must be pixel or mm, got {position_units!r}")
    px = _pixel_size(pixel_size)
    row_pitch: float | None = None  # m, to convert a log in mm
    if position_units == "mm":
        if px is None:
            raise StackImportError("positions in mm need the pixel size (pixel_size) to convert them to detector "
                                   "rows")
        row_pitch = px[0]
    gain_value = _gain(gain)
    raw: _RawLayout = {"shape": shape, "dtype": dtype, "offset": offset}
    with contextlib.ExitStack() as stack:
        series = stack.enter_context(Series(frames, **raw))
        J, H, W = series.shape
        data = _Counts(series, f"frames {_describe(frames)}")
        position = read_positions(positions, J, column=position_column)
        if row_pitch is not None:
            position = position * 1e-3 / row_pitch
        extra = {f"{_IMPORT_GROUP}/source_files": _strings(series.files),
                 f"{_IMPORT_GROUP}/source_dtype": str(series.dtype),
                 f"{_IMPORT_GROUP}/position_log": _strings([positions]),
                 f"{_IMPORT_GROUP}/position_units": position_units}
        dark_frame = None
        if dark is not None:
            dark_frame, files = _read_dark(dark, "dark", (H, W), **raw)
            extra[f"{_IMPORT_GROUP}/dark_files"] = _strings(files)
        if reference is not None:
            ref = read_reference(reference)
            width = (ref.data if isinstance(ref, SteppingReference) else ref.transmission).shape[-1]
            if width != W:
                raise StackImportError(f"reference {reference}: {width} columns, the frames have {W}")
            extra[f"{_IMPORT_GROUP}/reference_file"] = _strings([reference])
        else:
            ref_series = stack.enter_context(Series(reference_stepping, **raw))
            A_ref = ref_series.shape[1]
            if ref_series.shape[2] != W or A_ref > H:
                raise StackImportError(f"reference_stepping {_describe(reference_stepping)} has frames "
                                       f"{ref_series.shape[1:]}, the frames have {(H, W)} (a reference series is "
                                       f"recorded on the detector, or already cropped to the active area)")
            if len(ref_series) < 3:
                raise StackImportError(f"reference_stepping {_describe(reference_stepping)} has {len(ref_series)} "
                                       "steps; phase stepping needs at least 3")
            try:
                steps = nominal_steps(len(ref_series), steps_per_period=steps_per_period, phases=reference_phases)
            except StackImportError as exc:
                raise StackImportError(f"reference_stepping {_describe(reference_stepping)}: {exc}") from None
            ref_dark = dark_frame
            if reference_dark is not None:
                ref_dark, files = _read_dark(reference_dark, "reference_dark", (A_ref, W), **raw)
                extra[f"{_IMPORT_GROUP}/reference_dark_files"] = _strings(files)
            if A_ref < H:
                first, rows, ref_dark = _cropped(A_ref, H, dark_frame if reference_dark is None else None, ref_dark,
                                                 active_first_row, active_rows, _describe(reference_stepping))
                crop = slice(0, rows)
            else:
                first, rows = _active_rows(ref_series, ref_dark, active_first_row, active_rows,
                                           _describe(reference_stepping))
                crop = slice(first, first + rows)
            ref = SteppingReference(data=_Counts(ref_series, f"reference_stepping {_describe(reference_stepping)}",
                                                 crop),
                                    phase_step=steps,
                                    dark=None if ref_dark is None else ref_dark[crop] if A_ref == H else ref_dark)
            extra.update({f"{_IMPORT_GROUP}/reference_files": _strings(ref_series.files),
                          f"{_IMPORT_GROUP}/active_first_row": first})
            if steps_per_period is not None:
                extra[f"{_IMPORT_GROUP}/steps_per_period"] = float(steps_per_period)
        scan = Scan(data=data, position=position, dark=dark_frame, gain=gain_value, pixel_size=px, reference=ref)
        write_scan(output, scan, extra=extra, overwrite=overwrite)
    return scan


def _cropped(A: int, H: int, frames_dark, ref_dark, first: int | None, rows: int | None,
             name: str) -> tuple[int, int, np.ndarray | None]:
    """A reference series of A < H rows, already cropped to the active area: its first row on the detector (for
    the record, and to crop the frames' dark to it), its height and its dark (A, W).

    ``frames_dark`` (H, W), the frames' dark standing in for a missing reference dark, needs ``first``.
    """
    if rows is not None and rows != A:
        raise StackImportError(f"reference_stepping {name} has {A} rows, already cropped to the active area; "
                               f"active_rows={rows} differs")
    if frames_dark is not None:
        if first is None:
            raise StackImportError(f"reference_stepping {name} is already cropped to {A} rows: give the active "
                                   f"area's first detector row (active_first_row) to crop the dark to it, or a "
                                   f"reference_dark of {A} rows")
        if not 0 <= first <= H - A:
            raise StackImportError(f"active_first_row={first}: {A} rows from there do not lie within the {H} "
                                   f"detector rows")
        ref_dark = frames_dark[first:first + A]
    log.info("reference %s: %d rows, taken as already cropped to the active area", name, A)
    return (0 if first is None else int(first)), A, ref_dark


def _active_rows(series: Series, dark, first: int | None, rows: int | None, name: str) -> tuple[int, int]:
    """The active area of a reference series on the detector: as given, or found from the flux (logged)."""
    H = series.shape[1]
    if (first is None) != (rows is None):
        raise StackImportError("give both active_first_row and active_rows, or neither (found from the flux)")
    if first is None or rows is None:  # both, by the check above
        profile = np.zeros(H)
        for frame in series:
            profile += frame.mean(axis=1)
        profile = profile / len(series) - (0 if dark is None else dark.mean(axis=1))
        first, rows = active_area(profile)
        log.info("reference %s: active area rows %d to %d (%d rows) of %d, found from the flux", name, first,
                 first + rows - 1, rows, H)
    if not (0 <= first and rows >= 1 and first + rows <= H):
        raise StackImportError(f"active area rows {first} to {first + rows - 1} do not lie within the {H} detector "
                               "rows of the reference")
    return int(first), int(rows)
