"""A scanning acquisition (frames and a motor log of the interferometer's position) into a scan file, one frame at a
time, with a reference stepping series cropped to the active area or the reference of another scan file."""
from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..io import Scan, SteppingReference, read_reference, write_scan
from .common import (
    _IMPORT_GROUP,
    _checked_output,
    _Counts,
    _describe,
    _gain,
    _pixel_size,
    _read_dark,
    _strings,
    nominal_steps,
)
from .formats import Series, StackImportError, _RawLayout, _size

log = logging.getLogger(__name__)

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
