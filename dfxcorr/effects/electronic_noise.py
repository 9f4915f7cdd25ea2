"""``electronic_noise``: additive noise of the detector's readout, independent of the signal (flat panels).

variance = g * (Ibar - dark) + sigma_e^2 (the paper's eq. 7 neglects sigma_e). Estimated with the gain from
the fit's residuals, where the expected counts are low it dominates, and from the readout of unlit rows where
the file holds it (:mod:`dfxcorr.effects.detector_gain`); tested with the gain profiled. Reported as sigma_e
in detector units; ``load.electronic`` holds sigma_e^2.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..catalogue import Effect
from .base import Context, EffectBase, Estimate, Finding, Hypothesis, Option, Policy, State, Test
from .detector_gain import NoiseEstimate, noise_fit


class ElectronicNoise(EffectBase[NoiseEstimate]):
    entry = Effect("electronic_noise", None, False, ("sigma_e",), 0.0, "none",
                   "additive readout noise of the detector: variance = g * (Ibar - dark) + sigma_e^2")
    # a variance floor that the photon term cannot take up: modelled before the gain is judged against it.
    # It changes the samples' relative weights, most where the counts are low, where a fit under the wrong noise
    # model is worst: its trial fits afresh (measured on a flat panel, sigma_e 25 at 2000 counts: from the
    # current parameters the refit stalls at reduced chi-square 4.4 with column and block signatures appearing,
    # afresh it reaches 0.86 with them gone); and its estimate from that fit's residuals is biased: one refit at
    # the estimate of the trial's own fit
    policy = Policy(order=1, noise_model=True, fresh_start=True, refinements=1)

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test[NoiseEstimate] | None:
        fit = noise_fit(ctx, state, flagged, readout=True)
        t = fit.partial_test({"electronic": state.obs.electronic})
        change = abs(t.payload.electronic - state.obs.electronic)
        # material where it moves the variance of a typical sample by more than the practical floor
        typical = float(np.median(fit.gain * fit.lit)) if fit.lit.size else 1.0
        return replace(t, explains=t.statistic, material=change > ctx.cfg["diagnose"]["min_gain_change"] * typical)

    def trial(self, ctx: Context, state: State, test: Test[NoiseEstimate]) -> Hypothesis:
        return state.hypothesis.but(noise=replace(state.hypothesis.noise, electronic=test.payload.profiled[1]))

    def accepted(self, ctx: Context, before: State, after: State, test: Test[NoiseEstimate]) -> Finding:
        variance = after.hypothesis.noise.electronic
        sigma = float(np.sqrt(variance))
        return Finding("all pixels, most where the expected counts are low (noise, not the mean)",
                       f"sigma_e = {sigma:.3g} counts", {"value": sigma},
                       options=(Option("load.electronic", f"{variance:.4g}"),))

    def measure(self, ctx: Context, state: State) -> Estimate | None:
        # the electronic variance these residuals ask for, the gain held at the model's (not the file's unlit
        # readout: every part of the detector would share it)
        g = state.hypothesis.noise.gain
        fit = noise_fit(ctx, state, state.hypothesis.motion)
        _, variance = fit.regression(gain=g)
        sigma = float(np.sqrt(variance))
        se_variance = fit.standard_error(False, (g, variance))
        # sigma_e from its variance (delta method), as the finding reports it
        return Estimate(np.asarray(sigma), np.asarray(se_variance / max(2 * sigma, 1e-300)))


EFFECT = ElectronicNoise()
