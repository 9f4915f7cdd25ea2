"""``detector_gain``: the noise is not Poisson in the file's units (variance g * mean + electronic noise)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from .. import model as M
from ..catalogue import Effect
from ..observations import Observations
from .base import Context, EffectBase, Hypothesis, State, Test, chi2_test


def noise_model(obs: Observations, ibar: np.ndarray, images: M.Images, dsg: M.Design,
                weights: np.ndarray, *, exclude: np.ndarray | None = None) -> dict:
    """Gain and electronic variance from the residuals: E[r^2 / (1 - h)] = g (Ibar - dark) + sigma_e^2.

    Squared residuals are divided by 1 - h (h the leverage of the sample in its pixel's image fit):
    fitting the images removes that share of each sample's variance. Weighted least squares with
    weights 1 / variance^2 (the variance of a squared Gaussian residual).

    Returns
    -------
    dict
        'gain', 'electronic', and the per-sample 'r2' (leverage-corrected), 'mean' (Ibar - dark) and
        current 'variance' of the used samples.
    """
    h = M.leverage(obs, dsg, images, weights)
    sel = obs.use & (h < 0.99)
    if exclude is not None:
        sel &= ~exclude
    r2 = ((obs.counts - ibar) ** 2 / (1 - h))[sel]
    # the photon variance per unit gain: the mean times the pixel's variance factor (pixel_noise)
    mu = (np.maximum(ibar - obs.dark, 1e-3) * obs.pixel_gain(1.0)[obs.pixel])[sel]
    v0 = M.variance(obs, ibar)[sel]
    w = 1.0 / v0 ** 2
    A = np.stack([mu, np.ones_like(mu)], axis=1) * np.sqrt(w)[:, None]
    (g, e), *_ = np.linalg.lstsq(A, r2 * np.sqrt(w), rcond=None)
    if e < 0:
        g, e = float(np.sum(w * mu * r2) / np.sum(w * mu * mu)), 0.0
    return {"gain": float(g), "electronic": float(e), "r2": r2, "mean": mu, "variance": v0}


def gain_test(obs: Observations, ibar: np.ndarray, images: M.Images, dsg: M.Design, weights: np.ndarray, *,
              exclude: np.ndarray | None = None) -> Test:
    """Likelihood-ratio test of the estimated noise model against the current one (Gaussian, 2 dof).

    ``exclude`` (K, C) bool: samples left out (pixels whose frames disagree: a localised misfit must not
    pose as a global variance excess). Payload: 'gain', 'electronic'.
    """
    fit = noise_model(obs, ibar, images, dsg, weights, exclude=exclude)
    r2, v0 = fit["r2"], fit["variance"]
    v1 = fit["gain"] * fit["mean"] + fit["electronic"]
    stat = max(float(np.sum(np.log(v0 / v1) + r2 / v0 - r2 / v1)), 0.0)
    return chi2_test(stat, 2, payload={"gain": fit["gain"], "electronic": fit["electronic"]})


class DetectorGain(EffectBase):
    entry = Effect("detector_gain", None, False, (), 1.0, "none",
                   "noise is not Poisson in the file's units: variance = g * mean (+ electronic noise)")
    role = "noise"
    tier = 1

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test | None:
        obs, rec = state.obs, state.rec
        dsg = M.design(obs, state.params)
        images = M.solve_images(obs, dsg, rec.weights, keep_inverse=True)
        t = gain_test(obs, rec.expected, images, dsg, rec.weights,
                      exclude=obs.pixel_mask(ndimage.binary_dilation(flagged)))
        # the per-frame parameters, fitted on every n-th column, leave their noise in the other columns'
        # residuals: about n chi-square per parameter, an apparent gain that a stated one must not be taken for
        d = ctx.cfg["diagnose"]
        n_par = sum(np.size(p) for p in state.params.values())
        apparent = obs.gain * (1 + d["subsample"] * n_par * state.reduced_chi2 / max(state.chi2, 1.0))
        return replace(t, material=abs(t.payload["gain"] / apparent - 1) > d["min_gain_change"])

    def trial(self, ctx: Context, state: State, test: Test) -> Hypothesis:
        return state.hypothesis.but(noise=replace(state.hypothesis.noise, gain=test.payload["gain"],
                                                  electronic=test.payload["electronic"]))

    def accepted(self, ctx: Context, before: State, after: State, test: Test) -> dict:
        return {"gain": test.payload["gain"], "electronic": test.payload["electronic"]}

    def where(self, test: Test, obs: Observations) -> str:
        return "all pixels (noise, not the mean)"

    def estimate(self, extra: dict, params: dict, good: np.ndarray) -> str:
        return f"g = {extra['gain']:.3f}, electronic sigma = {np.sqrt(extra['electronic']):.3g} counts"

    def settings(self, cfg: dict, final: Hypothesis, extra: dict | None, out_dir: Path) -> list[str]:
        return [f"load.gain={final.noise.gain:.4g}", f"load.electronic={final.noise.electronic:.4g}"] \
            if extra is not None else []


EFFECT = DetectorGain()
