"""The scan file's layout, checked before any frame is read: shapes, dtypes, storage, links.

Every dataset the reader uses is checked to be numeric, of the shape the frames imply and stored in the
file (external links, external raw storage and virtual datasets only when allowed), so that the reader
that follows reads nothing unsized.
"""
from __future__ import annotations

import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, overload

import h5py
import numpy as np

from .types import DET as _DET
from .types import FORMAT, FORMAT_VERSION, ScanFormatError, lit_rows
from .types import FRAME_DTYPES as _FRAME_DTYPES

_MAPS = ("transmission", "visibility", "phase")
# HDF5 itself gives up after 16 nested soft links; a walk of our own stops at the same depth.
_MAX_LINK_DEPTH = 16
# A dataset read whole (dark, reference maps or series) larger than this must store at least 1/_MAX_EXPANSION of its
# bytes: a gzip dark map of a few MB expanded to 3 GB. Noisy counts compress a few times at most.
_MAX_EXPANDED = 256 << 20
_MAX_EXPANSION = 100
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
            expected = (math.prod(-(-n // c) for n, c in zip(dset.shape, dset.chunks, strict=True)) if lit is None
                        else _lit_chunks(dset.shape, dset.chunks, *lit))
            stored = dset.id.get_num_chunks()
            if stored < expected:
                raise ScanFormatError(f"/{path} declares {dset.shape} in {expected} chunks of {dset.chunks} but "
                                      f"stores {stored}: the data is not in the file")
            size = dset.id.get_storage_size()
            if lit is None and declared > _MAX_EXPANDED and declared > _MAX_EXPANSION * size:
                # read whole (the frames are read row block by row block): memory must follow the file's bytes
                raise ScanFormatError(f"/{path} expands from {size} stored bytes to {declared} ({dset.shape} "
                                      f"{dset.dtype}): refused, real detector data does not compress "
                                      f"{_MAX_EXPANSION} times")
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
            value = f.attrs[key]
        except (OSError, TypeError, ValueError, KeyError) as exc:
            raise ScanFormatError(f"/ attribute {key!r} cannot be read ({exc})") from None
        if isinstance(value, bytes):
            try:
                value.decode("utf-8")
            except UnicodeDecodeError:
                raise ScanFormatError(f"/ attribute {key!r} is not UTF-8 text") from None
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
    r0, r1 = lit_rows(position, active_rows, H).T
    lit = r1 > r0
    blocks = {(int(j) // cj, c) for j in np.flatnonzero(lit)
              for c in range(int(r0[j]) // ch, (int(r1[j]) - 1) // ch + 1)}
    return len(blocks) * -(-W // cw)
