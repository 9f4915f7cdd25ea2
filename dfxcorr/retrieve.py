"""Stage 5, full-detector retrieval: t, v and phi of every pixel with the fitted per-frame parameters.

The images are the closed-form weighted least-squares solution (paper eqs. 8-10) over all pixels and
all frames. The weights start from the data (eq. 6) and are then taken from the model itself, which
removes the bias that data weights cause at low counts.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import model as M


@dataclass
class Retrieval:
    """Images of the pixels held in the observations, and how well the model fits them.

    Attributes
    ----------
    images : Images
    expected : ndarray, shape (K, C)
        Model counts.
    weights : ndarray, shape (K, C)
        Inverse noise variances of the last solve.
    reduced_chi2 : float
        Pearson chi-square per degree of freedom over the solved pixels.
    """

    images: M.Images
    expected: np.ndarray
    weights: np.ndarray
    reduced_chi2: float


def retrieve(obs: M.Observations, params: dict, *, iterations: int = 2, n_frame_params: int | None = None,
             gain: float | None = None) -> Retrieval:
    """Solve the images for fixed effect parameters.

    Parameters
    ----------
    obs : Observations
        Samples with ``obs.use`` False (outside the region of interest) do not count.
    params : dict
        Effect parameters (see :func:`dfxcorr.model.neutral_params`).
    iterations : int
        1: data weights (paper eq. 6); each further iteration takes the weights from the previous model.
    n_frame_params : int, optional
        Free per-frame and global parameters, subtracted from the degrees of freedom (default: the
        size of ``params``).
    gain : float, optional
        Overrides ``obs.gain`` in the noise weights.

    Returns
    -------
    Retrieval
    """
    dsg = M.design(obs, params)
    g = obs.gain if gain is None else gain
    weights = M.noise_weights(obs, obs.counts, gain=g)
    for it in range(iterations):
        images = M.solve_images(obs, dsg, weights)
        ibar = M.expected(obs, dsg, images)
        if it + 1 < iterations:
            weights = M.noise_weights(obs, ibar, gain=g)
    n_par = sum(np.size(p) for p in params.values()) if n_frame_params is None else n_frame_params
    chi2 = reduced_chi2(obs, ibar, images.valid, n_params=n_par, gain=g)
    return Retrieval(images=images, expected=ibar, weights=weights, reduced_chi2=chi2)


def reduced_chi2(obs: M.Observations, ibar: np.ndarray, valid: np.ndarray, *, n_params: int = 0,
                 gain: float | None = None, per_pixel_unknowns: int = 3) -> float:
    """Pearson chi-square per degree of freedom over the used samples of valid pixels.

    dof = samples - per_pixel_unknowns * pixels - n_params.
    """
    chi2, samples, pixels = chi2_sums(obs, ibar, valid, gain=gain)
    dof = samples - per_pixel_unknowns * pixels - n_params
    return chi2 / max(dof, 1)


def chi2_sums(obs: M.Observations, ibar: np.ndarray, valid: np.ndarray, *,
              gain: float | None = None) -> tuple[float, int, int]:
    """Pearson chi-square over the used samples of valid pixels, the number of those samples and pixels.

    Each is a sum over pixels, so the sums of row blocks give :func:`reduced_chi2` of the whole scan.
    """
    sel = valid[obs.pixel] & obs.use
    return float(M.pearson(obs, ibar, gain=gain)[sel].sum()), int(sel.sum()), int(valid.sum())


def image_values(images: M.Images) -> dict[str, np.ndarray]:
    """t, v, phi per held pixel (R, C), NaN where not solvable."""
    nan = np.where(images.valid, 1.0, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        return {"transmission": images.t * nan, "dark_field": images.v * nan, "differential_phase": images.phi * nan}


def image_maps(obs: M.Observations, images: M.Images) -> dict[str, np.ndarray]:
    """Detector images t, v, phi (H, W), NaN where a pixel was not lit or not solvable."""
    return {k: obs.to_image(v) for k, v in image_values(images).items()}
