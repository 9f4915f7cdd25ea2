"""Stage 1, load: the dfxcorr scan file (``spec/scan-format.md``), read with every check and written atomically.

A scan holds the raw frames, the per-frame geometry (position of the active area, nominal phase step)
and the reference description of the unloaded interferometer, either as maps or as a phase-stepping
series. Reading refuses anything the format forbids with a :class:`ScanFormatError` whose message
names the dataset.
"""
from __future__ import annotations

import logging
import math
import os
import secrets
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, overload

import h5py
import numpy as np
from numpy.typing import DTypeLike

from .errors import DfxcorrError, OutputExistsError

log = logging.getLogger(__name__)

FORMAT = "dfxcorr-scan"
FORMAT_VERSION = 1
_DET = "entry/instrument/detector"
_FRAME_DTYPES = (np.uint16, np.uint32, np.float32, np.float64)


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


_MAPS = ("transmission", "visibility", "phase")
# HDF5 itself gives up after 16 nested soft links; a walk of our own stops at the same depth.
_MAX_LINK_DEPTH = 16
# Root attributes are read into Scan.attrs; real ones are short strings and numbers.
_MAX_ATTRIBUTE_BYTES = 1 << 20


@dataclass(frozen=True)
class Layout:
    """What :func:`validate_file` found: the sizes of a scan file, checked against each other and its storage.

    Attributes
    ----------
    J, H, W : int
        Frames, detector rows and columns of ``/entry/instrument/detector/data``.
    A : int
        Rows of the active area (of the reference maps or the stepping series).
    S : int or None
        Frames of ``/entry/reference/stepping/data`` when the reference is a stepping series, else None.
    external_files : tuple of str
        Files other than the scan file whose bytes the reader follows (external links, external raw storage,
        virtual dataset sources); empty unless allowed.
    """

    J: int
    H: int
    W: int
    A: int
    S: int | None
    external_files: tuple[str, ...] = ()


class _Walker:
    """Resolves the paths the reader uses one link at a time, refusing or recording what leaves the file."""

    def __init__(self, f: h5py.File, allow_external: bool):
        self.f = f
        self.allow_external = allow_external
        self.external: list[str] = []

    def _outside(self, path: str, what: str, files: Iterable[str] = ()) -> None:
        if not self.allow_external:
            raise ScanFormatError(f"/{path} is {what}; refused (set load.allow_external=true to follow it)")
        for name in files:
            self._record(name)

    def _record(self, name: str | os.PathLike) -> None:
        full = str(Path(name).resolve())
        if full != str(Path(self.f.filename).resolve()) and full not in self.external:
            self.external.append(full)

    def get(self, path: str) -> Any:
        """The object at ``path`` (or None when absent) after checking every link on the way."""
        parts = [p for p in path.split("/") if p]
        depth = 0
        k = 0
        while k < len(parts):
            here = "/" + "/".join(parts[:k + 1])
            try:
                link = self.f.get(here, getlink=True)
            except (KeyError, RuntimeError, OSError, ValueError) as exc:
                raise ScanFormatError(f"/{path}: cannot resolve {here} ({exc})") from None
            if link is None:
                if depth:
                    raise ScanFormatError(f"/{path}: dangling soft link ({here} does not exist)")
                return None
            if isinstance(link, h5py.SoftLink):
                depth += 1
                if depth > _MAX_LINK_DEPTH:
                    raise ScanFormatError(f"/{path}: soft links loop (more than {_MAX_LINK_DEPTH} at {here})")
                target = link.path if link.path.startswith("/") else "/".join(parts[:k]) + "/" + link.path
                parts = [p for p in target.split("/") if p] + parts[k + 1:]
                k = 0
                continue
            if isinstance(link, h5py.ExternalLink):
                self._outside(path, f"an external link to {link.filename}:{link.path}")
                break
            k += 1
        try:
            obj = self.f.get(path)
        except (KeyError, RuntimeError, OSError, ValueError) as exc:
            raise ScanFormatError(f"/{path}: dangling or broken link ({exc})") from None
        if obj is None:
            raise ScanFormatError(f"/{path}: dangling link")
        self._record(obj.file.filename)  # the file HDF5 actually opened behind an external link
        return obj

    @overload
    def dataset(self, path: str, *, required: Literal[True] = True, lit: tuple[np.ndarray, int] | None = None
                ) -> h5py.Dataset: ...

    @overload
    def dataset(self, path: str, *, required: bool, lit: tuple[np.ndarray, int] | None = None
                ) -> h5py.Dataset | None: ...

    def dataset(self, path: str, *, required: bool = True, lit: tuple[np.ndarray, int] | None = None
                ) -> h5py.Dataset | None:
        """The dataset at ``path`` with its storage checked, or None when optional and absent.

        ``lit`` = (position, A) for the frames: only the chunks that hold lit rows must be stored (a writer may
        leave the rest unallocated; they read as zeros, which the format allows where nothing is lit).
        """
        obj = self.get(path)
        if obj is None:
            if required:
                raise ScanFormatError(f"missing required dataset /{path}")
            return None
        if not isinstance(obj, h5py.Dataset):
            kind = "a group" if isinstance(obj, h5py.Group) else "a named datatype" if isinstance(
                obj, h5py.Datatype) else type(obj).__name__
            raise ScanFormatError(f"/{path} must be a dataset, found {kind}")
        if obj.shape is None:
            raise ScanFormatError(f"/{path} is empty (null dataspace)")
        if obj.dtype.kind not in "iuf":
            raise ScanFormatError(f"/{path} has dtype {obj.dtype}, expected numbers")
        self._storage(path, obj, lit)
        return obj

    def _storage(self, path: str, dset: h5py.Dataset, lit: tuple[np.ndarray, int] | None = None) -> None:
        """Refuse data that is declared but not stored, and storage outside the file unless allowed."""
        if dset.is_virtual:
            sources = sorted({vs.file_name for vs in dset.virtual_sources()})
            self._outside(path, f"a virtual dataset (sources {', '.join(sources)})")
            # HDF5 looks for a relative source beside the file first, then in the working directory
            here = Path(dset.file.filename).resolve().parent
            for name in sources:
                if name != ".":
                    self._record(here / name if (here / name).exists() else name)
            return
        declared = dset.size * dset.dtype.itemsize
        if dset.external:
            # HDF5 opens relative external raw files from the working directory (HDF5_EXTFILE_PREFIX unset)
            self._outside(path, f"stored in external raw file(s) {', '.join(e[0] for e in dset.external)}",
                          [e[0] for e in dset.external])
            present = 0
            for name, offset, size in dset.external:
                try:
                    avail = max(0, Path(name).stat().st_size - offset)
                except OSError:
                    avail = 0
                present += min(avail, size)
            if present < declared:
                raise ScanFormatError(f"/{path} declares {dset.shape} {dset.dtype} ({declared} bytes) but its "
                                      f"external files hold {present}")
            return
        if declared == 0:
            return
        if dset.chunks is not None:
            expected = math.prod(-(-n // c) for n, c in zip(dset.shape, dset.chunks, strict=True)) if lit is None \
                else _lit_chunks(dset.shape, dset.chunks, *lit)
            stored = dset.id.get_num_chunks()
            if stored < expected:
                raise ScanFormatError(f"/{path} declares {dset.shape} in {expected} chunks of {dset.chunks} but "
                                      f"stores {stored}: the data is not in the file")
        else:
            stored = dset.id.get_storage_size()
            if stored < declared:
                raise ScanFormatError(f"/{path} declares {dset.shape} {dset.dtype} ({declared} bytes) but stores "
                                      f"{stored} bytes: the data is not in the file")


def _expect_shape(path: str, dset: h5py.Dataset, shape: tuple, what: str) -> None:
    if dset.shape != shape:
        raise ScanFormatError(f"/{path} has shape {dset.shape}, expected {shape} ({what})")


def _expect_scalar(path: str, dset: h5py.Dataset) -> None:
    if dset.size != 1 or dset.ndim > 1:
        raise ScanFormatError(f"/{path} has shape {dset.shape}, expected a scalar")


def validate_file(f: h5py.File, *, allow_external: bool = False) -> Layout:
    """Check an open scan file's layout before any frame is read.

    Reads only attributes, shapes, dtypes and storage information; every dataset the reader uses is checked
    to be numeric, of the shape the frames imply and actually stored in the file (all chunks present, a
    contiguous dataset as long as it declares), so that a reader that follows reads nothing unsized.

    Parameters
    ----------
    f : h5py.File
        Open scan file.
    allow_external : bool
        Follow external links, external raw storage and virtual datasets (recorded in
        ``Layout.external_files``) instead of refusing them.

    Returns
    -------
    Layout

    Raises
    ------
    ScanFormatError
        Naming the dataset, attribute or link at fault.
    """
    fmt = f.attrs.get("format")
    if isinstance(fmt, bytes):
        fmt = fmt.decode(errors="replace")
    if not isinstance(fmt, str) or fmt != FORMAT:
        raise ScanFormatError(f"/ attribute 'format' is {fmt!r}, expected {FORMAT!r}")
    version = f.attrs.get("format_version")
    v = np.asarray(version) if version is not None else None
    if v is None or v.size != 1 or v.dtype.kind not in "iu" or int(v.reshape(-1)[0]) != FORMAT_VERSION:
        raise ScanFormatError(f"/ attribute 'format_version' is {version!r}, this reader knows {FORMAT_VERSION}")
    for key in f.attrs:
        try:
            if f.attrs.get_id(key).get_storage_size() > _MAX_ATTRIBUTE_BYTES:
                raise ScanFormatError(f"/ attribute {key!r} is larger than {_MAX_ATTRIBUTE_BYTES} bytes")
            f.attrs[key]
        except (OSError, TypeError, ValueError, KeyError) as exc:
            raise ScanFormatError(f"/ attribute {key!r} cannot be read ({exc})") from None
    walk = _Walker(f, allow_external)
    name = f"{_DET}/data"
    dset = walk.get(name)
    if not isinstance(dset, h5py.Dataset) or dset.shape is None:
        dset = walk.dataset(name)  # refuses it, naming what it is
    if dset.ndim != 3 or 0 in dset.shape:
        raise ScanFormatError(f"/{name} must be 3-D [J, H, W] and not empty, has shape {dset.shape}")
    if dset.dtype.type not in _FRAME_DTYPES:
        raise ScanFormatError(f"/{name} has dtype {dset.dtype}, expected uint16, uint32, float32 or float64")
    J, H, W = dset.shape
    _expect_shape("entry/scan/position", walk.dataset("entry/scan/position"), (J,), f"one per frame of /{name}")
    for key in ("phase_step", "exposure_time"):
        d = walk.dataset(f"entry/scan/{key}", required=False)
        if d is not None:
            _expect_shape(f"entry/scan/{key}", d, (J,), "one per frame")
    d = walk.dataset(f"{_DET}/dark", required=False)
    if d is not None:
        _expect_shape(f"{_DET}/dark", d, (H, W), "one value per detector pixel")
    for key in ("gain", "x_pixel_size", "y_pixel_size"):
        d = walk.dataset(f"{_DET}/{key}", required=False)
        if d is not None:
            _expect_scalar(f"{_DET}/{key}", d)
    S = None
    if all(walk.get(f"entry/reference/{m}") is not None for m in _MAPS):
        t = walk.dataset("entry/reference/transmission")
        if t.ndim != 2 or t.shape[1] != W or t.shape[0] == 0:
            raise ScanFormatError(f"/entry/reference/transmission has shape {t.shape}, expected [A, {W}]")
        for m in _MAPS[1:]:
            _expect_shape(f"entry/reference/{m}", walk.dataset(f"entry/reference/{m}"), t.shape,
                          "same as /entry/reference/transmission")
        A = t.shape[0]
    elif walk.get("entry/reference/stepping") is not None:
        base = "entry/reference/stepping"
        d = walk.dataset(f"{base}/data")
        if d.ndim != 3 or d.shape[2] != W or 0 in d.shape:
            raise ScanFormatError(f"/{base}/data has shape {d.shape}, expected [S, A, {W}]")
        S, A, _ = d.shape
        _expect_shape(f"{base}/phase_step", walk.dataset(f"{base}/phase_step"), (S,),
                      "one per frame of the stepping series")
        dk = walk.dataset(f"{base}/dark", required=False)
        if dk is not None:
            _expect_shape(f"{base}/dark", dk, (A, W), "one value per pixel of the active area")
    else:
        missing = next(m for m in _MAPS if walk.get(f"entry/reference/{m}") is None)
        raise ScanFormatError(f"missing required dataset /entry/reference/{missing} "
                              f"(or /entry/reference/stepping/data)")
    position = np.asarray(walk.dataset("entry/scan/position")[()], dtype=np.float64)
    # non-finite positions are refused by the reader; here they only must not break the count
    walk.dataset(name, lit=(np.nan_to_num(position, nan=0.0, posinf=0.0, neginf=0.0), A))
    return Layout(J=J, H=H, W=W, A=A, S=S, external_files=tuple(walk.external))


def _lit_chunks(shape: tuple, chunks: tuple, position: np.ndarray, active_rows: int) -> int:
    """Chunks of frames [J, H, W] that hold at least one lit row (0 <= r + 0.5 - position[j] < A)."""
    J, H, W = shape
    cj, ch, cw = chunks
    r0 = np.clip(np.ceil(position - 0.5), 0, H).astype(np.int64)
    r1 = np.clip(np.ceil(position + active_rows - 0.5), 0, H).astype(np.int64)
    lit = r1 > r0
    blocks = {(int(j) // cj, c) for j in np.flatnonzero(lit)
              for c in range(int(r0[j]) // ch, (int(r1[j]) - 1) // ch + 1)}
    return len(blocks) * -(-W // cw)


def _open(path: str | os.PathLike) -> h5py.File:
    """The scan file opened for reading, or a refusal naming it."""
    path = Path(path)
    if not path.is_file():
        raise ScanFormatError(f"{path}: no such file")
    if not h5py.is_hdf5(path):
        raise ScanFormatError(f"{path}: not an HDF5 file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise ScanFormatError(f"{path}: cannot open as HDF5 ({exc})") from None


def read_scan(path: str | os.PathLike, *, allow_external: bool = False) -> Scan:
    """Read and validate a dfxcorr scan file.

    Parameters
    ----------
    path : str or path-like
        HDF5 file following ``spec/scan-format.md``.
    allow_external : bool
        Follow external links, external raw storage and virtual datasets (see :func:`validate_file`);
        the files followed are listed in ``Scan.external_files``.

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
    with _open(path) as f:
        layout = validate_file(f, allow_external=allow_external)
        dset = _require(f, f"{_DET}/data")
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
        pixel_size: tuple[float, float] | None = None
        if all(p is not None for p in px):
            size_y, size_x = (float(np.asarray(p).reshape(-1)[0]) for p in px)
            pixel_size = (size_y, size_x)
        reference = _read_reference(f, W)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    return Scan(data=data, position=position, reference=reference, phase_step=phase_step, dark=dark,
                gain=gain, exposure_time=exposure, pixel_size=pixel_size, attrs=attrs,
                external_files=layout.external_files)


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


def _check_counts(name: str, data: FrameSource) -> None:
    """NaN or negative counts in float frames (array or HDF5 dataset), read one frame at a time."""
    if data.dtype.kind != "f":
        return
    for j in range(data.shape[0]):  # frame by frame keeps memory bounded
        frame = data[j]
        if not np.all(np.isfinite(frame)):
            raise ScanFormatError(f"/{name} frame {j} holds NaN or infinite counts")
        if np.any(frame < 0):
            raise ScanFormatError(f"/{name} frame {j} holds negative counts")


#: Bytes a temporary name adds to the output's name: ``.<name>.<8 hex digits>.part``.
TEMP_NAME_OVERHEAD = len(".") + len(".01234567.part")


def _exclusive_temp(path: Path) -> Path:
    """Create a new empty file ``.<name>.<random>.part`` beside ``path``, exclusively (never one another run holds)."""
    while True:
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.part")
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return tmp
        except FileExistsError:
            continue


def _move_new(tmp: Path, path: Path) -> None:
    """Give ``tmp`` the name ``path`` only if no file has that name (also not one that appeared meanwhile)."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise OutputExistsError(path) from None
    except OSError:  # a file system without hard links: check, then rename (a small window remains)
        if os.path.lexists(path):
            raise OutputExistsError(path) from None
        os.replace(tmp, path)
        return
    tmp.unlink()


@contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; move it to ``path`` on success, remove it on failure.

    The temporary file is created exclusively under a name of its own (``.<name>.<random>.part``), so
    concurrent runs writing the same output never share or remove each other's temporary files.
    Without ``overwrite`` the final step refuses a file that exists by then (:class:`OutputExistsError`,
    also when another run created it while this one was writing); with it, the rename replaces it.
    Readers never see a half-written file, and a failed or interrupted run leaves nothing behind.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _exclusive_temp(path)
    try:
        yield tmp
        if overwrite:
            os.replace(tmp, path)
        else:
            _move_new(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


#: Detector rows per HDF5 chunk of the frames: reading a frame's lit rows decompresses little beyond them.
CHUNK_ROWS = 64


def write_scan(path: str | os.PathLike, scan: Scan, *, extra: dict[str, Any] | None = None,
               compression: str | None = "gzip", frames: Iterable[tuple[int, int, np.ndarray]] | None = None,
               overwrite: bool = False) -> None:
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
    overwrite : bool
        Replace an existing file (otherwise :class:`OutputExistsError`).
    """
    with atomic_path(path, overwrite=overwrite) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = FORMAT_VERSION
        entry = f.create_group("entry")
        entry.attrs["NX_class"] = "NXentry"
        inst = entry.create_group("instrument")
        inst.attrs["NX_class"] = "NXinstrument"
        det = inst.create_group("detector")
        det.attrs["NX_class"] = "NXdetector"
        _write_frames(det, "data", scan.data, compression, chunk_rows=CHUNK_ROWS, blocks=frames)
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
            _write_frames(st, "data", scan.reference.data, compression, chunk_rows=scan.reference.data.shape[1])
            st.create_dataset("phase_step", data=scan.reference.phase_step).attrs["units"] = "rad"
            if scan.reference.dark is not None:
                st.create_dataset("dark", data=scan.reference.dark)
        else:
            ref.create_dataset("transmission", data=scan.reference.transmission)
            ref.create_dataset("visibility", data=scan.reference.visibility)
            ref.create_dataset("phase", data=scan.reference.phase).attrs["units"] = "rad"
        for key, value in (extra or {}).items():
            f.create_dataset(key, data=value)


def _write_frames(group: h5py.Group, name: str, frames: FrameSource, compression: str | None, *,
                  chunk_rows: int, blocks: Iterable[tuple[int, int, np.ndarray]] | None = None) -> None:
    """Write frames [N, H, W] one frame at a time, in chunks of (1, ``chunk_rows``, W).

    ``frames`` may read them lazily; ``blocks`` of (frame, first row, rows) replace them where given
    (rows not given stay 0), so that a producer can hand over one frame's lit rows at a time.
    """
    n, h, w = frames.shape
    dset = group.create_dataset(name, shape=(n, h, w), dtype=frames.dtype, chunks=(1, min(chunk_rows, h), w),
                                compression=compression)
    for k, r0, block in (blocks if blocks is not None else ((k, 0, frames[k]) for k in range(n))):
        dset[k, r0:r0 + block.shape[0]] = block


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

