"""Model-discrepancy diagnosis: where does a recording disagree with the model, and which physics is missing?

Each round fits the current model, then tests every catalogue effect the model lacks:

- mean effects (phase_offset ... harmonic) by Neyman's efficient-score (C(alpha)) test at the current
  fit: the score of the candidate's parameters, corrected for the model's own parameters through
  the profiled Fisher information (:func:`dfxcorr.model.fisher_matrix`), S = U*^T I*^+ U* / phi,
  chi-square with rank(I*) degrees of freedom. No refit is needed, the subsampled fit's estimates
  suffice, and dividing by the dispersion phi (Pearson chi-square per degree of freedom) keeps an
  unmodelled detector gain from posing as a mean effect;
- sample_motion by the per-pixel chi-square: pixels far beyond what noise allows, in numbers no
  chance explains (binomial test);
- detector_gain by a likelihood-ratio test of the variance model g (Ibar - dark) + electronic
  against the current one, considered only when no structured effect is left;
- detector_lag measured directly in the rows the active area has just left (:func:`lag_test`), tried
  before everything else and taken out of the counts (the data change, not the model);
- pixel_noise by anomalous detector columns and rows of the per-pixel chi-square, grouped into pixel
  classes with one variance factor each (:func:`pixel_noise_test`), tried just before detector_gain.

Whether an effect can be identified at all comes from the null space of the Fisher information
(:mod:`dfxcorr.analysis.identify`). The significant candidates (Holm's correction over the effects tried
in the round) are tried in turn: structured effects by the chi-square they explain, then detector_gain,
then sample_motion. A candidate is added only if it explains the misfit's signature: the residual
signatures of the fit (:func:`signatures`: by frame, row, column, (frame, row) block, fringe phase and
expected count, each tested against noise) that were significant must lose a set share of their excess
in a trial refit with it. The loop repeats until no candidate qualifies; signatures still significant
then are the report's ``unexplained`` entries (with pixel clusters that masking did not explain).
"""
from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage, stats

from .. import config as C
from .. import model as M
from .. import plots
from ..align import read_position_errors, subsample_columns
from ..fit import fit_vibrations, well_determined
from ..io import Scan, atomic_path
from ..mask import motion_score
from ..pipeline import Prepared, prepare, stage
from ..retrieve import Retrieval, image_maps, retrieve
from . import identify
from .identify import resolve_effects, visibility_unidentifiable
from .offsets import estimate_position_errors, offset_test, position_test, realign

log = logging.getLogger(__name__)

#: Effects tested, in catalogue order.
CANDIDATES = tuple(M.CATALOGUE)


@dataclass
class EffectReport:
    """One catalogue effect's verdict (the keys of ``spec/diagnosis.md``)."""

    name: str
    detected: bool
    identifiable: bool
    statistic: float
    dof: int
    p_value: float
    delta_chi2: float | None = None
    reduced_chi2_after: float | None = None
    where: str | None = None
    estimate: str | None = None
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        d = {k: v for k, v in asdict(self).items() if k != "extra" and v is not None}
        d.update(self.extra)
        return d


@dataclass
class Residuals:
    """Where the model and the recording disagree: mean squared standardized residual by location.

    Attributes
    ----------
    pixel : ndarray, shape (H, W)
        Per pixel, normalised by its degrees of freedom (1 = noise); NaN where not lit.
    frame : ndarray, shape (J,)
    x, x_value : ndarray
        Against the lateral coordinate (per held column).
    phase, phase_value : ndarray
        Against the fringe phase theta + phi, in 16 bins over (-pi, pi].
    count, count_value : ndarray
        Against the expected count, in logarithmic bins.
    """

    pixel: np.ndarray
    frame: np.ndarray
    x: np.ndarray
    x_value: np.ndarray
    phase: np.ndarray
    phase_value: np.ndarray
    count: np.ndarray
    count_value: np.ndarray


@dataclass
class Diagnosis:
    """The outcome of :func:`diagnose`."""

    scan: str
    base_model: list
    initial_chi2: float
    final_chi2: float
    effects: list
    final_model: list
    before: Residuals
    after: Residuals
    params: dict
    gain: float
    electronic: float
    motion_mask: np.ndarray
    criterion: str
    rounds: list
    unexplained: list
    signatures: list
    shape: tuple
    changes: list = field(default_factory=list)
    #: Where the final model reads the flat field: the global offset (rows, the configured one plus a detected
    #: reference_offset) and the per-frame position errors (J,) when position_error was detected, else None.
    reference_offset: float = 0.0
    position_errors: np.ndarray | None = None
    pixel_noise: np.ndarray | None = None

    def to_json(self) -> dict:
        """The ``diagnosis.json`` document of ``spec/diagnosis.md`` (version 2)."""
        return {"format": "dfxcorr-diagnosis", "format_version": 2, "scan": self.scan, "base_model": self.base_model,
                "reduced_chi2": {"initial": self.initial_chi2, "final": self.final_chi2},
                "effects": [e.to_json() for e in self.effects], "final_model": self.final_model,
                "unexplained": self.unexplained, "criterion": self.criterion, "rounds": self.rounds}


# --------------------------------------------------------------------------------------------------
# Locating the mismatch
# --------------------------------------------------------------------------------------------------


def locate(obs: M.Observations, dsg: M.Design, images: M.Images, ibar: np.ndarray) -> Residuals:
    """Mean squared standardized residual per pixel, frame, lateral position, fringe phase and count."""
    z2 = np.where(obs.use, M.pearson(obs, ibar), np.nan)
    used = obs.use.astype(float)
    n = obs.segment_sum(used)
    with np.errstate(invalid="ignore", divide="ignore"):
        pixel = obs.to_image(obs.segment_sum(np.nan_to_num(z2)) / (n - 3))
        frame = obs.frame_sum(np.nansum(z2, axis=1)) / obs.frame_sum(used.sum(axis=1))
        xs = np.nansum(z2, axis=0) / used.sum(axis=0)
    psi = np.angle(np.exp(1j * (dsg.theta + images.phi[obs.pixel])))
    edges = np.linspace(-np.pi, np.pi, 17)
    phase = _binned(psi, z2, edges)
    lo, hi = np.nanpercentile(np.where(obs.use, ibar, np.nan), [0.5, 99.5])
    cedges = np.geomspace(max(lo, 1e-3), max(hi, 2 * max(lo, 1e-3)), 13)
    count = _binned(ibar, z2, cedges)
    # a retrieval with 3 unknowns per pixel leaves (n - 3) / n of the variance in the residuals
    scale = float(np.nansum(n) / np.nansum(np.maximum(n - 3, 0)))
    return Residuals(pixel=pixel, frame=frame * scale, x=xs * scale, x_value=obs.x, phase=phase * scale,
                     phase_value=0.5 * (edges[1:] + edges[:-1]), count=count * scale,
                     count_value=np.sqrt(cedges[1:] * cedges[:-1]))


def _binned(value, z2, edges):
    ok = np.isfinite(z2)
    idx = np.digitize(value[ok], edges) - 1
    inside = (idx >= 0) & (idx < edges.size - 1)
    s = np.bincount(idx[inside], weights=z2[ok][inside], minlength=edges.size - 1)
    c = np.bincount(idx[inside], minlength=edges.size - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return s / c


# --------------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------------


#: Axes of the residual signatures (``unexplained`` in ``spec/diagnosis.md``, version 2).
SIGNATURE_AXES = ("frame", "row", "column", "frame_row", "phase", "count", "pixel")


def signatures(obs: M.Observations, params: dict, *, n_params: int, alpha: float,
               min_photons: float = 25.0) -> list[dict]:
    """Residual signatures of a fit, each tested against noise.

    On the fit's own samples (its columns: there the share of the residual that the per-frame
    parameters took is known), with z = (I - Ibar) / sd the standardized residual, h the sample's
    leverage in its pixel's image fit (3 unknowns per pixel) and c = sum z^2 / sum (1 - h) the
    dispersion:

    - variance signatures by frame, detector row, column, fringe phase (16 bins of theta + phi) and
      expected count (12 bins of equal size): per bin S = sum (z^2 - c (1 - h)), with variance
      sum c^2 (1 - h)^2 (2 + k), k the excess kurtosis of scaled Poisson noise (scaled up to the
      observed spread of z^2 where that is larger), or sum c^2 (2 (1 - h) + k (1 - h)^2) for bins that
      hold whole pixels (row, column: their residuals are correlated); sum S^2 / var is
      chi-square with (bins - 1) dof (c is estimated). A global variance excess is detector_gain's,
      not a signature;
    - mean signatures by frame and by (frame, row) block: per bin S = sum z with variance
      c sum (1 - h); chi-square with bins - P dof, P what the fit's per-frame parameters took of the
      bins' sums (their leverage on them; for the blocks, whatever a change of their frame's parameters
      could explain is regressed out, frame by frame, so an incompletely converged fit does not alarm);
    - the level: sum (z^2 - (1 - h)) against the stated noise model, 1 dof (kind 'level', axis
      'count': a variance misfit flat in the count, what detector_gain explains).

    h includes the leverage of the per-frame parameters (per frame, at fixed images), so the share of
    the residual variance that the fit on these columns took is accounted for sample by sample.

    Parameters
    ----------
    obs : Observations
        The fit's samples.
    params : dict
        The fitted effect parameters.
    n_params : int
        Number of fitted per-frame and global parameters.
    alpha : float
        Family-wise false-alarm probability: each signature's ``significant`` is Holm's verdict over
        all of them.
    min_photons : float
        The mean signatures use only samples expecting at least this many photons.

    Returns
    -------
    list of dict
        'axis', 'kind' ('variance' or 'mean'), 'statistic', 'dof', 'p_value', 'log_p', 'significant',
        'bins' (per-bin standardized S / sqrt(var)), 'bin_value' (bin centres: frame, row, column, block,
        phase in rad, count), 'relative' (per-bin S / expectation: relative variance excess, or mean z),
        'where', 'description'.
    """
    rec = retrieve(obs, params)
    dsg = M.design(obs, params)
    images = M.solve_images(obs, dsg, rec.weights, keep_inverse=True)
    ibar = M.expected(obs, dsg, images)
    sel = obs.use & images.valid[obs.pixel] & (rec.weights > 0)
    w = np.where(sel, rec.weights, 0.0)
    # the fit's per-frame parameters take their share too, largest where a frame's information is
    # (edge columns for the tilt, bright modulated samples for the phase)
    D = [d for n in params if M.effect(n).per_frame for d in M.sample_derivatives(obs, dsg, images, n)]
    info_inv = np.zeros((obs.n_frames, len(D), len(D)))
    if D:
        info = np.stack([np.stack([obs.frame_sum(np.sum(w * Da * Db, axis=1)) for Db in D], -1) for Da in D], -2)
        info_inv = np.linalg.pinv(info, rcond=1e-10, hermitian=True)
    Dn = np.stack(D, axis=-1) * np.sqrt(w)[..., None] if D else np.zeros(w.shape + (0,))
    h_par = np.einsum("kca,kab,kcb->kc", Dn, info_inv[obs.frame], Dn)
    h = np.where(sel, M.leverage(obs, dsg, images, rec.weights) + h_par, 0.0)
    keep = np.where(sel, np.clip(1.0 - h, 0.0, 1.0), 0.0)
    var = M.variance(obs, ibar)
    z = np.where(sel, (obs.counts - ibar) / np.sqrt(var), 0.0)
    c = float(np.sum(z ** 2) / np.sum(keep))
    g_true = c * obs.pixel_gain()[obs.pixel]
    kurt = g_true ** 3 * np.maximum(ibar - obs.dark, 1e-3) / (c * var) ** 2
    e = np.where(sel, z ** 2 - c * keep, 0.0)
    # at a few photons the weighted fit's mean is biased towards low counts: dim samples would give the
    # mean signatures a sign they do not have
    bright = sel & (np.maximum(ibar - obs.dark, 0.0) >= min_photons * g_true)
    kappa = np.where(sel, c ** 2 * keep ** 2 * (2.0 + kurt), 0.0)
    # the residuals of one pixel are correlated (covariance 1 - H, H its hat matrix): var sum_pixel z^2 =
    # 2 tr((1 - H)^2) = 2 sum (1 - h), not 2 sum (1 - h)^2. Bins that hold whole pixels (rows, columns)
    # need the former: with 5 phase steps the latter is 2.5 times too small
    kappa_pixels = np.where(sel, c ** 2 * (2.0 * keep + kurt * keep ** 2), 0.0)
    # the tails of z^2 are heavier than those of noise alone where the fit is slightly off sample by sample
    tails = max(float(np.sum(e ** 2) / np.sum(kappa)), 1.0)
    kappa *= tails
    kappa_pixels *= tails
    K, C_ = obs.counts.shape
    frame = np.broadcast_to(obs.frame[:, None], (K, C_))
    psi = np.angle(np.exp(1j * (dsg.theta + images.phi[obs.pixel])))
    pedges = np.linspace(-np.pi, np.pi, 17)
    cedges = np.quantile(ibar[sel], np.linspace(0, 1, 13)) if sel.any() else np.arange(13.0)
    labels = {
        "frame": (frame, np.arange(obs.n_frames)),
        "row": (np.broadcast_to(obs.row[:, None], (K, C_)), np.arange(obs.shape[1])),
        "column": (np.broadcast_to(np.arange(C_)[None, :], (K, C_)), obs.columns),
        "frame_row": (np.broadcast_to(np.arange(K)[:, None], (K, C_)), np.arange(K)),
        "phase": (np.clip(np.digitize(psi, pedges) - 1, 0, 15), 0.5 * (pedges[1:] + pedges[:-1])),
        "count": (np.clip(np.digitize(ibar, cedges[1:-1]), 0, 11), np.sqrt(np.abs(cedges[1:] * cedges[:-1]))),
    }
    kinds = [(a, "variance") for a in ("frame", "row", "column", "phase", "count")] + \
        [(a, "mean") for a in ("frame", "frame_row")]
    out = []
    for axis, kind in kinds:
        lab, value = labels[axis]
        nb = value.size
        lab = lab[sel]
        use = sel if kind == "variance" else bright
        S: np.ndarray
        V: np.ndarray
        expect: np.ndarray
        if kind == "variance":
            S = np.bincount(lab, weights=e[sel], minlength=nb)
            V = np.bincount(lab, weights=(kappa_pixels if axis in ("row", "column") else kappa)[sel], minlength=nb)
            expect = c * np.bincount(lab, weights=keep[sel], minlength=nb)
            lost = 1.0
        else:
            S = np.bincount(lab, weights=np.where(use, z, 0.0)[sel], minlength=nb)
            V = c * np.bincount(lab, weights=np.where(use, keep, 0.0)[sel], minlength=nb)
            expect = np.bincount(lab, weights=use[sel].astype(float), minlength=nb)
            # what the per-frame parameters took of each bin's sum: g^T I^-1 g with g = sum of the bin's
            # standardized derivatives (a bin lies within one frame on these axes)
            g = np.zeros((nb, Dn.shape[-1]))
            for a in range(Dn.shape[-1]):
                g[:, a] = np.bincount(lab, weights=np.where(use, Dn[..., a], 0.0)[sel], minlength=nb)
            first = np.zeros(nb, int)
            first[lab] = frame[sel]
            with np.errstate(divide="ignore", invalid="ignore"):
                lost = float(np.nansum(np.einsum("ba,bac,bc->b", g, info_inv[first], g) * c / V))
            if axis == "frame_row" and g.shape[1]:
                S, lost = _without_frame_terms(S, V, g, first)
        ok = V > 0
        if kind == "variance" and axis in ("row", "column") and ok.sum() > 10:
            # neighbouring pixels share frames, flat-field samples and the fit's per-frame parameters, so whole
            # lines scatter more than independent samples would: scaled to the bins' robust spread where that is
            # larger (measured 1.2-1.3x on clean tiled scans); a few anomalous lines stand out of it all the same
            zb = S[ok] / np.sqrt(V[ok])
            spread = 1.4826 * float(np.median(np.abs(zb - np.median(zb))))
            V = V * max(spread, 1.0) ** 2
        stat = float(np.sum(S[ok] ** 2 / V[ok]))
        dof = round(float(ok.sum()) - lost)
        if dof < 1:
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            std = np.where(ok, S / np.sqrt(V), np.nan)
            rel = np.where(ok & (expect > 0), S / expect, np.nan)
        out.append({"axis": axis, "kind": kind, "statistic": stat, "dof": dof,
                    "p_value": float(stats.chi2.sf(stat, dof)), "log_p": float(stats.chi2.logsf(stat, dof)),
                    "bins": std, "bin_value": value, "relative": rel})
        if axis == "frame_row":
            out[-1].update(frame=obs.frame, row=obs.row)
    # the global level against the stated noise model: detector_gain's signature (a count signature
    # that is flat in the count)
    level = float(np.sum(z ** 2 - keep))
    out.append({"axis": "count", "kind": "level", "statistic": level ** 2 / float(np.sum(kappa)), "dof": 1,
                "bins": np.array([level / np.sqrt(np.sum(kappa))]), "bin_value": np.array([np.nan]),
                "relative": np.array([level / np.sum(keep)])})
    out[-1].update(p_value=float(stats.chi2.sf(out[-1]["statistic"], 1)),
                   log_p=float(stats.chi2.logsf(out[-1]["statistic"], 1)))
    _holm(out, alpha)
    for sig in out:
        sig["where"], sig["description"] = _describe(sig, obs)
    return out


def _without_frame_terms(S: np.ndarray, V: np.ndarray, g: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, int]:
    """Block sums with what a change of their frame's parameters could explain taken out.

    Per frame, the standardized block sums S / sqrt(V) are regressed on the blocks' standardized
    parameter derivatives g / sqrt(V); the residual is noise with (blocks - rank) degrees of freedom
    whether or not the fit stopped exactly at its optimum.

    Returns
    -------
    S : ndarray
        Residual block sums (same scale as the input).
    lost : int
        Sum over frames of the regression's rank.
    """
    out = np.zeros_like(S)
    lost = 0
    root = np.sqrt(np.where(V > 0, V, np.inf))
    for j in np.unique(frame[V > 0]):
        b = np.flatnonzero((frame == j) & (V > 0))
        G = g[b] / root[b, None]
        coef, _, rank, _ = np.linalg.lstsq(G, S[b] / root[b], rcond=1e-8)
        out[b] = (S[b] / root[b] - G @ coef) * root[b]
        lost += int(rank)
    return out, lost


def _holm(tests: list[dict], alpha: float) -> None:
    """Mark each test's 'significant' by Holm's step-down procedure at family-wise level alpha."""
    order = sorted(range(len(tests)), key=lambda i: tests[i]["log_p"])
    going = True
    for rank, i in enumerate(order):
        going = going and tests[i]["log_p"] < np.log(alpha / (len(tests) - rank))
        tests[i]["significant"] = going


def _ranges(values: np.ndarray, limit: int = 4) -> str:
    """'3-7, 12, 40-60' for sorted integers (at most ``limit`` runs, then '...')."""
    runs, start = [], None
    for a, b in zip(values, [*list(values[1:]), None], strict=True):
        start = a if start is None else start
        if b is None or b != a + 1:
            runs.append(f"{start}-{a}" if a != start else f"{a}")
            start = None
    return ", ".join(runs[:limit]) + (", ..." if len(runs) > limit else "")


def _describe(sig: dict, obs: M.Observations) -> tuple[str, str]:
    """Where a signature sits (the bins that carry it) and a one-line description."""
    std, rel, value, axis = sig["bins"], sig["relative"], sig["bin_value"], sig["axis"]
    finite = np.isfinite(std)
    strong = finite & (np.abs(std) > 3.0)
    if not strong.any():
        order = np.argsort(-np.where(finite, std ** 2, -1.0))
        share = np.cumsum(std[order] ** 2) / max(np.nansum(std ** 2), 1e-300)
        strong = np.zeros(std.size, bool)
        strong[order[: int(np.searchsorted(share, 0.5)) + 1]] = True
    idx = np.flatnonzero(strong)
    if sig["kind"] == "level":
        return "all pixels and frames", (f"residual variance {100 * abs(rel[0]):.3g} % "
                                         f"{'above' if rel[0] > 0 else 'below'} the stated noise model everywhere")
    up, down = idx[std[idx] > 0], idx[std[idx] < 0]
    if axis == "frame":
        where = f"frames {_ranges(value[idx])}"
    elif axis == "row":
        where = f"detector rows {_ranges(value[idx])}"
    elif axis == "column":
        where = f"columns {_ranges(value[idx])}"
    elif axis == "frame_row":
        frames, rows = obs.frame[value[idx]], obs.row[value[idx]]
        where = (f"{idx.size} (frame, row) blocks in frames {frames.min()}-{frames.max()}, "
                 f"rows {rows.min()}-{rows.max()}")
    elif axis == "phase":
        where = "all frames; fringe phase " + ", ".join(f"{v:+.2f}" for v in value[idx][:6]) + " rad" \
            + (" (near the fringe maximum)" if np.all(np.abs(value[idx]) < np.pi / 2) else
               " (near the fringe minimum)" if np.all(np.abs(value[idx]) > np.pi / 2) else "")
    else:
        where = f"expected counts near {', '.join(f'{v:.3g}' for v in value[idx][:6])}"
    parts = []
    for side, name in ((up, "above"), (down, "below")):
        if side.size:
            size = float(np.nanmedian(np.abs(rel[side])))
            parts.append(f"{100 * size:.3g} % {name} noise in {side.size}" if sig["kind"] == "variance" else
                         f"{'+' if name == 'above' else '-'}{size:.3g} in {side.size}")
    total = f" of {int(finite.sum())} bins"
    if sig["kind"] == "variance":
        return where, "residual variance " + " and ".join(parts) + total
    return where, "mean standardized residual per sample " + " and ".join(parts) + total + ": the mean model is off"


def score_tests(obs: M.Observations, params: dict, weights: np.ndarray, model, candidates, *,
                dispersion: float) -> dict[str, dict]:
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
        name -> {'statistic', 'dof', 'p_value', 'log_p', 'explains', 'identifiable', 'excess', 'frames'}
        where 'explains' approximates the chi-square that adding the effect removes and 'frames' the
        per-frame share of the statistic (per-frame effects).
    """
    names = list(model) + [c for c in candidates if c not in model]
    full = {**M.neutral_params(names, obs.n_frames), **params}
    dsg = M.design(obs, full)
    images = M.solve_images(obs, dsg, weights, keep_inverse=True)
    resid = obs.counts - M.expected(obs, dsg, images)
    inf = identify.information(obs, dsg, images, weights, names)
    grad = M.gradient(obs, dsg, images, weights, resid, names)
    U = -0.5 * np.array([grad[n][(j, m) if j >= 0 else m]
                         for n, j, m in zip(inf.owner, inf.frame, inf.component, strict=True)])
    out = {}
    for name in candidates:
        cond = identify.conditional(inf, name, model)
        sel, inv, dof = cond.sel, cond.inverse, cond.dof
        # the efficient score: the candidate's score with what the model's own parameters explain taken out
        eff_score = U[sel] - cond.projector @ U[cond.base]
        stat = float(eff_score @ inv @ eff_score) / dispersion
        contrib = eff_score * (inv @ eff_score) / dispersion
        fr = inf.frame[sel]
        frames = np.bincount(fr[fr >= 0], weights=contrib[fr >= 0], minlength=obs.n_frames)
        out[name] = {"statistic": stat, "dof": dof, "p_value": float(stats.chi2.sf(stat, dof)) if dof else 1.0,
                     "log_p": float(stats.chi2.logsf(stat, dof)) if dof else 0.0, "explains": stat * dispersion,
                     "identifiable": cond.verdict.identifiable, "excess": cond.verdict.excess, "frames": frames}
    return out


def motion_test(obs: M.Observations, params: dict, *, p_pixel: float = 1e-6, min_pixels: int = 5) -> dict:
    """Pixels whose frames disagree beyond noise and remaining vibration misfit, in clusters.

    The per-pixel score is :func:`dfxcorr.mask.motion_score` at the current model (a reduced
    chi-square once what the fringe sensitivity explains is divided out); a pixel is flagged when that
    score is in the chi-square tail beyond ``p_pixel``, and counts only in a cluster of three or more.

    Returns
    -------
    dict
        'statistic' (chi-square in excess of its dof over the flagged pixels), 'dof' (flagged pixels),
        'p_value', 'log_p' (binomial: that many pixels below ``p_pixel`` by chance), 'explains',
        'mask' (H, W) bool.
    """
    score = motion_score(obs, params)
    dof = np.maximum(obs.segment_sum(obs.use.astype(float)) - 3, 1)
    ok = np.isfinite(score)
    logp = np.where(ok, stats.chi2.logsf(np.nan_to_num(score) * dof, dof), 0.0)
    flag = obs.to_image(ok & (logp < np.log(p_pixel)), fill=False).astype(bool)
    labels, count = ndimage.label(flag)
    if count:
        # a moving sample covers neighbouring pixels; isolated tail pixels are noise or outliers
        sizes = ndimage.sum(flag, labels, index=np.arange(1, count + 1))
        flag = np.isin(labels, 1 + np.flatnonzero(sizes >= 3))
    k = int(flag.sum())
    excess = obs.to_image(np.nan_to_num(score - 1) * dof, fill=0.0)
    log_p = float(stats.binom.logsf(k - 1, int(ok.sum()), p_pixel)) if k >= min_pixels else 0.0
    return {"statistic": float(excess[flag].sum()), "dof": k, "p_value": float(np.exp(log_p)), "log_p": log_p,
            "explains": float(excess[flag].sum()), "mask": flag, "identifiable": True, "excess": 0}


def noise_model(obs: M.Observations, ibar: np.ndarray, images: M.Images, dsg: M.Design,
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


def gain_test(obs: M.Observations, ibar: np.ndarray, images, dsg, weights, *,
              exclude: np.ndarray | None = None) -> dict:
    """Likelihood-ratio test of the estimated noise model against the current one (Gaussian, 2 dof).

    ``exclude`` (K, C) bool: samples left out (pixels whose frames disagree: a localised misfit must not
    pose as a global variance excess).
    """
    fit = noise_model(obs, ibar, images, dsg, weights, exclude=exclude)
    r2, v0 = fit["r2"], fit["variance"]
    v1 = fit["gain"] * fit["mean"] + fit["electronic"]
    stat = max(float(np.sum(np.log(v0 / v1) + r2 / v0 - r2 / v1)), 0.0)
    return {"statistic": stat, "dof": 2, "p_value": float(stats.chi2.sf(stat, 2)),
            "log_p": float(stats.chi2.logsf(stat, 2)), "gain": fit["gain"], "electronic": fit["electronic"],
            "identifiable": True, "excess": 0}


def lag_test(prep: Prepared) -> dict:
    """Detector lag measured where the model has nothing to say: the pixels the active area has just left.

    Without lag they hold the dark signal only; with lag a they hold a S_(j-1), the previous frame's
    lag-free signal (:meth:`dfxcorr.align.LitStore.lag_estimate`). The statistic is (a / se)^2, chi-square
    with 1 dof. Not identifiable without such pixels (phase stepping: every pixel is lit in every frame).

    Why a correction of the counts (S_j = I_j - dark - a S_(j-1), :func:`dfxcorr.model.lag_free`) and not a
    model term a Ibar_(j-1): the lag carries the previous frame's detected signal, its noise included, so
    the recursion with the true a returns the lag-free frames exactly (bar the storage's rounding) and
    every later stage, the compiled kernels included, sees Poisson data as if there had been no lag; a mean
    term would also need the lagged noise in the variance and would couple the frames of every pixel in
    the fit. Measured on the small test scan with a = 3 %: a estimated to 1e-5; the reduced chi-square of
    the paper's model drops from about 1.09 to that of the same scan without lag.
    """
    a, se = prep.store.lag_estimate()
    if not np.isfinite(a) or prep.store.lag:
        return {"statistic": 0.0, "dof": 1, "p_value": 1.0, "log_p": 0.0, "explains": 0.0,
                "identifiable": bool(np.isfinite(a)), "excess": 0, "value": 0.0, "se": se}
    stat = (a / se) ** 2 if se > 0 else (np.inf if a else 0.0)
    return {"statistic": float(stat), "dof": 1, "p_value": float(stats.chi2.sf(stat, 1)),
            "log_p": float(stats.chi2.logsf(stat, 1)) if np.isfinite(stat) else -np.inf, "explains": float(stat),
            "identifiable": True, "excess": 0, "value": a, "se": se}


def pixel_noise_test(obs: M.Observations, ibar: np.ndarray, valid: np.ndarray, *, alpha: float,
                     exclude: np.ndarray | None = None, fitted: np.ndarray | None = None) -> dict:
    """Pixel classes whose noise variance differs from the rest: found by detector column and row, factor per class.

    Per pixel, the Pearson chi-square X_i of its samples under the current noise model, each sample's z^2
    divided by the regular pixels' dispersion at its expected count (12 bins: a variance misfit that follows
    the count, a detector nonlinearity say, is no pixel class), and its degrees of freedom n_i - 3 (3 image
    unknowns). Per detector column (and row) the sum X against c times its dof,
    c the overall dispersion: z = (X - c dof) / (c sqrt(V)), V the variance of the summed z^2 (2 + g / mu
    per sample: scaled Poisson noise); columns and rows significant after Holm (alpha over all of them)
    are anomalous, and grouped by their variance ratio (:func:`_variance_groups`: lines whose ratios agree
    within noise). Classes: pixels sharing (column group, row group), group 0 regular; the regular class is
    the reference. Each other class gets the factor
    f = (X / dof of the class) / (X / dof of the regular class), so that its reduced chi-square becomes that
    of the rest (a global gain stays detector_gain's); where no pixel is regular (every row anomalous, say)
    the factors are against the stated noise model. Statistic: the Gaussian likelihood ratio of a
    variance scale per class, sum dof (f - 1 - ln f), chi-square with one dof per class.

    ``fitted`` (C,) marks the columns the per-frame parameters were fitted on: their residuals are smaller
    (the parameters took some of their variance, and of any misfit), so their dispersion reference is that
    of the regular fitted columns, per count bin like the rest.

    Returns
    -------
    dict
        'statistic', 'dof', 'p_value', 'log_p', 'explains', 'identifiable', 'excess', 'map' (H, W) factors
        (relative to the current ones), 'classes' (list of dict: 'columns', 'rows', 'pixels', 'factor').
    """
    sel = obs.use & valid[obs.pixel]
    if exclude is not None:
        sel &= ~exclude
    z2 = np.where(sel, M.pearson(obs, ibar), 0.0)
    g = obs.pixel_gain()[obs.pixel]
    kv = np.where(sel, 2.0 + g / np.maximum(ibar - obs.dark, 1e-3), 0.0)
    n = obs.segment_sum(sel.astype(float))
    dof = np.maximum(n - 3, 0.0)
    share = np.where(sel, (dof / np.maximum(n, 1))[obs.pixel], 0.0)  # a sample's share of its pixel's dof
    V = np.where(dof > 0, obs.segment_sum(kv) * dof / np.maximum(n, 1), 0.0)
    img = {k: obs.to_image(v, fill=0.0) for k, v in (("dof", dof), ("V", V))}
    H, W = obs.shape[1:]
    fmap = np.ones((H, W))
    none = {"statistic": 0.0, "dof": 0, "p_value": 1.0, "log_p": 0.0, "explains": 0.0, "identifiable": True,
            "excess": 0, "map": fmap, "classes": []}
    if img["dof"].sum() <= 0:
        return none
    # a variance misfit that depends on the expected count (detector nonlinearity, say) is not a pixel class:
    # z^2 is measured against the regular pixels' dispersion at the same count (12 bins of equal size)
    edges = np.quantile(ibar[sel], np.linspace(0, 1, 13)[1:-1])
    kind = np.zeros(obs.columns.size, int) if fitted is None else np.asarray(fitted, int)
    cbin = 2 * np.digitize(ibar, edges) + kind[None, :]
    groups = [np.zeros(W, int), np.zeros(H, int)]
    # the dispersion of the regular pixels, the anomalous columns and rows found against it: repeated until
    # they stay the same (anomalous lines would otherwise pull the reference and make the rest look anomalous)
    for _ in range(5):
        regular = (groups[1][:, None] == 0) & (groups[0][None, :] == 0)
        reg = sel & regular[obs.row][:, obs.columns]
        num = np.bincount(cbin[reg], weights=z2[reg], minlength=24)
        den = np.bincount(cbin[reg], weights=share[reg], minlength=24)
        per_count = np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)
        img["X"] = obs.to_image(np.where(dof > 0, obs.segment_sum(z2 / per_count[cbin]), 0.0), fill=0.0)
        c = _dispersion(img, regular)
        tests, lines = [], []
        for axis in (0, 1):
            # a column's sum over the regular rows, a row's over the regular columns
            keep = (groups[1][:, None] == 0) if axis == 0 else (groups[0][None, :] == 0)
            Xa, Da, Va = (np.where(keep, img[k], 0.0).sum(axis=axis) for k in ("X", "dof", "V"))
            ok = Da > 0
            z = np.where(ok, (Xa - c * Da) / (c * np.sqrt(np.where(ok, Va, 1.0))), 0.0)
            lines.append((Xa, Da, Va))
            tests += [{"log_p": float(np.log(2) + stats.norm.logsf(abs(v))), "axis": axis, "i": i}
                      for i, v in enumerate(z) if ok[i]]
        _holm(tests, alpha)
        new = []
        for axis in (0, 1):
            idx = np.array([t["i"] for t in tests if t["axis"] == axis and t["significant"]], int)
            Xa, Da, Va = lines[axis]
            new.append(_variance_groups(Xa[idx], Da[idx], Va[idx], idx, c=c, size=(W, H)[axis]))
        if all(np.array_equal(a, b) for a, b in zip(new, groups, strict=True)):
            break
        groups = new
    label = groups[1][:, None] * (groups[0].max() + 1) + groups[0][None, :]
    regular = label == 0
    if regular.all():
        return none
    c0 = _dispersion(img, regular)
    classes, stat = [], 0.0
    for k in np.unique(label[~regular]):
        m = label == k
        d = img["dof"][m].sum()
        if d <= 0:
            continue
        f = img["X"][m].sum() / d / c0
        fmap[m] = f
        stat += float(d * (f - 1 - np.log(f)))
        r_idx, c_idx = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        classes.append({"rows": _ranges(r_idx, limit=8), "columns": _ranges(c_idx, limit=8),
                        "pixels": int(m.sum()), "factor": float(f), "dof": float(d)})
    if not classes:
        return none
    k = len(classes)
    return {"statistic": stat, "dof": k, "p_value": float(stats.chi2.sf(stat, k)),
            "log_p": float(stats.chi2.logsf(stat, k)), "explains": stat, "identifiable": True, "excess": 0,
            "map": fmap, "classes": classes}


def _dispersion(img: dict, regular: np.ndarray) -> float:
    """Reduced chi-square of the regular pixels; 1 (the stated noise model) when every line is anomalous."""
    dof = img["dof"][regular].sum()
    return float(img["X"][regular].sum() / dof) if dof > 0 else 1.0


def _variance_groups(X: np.ndarray, dof: np.ndarray, V: np.ndarray, idx: np.ndarray, *, c: float, size: int,
                     z_split: float = 5.0) -> np.ndarray:
    """Group anomalous detector lines (columns or rows) whose variance ratios agree: 0 regular, 1, 2, ... groups.

    The lines ``idx`` (their chi-square sums X, dof and variances V), sorted by their ratio X / (c dof), join
    the current group while they lie within ``z_split`` standard deviations of its pooled ratio.
    """
    out = np.zeros(size, int)
    if idx.size == 0:
        return out
    ratio = X / (c * dof)
    order = np.argsort(ratio)
    g, Xg, Dg, Vg = 0, 0.0, 0.0, 0.0
    for i in order:
        if g and abs(ratio[i] - Xg / (c * Dg)) > z_split * np.sqrt(V[i] / dof[i] ** 2 + Vg / Dg ** 2):
            g, Xg, Dg, Vg = g + 1, 0.0, 0.0, 0.0
        g = max(g, 1)
        out[idx[i]] = g
        Xg, Dg, Vg = Xg + X[i], Dg + dof[i], Vg + V[i]
    return out


def class_chi2(obs: M.Observations, ibar: np.ndarray, valid: np.ndarray, classes: np.ndarray) -> dict[int, float]:
    """Reduced chi-square per pixel class: sum of Pearson residuals over sum of (samples - 3) per pixel.

    ``classes`` (H, W) int labels; returns label -> reduced chi-square (under the noise model of ``obs``).
    """
    sel = obs.use & valid[obs.pixel]
    n = obs.segment_sum(sel.astype(float))
    X = obs.to_image(obs.segment_sum(np.where(sel, M.pearson(obs, ibar), 0.0)), fill=0.0)
    dof = obs.to_image(np.maximum(n - 3, 0.0), fill=0.0)
    return {int(k): float(X[classes == k].sum() / dof[classes == k].sum()) for k in np.unique(classes)
            if dof[classes == k].sum() > 0}


def _held_noise(fmap: np.ndarray | None, obs: M.Observations) -> np.ndarray | None:
    """The variance factors (R, C) of the pixels ``obs`` holds, from a detector map (H, W); None stays None."""
    return None if fmap is None else fmap[np.ix_(obs.rows, obs.columns)]


def _set_pixel_noise(obs: M.Observations, fit_obs: M.Observations, fmap: np.ndarray | None) -> None:
    for o in (obs, fit_obs):
        o.noise = _held_noise(fmap, o)


def _lag_observations(prep: Prepared, like: M.Observations, shift: np.ndarray, fraction: float,
                      fit_cols: np.ndarray) -> tuple[Prepared, M.Observations, M.Observations]:
    """The preparation, test and fit observations with detector lag ``fraction`` taken out of the counts.

    ``like``: the current test observations (their region of interest, noise model and use are kept);
    ``shift``: where the flat field is read (a reference offset or position errors found before).
    """
    lag_prep = replace(prep, store=prep.store.lag_free(fraction))
    obs = realign(lag_prep, like, shift)
    return lag_prep, obs, obs.subset(fit_cols)


# --------------------------------------------------------------------------------------------------
# The loop
# --------------------------------------------------------------------------------------------------


def _chi2(obs: M.Observations, params: dict, *, n_params: int) -> tuple[float, float, Retrieval]:
    rec = retrieve(obs, params, n_frame_params=n_params)
    return rec.chi2_sum, rec.reduced_chi2, rec


def _where(name: str, test: dict, obs: M.Observations) -> str:
    if name == "sample_motion":
        return _motion_where(test["mask"])
    if name == "detector_gain":
        return "all pixels (noise, not the mean)"
    if name == "reference_offset":
        return "steps of the differential phase at the flat field's tile boundaries, all rows"
    if name == "detector_lag":
        return "all frames; signal in the rows the active area has just left"
    if name == "pixel_noise":
        return "; ".join(f"rows {c['rows']} x columns {c['columns']}" for c in test["classes"][:3])
    if not M.effect(name).per_frame:
        return "the whole detector (global parameters)"
    share = np.clip(test["frames"], 0, None)
    if share.sum() <= 0:
        return "no frame in particular"
    order = np.argsort(share)[::-1]
    top = np.sort(order[: max(1, int(np.searchsorted(np.cumsum(share[order]) / share.sum(), 0.5)) + 1)])
    spread = "all frames" if top.size > 0.3 * obs.n_frames else "few frames"
    return f"{spread}; half of the statistic in {top.size} frames, {top.min()}-{top.max()}"


def _motion_where(mask: np.ndarray) -> str:
    rows, cols = np.nonzero(mask)
    return (f"{rows.size} pixels in rows {rows.min()}-{rows.max()}, columns {cols.min()}-{cols.max()}"
            if rows.size else "nowhere")


def _estimate(name: str, params: dict, good: np.ndarray, extra: dict) -> str:
    if name == "detector_gain":
        return f"g = {extra['gain']:.3f}, electronic sigma = {np.sqrt(extra['electronic']):.3g} counts"
    if name == "sample_motion":
        return f"{extra['pixels']} pixels"
    if name == "reference_offset":
        return f"delta = {extra['value']:.3f} rows"
    if name == "position_error":
        return f"std {np.std(np.asarray(extra['values'])[good]):.3g} rows"
    if name == "detector_lag":
        return f"a = {100 * extra['value']:.4g} % (se {100 * extra['se']:.2g} %)"
    if name == "pixel_noise":
        return ", ".join(f"f = {c['factor']:.3g} ({c['pixels']} pixels)" for c in extra["classes"])
    p = params.get(name)
    if p is None:
        return ""
    e = M.effect(name)
    if e.per_frame:
        sd = np.std(p[good], axis=0)
        unit = " %" if name in ("dose", "visibility_loss") else (" rad" if e.channel == "phase" else "")
        factor = 100.0 if unit == " %" else 1.0
        return ", ".join(f"std {factor * s:.3g}{unit}" + (f" ({c})" if e.size > 1 else "")
                         for s, c in zip(sd, e.components, strict=True))
    if name == "harmonic":
        return f"a2 = {np.hypot(*p):.4g}, beta = {np.arctan2(p[1], p[0]):.3f} rad"
    return ", ".join(f"{c}: {v:.4g}" for c, v in zip(e.components, p, strict=True)) + " counts"


def diagnose(scan: Scan | str | Path | Prepared, cfg: dict | None = None, *, base: str = "configured") -> Diagnosis:
    """Locate model-data mismatch, name the missing effects, add them and refit until nothing is left.

    Parameters
    ----------
    scan : Scan, path or Prepared
        Prepared by :func:`dfxcorr.pipeline.prepare` (reference options, region of interest), as for
        a reconstruction.
    cfg : dict, optional
        Resolved configuration; its vibration section is the base model, its diagnose section the
        test settings.
    base : {'configured', 'none'}
        Start from the configured model, or from plain retrieval with no per-frame terms.

    Returns
    -------
    Diagnosis
    """
    cfg = C.defaults() if cfg is None else cfg
    d = cfg["diagnose"]
    timings: dict = {}
    prep = scan if isinstance(scan, Prepared) else prepare(scan, cfg, timings=timings)
    name = str(prep.path) if prep.path else prep.name
    scan, reference = prep.scan, prep.reference
    # the tests need every pixel: the diagnosis holds the whole scan (the reconstruction streams it)
    obs, roi = prep.observations()
    # the fit uses the tests' columns: a coarser fit's parameter noise would read as misfit
    fit_cols = subsample_columns(scan.shape[2], d["subsample"])
    fit_obs = obs.subset(fit_cols)
    usable = obs.use, fit_obs.use  # the prepared samples: detector faults (saturated, bad frames) stay out
    fitted = np.zeros(obs.columns.size, bool)
    fitted[fit_cols] = True
    shift = np.zeros(scan.shape[0])  # rows by which obs reads the flat field off the prepared alignment
    model = list(resolve_effects(cfg, scan, reference, fit_obs)) if base == "configured" else []
    base_model = list(model)
    good_frames = well_determined(fit_obs, cfg["fit"]["gauge_fraction"])
    motion = np.zeros(scan.shape[1:], bool)
    modelled_noise = False
    reports: dict[str, EffectReport] = {}
    detected: list[str] = []
    rounds: list[dict] = []
    last_tests: dict[str, dict] = {}
    rejected: dict[str, float] = {}
    changes: list[dict] = []
    blind: dict[str, dict] = {}  # unidentifiable effects tried: what a trial refit with them explained
    paper_why = visibility_unidentifiable(scan, reference)
    state = _fit_state(obs, fit_obs, model, {}, motion, cfg, timings, "round 0", usable=usable)
    initial = state["reduced_chi2"]
    before = locate(obs, M.design(obs, state["params"]), state["rec"].images, state["rec"].expected)
    for rnd in range(d["max_rounds"]):
        params, rec = state["params"], state["rec"]
        with stage(f"round {rnd}: tests", timings):
            dispersion = max(state["reduced_chi2"], 1e-6)
            weights = M.noise_weights(fit_obs, retrieve(fit_obs, params).expected)
            mean_candidates = [c for c in CANDIDATES if M.effect(c).channel is not None and c not in model]
            tests = score_tests(fit_obs, params, weights, model, mean_candidates, dispersion=dispersion)
            for c in ("visibility_loss", "visibility_tilt"):
                if paper_why and c in tests:
                    tests[c]["identifiable"] = False
            if not motion.any():
                tests["sample_motion"] = motion_test(obs, params, p_pixel=d["motion_p"], min_pixels=d["min_pixels"])
            if not modelled_noise:
                dsg = M.design(obs, params)
                outliers = tests["sample_motion"]["mask"] if "sample_motion" in tests else motion
                tests["detector_gain"] = gain_test(obs, rec.expected, M.solve_images(obs, dsg, rec.weights,
                                                                                       keep_inverse=True),
                                                   dsg, rec.weights,
                                                   exclude=ndimage.binary_dilation(outliers)[obs.row][:, obs.columns])
            # a phase-stepping recording has no scan positions to be off
            if "reference_offset" not in detected and not scan.is_stepping:
                tests["reference_offset"] = offset_test(prep, obs, params, shift)
            if "position_error" not in detected and not scan.is_stepping:
                tests["position_error"] = position_test(prep, fit_obs, params, shift, dispersion=dispersion)
            if "detector_lag" not in detected:
                tests["detector_lag"] = lag_test(prep)
            if "pixel_noise" not in detected:
                outliers = tests["sample_motion"]["mask"] if "sample_motion" in tests else motion
                tests["pixel_noise"] = pixel_noise_test(
                    obs, rec.expected, rec.images.valid, alpha=d["alpha"], fitted=fitted,
                    exclude=ndimage.binary_dilation(outliers)[obs.row][:, obs.columns])
        last_tests.update(tests)
        log.info("round %d: reduced chi-square %.4f; %s", rnd, state["reduced_chi2"],
                 ", ".join(f"{k} S={t['statistic']:.4g} (dof {t['dof']}{'' if t['identifiable'] else ', n.i.'})"
                           for k, t in sorted(tests.items(), key=lambda kv: -kv[1]["statistic"])))
        while (suspect := _strongest_unidentifiable(tests, alpha=d["alpha"], tried=blind)) is not None:
            # an effect this acquisition cannot determine may still be what the data show: if a trial refit with
            # it explains the misfit, no identifiable proxy may be named for it
            trial = _fit_state(obs, fit_obs, model + [suspect], params, motion, cfg, timings,
                               f"round {rnd}: trial {suspect} (not identifiable)", usable=usable)
            share = _explained_share(state["signatures"], trial["signatures"])
            _restore(obs, fit_obs, state)
            blind[suspect] = {"explains_misfit": share is None or share >= d["explain_share"],
                              "explained_share": share, "reduced_chi2_with": trial["reduced_chi2"]}
            if blind[suspect]["explains_misfit"]:
                log.warning("round %d: the misfit is what %s explains (reduced chi-square %.4f with it), which this "
                            "acquisition cannot identify: nothing else is named in its place", rnd, suspect,
                            trial["reduced_chi2"])
                break
        if any(b["explains_misfit"] for b in blind.values()):
            break
        chosen: tuple[str, dict] | None = None
        # the per-frame parameters, fitted on every n-th column, leave their noise in the other columns' residuals:
        # about n chi-square per parameter, an apparent gain that a stated one must not be taken for
        n_par = sum(np.size(p) for p in params.values())
        apparent = obs.gain * (1 + d["subsample"] * n_par * state["reduced_chi2"] / max(state["chi2"], 1.0))
        for candidate in _ranked(tests, alpha=d["alpha"], min_gain_change=d["min_gain_change"], gain=apparent):
            if candidate in rejected:
                continue
            t = tests[candidate]
            mask = ndimage.binary_dilation(t["mask"], iterations=1) if candidate == "sample_motion" else motion
            noise = (t["gain"], t["electronic"]) if candidate == "detector_gain" else (obs.gain, obs.electronic)
            views = _realigned(prep, obs, fit_obs, fit_cols, params, shift, candidate, t)
            # lag changes the data themselves: their fit starts afresh, as round 0 did
            lagged = _lag_observations(prep, obs, shift, t["value"], fit_cols) if candidate == "detector_lag" else None
            on, start = (views[:2], params) if lagged is None else (lagged[1:], {})
            noise_map = prep.pixel_noise
            if candidate == "pixel_noise":
                # the test's factors are relative to the current ones
                noise_map = t["map"] * (1.0 if prep.pixel_noise is None else prep.pixel_noise)
                _set_pixel_noise(obs, fit_obs, noise_map)
            trial = _fit_state(*on, model + [candidate] if M.effect(candidate).channel is not None else model,
                               start, mask, cfg, timings, f"round {rnd}: trial {candidate}", noise=noise,
                               usable=usable)
            share = _explained_share(state["signatures"], trial["signatures"])
            if share is None or share >= d["explain_share"] or (share >= 0 and _silences(state["signatures"],
                                                                                          trial["signatures"])):
                chosen = candidate, trial
                break
            log.info("round %d: %s removes %.0f %% of the significant residual signatures' excess: rejected",
                     rnd, candidate, 100 * share)
            rejected[candidate] = share
            _restore(obs, fit_obs, state)
            if candidate == "pixel_noise":
                _set_pixel_noise(obs, fit_obs, prep.pixel_noise)
        if chosen is None:
            break
        choice, trial = chosen
        t = tests[choice]
        extra: dict[str, Any] = {}
        # the data and noise model the state before the change was fitted with (lag and pixel_noise change them)
        before_obs = obs if choice != "pixel_noise" else replace(
            obs, noise=_held_noise(prep.pixel_noise, obs))
        if choice == "sample_motion":
            motion = trial["motion"]
            extra["pixels"] = int(motion.sum())
        elif choice == "detector_gain":
            modelled_noise = True
            extra = {"gain": t["gain"], "electronic": t["electronic"]}
        elif choice in ("reference_offset", "position_error"):
            obs, fit_obs, found = views
            # position errors in the gauge of phase_offset (median zero over the well-determined frames)
            extra = {"value": float(np.mean(found - shift))} if choice == "reference_offset" else \
                {"values": (found - shift - np.median((found - shift)[good_frames])).tolist()}
            shift = found
        elif choice == "detector_lag":
            assert lagged is not None  # the accepted trial's
            prep, obs, fit_obs = lagged
            extra = {"value": t["value"], "se": t["se"]}
        elif choice == "pixel_noise":
            prep = replace(prep, pixel_noise=noise_map)
            extra = {"classes": t["classes"]}
        else:
            model.append(choice)
        rejected.clear()  # a candidate that did not explain the misfit then may, now that the model changed
        detected.append(choice)
        reports[choice] = EffectReport(choice, True, True, t["statistic"], int(t["dof"]), t["p_value"],
                                       where=_where(choice, t, fit_obs), extra=extra)
        rounds.append({"round": rnd, "added": choice, "chi2_before": state["chi2"],
                       "reduced_chi2_before": state["reduced_chi2"], "reduced_chi2_after": trial["reduced_chi2"],
                       "delta_chi2": state["chi2"] - trial["chi2"], "explained_share": _explained_share(
                           state["signatures"], trial["signatures"])})
        reports[choice].delta_chi2 = rounds[-1]["delta_chi2"]
        reports[choice].reduced_chi2_after = trial["reduced_chi2"]
        reports[choice].estimate = _estimate(choice, trial["params"], good_frames, extra)
        changes.append(_change(choice, obs, state, trial, extra, before_obs=before_obs))
        log.info("round %d: adding %s", rnd, choice)
        state = trial
    params, rec = state["params"], state["rec"]
    after = locate(obs, M.design(obs, params), rec.images, rec.expected)
    effects = [reports[n] for n in detected]
    for n, t in sorted(last_tests.items(), key=lambda kv: -kv[1]["statistic"]):
        if n in reports:
            continue
        extra = {"excess_null_directions": t["excess"]} if t["excess"] else {}
        if n in rejected:
            extra["explained_share"] = rejected[n]
        extra.update(blind.get(n, {}))
        effects.append(EffectReport(n, False, bool(t["identifiable"]), t["statistic"], int(t["dof"]), t["p_value"],
                                    extra=extra))
    unexplained = _unexplained(state["signatures"], last_tests.get("sample_motion"), "sample_motion" in detected,
                               alpha=d["alpha"])
    criterion = (f"an effect is detected when its p-value beats Holm's threshold alpha / m (alpha = {d['alpha']}, "
                 f"m = effects tested in the round), it is identifiable, and, among those, it explains the most "
                 f"chi-square; structured effects first, then detector_gain (when the gain moves by more than "
                 f"{100 * d['min_gain_change']:.0f} %), then sample_motion ({d['min_pixels']} or more pixels in "
                 f"clusters of 3 whose per-pixel deviance has p < {d['motion_p']}). A candidate is added only if it "
                 f"explains the misfit's signature: after a trial refit with it, the excess (statistic - dof) of "
                 f"the residual signatures that were significant (Holm, alpha = {d['alpha']}) must shrink by "
                 f"{100 * d['explain_share']:.0f} % or more, or one of them must become insignificant while the "
                 f"excess does not grow; otherwise it stays out of the model (its explained "
                 f"share is reported) and the next candidate is tried. A significant effect that the acquisition "
                 f"cannot identify gets a trial refit first: if it explains the misfit so, the diagnosis stops "
                 f"there (naming a proxy would be the wrong physics). What stays significant is listed as "
                 f"unexplained")
    # the final alignment: the configured one, plus what was found (position_errors.txt holds the per-frame
    # shifts beyond the offset, common part included, so that reconstruct reads the flat field where this fit did)
    offset = float(reports["reference_offset"].extra["value"]) if "reference_offset" in reports else 0.0
    return Diagnosis(scan=name, base_model=base_model, initial_chi2=initial, final_chi2=state["reduced_chi2"],
                     effects=effects,
                     final_model=base_model + [n for n in detected if n in model and n not in base_model]
                     + [n for n in detected if n not in model],
                     before=before, after=after, params=params, gain=obs.gain, electronic=obs.electronic,
                     motion_mask=motion, criterion=criterion, rounds=rounds, unexplained=unexplained,
                     signatures=state["signatures"], shape=scan.shape, changes=changes,
                     reference_offset=cfg["align"]["reference_offset"] + offset,
                     position_errors=None if "position_error" not in reports else shift - offset + (
                         read_position_errors(cfg["align"]["position_errors"], scan.shape[0])
                         if cfg["align"]["position_errors"] is not None else 0.0),
                     pixel_noise=prep.pixel_noise if "pixel_noise" in detected else None)


def _change(name: str, obs: M.Observations, before: dict, after: dict, extra: dict, *,
            before_obs: M.Observations | None = None) -> dict:
    """What adding ``name`` changed, for its picture: images and residual maps before and after (H, W), and
    its per-frame estimate (J, n) where it has one. ``before_obs``: the observations of ``before`` where the
    change altered the data or their noise model (detector_lag, pixel_noise); default ``obs``."""
    out: dict[str, Any] = {"name": name, "reduced_chi2": (before["reduced_chi2"], after["reduced_chi2"])}
    for key, state, seen in (("before", before, before_obs or obs), ("after", after, obs)):
        rec = state["rec"]
        out[key] = image_maps(seen, rec.images)
        out[key]["residual"] = locate(seen, M.design(seen, state["params"]), rec.images, rec.expected).pixel
    values = after["params"].get(name) if M.effect(name).per_frame else None
    if values is None and "values" in extra:
        values = np.asarray(extra["values"], dtype=np.float64).reshape(len(extra["values"]), -1)
    out["per_frame"] = values
    out["components"] = M.effect(name).components
    return out


def _set_noise(obs: M.Observations, fit_obs: M.Observations, noise: tuple[float, float]) -> None:
    for o in (obs, fit_obs):
        o.gain, o.electronic = noise


def _restore(obs: M.Observations, fit_obs: M.Observations, state: dict) -> None:
    """Undo a rejected trial: the noise model and the masked pixels of ``state``."""
    _set_noise(obs, fit_obs, (state["gain"], state["electronic"]))
    _set_use(obs, fit_obs, state["motion"], state["usable"])


def _set_use(obs: M.Observations, fit_obs: M.Observations, motion: np.ndarray,
             usable: tuple[np.ndarray, np.ndarray]) -> None:
    """As in reconstruct: the tests count the region of interest, the fit also the samples without fringe
    (they monitor dose and background); ``motion`` pixels count in neither, nor samples outside ``usable``
    (the prepared ``use`` of each). The preparation zeroes v^f outside the region of interest, and the
    reference visibility is positive everywhere else."""
    obs.use = usable[0] & (obs.vf > 0) & ~motion[obs.row][:, obs.columns]
    fit_obs.use = usable[1] & ~motion[fit_obs.row][:, fit_obs.columns]


def _fit_state(obs: M.Observations, fit_obs: M.Observations, model: list, start: dict, motion: np.ndarray,
               cfg: dict, timings: dict, label: str, *, noise: tuple[float, float] | None = None,
               usable: tuple[np.ndarray, np.ndarray]) -> dict:
    """Fit ``model`` with ``motion`` pixels left out (and the noise model ``noise``); chi-square and signatures."""
    if noise is not None:
        _set_noise(obs, fit_obs, noise)
    _set_use(obs, fit_obs, motion, usable)
    params = {}
    with stage(f"{label}: fit {'+'.join(model) or 'images only'}", timings):
        if model:
            # after the first round the fit starts next to its optimum: no staging against local minima
            warm = bool(start)
            fitted = fit_vibrations(fit_obs, effects=model, start=start, gtol=cfg["fit"]["gtol"], staged=not warm,
                                    circmean_iterations=0 if warm else cfg["fit"]["circmean_iterations"],
                                    reweight=0 if warm else 1, precondition=cfg["fit"]["precondition"],
                                    preconditioner=cfg["fit"]["preconditioner"],
                                    visibility_gauge=cfg["fit"]["visibility_gauge"],
                                    visibility_quantile=cfg["fit"]["visibility_quantile"],
                                    gauge_fraction=cfg["fit"]["gauge_fraction"])
            params = {k: v for k, v in fitted.params.items() if k in model}
        n_par = sum(np.size(p) for p in params.values())
        chi2_sum, chi2_red, rec = _chi2(obs, params, n_params=n_par)
        sigs = signatures(fit_obs, params, n_params=n_par, alpha=cfg["diagnose"]["alpha"])
    return {"params": params, "chi2": chi2_sum, "reduced_chi2": chi2_red, "rec": rec, "signatures": sigs,
            "motion": motion, "usable": usable, "gain": obs.gain, "electronic": obs.electronic}


def _realigned(prep: Prepared, obs: M.Observations, fit_obs: M.Observations, fit_cols: np.ndarray, params: dict,
               shift: np.ndarray, candidate: str, test: dict
               ) -> tuple[M.Observations, M.Observations, np.ndarray]:
    """The samples a trial of ``candidate`` fits: realigned for reference_offset and position_error.

    Returns (obs, fit_obs, shift): the observations (all columns, and the fit's) and the per-frame rows by
    which they read the flat field off the prepared alignment (``shift`` unchanged for other candidates).
    """
    if candidate == "reference_offset":
        found = shift + test["value"]
        # one refinement at the corrected alignment: the step's sensitivity is a linearisation
        found = found + offset_test(prep, realign(prep, obs, found), params, found)["value"]
    elif candidate == "position_error":
        delta, _ = estimate_position_errors(prep, fit_obs, params, shift)
        found = shift + delta
    else:
        return obs, fit_obs, shift
    moved = realign(prep, obs, found)
    return moved, moved.subset(fit_cols), found


def _significant(tests: dict, alpha: float) -> list[str]:
    """The candidates whose test beats Holm's first threshold alpha / m (m = candidates tested in the round)."""
    return [k for k, t in tests.items() if t["log_p"] < np.log(alpha / len(tests))]


def _strongest_unidentifiable(tests: dict, *, alpha: float, tried: dict) -> str | None:
    """The not identifiable mean effect, not tried yet, whose score test is significant (Holm) with the largest
    explained chi-square; None if there is none."""
    cands = [k for k in _significant(tests, alpha) if not tests[k]["identifiable"] and k not in tried
             and M.effect(k).channel is not None]
    return max(cands, key=lambda k: tests[k]["explains"]) if cands else None


def _ranked(tests: dict, *, alpha: float, min_gain_change: float, gain: float) -> list[str]:
    """Significant identifiable candidates in the order they are tried.

    Holm over the m effects tested; structured effects (sample_motion included) by the chi-square they
    explain, detector_gain at the end but before sample_motion (a global variance excess is modelled
    before localised outliers are judged against it), pixel_noise just before detector_gain, detector_lag
    first (measured directly).
    """
    sig = {k for k in _significant(tests, alpha) if tests[k]["identifiable"]}
    # a reference offset's statistic comes from the image, not the likelihood (which barely sees it); its step
    # signature at the tile boundaries is specific, while mean-effect proxies would soak up what it does to the fit
    order = sorted((k for k in sig if k != "detector_gain"), key=lambda k: (k != "reference_offset",
                                                                            -tests[k]["explains"]))
    if "detector_lag" in order:
        # measured directly outside the active area: the mean effects would only soak up its traces
        order.insert(0, order.pop(order.index("detector_lag")))
    if "detector_gain" in sig and abs(tests["detector_gain"]["gain"] / gain - 1) > min_gain_change:
        at = order.index("sample_motion") if "sample_motion" in order else len(order)
        order.insert(at, "detector_gain")
    if "pixel_noise" in order:
        # a variance pattern: after the mean effects, before a global gain (its factors are relative to the
        # regular pixels, so a gain fitted first would be pulled by the anomalous ones) and localised outliers
        order.remove("pixel_noise")
        later = [order.index(k) for k in ("detector_gain", "sample_motion") if k in order]
        order.insert(min(later, default=len(order)), "pixel_noise")
    return order


def _excess(sigs: list[dict], keys: set) -> float:
    return sum(max(s["statistic"] - s["dof"], 0.0) for s in sigs if (s["axis"], s["kind"]) in keys)


def _explained_share(before: list[dict], after: list[dict]) -> float | None:
    """Share of the significant signatures' excess chi-square that a change removed (None: none significant)."""
    keys = {(s["axis"], s["kind"]) for s in before if s["significant"]}
    if not keys:
        return None
    return 1.0 - _excess(after, keys) / _excess(before, keys)


def _silences(before: list[dict], after: list[dict]) -> bool:
    """Whether a significant signature became insignificant (the candidate explains that signature)."""
    now = {(s["axis"], s["kind"]): s["significant"] for s in after}
    return any(s["significant"] and not now.get((s["axis"], s["kind"]), False) for s in before)


def _unexplained(sigs: list[dict], motion: dict | None, modelled_motion: bool, *, alpha: float) -> list[dict]:
    """The ``unexplained`` entries of diagnosis.json: significant signatures of the final fit."""
    out = [{"axis": s["axis"], "statistic": s["statistic"], "dof": s["dof"], "p_value": s["p_value"],
            "where": s["where"], "description": s["description"]} for s in sigs if s["significant"]]
    if motion is not None and not modelled_motion and motion["dof"] and motion["log_p"] < np.log(alpha):
        out.append({"axis": "pixel", "statistic": motion["statistic"], "dof": motion["dof"],
                    "p_value": motion["p_value"], "where": _motion_where(motion["mask"]),
                    "description": f"{int(motion['mask'].sum())} pixels whose frames disagree beyond noise, in "
                                   f"clusters; masking them does not explain the misfit"})
    return sorted(out, key=lambda u: u["p_value"])


def write_report(diag: Diagnosis, out_dir: Path, *, overwrite: bool = False) -> list[Path]:
    """Write ``diagnosis.json``, ``report.md``, ``residuals.png``, ``signatures.png``, one
    ``effect-<name>.png`` per detected effect and (if detected) ``motion_mask.tif`` and ``position_errors.txt``
    (one delta_j per frame, rows: ``align.position_errors``)."""
    import tifffile

    from ..export import check_output

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {k: out_dir / k for k in ("diagnosis.json", "report.md", "residuals.png", "signatures.png")}
    paths.update({c["name"]: out_dir / _effect_picture(c["name"]) for c in diag.changes})
    positions, mask, noise = (out_dir / n for n in ("position_errors.txt", "motion_mask.tif", "pixel_noise.tif"))
    optional = [(positions, diag.position_errors is not None), (mask, diag.motion_mask.any()),
                (noise, diag.pixel_noise is not None)]
    for p in [*paths.values(), *(p for p, written in optional if written)]:
        check_output(p, overwrite=overwrite)
    with atomic_path(paths["diagnosis.json"], overwrite=overwrite) as tmp:
        tmp.write_text(json.dumps(diag.to_json(), indent=2, default=float) + "\n")
    plots.plot_diagnosis(diag, paths["residuals.png"], overwrite=overwrite)
    plots.plot_signatures(diag.signatures, paths["signatures.png"], n_frames=diag.shape[0], n_rows=diag.shape[1],
                          overwrite=overwrite)
    for change in diag.changes:
        plots.plot_effect(change, paths[change["name"]], overwrite=overwrite)
    written = list(paths.values())
    if diag.motion_mask.any():
        with atomic_path(mask, overwrite=overwrite) as tmp:
            tifffile.imwrite(tmp, diag.motion_mask.astype(np.uint8))
        written.append(mask)
    if diag.position_errors is not None:
        with atomic_path(positions, overwrite=overwrite) as tmp:
            np.savetxt(tmp, diag.position_errors, fmt="%.6f",
                       header="position error delta_j of each frame (rows): dfxcorr reconstruct --set "
                              "align.position_errors=<this file>")
        written.append(positions)
    if diag.pixel_noise is not None:
        with atomic_path(noise, overwrite=overwrite) as tmp:
            tifffile.imwrite(tmp, diag.pixel_noise.astype(np.float32))
        written.append(noise)
    with atomic_path(paths["report.md"], overwrite=overwrite) as tmp:
        tmp.write_text(_markdown(diag, out_dir))
    return written


def _effect_picture(name: str) -> str:
    return f"effect-{name}.png"


def _markdown(diag: Diagnosis, out_dir: Path | None = None) -> str:
    lines = [f"# dfxcorr diagnose: {diag.scan}", "",
             (f"Base model: {', '.join(diag.base_model) or 'none (plain retrieval)'}. "
              f"Final model: {', '.join(diag.final_model) or 'none'}."), "",
             f"Reduced chi-square: {diag.initial_chi2:.4f} initially, {diag.final_chi2:.4f} at the end.", "",
             "![where the model and the data disagree](residuals.png)", "",
             ("Top row: mean squared standardized residual per pixel before and after (1 = photon noise). "
              "Below: the same by frame, lateral position, fringe phase and expected count."), "",
             ("| effect | detected | identifiable | statistic | dof | p-value | delta chi2 | reduced chi2 after "
              "| where | estimate |"), "|---|---|---|---|---|---|---|---|---|---|"]

    def fmt(v, f):
        return "" if v is None else format(v, f)

    for e in diag.effects:
        lines.append(f"| {e.name} | {'yes' if e.detected else 'no'} | {'yes' if e.identifiable else 'no'} | "
                     f"{e.statistic:.4g} | {e.dof} | {e.p_value:.3g} | {fmt(e.delta_chi2, '.4g')} | "
                     f"{fmt(e.reduced_chi2_after, '.4f')} | {_verdict_where(e)} | {e.estimate or ''} |")
    lines += ["", f"Criterion: {diag.criterion}.", "",
              ("delta chi2 is the change of the Pearson chi-square sum when the effect was added; for detector_gain "
               "it is negative when the noise is below Poisson (the reduced chi-square then rises towards 1)."), "",
              ("Not identifiable means the Fisher information has directions of that effect's parameters without "
               "information beyond its gauge: the acquisition cannot tell it from the images or the model's other "
               "effects (paper Sec. II-F), so it is never reported as detected."), "",
              "## Unexplained", ""]
    if diag.unexplained:
        lines += [(f"The final model still leaves {len(diag.unexplained)} significant residual signature(s) that no "
                   "catalogue effect explains (significant after Holm's correction over the signatures tested; the "
                   "model is not complete here, whatever the reduced chi-square says):"), "",
                  "| axis | statistic | dof | p-value | where | description |", "|---|---|---|---|---|---|"]
        lines += [f"| {u['axis']} | {u['statistic']:.4g} | {u['dof']} | {u['p_value']:.3g} | {u['where']} | "
                  f"{u['description']} |" for u in diag.unexplained]
    else:
        lines += ["None: no residual signature of the final fit is significant."]
    lines += ["", "![residual signatures of the final fit](signatures.png)", "",
              ("Residual signatures of the final fit on its own columns: per bin, the excess of the squared "
               "(variance) or plain (mean) standardized residual over what noise leaves after the fit took its "
               "share (3 image unknowns per pixel, the per-frame parameters' leverage), in units of its standard "
               "deviation; bins beyond 3 sigma in red, panel titles in red where the signature is significant."), ""]
    if diag.changes:
        lines += ["## What each detected effect changed", ""]
        for c in diag.changes:
            lines += [f"![adding {c['name']}]({_effect_picture(c['name'])})", ""]
        lines += [("Per effect, in the order added: the differential-phase and dark-field images of the fit before "
                   "and after adding it, and their difference; the residual per pixel before and after; its "
                   "per-frame estimate against frame where it has one."), ""]
    if diag.motion_mask.any():
        lines += [f"The pixels taken as moving are in motion_mask.tif ({int(diag.motion_mask.sum())} pixels).", ""]
    sets = reconstruct_settings(diag, out_dir=out_dir)
    lines += ["To reconstruct with the final model:", "",
              f"    dfxcorr reconstruct {diag.scan} -o result.h5" + "".join(f" --set {s}" for s in sets), ""]
    return "\n".join(lines)


def _verdict_where(e: EffectReport) -> str:
    if e.extra.get("explains_misfit"):
        return (f"explains the misfit (a trial refit with it reaches reduced chi-square "
                f"{e.extra['reduced_chi2_with']:.4f}), but this acquisition cannot identify it: nothing else is "
                f"named in its place")
    if "explained_share" in e.extra:
        return (f"significant, but a trial refit removes only {100 * e.extra['explained_share']:.0f} % of the "
                f"signatures' excess: not added")
    return e.where or ""


def reconstruct_settings(diag: Diagnosis, *, out_dir: Path | None = None) -> list[str]:
    """The ``--set`` options that make ``reconstruct`` use the diagnosis's final model.

    ``out_dir``: where :func:`write_report` put ``position_errors.txt`` and ``pixel_noise.tif`` (default: the
    current directory).
    """
    keys = {e: k for k, e in C.VIBRATION_EFFECTS.items()}
    sets = [f"vibration.{keys[n]}=true" for n in diag.final_model if n in keys and n not in diag.base_model]
    sets += [f"vibration.{keys[n]}=false" for n in M.PAPER_MODEL if n not in diag.final_model]
    if "sample_motion" in diag.final_model:
        sets.append("mask.enabled=true")
    if "detector_gain" in diag.final_model:
        sets += [f"load.gain={diag.gain:.4g}", f"load.electronic={diag.electronic:.4g}"]
    if diag.reference_offset:
        sets.append(f"align.reference_offset={diag.reference_offset:.4g}")
    if diag.position_errors is not None:
        sets.append(f"align.position_errors={Path(out_dir or '.') / 'position_errors.txt'}")
    sets += [f"load.detector_lag={e.extra['value']:.6g}" for e in diag.effects
             if e.name == "detector_lag" and e.detected]
    if "pixel_noise" in diag.final_model:
        sets.append(f"load.pixel_noise={Path(out_dir or '.') / 'pixel_noise.tif'}")
    return sets


