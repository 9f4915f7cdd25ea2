"""Stage 2, flat-field alignment: the reference (interferometer coordinates) onto each frame's detector rows.

Pixel (r, c) sees the interferometer at local row u = r + 0.5 - position[j] and is lit iff 0 <= u < A
(``spec/scan-format.md``). Reference maps are sampled at u = k + 0.5 and interpolated linearly between
centres, extrapolated linearly over the outer half rows. The phase is unwrapped along u first: linear
interpolation of wrapped values would put a wrong phase into every sample near a wrap.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .errors import DfxcorrError
from .io import Reference, Scan, SteppingReference
from .model import Observations, lateral_coordinate

log = logging.getLogger(__name__)


class AlignmentError(DfxcorrError, ValueError):
    """No usable pixel, or a reference that cannot be aligned."""


def interpolate_rows(maps: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Linear interpolation of row-sampled maps at continuous local rows.

    Parameters
    ----------
    maps : ndarray, shape (A, W)
        Values at the row centres u = k + 0.5.
    u : ndarray, shape (K,)
        Local rows (0 <= u < A for lit samples); the outer half rows are extrapolated linearly.

    Returns
    -------
    ndarray, shape (K, W)
    """
    A = maps.shape[0]
    if A == 1:
        return np.repeat(maps, u.size, axis=0)
    f = np.asarray(u, dtype=np.float64) - 0.5
    k0 = np.clip(np.floor(f).astype(np.int64), 0, A - 2)
    a = (f - k0)[:, None]
    return (1.0 - a) * maps[k0] + a * maps[k0 + 1]


def lit_blocks(position: np.ndarray, active_rows: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All (row, frame) pairs in which a detector row is illuminated, sorted by row.

    Returns
    -------
    row, frame : ndarray of int, shape (K,)
    u : ndarray, shape (K,)
        Local interferometer row of each pair.
    """
    u = np.arange(height)[:, None] + 0.5 - np.asarray(position, dtype=np.float64)[None, :]
    row, frame = np.nonzero((u >= 0) & (u < active_rows))
    return row, frame, u[row, frame]


def build_observations(scan: Scan, reference: Reference, *, columns: np.ndarray | None = None,
                       min_frames: int = 3, pixel_mask: np.ndarray | None = None,
                       gain: float | None = None) -> Observations:
    """Align the flat field to every lit sample and collect the data as :class:`Observations`.

    Parameters
    ----------
    scan : Scan
    reference : Reference
        Flat-field maps (A, W); the phase may be wrapped.
    columns : ndarray of int, optional
        Detector columns to hold (default all).
    min_frames : int
        Rows lit in fewer frames than this (the number of per-pixel unknowns) are left out with a
        warning.
    pixel_mask : ndarray of bool, shape (H, W), optional
        False for pixels that must not enter (their samples get ``use = False``).
    gain : float, optional
        Overrides the file's detector gain.

    Returns
    -------
    Observations

    Raises
    ------
    AlignmentError
        If no row is lit in at least ``min_frames`` frames.
    """
    J, H, W = scan.shape
    A = reference.transmission.shape[0]
    cols = np.arange(W) if columns is None else np.asarray(columns, dtype=np.int64)
    row, frame, u = lit_blocks(scan.position, A, H)
    n_lit = np.bincount(row, minlength=H)
    short = (n_lit > 0) & (n_lit < min_frames)
    if np.any(short):
        log.warning("%d detector rows are lit in fewer than %d frames and are left out (rows %s)",
                    int(short.sum()), min_frames, _ranges(np.flatnonzero(short)))
        keep = n_lit[row] >= min_frames
        row, frame, u = row[keep], frame[keep], u[keep]
    if row.size == 0:
        raise AlignmentError(f"no detector row is lit in at least {min_frames} frames: nothing to fit "
                             f"(dataset /entry/scan/position)")
    assert scan.phase_step is not None and scan.dark is not None  # filled in by Scan.__post_init__
    phase = np.unwrap(reference.phase, axis=0)
    tf = interpolate_rows(reference.transmission[:, cols], u)
    vf = interpolate_rows(reference.visibility[:, cols], u)
    phif = interpolate_rows(phase[:, cols], u) + scan.phase_step[frame][:, None]
    counts = scan.data[frame[:, None], row[:, None], cols[None, :]].astype(np.float64)
    dark = scan.dark[row[:, None], cols[None, :]]
    use = np.ones(counts.shape, bool) if pixel_mask is None else pixel_mask[row[:, None], cols[None, :]]
    return Observations(counts=counts, tf=tf, vf=vf, phif=phif, dark=dark, use=use, row=row, frame=frame,
                        columns=cols, shape=(J, H, W), gain=scan.gain if gain is None else gain)


def stepping_observations(data: np.ndarray, phase_step: np.ndarray, *, dark: np.ndarray | None = None,
                          gain: float = 1.0) -> Observations:
    """Observations of a phase-stepping series of the unloaded interferometer (flat field 1, 1, 0).

    Parameters
    ----------
    data : ndarray, shape (S, A, W)
    phase_step : ndarray, shape (S,)
    dark : ndarray, shape (A, W), optional

    Returns
    -------
    Observations
        Fitting images to it gives t^f, v^f and phi^f of the series.
    """
    S, A, W = data.shape
    flat = Reference(np.ones((A, W)), np.ones((A, W)), np.zeros((A, W)))
    series = Scan(data=data, position=np.zeros(S), reference=flat, phase_step=np.asarray(phase_step, float),
                  dark=dark, gain=gain)
    return build_observations(series, flat)


@dataclass
class ReferenceFit:
    """Flat-field maps retrieved from a stepping series, with what the fit said about the steps.

    Attributes
    ----------
    reference : Reference
    params : dict
        Estimated per-step effects (phase_offset: step phase errors in rad, dose), empty when the
        nominal steps were taken as exact.
    reduced_chi2 : dict
        'nominal': Pearson chi-square per degree of freedom with the nominal steps; 'fitted': with the
        estimated step errors and dose (absent when not estimated). Over the modulated pixels.
    """

    reference: Reference
    params: dict
    reduced_chi2: dict


def fit_reference(ref: SteppingReference, *, gain: float = 1.0, effects: Sequence[str] = ("phase_offset", "dose"),
                  optional: Sequence[str] = ("dose",), min_visibility: float | str = "auto",
                  subsample: int = 4) -> ReferenceFit:
    """Flat-field maps from a stepping series, with per-step phase errors and dose estimated.

    The series is a phase-stepping recording of the unloaded interferometer: flat field 1, 1, 0 and the
    images are the maps. Step phase errors and dose fluctuations are per-frame effects of the same
    model, so the maximum-likelihood vibration fit estimates them. Per-step visibility loss is never
    identifiable here (paper Sec. II-F). Per-step dose is identifiable only where some pixels carry
    no fringe (outside the gratings): where every pixel is modulated, a dose modulation in step with
    the phase trades off exactly against the maps (see :mod:`dfxcorr.analysis.identify`). Unmodulated pixels
    therefore enter the step fit as dose monitors; the reduced chi-square is reported over the
    modulated ones.

    Parameters
    ----------
    ref : SteppingReference
    gain : float
    effects : sequence of str
        Per-step effects to estimate (phase_offset, tilt, dose); empty: nominal steps.
    optional : sequence of str
        Effects of ``effects`` to leave out (with a log line) where not identifiable; the others are
        refused with an error.
    min_visibility : float or 'auto'
        Pixels below this visibility carry no fringe (chi-square region).
    subsample : int
        Every n-th column enters the step fit.

    Returns
    -------
    ReferenceFit
        Visibility is clipped into (0, 1] (a noisy estimate can exceed 1).

    Raises
    ------
    AlignmentError
        If fewer than 3 steps are given, the steps do not determine a sinusoid, or a required effect is
        not identifiable.
    """
    from .analysis import identify
    from .fit import fit_vibrations, initial_weights
    from .retrieve import retrieve

    S = ref.data.shape[0]
    if S < 3:
        raise AlignmentError(f"/entry/reference/stepping/data has {S} steps; at least 3 are needed")
    unknown = [e for e in effects if e not in ("phase_offset", "tilt", "dose")]
    if unknown:
        raise AlignmentError(f"{', '.join(unknown)} cannot be estimated from a reference stepping series "
                             f"(not identifiable there, paper Sec. II-F)")
    obs = stepping_observations(ref.data, ref.phase_step, dark=ref.dark, gain=gain)
    nominal = retrieve(obs, {})
    if not np.any(nominal.images.valid):
        raise AlignmentError("/entry/reference/stepping/phase_step does not determine a sinusoid")
    vis = obs.to_image(nominal.images.v, fill=0.0)
    thr = auto_visibility_threshold(vis) if min_visibility == "auto" else float(min_visibility)
    roi = obs.subset(np.arange(obs.columns.size))
    roi.use = (np.nan_to_num(vis) >= thr)[obs.row][:, obs.columns]
    chi2 = {"nominal": retrieve(roi, {}).reduced_chi2}
    params, rec = {}, nominal
    fit_obs = obs.subset(subsample_columns(obs.columns.size, subsample))
    # unmodulated pixels (outside the gratings) have transmission as their only unknown: dose monitors
    fit_obs.vf = np.where(roi.use[:, fit_obs.columns], fit_obs.vf, 0.0)
    chosen: list[str] = []
    for verdict in identify.select(fit_obs, initial_weights(fit_obs, {}), effects if S > 3 else ()):
        if verdict.identifiable:
            chosen.append(verdict.name)
            continue
        why = (f"per-step {verdict.name} is not identifiable in this reference series ({verdict.excess} "
               f"direction(s) without information: every pixel is modulated, so it trades off against the maps)")
        if verdict.name not in optional:
            raise AlignmentError(why)
        log.info("%s; not fitted", why)
    if chosen:
        params = fit_vibrations(fit_obs, effects=chosen, staged=False, circmean_iterations=0).params
        rec = retrieve(obs, params)
        chi2["fitted"] = retrieve(roi, params).reduced_chi2
    images = rec.images
    t = np.where(images.valid, images.t, np.nan)
    v = images.v
    phase = images.phi
    bad = ~np.isfinite(t) | (t <= 0)
    if np.any(bad):
        log.warning("reference stepping series: %d pixels without usable signal", int(bad.sum()))
        t = np.where(bad, np.nanmedian(t[~bad]) if np.any(~bad) else 1.0, t)
    v = np.clip(np.nan_to_num(v, nan=1e-3), 1e-3, 1.0)
    return ReferenceFit(Reference(transmission=t, visibility=v, phase=phase), params, chi2)


def auto_visibility_threshold(visibility: np.ndarray) -> float:
    """A quarter of the 95th percentile of the reference visibility: splits fringe from no fringe.

    Outside the gratings and in detector gaps the visibility is noise (about 0.01); on the gratings it
    is tens of percent, so the split is wide and the factor uncritical.
    """
    v = np.asarray(visibility)[np.isfinite(visibility)]
    return 0.25 * float(np.percentile(v, 95)) if v.size else 0.0


def resolve_reference(scan: Scan, *, effects: Sequence[str] = ("phase_offset", "dose"),
                      optional: Sequence[str] = ("dose",)) -> Reference:
    """The scan's flat-field maps, retrieved from its stepping series if that is what it holds.

    Parameters
    ----------
    effects, optional : sequence of str
        Per-step effects of a reference stepping series to estimate (see :func:`fit_reference`).
    """
    if isinstance(scan.reference, SteppingReference):
        fitted = fit_reference(scan.reference, gain=scan.gain, effects=effects, optional=optional)
        log.info("flat field from the reference stepping series (%d steps): reduced chi-square %s",
                 scan.reference.data.shape[0], ", ".join(f"{k} {v:.4f}" for k, v in fitted.reduced_chi2.items()))
        if "phase_offset" in fitted.params:
            log.info("reference step phase errors (rad): %s",
                     np.array2string(fitted.params["phase_offset"][:, 0], precision=3))
        return fitted.reference
    return scan.reference


def subsample_columns(width: int, n: int, *, offset: int | None = None) -> np.ndarray:
    """Every n-th detector column (paper Sec. II-D.1), starting at ``offset`` (default n // 2)."""
    start = n // 2 if offset is None else offset
    if not 0 <= start < width:
        raise ValueError(f"column offset {start} outside the detector (0..{width - 1})")
    return np.arange(start, width, n)


def tilt_alias_period(width: int, n: int) -> float:
    """Tilt change (rad) to which the cost on every n-th column is blind: pi W / n (paper Sec. II-D.1).

    On columns spaced by n the lateral coordinate steps by 2n/W, so adding pi W / n to the tilt adds
    a multiple of 2 pi at every held column up to a constant that the phase offset absorbs.
    """
    return np.pi * width / n


def _ranges(idx: np.ndarray) -> str:
    if idx.size == 0:
        return ""
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.r_[idx[0], idx[breaks + 1]]
    ends = np.r_[idx[breaks], idx[-1]]
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in zip(starts, ends, strict=True))


__all__ = ["AlignmentError", "ReferenceFit", "auto_visibility_threshold", "build_observations", "fit_reference",
           "interpolate_rows", "lit_blocks", "resolve_reference", "stepping_observations", "subsample_columns",
           "tilt_alias_period", "lateral_coordinate"]
