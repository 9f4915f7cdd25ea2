"""The outcome of a reconstruction, as handed from the pipeline to the export stage."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import model as M


def paper_params(params: dict, n_frames: int) -> dict:
    """The paper's three parameters (eq. 19) at their neutral values where ``params`` lacks them.

    Parameters
    ----------
    params : dict
        Effect name -> per-frame (J, n) or global (n,) parameters; every entry is kept.
    n_frames : int
        J.
    """
    return {**M.neutral_params(M.PAPER_MODEL, n_frames), **params}


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

    IMAGES = ("transmission", "dark_field", "differential_phase")

    def image(self, name: str) -> np.ndarray:
        """One of :attr:`IMAGES` by name."""
        return getattr(self, name)
