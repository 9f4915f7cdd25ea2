"""The noise model: the variance of a sample, its Pearson residual and the weights of the fits.

variance = f_i * g * (Ibar - dark) + sigma_e^2: scaled Poisson noise of the photons (g detector units per
photon, f_i the pixel's variance factor, ``pixel_noise``; dark the detector's own, not known unmodulated photons
such as scatter: :meth:`~dfxcorr.observations.Observations.photons`) plus the detector's electronic noise.

One variance serves the chi-square and the weights alike (and the compiled retrieval, :mod:`dfxcorr.kernels`):
the photon term is taken at least at one count (:data:`MIN_SIGNAL`), so a sample whose expected count is at
the dark level is neither weighted infinitely nor a 1e5 outlier when the electronic noise is not modelled
(before, the chi-square took 1e-3 counts and the weights one).
"""
from __future__ import annotations

import numpy as np

from .observations import Observations

#: The least photon signal (detector units, :meth:`Observations.photons`) whose noise the variance counts.
MIN_SIGNAL = 1.0


def variance(obs: Observations, ibar: np.ndarray, *, gain: float | None = None) -> np.ndarray:
    """Noise variance of each sample, f g max(photons, 1) + electronic (f g: :meth:`Observations.pixel_gain`; the
    photon signal Ibar minus the detector's dark: :meth:`Observations.photons`)."""
    return obs.sample_gain(gain) * np.maximum(obs.photons(ibar), MIN_SIGNAL) + obs.electronic


def pearson(obs: Observations, ibar: np.ndarray, *, gain: float | None = None) -> np.ndarray:
    """Pearson residual squared (I - Ibar)^2 / variance per sample, shape (K, C)."""
    return (obs.counts - ibar) ** 2 / variance(obs, ibar, gain=gain)


def noise_weights(obs: Observations, ibar: np.ndarray, *, gain: float | None = None) -> np.ndarray:
    """Inverse noise variance of the used samples, 0 elsewhere."""
    return np.where(obs.use, 1.0 / variance(obs, ibar, gain=gain), 0.0)
