"""``beam_path``: the beam paths through the sample change during the scan (the paper's Sec. V).

Where the source travels with the gratings (or the sample lies away from the plane the geometry assumes), frame j
sees the sample displaced along the scan by d_j = kappa (c_j - c_0) rows, c_j the active area's centre and c_0 the
detector's: its samples read the images at u + d_j, between rows (:class:`dfxcorr.observations.Reading`; the
images of a column are then one block-tridiagonal solve, :mod:`dfxcorr.banded`). The correction is
``geometry.parallax`` = kappa, applied to every stage through the samples' reading.

The images are those each pixel sees with the active area centred on it (:attr:`dfxcorr.align.LitStore.parallax`):
pixel r's samples read them at r + kappa (c_j - r) / (1 + kappa), within a fraction of a row of their own.

The test is the score test of kappa at the current fit: the derivative of the expected counts with respect to
kappa is how far the read position moves times the images' slope there pushed through the model,
d Ibar / d kappa = (c_j - r) / (1 + kappa)^2 sum_a X_a d coef_a / du. The images absorb what is common to a pixel's
frames, so only the part of that field orthogonal to the images' own design counts; its weighted product with the
residuals over its information is the Newton step in kappa, and their ratio squared a chi-square with 1 dof
(conservative: the per-frame parameters could absorb a little more of the field). A phase-stepping recording,
whose active area never moves, cannot show it.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from .. import model as M
from ..align import LitStore
from ..catalogue import Effect
from ..noise import noise_weights
from ..observations import Observations
from ..preparation import Correctable
from .base import (
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
    dispersion,
)


def read_slope(obs: Observations, coef: np.ndarray, moves: np.ndarray) -> np.ndarray:
    """d coef / du where each sample reads the images, in the direction its read position moves (K, C, ...).

    Between rows the images are linear in the read position: the slope of that interval. On a row (the paper's
    geometry, kappa = 0) the slope of the interval the read position moves into as kappa grows (``moves``, (K,)):
    the one-sided derivative of the model.
    """
    R = coef.shape[0]
    lo = obs.pixel if obs.reading is None else obs.reading.lo
    frac = np.zeros(lo.size) if obs.reading is None else obs.reading.frac
    forward = coef[np.minimum(lo + 1, R - 1)] - coef[lo]
    backward = coef[lo] - coef[np.maximum(lo - 1, 0)]
    ahead = ((frac > 0) | (moves >= 0)).reshape((-1,) + (1,) * (coef.ndim - 1))
    return np.where(ahead, forward, backward)


def kappa_field(obs: Observations, dsg: M.Design, images: M.Images, moves: np.ndarray) -> np.ndarray:
    """d Ibar / d kappa at every sample (K, C): how far its read position moves per unit kappa times
    sum_a X_a d coef_a / du (:func:`read_slope`).

    Parameters
    ----------
    obs : Observations
    dsg : Design
    images : Images
    moves : ndarray, shape (K,)
        d(read position) / d kappa of each block (rows).
    """
    at = obs.gather(images.coef)
    slope = read_slope(obs, images.coef, moves)
    Xc, Xs = M.image_columns(dsg, at[..., 1], at[..., 2])
    return moves[:, None] * (dsg.A * slope[..., 0] + Xc * slope[..., 1] + Xs * slope[..., 2])


def kappa_score(obs: Observations, params: dict[str, np.ndarray], images: M.Images, moves: np.ndarray, *,
                samples: float = 1e6) -> tuple[float, float]:
    """Score sum w r F_perp and information sum w F_perp^2 of kappa at the images and parameters given.

    F_perp is :func:`kappa_field` less its least-squares fit by the images' own design (what the images absorb);
    w the inverse noise variances of the model, r the residuals. Computed a run of about ``samples`` samples'
    columns at a time.
    """
    score = info = 0.0
    for _, sub, im, dsg, ibar in M.expected_by_columns(obs, params, images, samples=samples):
        w = np.where(sub.gather_valid(im.valid), noise_weights(sub, ibar), 0.0)
        F = kappa_field(sub, dsg, im, moves)
        at = sub.gather(im.coef)
        design = [dsg.A, *M.image_columns(dsg, at[..., 1], at[..., 2])]
        fitted = sub.gather(M.solve_pixels(sub, design, F, w)[0])
        perp = F - sum(fitted[..., a] * X for a, X in enumerate(design))
        score += float(np.sum(w * (sub.counts - ibar) * perp))
        info += float(np.sum(w * perp * perp))
    return score, info


def read_moves(store: LitStore, kappa: float) -> np.ndarray:
    """d(read position) / d kappa of every block of ``store`` at ``kappa`` (rows): the samples of pixel r read the
    images at r + kappa (c_j - r) / (1 + kappa) (:attr:`dfxcorr.align.LitStore.parallax`)."""
    return store.centred() / (1.0 + kappa) ** 2


class BeamPath(EffectBase[Estimate]):
    entry = Effect("beam_path", None, False, ("kappa",), 0.0, "none",
                   "the beam paths change during the scan: frame j sees the sample images displaced along the scan "
                   "by kappa (c_j - c_0) rows", unit="rows per row")
    # a geometry, tested before the catalogue's mean terms and the moving parts of a sample that would take up
    # pieces of what it does; the score's step is a linearisation: refined at the trial's fit. Judged on its own
    # score: sub-pixel structure moving across the pixels stays beyond what images on the pixel grid describe
    policy = Policy(order=1, astray_check=True, refinements=2, own_signature=True)

    def configured(self, cfg: dict[str, Any], *, n_frames: int, detector: tuple[int, int]) -> Any:
        return cfg["geometry"]["parallax"] or None

    def apply(self, data: Correctable, setting: Any) -> Correctable:
        position = data.store.position
        if position is not None and np.ptp(position) == 0:
            # the active area never moves (phase stepping): the beam paths cannot change
            return data
        return replace(data, store=data.store.with_parallax(data.store.parallax + float(setting)))

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test[Estimate] | None:
        if ctx.stepping:
            return None
        store = ctx.corrected(state.hypothesis).store
        # the blocks of the held rows' observations are the store's, in its order
        lo, hi = np.searchsorted(store.row, (state.obs.row[0], state.obs.row[-1] + 1))
        moves = read_moves(store, store.parallax)[lo:hi]
        obs = replace(state.obs, use=state.obs.use & ~state.obs.pixel_mask(flagged))
        score, info = kappa_score(obs, state.params, state.rec.images, moves)
        if info <= 0:
            return Test(0.0, 1, 1.0, 0.0, Estimate(np.asarray(0.0), np.asarray(np.inf)), identifiable=False,
                        excess=1)
        scale = dispersion(state)
        step, se = score / info, float(np.sqrt(scale / info))
        stat = score ** 2 / (info * scale)
        return chi2_test(stat, 1, Estimate(np.asarray(step), np.asarray(se)), explains=stat)

    def trial(self, ctx: Context, state: State, test: Test[Estimate]) -> Hypothesis:
        return state.hypothesis.but(corrections=(*state.hypothesis.corrections, (self.name, float(test.payload.value))))

    def _kappa(self, hypothesis: Hypothesis) -> float:
        """The kappa a hypothesis holds beyond the configured one."""
        return float(sum(setting for name, setting in hypothesis.corrections if name == self.name))

    def accepted(self, ctx: Context, before: State, after: State, test: Test[Estimate]) -> Finding:
        found = self.measure(ctx, after)
        assert found is not None
        kappa, se = float(found.value), float(found.se)
        return Finding("all frames; the sample seen displaced along the scan in proportion to the active area's "
                       "distance from the detector's centre",
                       f"kappa = {kappa:.4g} rows per row (se {se:.2g})", {"value": kappa, "se": se},
                       options=(Option("geometry.parallax", f"{kappa:.6g}"),))

    def measure(self, ctx: Context, state: State) -> Estimate | None:
        if ctx.stepping:
            return None
        t = self.test(ctx, state, np.zeros(state.hypothesis.motion.shape, bool))
        if t is None:
            return None
        kappa = ctx.cfg["geometry"]["parallax"] + self._kappa(state.hypothesis) + float(t.payload.value)
        return Estimate(np.asarray(kappa), np.asarray(t.payload.se))


EFFECT = BeamPath()
