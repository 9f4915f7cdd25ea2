"""Where a recording and the model disagree: residual maps, and residual signatures tested against noise.

:func:`locate` gives the mean squared standardized residual by pixel, frame, lateral position, fringe
phase and expected count (the report's pictures). :func:`signatures` tests the residuals of a fit along
each axis (frame, row, column, (frame, row) block, fringe phase, expected count) against what noise
leaves after the fit took its share: what the diagnosis asks an effect to explain, and what it reports
as ``unexplained`` where nothing does.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import model as M
from ..chunks import row_counts
from ..effects.residuals import reduced_map, squared_residuals
from ..noise import variance
from ..observations import Observations
from ..retrieve import Retrieval, retrieve
from ..stats import chi2_tail, digitize, holm, ranges


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


def locate(obs: Observations, params: dict[str, Any], images: M.Images, *, counts: np.ndarray,
           chunk: float = 5e5) -> Residuals:
    """Mean squared standardized residual per pixel, frame, lateral position, fringe phase and count, over the used
    samples of solved pixels (the per-pixel map is :func:`dfxcorr.effects.residuals.reduced_map`'s).

    Computed a run of columns at a time (about ``chunk`` samples: :func:`dfxcorr.effects.residuals.squared_residuals`),
    the expected counts from ``images`` and the model at ``params``, so that a scan of every column holds one run's
    temporaries. ``counts``: expected counts whose 0.5 and 99.5 percentiles bound the count bins (the fit's
    columns' do: the bins need not see every sample).
    """
    C = obs.columns.size
    n = np.zeros((obs.starts.size, C))
    z2_pixel = np.zeros((obs.starts.size, C))
    frame_z2, frame_n = np.zeros(obs.n_frames), np.zeros(obs.n_frames)
    xs = np.full(C, np.nan)
    edges = np.linspace(-np.pi, np.pi, 17)
    lo, hi = np.nanpercentile(counts, [0.5, 99.5])
    cedges = np.geomspace(max(lo, 1e-3), max(hi, 2 * max(lo, 1e-3)), 13)
    phase = np.zeros((2, edges.size - 1))
    count = np.zeros((2, cedges.size - 1))
    phi = images.phi
    for cols, sub, ibar, sel, z2 in squared_residuals(obs, params, images, samples=chunk):
        used = sel.sum(axis=0)
        n[:, cols] = row_counts(sub, sel)
        z2_pixel[:, cols] = sub.segment_sum(z2)
        frame_z2 += sub.frame_sum(z2.sum(axis=1))
        frame_n += sub.frame_sum(sel.sum(axis=1))
        with np.errstate(invalid="ignore", divide="ignore"):
            xs[cols] = z2.sum(axis=0) / used
        theta = M.fringe_phase(sub, M.channels(params, x=sub.x, n_frames=sub.n_frames))
        phase += _binned(M.wrap_angle(theta + phi[:, cols][sub.pixel]), z2, sel, edges)
        count += _binned(ibar, z2, sel, cedges)
    with np.errstate(invalid="ignore", divide="ignore"):
        pixel = obs.to_image(reduced_map(z2_pixel, n - 3))
        frame, phase_mean, count_mean = frame_z2 / frame_n, phase[0] / phase[1], count[0] / count[1]
    # a retrieval with 3 unknowns per pixel leaves (n - 3) / n of the variance in the residuals
    scale = float(np.nansum(n) / np.nansum(np.maximum(n - 3, 0)))
    return Residuals(pixel=pixel, frame=frame * scale, x=xs * scale, x_value=obs.x, phase=phase_mean * scale,
                     phase_value=0.5 * (edges[1:] + edges[:-1]), count=count_mean * scale,
                     count_value=np.sqrt(cedges[1:] * cedges[:-1]))


def _binned(value: np.ndarray, z2: np.ndarray, sel: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Sum of the selected ``z2`` and their number in each bin of ``value`` between ``edges``, shape (2, bins)."""
    nb = edges.size - 1
    idx = digitize(value, edges).ravel().astype(np.intp) - 1
    # the samples outside every bin, or not selected, go to one more bin, dropped: no copies of the rest
    idx[~sel.ravel() | (idx < 0) | (idx >= nb)] = nb
    return np.stack([np.bincount(idx, weights=np.where(idx < nb, z2.ravel(), 0.0), minlength=nb + 1)[:nb],
                     np.bincount(idx, minlength=nb + 1)[:nb]])


#: Axes of the residual signatures (``unexplained`` in ``spec/diagnosis.md``, version 2).
SIGNATURE_AXES = ("frame", "row", "column", "frame_row", "phase", "count", "pixel")


def signatures(obs: Observations, params: dict[str, Any], *, alpha: float, min_photons: float = 25.0,
               rec: Retrieval | None = None, leverage: np.ndarray | None = None) -> list[dict[str, Any]]:
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
    alpha : float
        Family-wise false-alarm probability: each signature's ``significant`` is Holm's verdict over
        all of them.
    min_photons : float
        The mean signatures use only samples expecting at least this many photons.
    rec : Retrieval, optional
        The retrieval of ``obs`` with ``params`` that keeps the inverse normal matrices (default: made here).
    leverage : ndarray, shape (K, C), optional
        The samples' leverage in their pixels' images at ``rec`` (:func:`dfxcorr.model.leverage`), where the caller
        holds it (default: made here).

    Returns
    -------
    list of dict
        'axis', 'kind' ('variance' or 'mean'), 'statistic', 'dof', 'p_value', 'log_p', 'significant',
        'bins' (per-bin standardized S / sqrt(var)), 'bin_value' (bin centres: frame, row, column, block,
        phase in rad, count), 'relative' (per-bin S / expectation: relative variance excess, or mean z),
        'where', 'description'.
    """
    rec = retrieve(obs, params, keep_inverse=True) if rec is None else rec
    dsg = M.design(obs, params)
    images, ibar = rec.images, rec.expected
    sel = obs.use & obs.gather_valid(images.valid) & (rec.weights > 0)
    w = np.where(sel, rec.weights, 0.0)
    # the fit's per-frame parameters take their share too, largest where a frame's information is
    # (edge columns for the tilt, bright modulated samples for the phase)
    h_par, info_inv, Dn = M.frame_leverage(obs, dsg, images, w, params)
    h = np.where(sel, (M.leverage(obs, dsg, images, rec.weights) if leverage is None else leverage) + h_par, 0.0)
    keep = np.where(sel, np.clip(1.0 - h, 0.0, 1.0), 0.0)
    var = variance(obs, ibar)
    z = np.where(sel, (obs.counts - ibar) / np.sqrt(var), 0.0)
    c = float(np.sum(z ** 2) / np.sum(keep))
    g_true = c * obs.sample_gain()
    kurt = g_true ** 3 * np.maximum(obs.photons(ibar), 1e-3) / (c * var) ** 2
    e = np.where(sel, z ** 2 - c * keep, 0.0)
    # at a few photons the weighted fit's mean is biased towards low counts: dim samples would give the
    # mean signatures a sign they do not have
    bright = sel & (np.maximum(obs.photons(ibar), 0.0) >= min_photons * g_true)
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
    at = obs.gather(images.coef)
    psi = M.wrap_angle(M.fringe_phase(obs, dsg.channels) + np.arctan2(at[..., 2], at[..., 1]))
    pedges = np.linspace(-np.pi, np.pi, 17)
    cedges = np.quantile(ibar[sel], np.linspace(0, 1, 13)) if sel.any() else np.arange(13.0)
    labels = {
        "frame": (frame, np.arange(obs.n_frames)),
        "row": (np.broadcast_to(obs.row[:, None], (K, C_)), np.arange(obs.shape[1])),
        "column": (np.broadcast_to(np.arange(C_)[None, :], (K, C_)), obs.columns),
        "frame_row": (np.broadcast_to(np.arange(K)[:, None], (K, C_)), np.arange(K)),
        # a sample without fringe (outside the region of interest: it monitors dose and background) has no fringe
        # phase: its label is past the last bin, whose sums leave it out
        "phase": (np.where(obs.in_roi, np.clip(digitize(psi, pedges) - 1, 0, 15), 16),
                  0.5 * (pedges[1:] + pedges[:-1])),
        "count": (np.clip(digitize(ibar, cedges[1:-1]), 0, 11), np.sqrt(np.abs(cedges[1:] * cedges[:-1]))),
    }
    kinds = ([(a, "variance") for a in ("frame", "row", "column", "phase", "count")]
             + [(a, "mean") for a in ("frame", "frame_row")])
    # the selected samples' labels and weights of every axis's sums, taken out once (each axis's bins are a bincount
    # of them)
    selected = {axis: lab[sel] for axis, (lab, _) in labels.items()}
    weights = {"e": e[sel], "kappa": kappa[sel], "kappa_pixels": kappa_pixels[sel], "keep": keep[sel],
               "z_bright": np.where(bright, z, 0.0)[sel], "keep_bright": np.where(bright, keep, 0.0)[sel],
               "bright": bright[sel].astype(float)}
    D_bright = [np.where(bright, Dn[..., a], 0.0)[sel] for a in range(Dn.shape[-1])]
    out = []
    for axis, kind in kinds:
        lab, value = selected[axis], labels[axis][1]
        nb = value.size
        S: np.ndarray
        V: np.ndarray
        expect: np.ndarray
        if kind == "variance":
            S = np.bincount(lab, weights=weights["e"], minlength=nb)
            V = np.bincount(lab, weights=weights["kappa_pixels" if axis in ("row", "column") else "kappa"],
                            minlength=nb)
            expect = c * np.bincount(lab, weights=weights["keep"], minlength=nb)
            lost = 1.0
        else:
            S = np.bincount(lab, weights=weights["z_bright"], minlength=nb)
            V = c * np.bincount(lab, weights=weights["keep_bright"], minlength=nb)
            expect = np.bincount(lab, weights=weights["bright"], minlength=nb)
            # what the per-frame parameters took of each bin's sum: g^T I^-1 g with g = sum of the bin's
            # standardized derivatives (a bin lies within one frame on these axes)
            g = np.zeros((nb, Dn.shape[-1]))
            for a, Da in enumerate(D_bright):
                g[:, a] = np.bincount(lab, weights=Da, minlength=nb)
            first = np.zeros(nb, int)
            first[lab] = selected["frame"]
            # at most the bin's own one: a frame the fit cannot determine (its inverse information infinite, on a fit
            # of a few columns) takes all of its bins
            with np.errstate(divide="ignore", invalid="ignore"):
                lost = float(np.nansum(np.minimum(np.einsum("ba,bac,bc->b", g, info_inv[first], g) * c / V, 1.0)))
            if axis == "frame_row" and g.shape[1]:
                S, lost = _without_frame_terms(S, V, g, first)
        S, V, expect = S[:nb], V[:nb], expect[:nb]
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
        p_value, log_p = chi2_tail(stat, dof)
        out.append({"axis": axis, "kind": kind, "statistic": stat, "dof": dof,
                    "p_value": p_value, "log_p": log_p,
                    "bins": std, "bin_value": value, "relative": rel})
        if axis == "frame_row":
            out[-1].update(frame=obs.frame, row=obs.row)
    # the global level against the stated noise model: detector_gain's signature (a count signature
    # that is flat in the count)
    level = float(np.sum(z ** 2 - keep))
    # a sum over whole pixels: their residuals' correlation counts (kappa_pixels, as for rows and columns); with the
    # independent-sample variance a clean flat panel (its read noise stated) read 2.6 % below noise at p 7e-4
    spread = float(np.sum(kappa_pixels))
    p_value, log_p = chi2_tail(level ** 2 / spread, 1)
    out.append({"axis": "count", "kind": "level", "statistic": level ** 2 / spread, "dof": 1,
                "p_value": p_value, "log_p": log_p,
                "bins": np.array([level / np.sqrt(spread)]), "bin_value": np.array([np.nan]),
                "relative": np.array([level / np.sum(keep)])})
    for sig, significant in zip(out, holm([float(s["log_p"]) for s in out], alpha), strict=True):
        sig["significant"] = significant
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


def _describe(sig: dict[str, Any], obs: Observations) -> tuple[str, str]:
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
        where = f"frames {ranges(value[idx], limit=4)}"
    elif axis == "row":
        where = f"detector rows {ranges(value[idx], limit=4)}"
    elif axis == "column":
        where = f"columns {ranges(value[idx], limit=4)}"
    elif axis == "frame_row":
        frames, rows = obs.frame[value[idx]], obs.row[value[idx]]
        where = (f"{idx.size} (frame, row) blocks in frames {frames.min()}-{frames.max()}, "
                 f"rows {rows.min()}-{rows.max()}")
    elif axis == "phase":
        where = ("all frames; fringe phase " + ", ".join(f"{v:+.2f}" for v in value[idx][:6]) + " rad"
                 + (" (near the fringe maximum)" if np.all(np.abs(value[idx]) < np.pi / 2) else
                    " (near the fringe minimum)" if np.all(np.abs(value[idx]) > np.pi / 2) else ""))
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
