"""The flat field of a scan: given maps, or retrieved from a reference stepping series by the vibration fit.

A stepping series of the unloaded interferometer is a phase-stepping recording whose images are the
flat-field maps; its per-step phase errors and dose are per-frame effects of the one model, so the
maximum-likelihood fit (:mod:`dfxcorr.fit`) estimates them. This module sits after the fit and the
retrieval in the import order; the alignment stage only consumes the maps it returns.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import DTypeLike

from . import config as C
from . import identify
from .align import AlignmentError, build_observations, subsample_columns
from .catalogue import effect
from .fit import fit_vibrations
from .io import FrameSource, Reference, Scan, SteppingReference
from .observations import Observations
from .retrieve import retrieve

log = logging.getLogger(__name__)


def stepping_observations(data: FrameSource, phase_step: np.ndarray, *, dark: np.ndarray | None = None,
                          gain: float = 1.0, dtype: DTypeLike = np.float64) -> Observations:
    """Observations of a phase-stepping series of the unloaded interferometer (flat field 1, 1, 0).

    Parameters
    ----------
    data : ndarray or FrameSource, shape (S, A, W)
    phase_step : ndarray, shape (S,)
    dark : ndarray, shape (A, W), optional
    gain : float
    dtype : numpy dtype
        Of the sample arrays (:meth:`dfxcorr.align.LitStore.observations`).

    Returns
    -------
    Observations
        Fitting images to it gives t^f, v^f and phi^f of the series.
    """
    S, A, W = data.shape
    flat = Reference(np.ones((A, W)), np.ones((A, W)), np.zeros((A, W)))
    series = Scan(data=data, position=np.zeros(S), reference=flat, phase_step=np.asarray(phase_step, float),
                  dark=dark, gain=gain)
    return build_observations(series, flat, dtype=dtype)


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


def fit_reference(ref: SteppingReference, *, gain: float = 1.0, effects=None, optional=None,
                  min_visibility: float | str = "auto", subsample: int = 4) -> ReferenceFit:
    """Flat-field maps from a stepping series, with per-step phase errors and dose estimated.

    The series is a phase-stepping recording of the unloaded interferometer: flat field 1, 1, 0 and the
    images are the maps. Step phase errors and dose fluctuations are per-frame effects of the same
    model, so the maximum-likelihood vibration fit estimates them. Per-step visibility loss is never
    identifiable here (paper Sec. II-F). Per-step dose is identifiable only where some pixels carry
    no fringe (outside the gratings): where every pixel is modulated, a dose modulation in step with
    the phase trades off exactly against the maps (see :mod:`dfxcorr.identify`). Unmodulated pixels
    therefore enter the step fit as dose monitors; the reduced chi-square is reported over the
    modulated ones.

    Parameters
    ----------
    ref : SteppingReference
    gain : float
    effects : sequence of str, optional
        Per-step effects to estimate (e.g. phase_offset, tilt, dose); empty: nominal steps. Default: those of
        the default configuration (:func:`dfxcorr.config.reference_effects`).
    optional : sequence of str, optional
        Effects of ``effects`` to leave out (with a log line) where not identifiable; the others are
        refused with an error. Default: as ``effects``.
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
    asked, maybe = C.reference_effects(C.defaults())
    effects, optional = asked if effects is None else effects, maybe if optional is None else optional
    S = ref.data.shape[0]
    if S < 3:
        raise AlignmentError(f"/entry/reference/stepping/data has {S} steps; at least 3 are needed")
    # the flat field is the same in every step: a per-step visibility trades off against the maps
    unsupported = [e for e in effects if effect(e).channel == "visibility"]
    if unsupported:
        raise AlignmentError(f"{', '.join(unsupported)} cannot be estimated from a reference stepping series "
                             f"(not identifiable there, paper Sec. II-F)")
    # float32 as the scan's own reconstruction: the kernels compile for one dtype per run
    obs = stepping_observations(ref.data, ref.phase_step, dark=ref.dark, gain=gain, dtype=np.float32)
    nominal = retrieve(obs, {})
    if not np.any(nominal.images.valid):
        raise AlignmentError("/entry/reference/stepping/phase_step does not determine a sinusoid")
    vis = obs.to_image(nominal.images.v, fill=0.0)
    thr = auto_visibility_threshold(vis) if min_visibility == "auto" else float(min_visibility)
    roi = replace(obs, use=obs.pixel_mask(np.nan_to_num(vis) >= thr))
    chi2 = {"nominal": retrieve(roi, {}).reduced_chi2}
    params, rec = {}, nominal
    fit_obs = obs.subset(subsample_columns(obs.columns.size, subsample))
    # unmodulated pixels (outside the gratings) have transmission as their only unknown: dose monitors
    fit_obs = fit_obs.keep_fringe(roi.use[:, fit_obs.columns])
    chosen: list[str] = []
    for verdict in identify.select(fit_obs, effects if S > 3 else ()):
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


def resolve_reference(scan: Scan, *, effects=None, optional=None) -> Reference:
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


__all__ = ["ReferenceFit", "auto_visibility_threshold", "fit_reference", "resolve_reference",
           "stepping_observations"]
