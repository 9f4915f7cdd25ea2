"""``detector_gain``: the noise is not Poisson in the file's units (variance g * mean + electronic noise).

The noise model's two parameters, the gain g and the electronic variance sigma_e^2, are estimated together
from the fit's residuals (:func:`noise_model`); each is tested with the other profiled (a partial
likelihood-ratio test, 1 dof), so that a gain error is not named electronic noise nor the other way round.
The electronic variance's test also reads the readout of rows that no frame lights near then, where the file
holds it (:func:`unlit_readout`: a direct measurement of sigma_e^2). The gain's does not: with sigma_e^2
pinned by them, the lit residuals' small bias at low counts (2.6 % below the stated noise on a clean flat
panel at ~40 photons and read noise 25, where a nonlinear fit takes more than its linear leverage) would all
be put on the gain (g = 0.42 where the truth is 1). This module tests the gain; :mod:`dfxcorr.effects.electronic_noise`
the electronic variance.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from .. import model as M
from ..catalogue import Effect
from ..io import Scan, frame_rows, lit_rows
from ..noise import MIN_SIGNAL, variance
from ..observations import Observations
from ..preparation import Prepared
from .base import (
    Consistency,
    Context,
    EffectBase,
    Estimate,
    Finding,
    Hypothesis,
    Option,
    Policy,
    State,
    Test,
    chi2_test,
)
from .residuals import image_leverage, line_consistency, pixel_chi2

#: The least gain the regression returns (detector units per photon): a variance needs a photon term.
MIN_GAIN = 1e-6


@dataclass(frozen=True)
class NoiseEstimate:
    """A noise model's test payload: the gain and electronic variance fitted together, and the tested parameter's
    estimate with the other at its current value (``profiled``: gain, electronic variance)."""

    gain: float
    electronic: float
    profiled: tuple[float, float]


@dataclass(frozen=True)
class NoiseFit:
    """Leverage-corrected squared residuals of the used samples and the noise models fitted to them.

    Attributes
    ----------
    r2, mean, variance : ndarray, shape (N,)
        (I - Ibar)^2 / (1 - h), the photon signal per unit gain (:meth:`Observations.photons` times the pixel's
        factor) and the current variance of each sample.
    gain, electronic : float
        The current noise model.
    joint : (float, float)
        Gain and electronic variance fitted together.
    readout : int
        How many of the samples, the last ones, are unlit readout (:func:`unlit_readout`).
    """

    r2: np.ndarray
    mean: np.ndarray
    variance: np.ndarray
    gain: float
    electronic: float
    joint: tuple[float, float]
    readout: int = 0

    @property
    def lit(self) -> np.ndarray:
        """``mean`` of the lit samples."""
        return self.mean[:self.mean.size - self.readout]

    def and_readout(self, readout: np.ndarray) -> NoiseFit:
        """The same with unlit readout (:func:`unlit_readout`, (N,)) added: samples whose photon signal is known to
        be nil, E[r^2] = sigma_e^2 exactly (the model's floor of :data:`dfxcorr.noise.MIN_SIGNAL`, there for
        expected counts that a fit puts at or below the dark, does not apply: taken at one count, a read noise of 1
        would be indistinguishable from none). Their regression weight is that of the current electronic variance, or of
        one count where it is nil."""
        if not readout.size:
            return self
        weight_at = self.electronic or self.gain * MIN_SIGNAL
        fit = NoiseFit(np.concatenate([self.r2, readout ** 2]), np.concatenate([self.mean, np.zeros(readout.size)]),
                       np.concatenate([self.variance, np.full(readout.size, weight_at)]), self.gain, self.electronic,
                       self.joint, self.readout + readout.size)
        return replace(fit, joint=fit.regression())

    def regression(self, *, gain: float | None = None, electronic: float | None = None) -> tuple[float, float]:
        """(g, sigma_e^2) fitted to E[r2] = g mean + sigma_e^2, either held where given; g > 0, sigma_e^2 >= 0.

        Weighted least squares with weights 1 / variance^2 (the variance of a squared Gaussian residual).
        """
        w = 1.0 / self.variance ** 2
        if gain is not None:
            return gain, max(float(np.sum(w * (self.r2 - gain * self.mean)) / np.sum(w)), 0.0)
        if electronic is not None:
            return max(float(np.sum(w * self.mean * (self.r2 - electronic)) / np.sum(w * self.mean ** 2)),
                       MIN_GAIN), electronic
        A = np.stack([self.mean, np.ones_like(self.mean)], axis=1) * np.sqrt(w)[:, None]
        (g, e), *_ = np.linalg.lstsq(A, self.r2 * np.sqrt(w), rcond=None)
        if e < 0:
            return self.regression(electronic=0.0)
        if g < MIN_GAIN:
            return self.regression(gain=MIN_GAIN)
        return float(g), float(e)

    def deviance(self, gain: float, electronic: float) -> float:
        """-2 log-likelihood of the residuals under a noise model (Gaussian), up to a constant."""
        # unlit readout has no photon term: with no electronic variance either, its spread is impossible (an infinite
        # deviance, not a warning)
        v = np.maximum(gain * self.mean + electronic, 1e-300)
        with np.errstate(over="ignore"):
            return float(np.sum(np.log(v) + self.r2 / v))

    def partial_test(self, held: dict[str, float]) -> Test[NoiseEstimate]:
        """Likelihood ratio of the joint noise model against the current one with only ``held`` (the parameter
        tested, at its current value) fixed and the other refitted; 1 dof."""
        g1, e1 = self.joint
        null = self.regression(**held)
        stat = max(self.deviance(*null) - self.deviance(g1, e1), 0.0)
        other = {"electronic": self.electronic} if "gain" in held else {"gain": self.gain}
        return chi2_test(stat, 1, NoiseEstimate(g1, e1, self.regression(**other)))

    def standard_error(self, gain: bool, at: tuple[float, float]) -> float:
        """The standard error of the gain (``gain``) or of the electronic variance with the other held, at the
        noise model ``at``: the inverse of the Fisher information of the squared residuals' regression (each a
        Gaussian variance, information 1 / (2 v^2) per sample)."""
        v = np.maximum(at[0] * self.mean + at[1], 1e-12)
        x = self.mean if gain else np.ones_like(self.mean)
        info = float(np.sum(x ** 2 / (2 * v ** 2)))
        return 1.0 / np.sqrt(info) if info > 0 else np.inf


#: Frames, and rows on each side of the lit band, whose unlit readout :func:`unlit_readout` reads: a sample of the
#: file, not all of it (a clinical scan's unlit rows are most of its 4 GB).
UNLIT_FRAMES, UNLIT_ROWS = 16, 16


def unlit_readout(scan: Scan, *, frames: int = UNLIT_FRAMES, rows: int = UNLIT_ROWS) -> np.ndarray:
    """Readout noise of rows that no frame lights near then, where the file holds their readout (a flat panel).

    From up to ``frames`` evenly spread frames that light rows, up to ``rows`` contiguous rows on either side of the
    lit band, at least half the band's height (and 4 rows) away from the rows lit (:func:`dfxcorr.io.lit_rows`) in
    that frame and the three before it (the detector lag of rows just left). Each row's mean is taken out (a row
    offset, line noise or a dark-map error, is no readout noise; the W / (W - 1) makes up for the mean), so the
    values' mean square estimates sigma_e^2 whatever the dark map's row levels say: the readout's noise as
    recorded, integer rounding included (1/12 count^2, which every sample carries). A pixel-by-pixel error of
    the dark map would count as read noise here (differences of frames would cancel it; not done). Rows read
    as all zeros were not read out (the format lets a writer leave them unallocated).

    Parameters
    ----------
    scan : Scan
    frames : int
        Most frames read.
    rows : int
        Most rows read on each side of a frame's lit band.

    Returns
    -------
    ndarray, shape (N,)
        Counts minus dark minus their row's mean (detector units); empty for a phase-stepping recording or a
        file without unlit readout.
    """
    J, H, W = scan.shape
    A = scan.active_rows
    if scan.is_stepping or W < 2 or J == 0:
        return np.zeros(0)
    margin = max(4, A // 2)
    bounds = lit_rows(scan.position, A, H)
    out = []
    for j in np.unique(np.linspace(0, J - 1, min(frames, J)).round().astype(int)):
        recent = bounds[max(j - 3, 0):j + 1]
        recent = recent[recent[:, 1] > recent[:, 0]]
        if not recent.size:
            continue
        top, bottom = int(recent[:, 0].min()) - margin, int(recent[:, 1].max()) + margin
        for a, b in ((max(top - rows, 0), max(top, 0)), (min(bottom, H), min(bottom + rows, H))):
            if b - a < 1:
                continue
            block = frame_rows(scan.data, j, a, b).astype(np.float64)
            read = np.any(block, axis=1)
            if not read.any():
                continue
            dev = (block - np.asarray(scan.dark)[a:b])[read]
            out.append(((dev - dev.mean(axis=1, keepdims=True)) * np.sqrt(W / (W - 1))).ravel())
    return np.concatenate(out) if out else np.zeros(0)


def noise_model(obs: Observations, ibar: np.ndarray, h: np.ndarray, *, exclude: np.ndarray | None = None
                ) -> NoiseFit:
    """The noise model fitted to the residuals: E[r^2 / (1 - h)] = g photons + sigma_e^2 (:meth:`Observations.photons`).

    Squared residuals are divided by 1 - h (h (K, C) the leverage of the sample in the fit: its pixel's images,
    and the per-frame parameters where they were fitted on these samples): the fit removes that share of each
    sample's variance. ``exclude`` (K, C) bool: samples left out (pixels whose frames disagree: a localised
    misfit must not pose as a global variance excess).
    """
    sel = obs.use & (h < 0.99)
    if exclude is not None:
        sel &= ~exclude
    r2 = (obs.counts - ibar)[sel] ** 2 / (1 - h[sel])
    # the photon variance per unit gain: the mean times the pixel's variance factor (pixel_noise)
    mu = (np.maximum(obs.photons(ibar), MIN_SIGNAL) * obs.sample_gain(1.0))[sel]
    fit = NoiseFit(r2, mu, variance(obs, ibar)[sel], obs.gain, obs.electronic, (obs.gain, obs.electronic))
    return replace(fit, joint=fit.regression())


def state_noise(state: State, flagged: np.ndarray) -> NoiseFit:
    """The noise model fitted to the fit ``state``'s residuals on its own columns, the pixels ``flagged`` (H, W)
    (and their rim) left out."""
    obs, params, rec = state.fit_obs, state.params, state.fit_rec
    dsg = M.design(obs, params)
    w = np.where(obs.use & obs.gather_valid(rec.images.valid), rec.weights, 0.0)
    h = image_leverage(state) + M.frame_leverage(obs, dsg, rec.images, w, params)[0]
    return noise_model(obs, rec.expected, h, exclude=obs.pixel_mask(ndimage.binary_dilation(flagged)))


def scan_readout(prep: Prepared) -> np.ndarray:
    """The unlit readout of a prepared scan's file (:func:`unlit_readout`)."""
    return unlit_readout(prep.scan)


def noise_fit(ctx: Context, state: State, flagged: np.ndarray, *, readout: bool = False) -> NoiseFit:
    """The noise model of the fit ``state`` on its own columns (:func:`state_noise`, once per state); with
    ``readout``, the unlit readout of the scan's file joins it (:meth:`NoiseFit.and_readout`).

    On the fit's columns the share of each sample's noise that the per-frame parameters took is known (their
    leverage); on the others their estimation noise adds variance that would read as a gain (measured: a flat
    panel with its read noise stated, fitted on every 4th column, gave g = 1.056 from every column, nothing on
    every column fitted).
    """
    fit = state.cached(state_noise, flagged)
    return fit.and_readout(ctx.cached(scan_readout, state.hypothesis)) if readout else fit


class DetectorGain(EffectBase[NoiseEstimate]):
    entry = Effect("detector_gain", None, False, (), 1.0, "none",
                   "noise is not Poisson in the file's units: variance = g * mean (+ electronic noise)")
    policy = Policy(noise_model=True)

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test[NoiseEstimate] | None:
        t = noise_fit(ctx, state, flagged).partial_test({"gain": state.obs.gain})
        return replace(t, explains=t.statistic,
                       material=abs(t.payload.gain / state.obs.gain - 1) > ctx.cfg["diagnose"]["min_gain_change"])

    def trial(self, ctx: Context, state: State, test: Test[NoiseEstimate]) -> Hypothesis:
        # with electronic noise in the model (stated or found) both are refitted together: an electronic variance
        # estimated under the wrong gain is off by what the gain's error left at low counts
        g, e = ((test.payload.gain, test.payload.electronic) if state.obs.electronic > 0
                else test.payload.profiled)
        return state.hypothesis.but(noise=replace(state.hypothesis.noise, gain=g, electronic=e))

    def consistency(self, ctx: Context, before: State, state: State) -> Consistency | None:
        # a gain scales the variance of every pixel alike: its change must be one factor along the detector's rows
        # and columns (:func:`line_consistency` with all pixels one class). The variance excess of a moving patch
        # (sample motion below its per-pixel detection limit) raised the gain by 3.1 % where it was 1, the strata by
        # row asking for -0.70, -0.74, 1.31, 6.85, -0.59, -0.12 times that change (a true 1.05: 0.77 ... 1.24).
        # The change is that of the variance, pooled over the pixels: the trial may refit the electronic noise with
        # the gain, so the gain's ratio alone is not it (a gain moved by 0.5 % would make its strata's noise a
        # spread of 1)
        X, dof, before_total = pixel_chi2(state.obs, state.params, state.rec.images, under=before.hypothesis.noise)
        f = before_total / max(float(X.sum()), 1e-300)
        return line_consistency(np.where(dof > 0, f, 1.0), X, dof)

    def accepted(self, ctx: Context, before: State, after: State, test: Test[NoiseEstimate]) -> Finding:
        g = after.hypothesis.noise.gain
        return Finding("all pixels (noise, not the mean)", f"g = {g:.3f}", {"gain": g},
                       options=(Option("load.gain", f"{g:.4g}"),))

    def measure(self, ctx: Context, state: State) -> Estimate | None:
        # the gain these residuals ask for, the electronic variance held at the model's
        e = state.hypothesis.noise.electronic
        fit = noise_fit(ctx, state, state.hypothesis.motion)
        g, _ = fit.regression(electronic=e)
        return Estimate(np.asarray(g), np.asarray(fit.standard_error(True, (g, e))))


EFFECT = DetectorGain()
