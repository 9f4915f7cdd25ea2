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

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .. import engine as E
from .. import identify
from .. import model as M
from ..catalogue import CATALOGUE, Effect, effect, neutral_params
from ..noise import noise_weights
from ..observations import Observations
from ..stats import frames_where
from .base import (
    MEAN,
    Consistency,
    ConsistencyAxis,
    Context,
    EffectBase,
    Estimate,
    Finding,
    Hypothesis,
    Option,
    Pair,
    Params,
    State,
    Test,
    chi2_test,
    dispersion,
    strongest,
)


@dataclass(frozen=True)
class Score:
    """A channel effect's score test: the share of its statistic in each frame, shape (J,)."""

    frames: np.ndarray


@dataclass(frozen=True)
class Scores:
    """Efficient-score tests of channel effects at one fit, and what tests several of them together.

    Attributes
    ----------
    tests : dict
        name -> its test given the model.
    information : Information
        The profiled Fisher information of the model and the candidates.
    score : ndarray
        The score in the information's order.
    model : tuple of str
    dispersion : float
    """

    tests: dict[str, Test[Score]]
    information: identify.Information
    score: np.ndarray
    model: tuple[str, ...]
    dispersion: float

    def together(self, names: tuple[str, ...]) -> tuple[float, int]:
        """The efficient-score statistic of several candidates together, given the model, and its dof."""
        cond = identify.conditional(self.information, names, self.model)
        u = self.score[cond.sel] - cond.projector @ self.score[cond.base]
        return float(u @ cond.inverse @ u) / self.dispersion, cond.dof

    def pair(self, a: str, b: str) -> Pair:
        """Two candidates together: each one's share of their joint statistic beyond the other's test alone."""
        joint, dof = self.together((a, b))
        ta, tb = self.tests[a], self.tests[b]
        beyond = {a: (max(joint - tb.statistic, 0.0), dof - tb.dof), b: (max(joint - ta.statistic, 0.0), dof - ta.dof)}
        return Pair(beyond, ta.dof + tb.dof - dof)


def score_tests(obs: Observations, params: Params, weights: np.ndarray, model: Sequence[str],
                candidates: Sequence[str], *, dispersion: float) -> Scores:
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
    Scores
        Its tests: name -> Test; ``explains`` approximates the chi-square that adding the effect removes, the
        payload the per-frame share of the statistic (per-frame effects).
    """
    names = list(model) + [c for c in candidates if c not in model]
    full = {**neutral_params(names, obs.n_frames), **params}
    ch = M.channels(full, x=obs.x, n_frames=obs.n_frames)
    images, _ = E.solved(obs, ch, weights)
    inf = identify.information(obs, ch, images, weights, names)
    U = _score(inf, E.parameter_sums(obs, ch, weights, names)[1])
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
        # directions without information that the candidate has only beside the model's effects (each alone
        # determines them) do not make it unidentifiable: the rest of its parameters is tested, and a fit with it
        # leaves those directions where the model's effect put them (a gauge: the first added takes them)
        shared = bool(cond.verdict.excess and cond.dof > 0
                      and identify.conditional(inf, name, ()).verdict.identifiable)
        out[name] = chi2_test(stat, cond.dof, Score(frames), explains=stat * dispersion,
                              identifiable=cond.verdict.identifiable or shared,
                              excess=0 if shared else cond.verdict.excess,
                              shared=cond.verdict.excess if shared else 0)
    return Scores(out, inf, U, tuple(model), dispersion)


def _score(inf: identify.Information, grad: Params) -> np.ndarray:
    """The score (half the negative gradient of the cost) in the order of the information's entries."""
    return -0.5 * np.array([grad[n][(j, m) if j >= 0 else m]
                            for n, j, m in zip(inf.owner, inf.frame, inf.component, strict=True)])


def strata(obs: Observations, expected: np.ndarray, *, by: str, n: int = 6) -> np.ndarray:
    """Stratum of each sample by its pixel: ``n`` strata of equally many pixels.

    Parameters
    ----------
    obs : Observations
    expected : ndarray, shape (K, C)
        Expected counts (detector units).
    by : {'count', 'row'}
        The pixel's mean expected count, or its detector row.
    n : int
        Number of strata.

    Returns
    -------
    ndarray of int, shape (K, C)
        0 (dimmest pixels, or first rows) ... n - 1; -1 for pixels without samples in use.
    """
    used = obs.use.astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        level = obs.segment_sum(np.where(obs.use, expected, 0.0)) / obs.segment_sum(used)
    if by not in ("count", "row"):
        raise ValueError(f"strata by 'count' or 'row', not {by!r}")
    if by == "row":
        level = np.where(np.isfinite(level), obs.rows[:, None].astype(float), np.nan)
    ok = np.isfinite(level)
    out = np.full(level.shape, -1)
    if ok.sum() >= n:
        edges = np.quantile(level[ok], np.linspace(0, 1, n + 1)[1:-1])
        out[ok] = np.searchsorted(edges, level[ok])
    return out[obs.pixel]


def heterogeneity(obs: Observations, params: Params, weights: np.ndarray, model: Sequence[str], name: str, *,
                  labels: Mapping[ConsistencyAxis, np.ndarray]) -> Consistency:
    """Whether an effect in the model has one size in every stratum of pixels, along each of some axes.

    A score test at the fit with the effect (``params``, theta), of the alternative that its parameters
    are theta (1 + gamma_k) in stratum k, everything else shared: a catalogue effect that a detector
    effect outside the catalogue mimics (a non-linearity's second harmonic, a ghost's change of dose)
    has a size that changes with the count or along the rows. The profiled information and the score
    are sums over pixels, so each stratum's share is the kernel's with the other pixels' weights set to
    zero; each stratum's share is divided by its own dispersion (Pearson chi-square per degree of
    freedom, a quasi-likelihood), so a noise model that is off by a factor that changes with the count
    does not pose as a change of size. Two contrasts of the gamma_k, Bonferroni over both: a trend
    along the strata's order (1 dof) and any difference (strata - 1 dof); S = U*^T I*^+ U*, U* and I*
    the contrasts' score and information with what the shared parameters explain taken out. Each axis is
    tested so, and the strongest of them counts (Bonferroni over the axes); the images are solved once.

    Parameters
    ----------
    obs : Observations
        The fit's samples.
    params : dict
        The fitted parameters of the model, ``name`` among them.
    weights : ndarray, shape (K, C)
        Inverse noise variances.
    model : sequence of str
        The mean effects in the model (``name`` included).
    name : str
    labels : mapping
        Axis name -> stratum of each sample, ndarray of int, shape (K, C) (:func:`strata`; negative: left out).

    Returns
    -------
    Consistency
        The axis that decided, and the size of the effect in each of its strata under the contrast that decided,
        relative to the shared fit's (1; one step from it), in the strata's order.
    """
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    images, resid = E.solved(obs, ch, weights)
    found = {axis: _heterogeneity(obs, ch, images, resid, params, weights, model, name, labels=lab)
             for axis, lab in labels.items()}
    axis, t = strongest(found)
    return Consistency(t.statistic, t.dof, t.p_value, t.log_p, axis, t.payload)


def _heterogeneity(obs: Observations, ch: M.Channels, images: M.Images, resid: np.ndarray, params: Params,
                   weights: np.ndarray, model: Sequence[str], name: str, *, labels: np.ndarray
                   ) -> Test[tuple[float, ...]]:
    """:func:`heterogeneity` along one axis, at the fit's channels, images and residuals (K, C); the payload is the
    strata's sizes. A stratum holds whole pixels: the gradient of its reduced cost is that at the fit's images."""
    n = int(labels.max()) + 1
    if n < 2:
        return chi2_test(0.0, 0, ())
    names = list(model)
    e = effect(name)
    total: Any = 0.0
    U_eta: Any = 0.0
    u, own, cross = np.zeros(n), np.zeros(n), []
    for k in range(n):
        inside = obs.use & (labels == k)
        # a pixel's samples beyond its three images are what its residuals have to spread
        dof = float(np.sum(np.maximum(obs.segment_sum(inside.astype(float)) - 3, 0)))
        phi = max(float(np.sum(np.where(inside, weights * resid ** 2, 0.0))) / max(dof, 1.0), 1e-12)
        wk = np.where(inside, weights, 0.0)
        inf = identify.information(obs, ch, images, wk, names)
        # quasi-likelihood: the stratum's score and information over its own dispersion (the images' profile
        # uses every weight as it is, so the weights themselves are not rescaled)
        matrix = inf.matrix / phi
        score = _score(inf, E.parameter_sums(obs, ch, wk, names)[1]) / phi
        live, sel = inf.live, inf.live & (inf.owner == name)  # the same for every stratum: frames, not weights
        # the alternative: the effect as fitted, of another size in each stratum (theta_k = (1 + gamma_k) theta):
        # a parameter per stratum, however many the effect has, so a per-frame effect is tested with a few dof
        size = np.array([params[name][(j, m) if j >= 0 else m] - e.neutral
                         for j, m in zip(inf.frame[sel], inf.component[sel], strict=True)])
        u[k], own[k] = size @ score[sel], size @ matrix[np.ix_(sel, sel)] @ size
        cross.append(size @ matrix[np.ix_(sel, live)])
        total = total + matrix[np.ix_(live, live)]
        U_eta = U_eta + score[live]
    C = np.stack(cross)
    # two contrasts of the strata's sizes, Bonferroni over both: a size that drifts along the strata's order (where
    # a detector effect grows or fades with the count), and any difference
    contrasts = {"trend": (np.arange(n) - (n - 1) / 2)[:, None], "any": np.eye(n)[:, 1:]}
    inv_total = identify.pinv_rank(np.asarray(total))[0]
    found = {}
    for key, Z in contrasts.items():
        eff_score = Z.T @ u - Z.T @ C @ inv_total @ U_eta
        eff_info = Z.T @ np.diag(own) @ Z - Z.T @ C @ inv_total @ C.T @ Z
        inv, dof = identify.pinv_rank(eff_info, np.diag(Z.T @ np.diag(own) @ Z))
        # the sizes this alternative estimates (one step from the shared fit), centred on the shared size: their
        # information-weighted mean is the shared fit's (a stratum as the contrasts' baseline must not matter)
        g = Z @ (inv @ eff_score)
        sizes = 1.0 + g - own @ g / max(own.sum(), 1e-300)
        found[key] = chi2_test(float(eff_score @ inv @ eff_score), dof, tuple(float(s) for s in sizes))
    return strongest(found)[1]


def round_scores(state: State) -> Scores:
    """The score tests of every channel effect the fit ``state`` lacks: one Fisher information serves them all."""
    model = state.hypothesis.effects
    obs = state.fit_obs
    weights = noise_weights(obs, state.fit_rec.expected)
    return score_tests(obs, state.params, weights, model, [n for n in CATALOGUE if n not in model],
                       dispersion=max(state.reduced_chi2, 1e-6))


class ChannelEffect(EffectBase[Score]):
    """A term of the expected count: tested by its efficient score, added to the model by a refit with it."""

    policy = MEAN

    def __init__(self, entry: Effect):
        self.entry = entry

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test[Score] | None:
        if self.name in state.hypothesis.effects:
            return None
        t = state.cached(round_scores).tests[self.name]
        return replace(t, identifiable=False) if self.entry.channel == "visibility" and ctx.visibility_why else t

    def trial(self, ctx: Context, state: State, test: Test[Score]) -> Hypothesis:
        return self.joined(state.hypothesis)

    def joined(self, hypothesis: Hypothesis) -> Hypothesis:
        return hypothesis.but(effects=(*hypothesis.effects, self.name))

    def beside(self, ctx: Context, state: State, other: str) -> Pair | None:
        scores = state.cached(round_scores)
        if self.name not in scores.tests or other not in scores.tests:
            return None
        return scores.pair(self.name, other)

    def consistency(self, ctx: Context, before: State, state: State) -> Consistency | None:
        # by count (a non-linearity, an additive artefact) and by detector row (an artefact on some rows of a
        # frame, as a ghost of an earlier frame): the stronger of the two, Bonferroni over both
        obs, expected = state.fit_obs, state.fit_rec.expected
        axes: tuple[ConsistencyAxis, ...] = ("count", "row")
        return heterogeneity(obs, state.params, noise_weights(obs, expected), state.hypothesis.effects, self.name,
                             labels={by: strata(obs, expected, by=by) for by in axes})

    def accepted(self, ctx: Context, before: State, after: State, test: Test[Score]) -> Finding:
        e = self.entry
        where = (frames_where(test.payload.frames, after.fit_obs.n_frames) if e.per_frame
                 else "the whole detector (global parameters)")
        p = after.params.get(self.name)
        return Finding(where, "" if p is None else self.describe(p, ctx.good_frames),
                       options=(Option(e.config, "true"),) if e.config else (),
                       per_frame=p if e.per_frame else None)

    def measure(self, ctx: Context, state: State) -> Estimate | None:
        if self.name not in state.params:
            return None
        # the fit's standard errors are the stated noise model's: scaled to the data's own spread
        return Estimate(state.params[self.name], state.uncertainty[self.name] * np.sqrt(dispersion(state)))

    def describe(self, p: np.ndarray, good: np.ndarray) -> str:
        """One line: the size of fitted parameters ``p`` (per frame: their spread over the frames ``good``)."""
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


#: One per entry of the model's catalogue, in its order.
EFFECTS = tuple(ChannelEffect(e) for e in CATALOGUE.values())
