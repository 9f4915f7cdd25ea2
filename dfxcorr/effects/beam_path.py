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
    dispersion,
)


def read_slope(obs: Observations, coef: np.ndarray, moves: np.ndarray) -> np.ndarray:
    """d coef / du where each sample reads the images, in the direction its read position moves (K, C, ...).

    Between rows the images are linear in the read position: the slope of that interval. On a row (the paper's
    geometry, kappa = 0) the slope of the interval the read position moves into as kappa grows (``moves``, (K,)):
    the one-sided derivative of the model.
    """
    lo, _, frac = obs.read_rows()
    forward = coef[np.minimum(lo + 1, coef.shape[0] - 1)] - coef[lo]
    backward = coef[lo] - coef[np.maximum(lo - 1, 0)]
    ahead = ((frac > 0) | (moves >= 0)).reshape((-1,) + (1,) * (coef.ndim - 1))
    return np.where(ahead, forward, backward)


def kappa_field(obs: Observations, dsg: M.Design, images: M.Images, moves: np.ndarray, *,
                at: np.ndarray | None = None) -> np.ndarray:
    """d Ibar / d kappa at every sample (K, C): how far its read position moves per unit kappa times
    sum_a X_a d coef_a / du (:func:`read_slope`).

    Parameters
    ----------
    obs : Observations
    dsg : Design
    images : Images
    moves : ndarray, shape (K,)
        d(read position) / d kappa of each block (rows).
    at : ndarray, shape (K, C, 3), optional
        The images at every sample (``obs.gather(images.coef)``), where the caller has them.
    """
    at = obs.gather(images.coef) if at is None else at
    slope = read_slope(obs, images.coef, moves)
    Xc, Xs = M.image_columns(dsg, at[..., 1], at[..., 2])
    return moves[:, None] * (dsg.A * slope[..., 0] + Xc * slope[..., 1] + Xs * slope[..., 2])


def kappa_score(obs: Observations, params: dict[str, np.ndarray], images: M.Images, moves: np.ndarray, *,
                labels: np.ndarray | None = None, samples: float = 2.5e5) -> tuple[np.ndarray, np.ndarray]:
    """Score sum w r F_perp and information sum w F_perp^2 of kappa at the images and parameters given, per stratum.

    F_perp is :func:`kappa_field` less its least-squares fit by the images' own design (what the images absorb);
    w the inverse noise variances of the model, r the residuals. ``labels`` (K,): the stratum of each block (-1:
    left out; strata of whole rows); None: one. Computed a run of about ``samples`` samples' columns at a time.

    Returns
    -------
    score, info : ndarray, shape (n,)
        Per stratum.
    """
    n = 1 if labels is None else max(int(labels.max()) + 1, 1)
    score, info = np.zeros(n), np.zeros(n)
    for _, sub, im, dsg, ibar in M.expected_by_columns(obs, params, images, samples=samples):
        w = np.where(sub.gather_valid(im.valid), noise_weights(sub, ibar), 0.0)
        at = sub.gather(im.coef)
        F = kappa_field(sub, dsg, im, moves, at=at)
        design = [dsg.A, *M.image_columns(dsg, at[..., 1], at[..., 2])]
        fitted = sub.gather(M.solve_pixels(sub, design, F, w)[0])
        perp = F - sum(fitted[..., a] * X for a, X in enumerate(design))
        # the strata are whole rows: one label per block, the samples' sums over columns first
        lab = np.zeros(sub.row.size, np.int64) if labels is None else labels
        keep = lab >= 0
        score += np.bincount(lab[keep], weights=np.sum(w * (sub.counts - ibar) * perp, axis=1)[keep], minlength=n)
        info += np.bincount(lab[keep], weights=np.sum(w * perp * perp, axis=1)[keep], minlength=n)
    return score, info


def row_strata(obs: Observations, n: int = 6) -> np.ndarray:
    """Stratum of each block (K,): ``n`` strata of equally many of the detector rows that have samples in use
    (0: the first rows), -1 for the blocks of rows without."""
    lit = obs.segment_sum(np.asarray(obs.use.any(axis=1), dtype=np.int64)) > 0
    out = np.full(obs.rows.size, -1)
    if lit.sum() >= n:
        edges = np.quantile(obs.rows[lit], np.linspace(0, 1, n + 1)[1:-1])
        out[lit] = np.searchsorted(edges, obs.rows[lit])
    return out[obs.pixel]


def one_size(score: np.ndarray, info: np.ndarray) -> tuple[float, int]:
    """The test that the strata share one step in kappa: sum U^2 / I - (sum U)^2 / sum I (chi-square with the strata
    less one dof, before the dispersion) and its dof."""
    ok = info > 0
    if ok.sum() < 2:
        return 0.0, 0
    stat = float(np.sum(score[ok] ** 2 / info[ok])) - float(score[ok].sum()) ** 2 / float(info[ok].sum())
    return max(stat, 0.0), int(ok.sum()) - 1


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
        score, info = self._strata(ctx, state, flagged)
        total = float(info.sum())
        if total <= 0:
            return Test(0.0, 1, 1.0, 0.0, Estimate(np.asarray(0.0), np.asarray(np.inf)), identifiable=False,
                        excess=1)
        # one geometry for the whole detector: the common step is judged against how much the strata of rows
        # disagree about it where that exceeds their noise (a misfit of another kind that the score picked up asks
        # for steps of other sizes and signs in other rows; quasi-likelihood, as the dispersion for the samples)
        spread_stat, dof = one_size(score, info)
        scale = dispersion(state) * (max(1.0, spread_stat / dispersion(state) / dof) if dof else 1.0)
        step, se = float(score.sum()) / total, float(np.sqrt(scale / total))
        stat = float(score.sum()) ** 2 / (total * scale)
        return chi2_test(stat, 1, Estimate(np.asarray(step), np.asarray(se)), explains=stat)

    def _strata(self, ctx: Context, state: State, flagged: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """kappa's score and information at ``state`` on each of six strata of detector rows, ``flagged`` pixels
        left out."""
        moves = self._moves(ctx.corrected(state.hypothesis).store, state.obs)
        obs = replace(state.obs, use=state.obs.use & ~state.obs.pixel_mask(flagged))
        return kappa_score(obs, state.params, state.rec.images, moves, labels=row_strata(obs))

    def consistency(self, ctx: Context, before: State, state: State) -> Consistency | None:
        # one geometry for the whole detector: kappa refitted on the pixels of each stratum of detector rows (one
        # step from the trial's kappa) must agree; a misfit of another kind that the score picked up does not
        store = ctx.corrected(state.hypothesis).store
        if not store.parallax:
            return None
        score, info = self._strata(ctx, state, state.hypothesis.motion)
        stat, dof = one_size(score, info)
        if dof < 1:
            return None
        ok = info > 0
        sizes = 1.0 + (score[ok] / info[ok]) / store.parallax
        t = chi2_test(stat / dispersion(state), dof, tuple(float(v) for v in sizes))
        return Consistency(t.statistic, t.dof, t.p_value, t.log_p, "row", t.payload)

    @staticmethod
    def _moves(store: LitStore, obs: Observations) -> np.ndarray:
        """d(read position) / d kappa of the blocks of ``obs`` (the held rows' blocks are the store's, in its
        order)."""
        lo, hi = np.searchsorted(store.row, (obs.row[0], obs.row[-1] + 1))
        return read_moves(store, store.parallax)[lo:hi]

    def trial(self, ctx: Context, state: State, test: Test[Estimate]) -> Hypothesis:
        return state.hypothesis.but(corrections=(*state.hypothesis.corrections, (self.name, float(test.payload.value))))

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
        # the corrected scan holds the configured kappa and the hypothesis's
        kappa = ctx.corrected(state.hypothesis).store.parallax + float(t.payload.value)
        return Estimate(np.asarray(kappa), np.asarray(t.payload.se))


EFFECT = BeamPath()
