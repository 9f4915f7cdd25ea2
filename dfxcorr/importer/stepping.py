"""A phase-stepping recording (sample and reference series) into a scan file: ``spec/scan-format.md`` with A = H,
all positions 0 and ``scan/phase_step`` holding the nominal step phases."""
from __future__ import annotations

import numpy as np

from ..io import Scan, SteppingReference, write_scan
from .common import _IMPORT_GROUP, _checked_output, _describe, _gain, _pixel_size, _read_dark, _strings, nominal_steps
from .formats import StackImportError, _read_series, frame_dtype


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
