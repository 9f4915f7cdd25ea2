"""Frame files of other layouts read lazily and losslessly: .npy stacks, TIFF pages, headerless raw frames.

Every file's size is checked from its header before its data is read. Frame dtypes the scan format does not
allow are converted to the smallest allowed type that holds every value of the source type exactly (see
:func:`frame_dtype`), or refused.
"""
from __future__ import annotations

import glob
import logging
import math
import os
import re
from pathlib import Path
from typing import TypedDict

import numpy as np
import tifffile

from ..errors import DfxcorrError

_NPY = {".npy"}
_TIFF = {".tif", ".tiff"}
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
