"""The outcome of a reconstruction, as handed from the pipeline to the export stage."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .catalogue import PAPER_MODEL, neutral_params
from .stats import chi2_quantile


def paper_params(params: dict, n_frames: int) -> dict:
    """The paper's three parameters (eq. 19) at their neutral values where ``params`` lacks them.

    Parameters
    ----------
    params : dict
        Effect name -> per-frame (J, n) or global (n,) parameters; every entry is kept.
    n_frames : int
        J.
    """
    return {**neutral_params(PAPER_MODEL, n_frames), **params}


#: Tail probability on each side beyond which a reduced chi-square is not noise: that of five standard deviations.
MISFIT_TAIL = 2.9e-7
#: The least factor by which a flagged reduced chi-square lies above 1 or below it: with millions of degrees of
#: freedom no model of real data holds to the noise's few thousandths, but twice or half the noise variance is a
#: wrong model or noise model (two frames swapped, a gain stated too high).
MISFIT_FACTOR = 2.0


def chi2_limits(dof: int) -> tuple[float, float]:
    """The reduced chi-square a right model with ``dof`` degrees of freedom may reach from noise alone: (low, high).

    The chi-square distribution's quantiles at :data:`MISFIT_TAIL` on each side (about 1 -+ 5 sqrt(2 / dof) for
    large dof), widened to at least [1 / :data:`MISFIT_FACTOR`, :data:`MISFIT_FACTOR`]; beyond either the model or
    its noise model is wrong (``dfxcorr diagnose`` says which).
    """
    dof = max(int(dof), 1)
    return (min(float(chi2_quantile(MISFIT_TAIL, dof)) / dof, 1 / MISFIT_FACTOR),
            max(float(chi2_quantile(MISFIT_TAIL, dof, upper=True)) / dof, MISFIT_FACTOR))


@dataclass
class Result:
    """Everything a reconstruction produced.

    Attributes
    ----------
    transmission, dark_field, differential_phase : ndarray, shape (H, W)
        t, v (1 = no scattering) and phi (rad); NaN where a pixel was never illuminated or was
        left out.
    params : dict
        Effect name -> estimated per-frame (J, n) or global (n,) parameters, gauge fixed.
    estimated : dict
        Effect name -> bool, False for parameters held at their neutral value.
    uncertainty : dict
        Effect name -> one-sigma uncertainty (same shape as ``params``).
    fit_mask : ndarray of uint8, shape (H, W)
        1 where the pixel entered the vibration fit.
    motion_mask : ndarray of uint8, shape (H, W)
        1 where the motion check flagged the pixel (left out of the fit).
    cost : ndarray
        Cost after each iteration of the fit.
    cost_stage : list of str
        Fit stage of each cost entry.
    reduced_chi2 : float
        Pearson chi-square per degree of freedom of the final model over all illuminated pixels.
    dof : int
        Its degrees of freedom (0 where not known).
    method : str
        Estimator used ('ml', 'alternating', 'correlation', 'none').
    config : dict
        The fully resolved configuration.
    provenance : dict
        program, version, date, command_line, input_file, input_sha256.
    uncorrected : dict, optional
        'transmission', 'dark_field', 'differential_phase' retrieved with neutral per-frame
        parameters (for previews and comparisons).
    timings : dict
        Stage name -> seconds.
    extra : dict
        Further named arrays worth keeping (written under /entry/dfxcorr/extra).
    pixel_size : tuple of float or None
        (y, x) pixel pitch of the images in m (the detector's), None where the scan does not record it.
    """

    transmission: np.ndarray
    dark_field: np.ndarray
    differential_phase: np.ndarray
    params: dict
    estimated: dict
    uncertainty: dict
    fit_mask: np.ndarray
    motion_mask: np.ndarray
    cost: np.ndarray
    cost_stage: list
    reduced_chi2: float
    method: str
    config: dict
    provenance: dict
    uncorrected: dict | None = None
    timings: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    pixel_size: tuple[float, float] | None = None
    dof: int = 0

    IMAGES = ("transmission", "dark_field", "differential_phase")

    def image(self, name: str) -> np.ndarray:
        """One of :attr:`IMAGES` by name."""
        return getattr(self, name)

    @property
    def misfit(self) -> bool:
        """True where the reduced chi-square lies outside what noise allows (:func:`chi2_limits`)."""
        lo, hi = chi2_limits(self.dof)
        return bool(self.dof > 0 and not lo <= self.reduced_chi2 <= hi)
