"""Checks before any work: every output of a command, and a configuration against a scan (``dfxcorr check``).

Every command lists the files it will write and calls :func:`check_outputs` before it reads or
computes anything, so that a refusal never comes after minutes of work or leaves a file behind.
:func:`plan` checks a resolved configuration against a scan's geometry (subsampling and its alias
limit, column offset, motion-mask dilation, diagnosis subsampling, visibility effects the acquisition
cannot determine) without fitting, and estimates the memory the run will need.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import config as C
from . import io
from .align import lit_blocks, no_lit_rows
from .errors import DfxcorrError, OutputExistsError, require_regular_file
from .faults import Faults, find_faults, saturation_level

if TYPE_CHECKING:  # the planning (numba kernels) is imported only where a check runs the pilot
    from .planning import ColumnPlan
    from .preparation import Prepared

#: Name length limit where the file system does not tell (bytes; ext4, XFS, Lustre, GPFS).
NAME_MAX = 255
#: Memory model of a streamed reconstruction: the store of lit rows (counts as stored), the images
#: (corrected and uncorrected t, v, phi in float64: 48 bytes per pixel), the retrieval's row blocks
#: (``retrieve.block_mb``) and the fit's samples (FIT_BYTES each: the float32 counts, t^f, the fringe's two
#: quadratures, dark and weights, the use and region masks, and a reweighting's new weights beside the old). The
#: stages' peaks do not coincide, so against the peak resident set (/usr/bin/time -v, 2 cores, docs/benchmark.json)
#: it errs high: at 195 x 2880 x 2880 1.36 GiB for 1.10 measured, 1.96 GiB for 1.53 with fit.max_samples 2.8e7;
#: 0.78 GiB for 0.58 at 195 x 1440 x 1440 (100 bytes per fit sample, the layout before the quadratures replaced
#: v^f and phi^f and the fit got faster, said 1.80, 3.67 and 1.20 GiB).
IMAGE_BYTES = 48
FIT_BYTES = 32
#: Resident memory of the interpreter with numpy, scipy, h5py, numba and dfxcorr loaded.
BASE_BYTES = 150 * 2 ** 20


class OutputError(DfxcorrError, OSError):
    """An output that cannot or must not be written; the message names it."""


def _name(path) -> str:
    """A path for a message, also when its bytes are not UTF-8."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def _require_utf8(path, what: str) -> None:
    try:
        os.fsencode(path).decode("utf-8")
    except UnicodeDecodeError:
        raise OutputError(f"{_name(path)}: the {what} name is not valid UTF-8 (every file name is recorded in the "
                          f"results as UTF-8); rename it") from None


def _identity(path) -> tuple[int, int] | None:
    """(st_dev, st_ino) of an existing file, following symbolic links; None if there is none."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def _existing_folder(folder: Path) -> Path:
    """The nearest folder of ``folder`` and its parents that exists (the writers create the rest)."""
    folder = Path(os.path.abspath(folder))
    while not os.path.lexists(folder) and folder != folder.parent:
        folder = folder.parent
    return folder


def _probe(folder: Path) -> None:
    """Refuse a folder in which this process cannot create files (permissions, read-only mounts, quotas)."""
    if not folder.is_dir():
        raise OutputError(f"{_name(folder)} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{_name(folder)}: no permission to write in this folder")
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".dfxcorr-probe-")
    except OSError as exc:
        raise OutputError(f"{_name(folder)}: cannot create files in this folder ({exc.strerror})") from None
    os.close(fd)
    os.unlink(probe)


def _name_max(folder: Path) -> int:
    try:
        return os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):
        return NAME_MAX


def check_outputs(outputs, *, inputs=(), overwrite: bool = False, appended=()) -> None:
    """Refuse, before any work, every output a command could not write or must not write.

    Parameters
    ----------
    outputs : iterable of path
        Files the command writes (each through :func:`dfxcorr.io.atomic_path`).
    inputs : iterable of path
        Files the command reads (scan, configuration, truth, source series). No output may be one of
        them under any spelling: files are compared by (device, inode), so relative and absolute names,
        symbolic and hard links are all recognised.
    overwrite : bool
        Existing outputs may be replaced.
    appended : iterable of path
        Files the command appends to (the log file): they may exist, but their folder must.

    Raises
    ------
    OutputExistsError
        An output exists and ``overwrite`` is False.
    OutputError
        An output is an input or written twice, is a folder, lies in a folder that cannot be created or
        written, has a name too long for its temporary name (``.<name>.<8 hex>.part``), or a name (of an
        input too) that is not UTF-8.
    """
    known = {}
    for p in inputs:
        _require_utf8(p, "input")
        require_regular_file(p)
        ident = _identity(p)
        if ident is not None:
            known[ident] = p
    written: dict = {}
    probed: set = set()
    for p, append in [(Path(o), False) for o in outputs] + [(Path(a), True) for a in appended]:
        _require_utf8(p, "output")
        ident = _identity(p)
        if ident in known:
            also = "" if os.fspath(known[ident]) == os.fspath(p) else f" ({_name(known[ident])})"
            raise OutputError(f"{_name(p)} is also an input{also}; write the output elsewhere")
        key = ident or os.path.realpath(p)
        if key in written:
            raise OutputError(f"{_name(p)} would be written twice (also as {_name(written[key])})")
        written[key] = p
        if p.is_dir():
            raise OutputError(f"{_name(p)} is a folder, not an output file")
        if not append and os.path.lexists(p) and not overwrite:
            raise OutputExistsError(p)
        folder = _existing_folder(p.parent)
        if append and folder != Path(os.path.abspath(p.parent)):
            raise OutputError(f"{_name(p)}: folder {_name(p.parent)} does not exist")
        if append:
            require_regular_file(p, "log file")  # appending to a FIFO waits for a reader
        extra = 0 if append else io.TEMP_NAME_OVERHEAD
        if len(os.fsencode(p.name)) + extra > _name_max(folder):
            raise OutputError(f"{_name(p)}: the name is too long ({len(os.fsencode(p.name))} bytes; with the "
                              f"temporary name's {extra} more, at most {_name_max(folder)})")
        if folder not in probed:
            _probe(folder)
            probed.add(folder)


def check_folder(folder) -> None:
    """Refuse, before any work, an output folder that cannot be replaced as a unit (:func:`dfxcorr.io.atomic_folder`).

    Raises
    ------
    OutputError
        ``folder`` is a file, is the working directory or holds it (the swap would leave the run, and the shell it
        was typed in, in a removed folder), or its parent cannot take the new folder beside it (permissions, a
        name too long for the temporary name).
    """
    _require_utf8(folder, "output")
    path = Path(os.path.realpath(folder))
    if os.path.lexists(path) and not path.is_dir():
        raise OutputError(f"{_name(folder)} is not a folder")
    cwd = Path.cwd().resolve()
    if path == cwd or path in cwd.parents:
        raise OutputError(f"{_name(folder)} is the working directory or holds it: its files are replaced as a whole, "
                          f"by a new folder; give the output a folder of its own")
    parent = _existing_folder(path.parent)
    if len(os.fsencode(path.name)) + io.TEMP_NAME_OVERHEAD > _name_max(parent):
        raise OutputError(f"{_name(folder)}: the name is too long for its temporary name (at most "
                          f"{_name_max(parent) - io.TEMP_NAME_OVERHEAD} bytes)")
    _probe(parent)


# --------------------------------------------------------------------------------------------------
# The configuration against a scan
# --------------------------------------------------------------------------------------------------


@dataclass
class Plan:
    """What ``reconstruct`` would do with a scan and a configuration.

    Attributes
    ----------
    scan : str
    shape : tuple of int
        (J, H, W).
    dtype : str
    active_rows : int
    stepping : bool
    rows_used : int
        Detector rows lit in at least ``align.min_frames`` frames.
    lit_samples : int
        Samples (frame, row, column) entering the reconstruction.
    method : str
    columns : ndarray of int
        Columns of the vibration fit (empty for ``fit.method=none``).
    fit_plan : ColumnPlan or None
        How they were chosen, the predicted uncertainty and time (None for ``fit.method=none``).
    effects : tuple of str
        Configured effects that remain candidates (the Fisher check of the run may still drop ``auto`` ones).
    dropped : dict
        Effect -> why it will not be fitted.
    memory_bytes : int
        Estimate of the peak resident memory, see :func:`memory_estimate`.
    outputs : list of Path
    """

    scan: str
    shape: tuple
    dtype: str
    active_rows: int
    stepping: bool
    rows_used: int
    lit_samples: int
    method: str
    columns: np.ndarray
    fit_plan: ColumnPlan | None
    effects: tuple
    dropped: dict = field(default_factory=dict)
    memory_bytes: int = 0
    outputs: list = field(default_factory=list)

    def summary(self) -> str:
        """Lines for the terminal."""
        J, H, W = self.shape
        fit = ("none: no vibration fit" if self.fit_plan is None else
               f"{self.method} on {self.columns.size} of {W} columns: {self.fit_plan.summary()}")
        lines = [f"scan {self.scan}: {J} frames of {H} x {W} ({self.dtype}), active area {self.active_rows} rows"
                 + (", phase stepping" if self.stepping else ""),
                 f"rows used: {self.rows_used} of {H}; lit samples: {self.lit_samples}",
                 f"vibration fit: {fit}",
                 f"effects: {', '.join(self.effects) or 'none'}"]
        lines += [f"  {name} will not be fitted: {why}" for name, why in self.dropped.items()]
        lines.append(f"memory: about {self.memory_bytes / 2 ** 30:.2f} GiB (lit rows as stored, images, row "
                     f"blocks, {FIT_BYTES} bytes per fit sample, {BASE_BYTES // 2 ** 20} MiB)")
        lines += [f"output: {_name(p)}" + (" (replaced)" if os.path.lexists(p) else "") for p in self.outputs]
        return "\n".join(lines)


def memory_estimate(shape, *, itemsize: int, lit_samples: int, fit_samples: int, block_mb: float) -> int:
    """Peak resident memory of a reconstruction (bytes).

    lit samples x ``itemsize`` (the store) + :data:`IMAGE_BYTES` per pixel + ``block_mb`` MB (the row
    blocks) + :data:`FIT_BYTES` per fit sample + :data:`BASE_BYTES`.
    """
    _, H, W = shape
    return int(lit_samples * itemsize + IMAGE_BYTES * H * W + block_mb * 1e6 + FIT_BYTES * fit_samples
               + BASE_BYTES)


def _columns(scan: io.Scan, cfg: dict, samples_per_column: int, *, prep: Prepared | None) -> ColumnPlan:
    from .planning import (
        ColumnPlan,
        coarse_step,
        column_step,
        fit_columns,
        fit_seconds,
        plan_columns,
        slowdown,
        start_seconds,
    )

    W = scan.shape[2]
    n = cfg["fit"]["subsample"]
    try:
        if n == "auto" and prep is not None:
            return plan_columns(prep, cfg, report=False)
        step = column_step(W, samples_per_column, most=cfg["fit"]["max_samples"]) if n == "auto" else n
        cols = fit_columns(W, cfg, step)
        coarse = coarse_step(cfg, cols.size, samples_per_column, step=step, width=W)
        return ColumnPlan(columns=cols, why="fit.subsample" if n != "auto" else
                          "at most; auto chooses at run time from a pilot, which dfxcorr check runs",
                          seconds=fit_seconds(cols.size, samples_per_column, coarse, slowdown=slowdown(cfg)),
                          start_seconds=start_seconds(cfg, cols.size, samples_per_column), coarse=coarse)
    except ValueError as exc:
        if isinstance(exc, DfxcorrError):
            raise
        offset = cfg["fit"]["column_offset"]
        if offset is not None:
            raise C.ConfigError(
                f"fit.column_offset={offset} is outside the detector's columns 0..{W - 1}") from None
        first = f" (its first column would be {n // 2})" if isinstance(n, int) else ""
        raise C.ConfigError(f"fit.subsample={n} leaves no column of {W}{first}; use at most {W // 4}") from None


def _visibility_reasons(scan: io.Scan) -> str | None:
    """Why visibility effects cannot be determined by this acquisition (paper Sec. II-F), or None."""
    from .planning import visibility_unidentifiable
    from .reference import resolve_reference

    reference = scan.reference
    if isinstance(reference, io.SteppingReference) and not scan.is_stepping:
        reference = resolve_reference(scan, effects=(), optional=())
    return visibility_unidentifiable(scan, reference)


#: Unknowns of every pixel's images (t, v, phi): a pixel seen in no more frames is fitted exactly.
IMAGE_UNKNOWNS = 3


class NothingToTestError(DfxcorrError, ValueError):
    """A diagnosis of a recording whose images leave no residual to test."""


def require_residuals(frames_per_row: np.ndarray) -> None:
    """Refuse a diagnosis where every pixel is seen in at most :data:`IMAGE_UNKNOWNS` frames.

    ``frames_per_row``: frames in which each detector row the run uses is lit. Its images then fit every sample
    exactly: no residual is left, so no effect, noise or signature can be tested.

    Raises
    ------
    NothingToTestError
    """
    most = int(np.max(frames_per_row, initial=0))
    if most <= IMAGE_UNKNOWNS:
        raise NothingToTestError(f"every pixel is seen in at most {most} frames, which its {IMAGE_UNKNOWNS} image "
                                 f"unknowns (t, v, phi) fit exactly: no residual is left to diagnose (it needs "
                                 f"pixels seen in at least {IMAGE_UNKNOWNS + 1} frames, e.g. {IMAGE_UNKNOWNS + 1} "
                                 f"phase steps)")


def plan(scan: io.Scan, cfg: dict, *, name: str = "", outputs=(), diagnose: bool = False,
         pilot: bool = False) -> Plan:
    """Check a resolved configuration against a scan without fitting; what ``reconstruct`` would do.

    Parameters
    ----------
    scan : Scan
        From :func:`dfxcorr.io.read_scan` (``header_only`` is enough).
    cfg : dict
        Resolved configuration.
    name : str
        The scan's name for the summary.
    outputs : sequence of path
        Listed in the summary.
    diagnose : bool
        Also check the ``diagnose`` section.
    pilot : bool
        Prepare the scan as the run does (reading its frames, leaving its detector faults out), decide which
        configured effects its fit can determine with the run's own rule on the fit's observations, its motion
        mask applied (:func:`dfxcorr.planning.resolve_effects` on :func:`dfxcorr.pipeline.fit_observations`),
        and for ``fit.subsample: auto`` run the pilot that chooses those columns
        (:func:`dfxcorr.planning.plan_columns`). Otherwise only the visibility effects are judged (from the
        geometry) and the columns are the most auto may take.

    Raises
    ------
    ConfigError
        Naming the key: subsampling beyond the detector or its alias limit, a column offset outside the
        detector, a mask dilation beyond the detector's size, a diagnosis subsampling beyond it.
    IdentifiabilityError
        An effect set to true that this acquisition cannot determine (with ``pilot``: judged as the run judges
        it; otherwise the visibility effects only).
    NothingToTestError
        With ``diagnose``: every pixel is seen in at most :data:`IMAGE_UNKNOWNS` frames.
    """
    from .effects import REGISTRY
    from .planning import VISIBILITY_EFFECTS, drop_visibility, resolve_effects

    J, H, W = scan.shape
    method = cfg["fit"]["method"]
    if cfg["mask"]["dilate"] > max(H, W):
        raise C.ConfigError(f"mask.dilate={cfg['mask']['dilate']} exceeds the detector ({H} x {W} pixels); "
                            f"use at most {max(H, W)}")
    if diagnose and cfg["diagnose"]["subsample"] // 2 >= W:
        n = cfg["diagnose"]["subsample"]
        raise C.ConfigError(f"diagnose.subsample={n} leaves no column of {W} (its first column would be {n // 2}); "
                            f"use at most {2 * W - 1}")
    count = np.bincount(lit_blocks(scan.position, scan.active_rows, H)[0], minlength=H)
    used = count >= cfg["align"]["min_frames"]
    if not used.any():  # what collect_lit_rows refuses, in its words
        raise no_lit_rows(cfg["align"]["min_frames"])
    if diagnose:
        require_residuals(count[used])
    # what the configuration asks of each effect (the files it names), checked against the scan as the run's
    # preparation does
    for effect in REGISTRY.values():
        effect.configured(cfg, n_frames=J, detector=(H, W))
    lit = int(count[used].sum()) * W
    # what the settings and the geometry alone refuse comes before the scan is prepared (reading its frames)
    fit_plan = None if method == "none" else _columns(scan, cfg, lit // W, prep=None)
    effects = C.effects_of(cfg) if method != "none" else ()
    why = _visibility_reasons(scan) if set(VISIBILITY_EFFECTS) & set(effects) else None
    kept, dropped = drop_visibility(cfg, effects, why)
    prep = None
    if pilot and method != "none":
        from .preparation import prepare

        prep = prepare(scan, cfg, effects=REGISTRY.values())
        if cfg["fit"]["subsample"] == "auto":
            fit_plan = _columns(scan, cfg, lit // W, prep=prep)
    columns = np.zeros(0, int) if fit_plan is None else fit_plan.columns
    if prep is not None and fit_plan is not None:  # the run's decision, on the run's data
        from .pipeline import fit_motion_mask, fit_observations
        from .planning import row_blocks

        moving = fit_motion_mask(prep, cfg, fit_plan, row_blocks(prep.store, cfg["retrieve"]["block_mb"]))
        chosen = resolve_effects(cfg, prep.scan, prep.reference, fit_observations(prep, columns, moving))
        dropped.update({name: "the Fisher information of this acquisition has directions of its parameters "
                              "without information beyond its gauge" for name in kept if name not in chosen})
        kept = list(chosen)
    effects = tuple(kept)
    return Plan(scan=name, shape=(J, H, W), dtype=str(scan.data.dtype), active_rows=scan.active_rows,
                stepping=scan.is_stepping, rows_used=int(used.sum()), lit_samples=lit, method=method,
                columns=columns, fit_plan=fit_plan, effects=effects, dropped=dropped,
                memory_bytes=memory_estimate(scan.shape, itemsize=scan.data.dtype.itemsize, lit_samples=lit,
                                             fit_samples=columns.size * (lit // W),
                                             block_mb=cfg["retrieve"]["block_mb"]),
                outputs=[Path(p) for p in outputs])


def detector_faults(scan: io.Scan, cfg: dict) -> Faults:
    """The detector faults ``reconstruct`` will leave out (:mod:`dfxcorr.faults`), from the lit rows of each frame.

    Reads each frame's rows lit in at least ``align.min_frames`` frames once, one frame at a time.
    """
    J, H, _ = scan.shape
    used = np.bincount(lit_blocks(scan.position, scan.active_rows, H)[0], minlength=H) >= cfg["align"]["min_frames"]
    bounds = io.lit_rows(scan.position, scan.active_rows, H)

    def blocks():
        opener = scan.data.open() if isinstance(scan.data, io.H5Frames) else nullcontext(scan.data)
        with opener as data:
            for j, (r0, r1) in enumerate(bounds):
                rows = np.arange(r0, r1)[used[r0:r1]]
                if rows.size:
                    yield j, rows, np.asarray(data[j, r0:r1])[rows - r0]

    assert scan.dark is not None  # Scan.__post_init__ fills it
    return find_faults(blocks(), shape=scan.shape, dark=scan.dark,
                       level=saturation_level(scan.data.dtype, cfg["load"]["saturation"]))
