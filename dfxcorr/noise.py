"""The noise model: the variance of a sample, its Pearson residual and the weights of the fits.

variance = f_i * g * (Ibar - dark) + sigma_e^2: scaled Poisson noise of the photons (g detector units per
photon, f_i the pixel's variance factor, ``pixel_noise``) plus the detector's electronic noise.
"""
from __future__ import annotations

import numpy as np

from .observations import Observations


def variance(obs: Observations, ibar: np.ndarray, *, gain: float | None = None, floor: float = 1e-3) -> np.ndarray:
    """Noise variance of each sample, f g (Ibar - dark) + electronic (f g: :meth:`Observations.pixel_gain`), (K, C)."""
    g: np.ndarray | float = obs.gain if gain is None else gain
    if obs.noise is not None or obs.offset_noise is not None:
        g = obs.pixel_gain(gain)[obs.pixel]
    return g * np.maximum(ibar - obs.dark, floor) + obs.electronic


def pearson(obs: Observations, ibar: np.ndarray, *, gain: float | None = None,
            floor: float = 1e-3) -> np.ndarray:
    """Pearson residual squared (I - Ibar)^2 / variance per sample, shape (K, C)."""
    return (obs.counts - ibar) ** 2 / variance(obs, ibar, gain=gain, floor=floor)


def noise_weights(obs: Observations, ibar: np.ndarray, *, gain: float | None = None,
                  floor: float = 1.0) -> np.ndarray:
    """Inverse noise variance of the used samples (shot noise floored at ``floor`` counts), 0 elsewhere."""
    return np.where(obs.use, 1.0 / variance(obs, ibar, gain=gain, floor=floor), 0.0)
