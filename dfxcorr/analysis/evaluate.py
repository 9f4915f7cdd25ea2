"""Comparison with ground truth: vibration-parameter and image errors in the gauge of paper eq. 22."""
from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from ..align import gauge_frames, lit_blocks
from ..catalogue import effect, truth_keys

#: Result effect name -> truth key (shared truth files and the simulator use these keys).
TRUTH_KEYS = truth_keys()


def gauge_median(p: np.ndarray, good: np.ndarray, *, scale: bool) -> np.ndarray:
    """Remove the median (shift effects) or divide by it (scale effects) over the frames ``good``."""
    med = np.median(p[good])
    return p / med if scale else p - med


def frames_lighting(position: np.ndarray, active_rows: int, height: int, fraction: float = 0.5) -> np.ndarray:
    """The frames that set the gauge, from the scan's geometry (:func:`dfxcorr.align.gauge_frames` of the rows each
    frame lights, :func:`dfxcorr.align.lit_blocks`), shape (J,) bool."""
    frame = lit_blocks(position, active_rows, height)[1]
    return gauge_frames(np.bincount(frame, minlength=np.size(position)), fraction)


def _estimated(params: dict[str, Any], truth: dict[str, Any]) -> Iterator[tuple[str, np.ndarray, np.ndarray, bool]]:
    """Each per-frame effect that has a truth key: its name, estimate and truth (J,), and whether its gauge is a
    scale (else a shift)."""
    for name, key in TRUTH_KEYS.items():
        if name in params and key in truth:
            yield (name, np.asarray(params[name], dtype=float)[:, 0], np.asarray(truth[key], dtype=float),
                   effect(name).gauge == "scale")


def _gauged_errors(params: dict[str, Any], truth: dict[str, Any], good: np.ndarray) -> dict[str, np.ndarray]:
    """Estimate - truth of each per-frame effect that has a truth key, each first put in the median gauge over the
    frames ``good`` (:func:`gauge_median`), shape (J,)."""
    return {name: gauge_median(est, good, scale=scale) - gauge_median(tru, good, scale=scale)
            for name, est, tru, scale in _estimated(params, truth)}


def vibration_rmse(params: dict[str, Any], truth: dict[str, Any], good: np.ndarray) -> dict[str, float]:
    """RMSE of each per-frame effect against the truth over ``good`` frames, both in the median gauge."""
    return {name: float(np.sqrt(np.mean(err[good] ** 2))) for name, err in _gauged_errors(params, truth, good).items()}


def _aligned_errors(params: dict[str, Any], truth: dict[str, Any], good: np.ndarray) -> dict[str, np.ndarray]:
    """Estimate - truth of each per-frame effect that has a truth key, the truth carried into the estimate's gauge by
    the median over the frames ``good`` of their difference (shift effects) or ratio (scale effects), shape (J,).

    Not each put in its own median gauge (:func:`_gauged_errors`): the errors are far smaller than the spread of
    the values, so both medians fall on the same frame and that frame's error would be subtracted from every other
    (doubling the variance of the errors the standard errors describe)."""
    out = {}
    for name, est, tru, scale in _estimated(params, truth):
        if scale:
            with np.errstate(divide="ignore", invalid="ignore"):
                out[name] = est - np.median((est / tru)[good]) * tru
        else:
            out[name] = est - tru - np.median((est - tru)[good])
    return out


def vibration_pulls(params: dict[str, Any], uncertainty: dict[str, Any], truth: dict[str, Any], good: np.ndarray
                    ) -> dict[str, float]:
    """RMS of (estimate - truth) / reported standard error of each per-frame effect over the ``good`` frames whose
    error is finite and positive, the truth in the estimate's gauge (:func:`_aligned_errors`; 1 where the reported
    errors are right)."""
    out = {}
    for name, err in _aligned_errors(params, truth, good).items():
        if name not in uncertainty:
            continue
        se = np.asarray(uncertainty[name])[:, 0]
        ok = good & np.isfinite(se) & (se > 0)
        out[name] = float(np.sqrt(np.mean((err[ok] / se[ok]) ** 2)))
    return out


def image_rmse(images: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """RMSE of t, v and phi (phase wrapped to (-pi, pi]) against the truth over finite pixels."""
    out = {}
    for name in ("transmission", "dark_field", "differential_phase"):
        a, b = np.asarray(images[name], float), np.asarray(truth[f"image_{name}"], float)
        ok = np.isfinite(a) & np.isfinite(b)
        d = a[ok] - b[ok]
        if name == "differential_phase":
            d = np.angle(np.exp(1j * d))
        out[name] = float(np.sqrt(np.mean(d ** 2)))
    return out
