"""Writing files atomically (a temporary name of their own, renamed when complete) and writing scan files."""
from __future__ import annotations

import fcntl
import os
import re
import secrets
import shutil
import signal
import sys
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import TracebackType
from typing import Any

import h5py
import numpy as np

from ..errors import OutputExistsError, WriteError
from .types import FORMAT, FORMAT_VERSION, FrameSource, Scan, SteppingReference

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


@contextmanager
def _signals_held() -> Iterator[None]:
    """Hold back SIGINT, SIGTERM and SIGHUP until the steps inside are complete, then deliver them.

    Their handlers are swapped for a recorder (a thread mask would not do: the process-directed signal goes to
    any thread that does not block it, and Python runs its handler in the main thread all the same). Outside
    the main thread nothing is needed: Python's handlers interrupt the main thread only.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    held = [s for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP) if signal.getsignal(s) is not None]
    before = {s: signal.signal(s, lambda signum, frame: caught.append(signum)) for s in held}
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
        for signum in caught:
            signal.raise_signal(signum)


@contextmanager
def atomic_folder(path: str | os.PathLike, *, names: Iterable[str], overwrite: bool = False) -> Iterator[Path]:
    """Yield a new empty folder beside the folder ``path``; it becomes ``path`` as a unit on success, and is removed
    on failure or interrupt.

    ``names`` are every file name the writer may put in it. In an existing ``path`` the entries of those names are
    the previous run's: they are replaced as a whole, also those this run does not write again. Any other entry
    (a scan or configuration kept there) is carried into the new folder. The swap (the old folder renamed aside,
    the new one renamed in, the other entries moved over, the old one removed) runs with the interrupts held back
    and the parent folder locked against a concurrent swap, so a reader finds one run's files or the previous
    run's, never a mix. Without ``overwrite`` an entry of those names that appeared meanwhile is refused
    (:class:`OutputExistsError`). A symbolic link to the folder is followed: its target is replaced.
    """
    path = Path(os.path.realpath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:  # a name of its own, created with the permissions a new folder gets (mkdtemp's are private)
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.part")
        try:
            os.mkdir(tmp)
            break
        except FileExistsError:
            continue
    try:
        yield tmp
        with _signals_held():
            _swap_in(tmp, path, names=set(names), overwrite=overwrite)
    except BaseException:
        with _signals_held():
            shutil.rmtree(tmp, ignore_errors=True)
        raise


def _swap_in(new: Path, path: Path, *, names: set[str], overwrite: bool) -> None:
    """Put the folder ``new`` in the place of the folder ``path`` (:func:`atomic_folder`)."""
    lock = os.open(path.parent, os.O_RDONLY)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not os.path.lexists(path):
            os.rename(new, path)
            return
        if not path.is_dir():
            raise WriteError(f"{path} is not a folder; nothing was replaced")
        entries = os.listdir(path)
        ours = [e for e in entries if e in names]
        if ours and not overwrite:
            raise OutputExistsError(path / ours[0])
        os.chmod(new, path.stat().st_mode)
        aside = new.with_suffix(".old")
        os.rename(path, aside)
        os.rename(new, path)
        for e in entries:
            if e not in names:
                os.rename(aside / e, path / e)
        shutil.rmtree(aside)
    finally:
        os.close(lock)  # releases the lock


@contextmanager
def h5_output(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[h5py.File]:
    """An HDF5 file open for writing under :func:`atomic_path`; a failed write (a full disk) ends in one error.

    When HDF5 cannot write, every object h5py releases afterwards fails to flush again and h5py reports each
    failure as a traceback (through ``sys.excepthook`` and ``sys.unraisablehook``, which drop those while the
    file is written). The first error is raised as a :class:`WriteError` naming the output; the temporary file
    is removed and an earlier ``path`` stays as it was. HDF5 cannot release such a file: the command line
    then exits without the interpreter's teardown.
    """
    hooks = sys.excepthook, sys.unraisablehook
    sys.excepthook = lambda kind, value, tb: None if _from_h5py(tb) else hooks[0](kind, value, tb)
    sys.unraisablehook = lambda u: None if _from_h5py(u.exc_traceback) else hooks[1](u)
    try:
        with atomic_path(path, overwrite=overwrite) as tmp, h5py.File(tmp, "w") as f:
            yield f
    except OSError as exc:
        raise WriteError(f"{path}: cannot write ({_reason(exc)}); nothing was replaced") from None
    finally:
        sys.excepthook, sys.unraisablehook = hooks


def _from_h5py(tb: TracebackType | None) -> bool:
    """Whether a traceback ends in h5py's release of an object (``_objects.pyx``)."""
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb is not None and tb.tb_frame.f_code.co_filename.endswith("_objects.pyx")


def _reason(exc: OSError) -> str:
    """The operating system's reason behind an HDF5 write error ('No space left on device'), else its first line."""
    found = re.search(r"errno = (\d+)", str(exc))
    return os.strerror(int(found.group(1))) if found else str(exc).splitlines()[0]


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
    with h5_output(path, overwrite=overwrite) as f:
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
