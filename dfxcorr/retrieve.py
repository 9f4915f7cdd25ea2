"""Stage 5, full-detector retrieval: t, v and phi of every pixel with the fitted per-frame parameters.

The images are the closed-form weighted least-squares solution (paper eqs. 8-10) over all pixels and
all frames. The weights start from the data (eq. 6) and are then taken from the model itself, which
removes the bias that data weights cause at low counts.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import engine as E
from . import kernels as K
from . import model as M
from .align import to_detector_rows
from .noise import pearson
from .observations import Observations


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
    chi2_sum : float
        That Pearson chi-square, summed over the used samples of the solved pixels.
    samples : int
        Those samples (the pixels are ``images.valid.sum()``): sums over blocks of pixels add up.
    """

    images: M.Images
    expected: np.ndarray
    weights: np.ndarray
    reduced_chi2: float
    chi2_sum: float = 0.0
    samples: int = 0


def retrieve(obs: Observations, params: dict, *, iterations: int = 2, n_frame_params: int | None = None,
             gain: float | None = None, keep_inverse: bool = False, keep_expected: bool = True,
             channels: M.Channels | None = None) -> Retrieval:
    """Solve the images for fixed effect parameters.

    Parameters
    ----------
    obs : Observations
        Samples with ``obs.use`` False (outside the region of interest) do not count.
    params : dict
        Effect parameters (see :func:`dfxcorr.catalogue.neutral_params`).
    iterations : int
        1: data weights (paper eq. 6); each further iteration takes the weights from the previous model.
    n_frame_params : int, optional
        Free per-frame and global parameters, subtracted from the degrees of freedom (default: the
        size of ``params``).
    gain : float, optional
        Overrides ``obs.gain`` in the noise weights.
    keep_inverse : bool
        Keep the inverse normal matrices of the last solve in the images (for leverages and Fisher information).
    keep_expected : bool
        Return the expected counts and weights; without them both are (0, C) and the pass writes nothing per
        sample (images and chi-square alone).
    channels : Channels, optional
        ``params``' channel values at ``obs``' columns (:func:`dfxcorr.model.channels`), where the caller holds them
        (the blocks of rows of one scan share them); default made here.

    Returns
    -------
    Retrieval
    """
    K.set_threads()
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames) if channels is None else channels
    out = E.retrieve(obs, ch, iterations=iterations, gain=gain, keep_inverse=keep_inverse,
                     keep_expected=keep_expected)
    images = M.Images(out["coef"], out["valid"], out["inverse"], out["coupling"])
    n_par = sum(np.size(p) for p in params.values()) if n_frame_params is None else n_frame_params
    chi2 = per_dof(out["chi2"], out["samples"], int(images.valid.sum()), n_par, 3)
    return Retrieval(images=images, expected=out["expected"], weights=out["weights"], reduced_chi2=chi2,
                     chi2_sum=float(out["chi2"]), samples=int(out["samples"]))


def reduced_chi2(obs: Observations, ibar: np.ndarray, valid: np.ndarray, *, n_params: int = 0,
                 gain: float | None = None, per_pixel_unknowns: int = 3) -> float:
    """Pearson chi-square per degree of freedom over the used samples of valid pixels.

    dof = samples - per_pixel_unknowns * pixels - n_params.
    """
    chi2, samples, pixels = chi2_sums(obs, ibar, valid, gain=gain)
    return per_dof(chi2, samples, pixels, n_params, per_pixel_unknowns)


def per_dof(chi2: float, samples: int, pixels: int, n_params: int, per_pixel_unknowns: int) -> float:
    """Chi-square per degree of freedom, dof = samples - per_pixel_unknowns * pixels - n_params (at least 1): of one
    retrieval, or of the summed chi-square, samples and pixels of several blocks of pixels."""
    return chi2 / max(samples - per_pixel_unknowns * pixels - n_params, 1)


def chi2_sums(obs: Observations, ibar: np.ndarray, valid: np.ndarray, *,
              gain: float | None = None) -> tuple[float, int, int]:
    """Pearson chi-square over the used samples of valid pixels, the number of those samples and pixels.

    Each is a sum over pixels, so the sums of row blocks give :func:`reduced_chi2` of the whole scan.
    """
    sel = obs.gather_valid(valid) & obs.use
    return float(pearson(obs, ibar, gain=gain)[sel].sum()), int(sel.sum()), int(valid.sum())


def image_values(images: M.Images) -> dict[str, np.ndarray]:
    """t, v, phi per held pixel (R, C), NaN where not solvable."""
    nan = np.where(images.valid, 1.0, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        return {"transmission": images.t * nan, "dark_field": images.v * nan, "differential_phase": images.phi * nan}


def image_maps(obs: Observations, images: M.Images) -> dict[str, np.ndarray]:
    """Detector images t, v, phi (H, W), NaN where a pixel was not lit or not solvable; where the samples read the
    images between rows (``beam_path``), as the detector-centred frame sees them (:func:`detector_rows`)."""
    maps = {k: obs.to_image(v) for k, v in image_values(images).items()}
    return detector_rows(maps, obs.reading.kappa) if obs.reading is not None and obs.reading.kappa else maps


def detector_rows(maps: dict[str, np.ndarray], kappa: float) -> dict[str, np.ndarray]:
    """Images each pixel sees with the active area centred on it, as a frame centred on the detector sees them
    (:func:`dfxcorr.align.to_detector_rows`): t, v, phi maps (H, W) in, the same out."""
    t, v, phi = maps["transmission"], maps["dark_field"], maps["differential_phase"]
    tcs = to_detector_rows(np.stack([t, t * v * np.cos(phi), t * v * np.sin(phi)], axis=-1), kappa)
    with np.errstate(divide="ignore", invalid="ignore"):
        return {"transmission": tcs[..., 0], "dark_field": np.hypot(tcs[..., 1], tcs[..., 2]) / tcs[..., 0],
                "differential_phase": np.arctan2(tcs[..., 2], tcs[..., 1])}

