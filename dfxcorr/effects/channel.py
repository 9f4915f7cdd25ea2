"""The model's channel effects (phase_offset ... harmonic): one implementation over their catalogue entries.

Each is tested by Neyman's efficient-score (C(alpha)) test at the current fit: the score of the
candidate's parameters, corrected for the model's own parameters through the profiled Fisher
information (:func:`dfxcorr.identify.information`), S = U*^T I*^+ U* / phi, chi-square with rank(I*)
degrees of freedom. No refit is needed, the subsampled fit's estimates suffice, and dividing by the
dispersion phi (Pearson chi-square per degree of freedom) keeps an unmodelled detector gain from posing
as a mean effect. Whether the acquisition determines it comes from the null space of the same
information (:mod:`dfxcorr.identify`).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from .. import identify
from .. import model as M
from ..catalogue import CATALOGUE, Effect
from ..observations import Observations
from ..retrieve import retrieve
from .base import Context, EffectBase, Hypothesis, State, Test, chi2_test, frames_where


def score_tests(obs: Observations, params: dict, weights: np.ndarray, model, candidates, *,
                dispersion: float) -> dict[str, Test]:
    """Efficient-score tests of mean effects at the current fit.

    Parameters
    ----------
    obs : Observations
        Samples for the test (their ``use`` decides which count).
    params : dict
        Current parameters of the model's effects.
    weights : ndarray, shape (K, C)
        Inverse noise variances of the current noise model.
    model, candidates : sequence of str
        Mean effects in the model, and those to test.
    dispersion : float
        Pearson chi-square per degree of freedom (scales the statistic).

    Returns
    -------
    dict
        name -> Test; ``explains`` approximates the chi-square that adding the effect removes, the payload's
        'frames' the per-frame share of the statistic (per-frame effects).
    """
    names = list(model) + [c for c in candidates if c not in model]
    full = {**M.neutral_params(names, obs.n_frames), **params}
    dsg = M.design(obs, full)
    images = M.solve_images(obs, dsg, weights, keep_inverse=True)
    resid = obs.counts - M.expected(obs, dsg, images)
    inf = identify.information(obs, dsg.channels, images, weights, names)
    grad = M.gradient(obs, dsg, images, weights, resid, names)
    U = -0.5 * np.array([grad[n][(j, m) if j >= 0 else m]
                         for n, j, m in zip(inf.owner, inf.frame, inf.component, strict=True)])
    out = {}
    for name in candidates:
        cond = identify.conditional(inf, name, model)
        sel, inv = cond.sel, cond.inverse
        # the efficient score: the candidate's score with what the model's own parameters explain taken out
        eff_score = U[sel] - cond.projector @ U[cond.base]
        stat = float(eff_score @ inv @ eff_score) / dispersion
        contrib = eff_score * (inv @ eff_score) / dispersion
        fr = inf.frame[sel]
        frames = np.bincount(fr[fr >= 0], weights=contrib[fr >= 0], minlength=obs.n_frames)
        out[name] = chi2_test(stat, cond.dof, explains=stat * dispersion, identifiable=cond.verdict.identifiable,
                              excess=cond.verdict.excess, payload={"frames": frames})
    return out


def _round_scores(ctx: Context, state: State) -> dict[str, Test]:
    """The score tests of every channel effect the fit ``state`` lacks: one Fisher information serves them all
    (kept in the diagnosis's memo for the state last asked about)."""
    held = ctx.memo.get("scores")
    if held is None or held[0] is not state:
        model = state.hypothesis.effects
        obs = state.fit_obs
        weights = M.noise_weights(obs, retrieve(obs, state.params).expected)
        held = state, score_tests(obs, state.params, weights, model, [n for n in CATALOGUE if n not in model],
                                  dispersion=max(state.reduced_chi2, 1e-6))
        ctx.memo["scores"] = held
    return held[1]


class ChannelEffect(EffectBase):
    """A term of the expected count: tested by its efficient score, added to the model by a refit with it."""

    def __init__(self, entry: Effect):
        self.entry = entry

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test | None:
        if self.name in state.hypothesis.effects:
            return None
        t = _round_scores(ctx, state)[self.name]
        return replace(t, identifiable=False) if self.entry.channel == "visibility" and ctx.visibility_why else t

    def trial(self, ctx: Context, state: State, test: Test) -> Hypothesis:
        return state.hypothesis.but(effects=(*state.hypothesis.effects, self.name))

    def where(self, test: Test, obs: Observations) -> str:
        if not self.entry.per_frame:
            return "the whole detector (global parameters)"
        return frames_where(test.payload["frames"], obs.n_frames)

    def estimate(self, extra: dict, params: dict, good: np.ndarray) -> str:
        p = params.get(self.name)
        if p is None:
            return ""
        e = self.entry
        if e.per_frame:
            sd = np.std(p[good], axis=0)
            # a factor of the expected count or visibility reads best in per cent
            unit, factor = (" %", 100.0) if e.gauge == "scale" else (f" {e.unit}" if e.unit else "", 1.0)
            return ", ".join(f"std {factor * s:.3g}{unit}" + (f" ({c})" if e.size > 1 else "")
                             for s, c in zip(sd, e.components, strict=True))
        if e.components == ("cos", "sin"):
            return f"a2 = {np.hypot(*p):.4g}, beta = {np.arctan2(p[1], p[0]):.3f} rad"
        return ", ".join(f"{c}: {v:.4g}" for c, v in zip(e.components, p, strict=True)) + f" {e.unit}"

    def per_frame(self, extra: dict, params: dict) -> np.ndarray | None:
        return params.get(self.name) if self.entry.per_frame else None

    def settings(self, cfg: dict, final: Hypothesis, extra: dict | None, out_dir: Path) -> list[str]:
        return [f"{self.entry.config}=true"] if extra is not None and self.entry.config else []


#: One per entry of the model's catalogue, in its order.
EFFECTS = tuple(ChannelEffect(e) for e in CATALOGUE.values())
