"""Stage 3, motion-pixel masking (paper Sec. II-E).

Where part of the sample moves during the scan, its pixels' frames disagree with any static image and
the fit would blame the gratings. Such pixels are found before the vibration fit from the per-pixel
residual of a retrieval without per-frame terms (eq. 35) and left out of the vibration fit only.

Vibrations raise that residual too, in proportion to how strongly a pixel's fringe responds to a phase
change (t v vf tf)^2 / Ibar. The score therefore divides the per-pixel reduced residual by
1 + gamma q_i, with q_i that sensitivity and gamma fitted robustly over all pixels, so that bright,
strongly modulated pixels are not masked merely for showing the vibrations the fit is meant to find.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from . import model as M


def motion_statistics(obs: M.Observations, params: dict | None = None,
                      weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel reduced residual and fringe sensitivity, the two ingredients of :func:`motion_score`.

    Pixels are independent here, so row blocks of a scan can be evaluated separately and their
    statistics combined by :func:`score_from_statistics`.

    Parameters
    ----------
    obs : Observations
    params : dict, optional
        Effect parameters of the model to compare with (default: none, paper eq. 35).
    weights : ndarray, shape (K, C), optional
        Inverse noise variances; default from a retrieval with ``params``.

    Returns
    -------
    eps, q : ndarray, shape (R, C)
        Reduced weighted residual (n - 3 degrees of freedom) and the phase sensitivity
        (t v vf tf)^2 / Ibar per sample averaged over the pixel; NaN where the pixel could not be solved.
    """
    dsg = M.design(obs, params or {})
    if weights is None:
        w0 = M.noise_weights(obs, np.maximum(obs.counts, 1.0))
        weights = M.noise_weights(obs, M.expected(obs, dsg, M.solve_images(obs, dsg, w0)))
    images = M.solve_images(obs, dsg, weights)
    resid = obs.counts - M.expected(obs, dsg, images)
    n = obs.segment_sum((weights > 0).astype(float))
    with np.errstate(divide="ignore", invalid="ignore"):
        eps = obs.segment_sum(weights * resid ** 2) / (n - 3)
        amp = np.hypot(images.coef[..., 1], images.coef[..., 2])[obs.pixel]
        q = obs.segment_sum(weights * (amp * np.hypot(dsg.Bc, dsg.Bs)) ** 2) / n
    ok = images.valid & (n > 3) & np.isfinite(eps) & np.isfinite(q)
    return np.where(ok, eps, np.nan), np.where(ok, q, np.nan)


def score_from_statistics(eps: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Motion score eps / (1 + gamma q), gamma fitted robustly over all finite pixels (any array shape)."""
    ok = np.isfinite(eps) & np.isfinite(q)
    gamma = max(float(np.median((eps[ok] - 1.0) / np.maximum(q[ok], 1e-12))), 0.0) if np.any(ok) else 0.0
    with np.errstate(invalid="ignore"):
        return np.where(ok, eps / (1.0 + gamma * q), np.nan)


def motion_score(obs: M.Observations, params: dict | None = None, weights: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel residual relative to what noise and (unmodelled) vibrations explain.

    Parameters as :func:`motion_statistics`.

    Returns
    -------
    ndarray, shape (R, C)
        About 1 for consistent pixels (a reduced chi-square with n - 3 degrees of freedom), NaN where
        the pixel could not be solved.
    """
    return score_from_statistics(*motion_statistics(obs, params, weights))


def robust_threshold(score: np.ndarray, *, sigma: float) -> float:
    """median + sigma * 1.4826 * MAD of the finite scores."""
    s = score[np.isfinite(score)]
    med = np.median(s)
    return float(med + sigma * 1.4826 * np.median(np.abs(s - med)))


def mask_from_score(image: np.ndarray, *, threshold: float | None = None, sigma: float = 6.0,
                    dilate: int = 1) -> tuple[np.ndarray, float]:
    """Pixels of a motion-score image (H, W) above the threshold, grown by ``dilate``; and the threshold."""
    thr = robust_threshold(image, sigma=sigma) if threshold is None else float(threshold)
    moving = np.nan_to_num(image, nan=0.0) > thr
    if dilate > 0 and moving.any():
        moving = ndimage.binary_dilation(moving, iterations=dilate)
    return moving, thr


def motion_mask(obs: M.Observations, *, threshold: float | None = None, sigma: float = 6.0,
                dilate: int = 1) -> tuple[np.ndarray, np.ndarray, float]:
    """Pixels whose frames disagree beyond noise and vibrations.

    Parameters
    ----------
    obs : Observations
    threshold : float, optional
        Absolute threshold on the score; default :func:`robust_threshold` with ``sigma``.
    sigma : float
    dilate : int
        Grow the flagged region by this many pixels (its rim is partly affected too).

    Returns
    -------
    moving : ndarray of bool, shape (H, W)
        True where the pixel is left out of the vibration fit.
    score : ndarray, shape (H, W)
        The motion score (NaN where not computed).
    threshold : float
        The threshold used.
    """
    image = obs.to_image(motion_score(obs))
    moving, thr = mask_from_score(image, threshold=threshold, sigma=sigma, dilate=dilate)
    return moving, image, thr
