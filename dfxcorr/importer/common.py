"""What both imports share: nominal steps, dark frames, checked options, the record of the sources, and frames
converted losslessly as they are written."""
from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from ..errors import OutputExistsError, gain_problem
from .formats import Series, StackImportError, _resolve_files, frame_dtype

_IMPORT_GROUP = "entry/dfxcorr_import"


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
    problem = gain_problem(value)
    if problem:
        raise StackImportError(f"gain {problem}, got {gain!r}")
    return value


def input_files(*sources) -> list[Path]:
    """Every file the given sources (globs, paths or lists; None skipped) name: what an import reads."""
    return [f for source in sources if source is not None for f in _resolve_files(source)]


def _checked_output(output, overwrite: bool, *sources) -> Path:
    """The output path of an import, refused before anything is read if it exists (without ``overwrite``), its
    folder is missing, or it is one of the files the ``sources`` name (:func:`dfxcorr.check.check_outputs`)."""
    from ..check import check_outputs

    output = Path(os.path.expanduser(os.fspath(output)))
    if output.exists() and not overwrite:
        raise OutputExistsError(output)
    if not output.parent.is_dir():
        raise StackImportError(f"output {output}: directory {output.parent} does not exist")
    check_outputs([output], inputs=input_files(*sources), overwrite=overwrite)
    return output


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
