"""Per-frame matters of the vibration fit: the gauge (paper eq. 22) and the frames that set it, phases wrapped into
one period, the priors that keep weakly lit frames near the others, and the grid search that moves such a frame
out of a wrong local minimum."""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from . import engine as E
from . import model as M
from .align import gauge_frames
from .catalogue import effect
from .observations import Observations


def wrap_phases(params: dict, obs: Observations) -> dict:
    """Move phase parameters into their symmetry window without changing the model.

    A phase offset is defined modulo 2 pi. On columns spaced by n the tilt is defined modulo the alias
    period pi W / n (paper Sec. II-D.1), up to a constant phase that the offset takes up. Frames that
    light only a few rows can land on such an equivalent solution; this brings them back.
    """
    out = dict(params)
    W = obs.shape[2]
    spacing = np.unique(np.diff(obs.columns))
    if "tilt" in out and spacing.size == 1 and "phase_offset" in out:
        period = 2 * np.pi * W / (2 * spacing[0])
        k = np.round(out["tilt"] / period)
        out["tilt"] = out["tilt"] - k * period
        out["phase_offset"] = out["phase_offset"] + k * period * obs.x[0]
    if "phase_offset" in out:
        out["phase_offset"] = np.angle(np.exp(1j * out["phase_offset"]))
    return out


def catalogue_prior(names: Iterable[str]) -> dict:
    """A wide prior for every per-frame effect: its neutral value, width from the catalogue."""
    return {n: (effect(n).neutral, effect(n).scale) for n in names if effect(n).per_frame}


def empirical_prior(params: dict, good: np.ndarray, *, floor: float = 1e-3) -> dict:
    """Per-frame parameters as draws from the distribution of the well-determined frames.

    Centre: their median; width: their robust standard deviation (1.4826 MAD, at least ``floor``).
    Where the data determine a frame this prior is negligible (a shrinkage of (sigma_fit / width)^2);
    where they hardly do, it keeps the frame among the plausible values.
    """
    out = {}
    for n, p in params.items():
        if effect(n).per_frame:
            med = np.median(p[good], axis=0)
            out[n] = (med, np.maximum(1.4826 * np.median(np.abs(p[good] - med), axis=0), floor))
    return out


def rescue_frames(obs: Observations, params: dict, weights: np.ndarray, frames: np.ndarray,
                  prior: dict, *, n_offset: int = 48, n_tilt: int = 41) -> tuple[dict, int]:
    """Global search over phase offset and tilt for frames that light only a few rows.

    With few rows a frame's cost has several local minima in (phi0, phi1) (on subsampled columns the
    tilt is moreover only defined modulo the alias period); L-BFGS keeps whichever it started in.
    Holding the images at their current values (each frame is one of many that determine a pixel),
    the frame's own cost plus the prior is evaluated on a grid over a full period of phi0 and +-4
    prior widths of phi1, and the frame moves to the best grid point where that beats its current value.

    Returns
    -------
    params : dict
        Updated copy.
    moved : int
        Number of frames moved.
    """
    params = {k: v.copy() for k, v in params.items()}
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    # the images alone: each frame's current cost below is its grid's at its own values (the retrieval's expected
    # counts and weights of every sample were 216 MB at 2.7e7 samples)
    now = E.retrieve(obs, ch, weights=weights, keep_expected=False)
    c1, w1 = (float(np.ravel(prior["tilt"][0])[0]), float(np.ravel(prior["tilt"][1])[0])) if "tilt" in prior else (0, 1)
    offsets = np.linspace(-np.pi, np.pi, n_offset, endpoint=False)
    tilts = c1 + np.linspace(-4 * w1, 4 * w1, n_tilt) if "tilt" in params else np.zeros(1)
    g0, g1 = (g.ravel() for g in np.meshgrid(offsets, tilts, indexing="ij"))
    c0, w0 = ((float(np.ravel(prior["phase_offset"][0])[0]), float(np.ravel(prior["phase_offset"][1])[0]))
              if "phase_offset" in prior else (0.0, np.inf))
    penalty = (np.angle(np.exp(1j * (g0 - c0))) / w0) ** 2 + ((g1 - c1) / w1) ** 2
    moved = 0
    for j in frames:
        sel = np.flatnonzero(obs.frame == j)
        now0 = params["phase_offset"][j, 0] if "phase_offset" in params else 0.0
        now1 = params["tilt"][j, 0] if "tilt" in params else c1
        sums = frame_cost_sums(obs, ch, now["coef"], weights, sel,
                               held=now0 + (now1 if "tilt" in params else 0.0) * obs.x)
        cost = grid_cost(sums, offsets, tilts, obs.x).ravel() + penalty
        here = grid_cost(sums, np.array([now0]), np.array([now1 if "tilt" in params else 0.0]), obs.x)
        current = float(here[0, 0]) + (np.angle(np.exp(1j * (now0 - c0))) / w0) ** 2 + ((now1 - c1) / w1) ** 2
        best = int(np.argmin(cost))
        if cost[best] < current - 1.0:
            params.setdefault("phase_offset", np.zeros((obs.n_frames, 1)))[j, 0] = g0[best]
            if "tilt" in params:
                params["tilt"][j, 0] = g1[best]
            moved += 1
    return params, moved


def frame_grid_cost(obs: Observations, ch: M.Channels, coef: np.ndarray, weights: np.ndarray, blocks: np.ndarray,
                    offsets: np.ndarray, tilts: np.ndarray, *, held: np.ndarray) -> np.ndarray:
    """Cost sum w (I - Ibar)^2 of some blocks of one frame, at fixed images, over a grid of phase offset and tilt.

    The frame's phase channel has its current offset + tilt (``held``, per column) replaced by
    psi = offset + tilt x. With E = exp(i psi) the model is a trigonometric polynomial,
    Ibar - offset - t A0 = Re(P E) + Re(Q E^2) (P: the fringe, Q: the second harmonic), so the cost
    is S0 + Re(sum_n E^n S_n) with per-column sums S_n over the blocks (n = 1..4): the grid costs
    O(samples + grid x columns) instead of O(samples x grid).

    Parameters
    ----------
    obs : Observations
    ch : Channels
        Current channel values.
    coef : ndarray, shape (R, C, 3)
        Images held fixed.
    weights : ndarray, shape (K, C)
    blocks : ndarray of int
        Blocks, all of one frame.
    offsets, tilts : ndarray, shapes (n0,), (n1,)
        Grid of the trial offset (rad) and tilt (rad per unit x).
    held : ndarray, shape (C,)
        The frame's current offset + tilt x, which the trial replaces (rad).

    Returns
    -------
    ndarray, shape (n0, n1)
    """
    return grid_cost(frame_cost_sums(obs, ch, coef, weights, blocks, held=held), offsets, tilts, obs.x)


def frame_cost_sums(obs: Observations, ch: M.Channels, coef: np.ndarray, weights: np.ndarray, blocks: np.ndarray, *,
                    held: np.ndarray) -> tuple[float, list[np.ndarray]]:
    """The sums S0 and S_n (n = 1..4, each (C,), complex) of :func:`frame_grid_cost`: the cost of the blocks at any
    phase offset and tilt is then :func:`grid_cost` of them."""
    j = obs.frame[blocks[0]]
    x = obs.x
    cf = obs.gather(coef, blocks)
    # the fringe t^f v^f exp(i theta) at the frame's held offset and tilt taken out, and t^f v^f exp(2i theta)
    F = (obs.fc[blocks] + 1j * obs.fs[blocks]) * np.exp(1j * (ch.phase_at(obs, blocks) - held))
    F2 = M.second_harmonic(F.real, F.imag)
    amp = ch.dose[j] * obs.tf[blocks]
    dv = ch.dose[j] * ch.vis_at(obs, blocks)
    P = dv * (cf[..., 1] + 1j * cf[..., 2]) * F
    # the harmonic follows the sample: m exp(2i phi) = e + i f of the images
    _, _, e, f = M.harmonic_factors(cf[..., 1], cf[..., 2])
    Q = dv * (e + 1j * f) * (ch.harmonic[0] + 1j * ch.harmonic[1]) * (F2[0] + 1j * F2[1])
    background = ch.background[0] + ch.background[1] * x[None, :] + ch.background[2] * obs.y[blocks, None]
    y = obs.counts[blocks] - obs.dark[blocks] - background - cf[..., 0] * amp
    w = weights[blocks]
    # r^2 = (y - Re PE - Re QE^2)^2, expanded with Re a Re b = (Re ab + Re a b*) / 2
    S0 = float(np.sum(w * (y ** 2 + 0.5 * np.abs(P) ** 2 + 0.5 * np.abs(Q) ** 2)))
    S = [np.sum(w * s, axis=0) for s in (-2 * y * P + np.conj(P) * Q, -2 * y * Q + 0.5 * P ** 2, P * Q, 0.5 * Q ** 2)]
    return S0, S


def grid_cost(sums: tuple[float, list[np.ndarray]], offsets: np.ndarray, tilts: np.ndarray, x: np.ndarray
              ) -> np.ndarray:
    """The cost S0 + Re(sum_n E^n S_n) of :func:`frame_cost_sums` on the grid ``offsets`` x ``tilts`` (rad, rad per
    unit of the lateral coordinate ``x`` (C,)), (n0, n1)."""
    S0, S = sums
    return S0 + sum(np.real(np.exp(1j * n * offsets)[:, None] * (np.exp(1j * n * np.outer(tilts, x)) @ Sn)[None, :])
                    for n, Sn in enumerate(S, start=1))


def rows_in_use(obs: Observations) -> np.ndarray:
    """Rows of each frame in ``obs`` that hold a sample the fit uses, (J,): none for a frame left out as a detector
    fault (:mod:`dfxcorr.faults`), whose parameters the data then do not determine at all."""
    return obs.frame_sum(np.any(obs.use, axis=1).astype(np.float64))


def well_determined(obs: Observations, fraction: float) -> np.ndarray:
    """Frames lighting at least ``fraction`` of the largest number of rows any frame lights in ``obs`` with samples
    in use (:func:`rows_in_use`), (J,) (:func:`dfxcorr.align.gauge_frames`). A frame left out is never one: its
    neutral parameters would pull the gauge, the empirical prior and the reported spread towards them."""
    return gauge_frames(rows_in_use(obs), fraction)


def fix_gauge(params: dict, good: np.ndarray, *, visibility_gauge: str = "max",
              visibility_quantile: float = 0.99) -> dict:
    """Select one of the equivalent solutions (paper eq. 22).

    'shift' effects get median zero over the well-determined frames; 'scale' effects are divided by a
    robust normaliser (dose: median; visibility_loss: per ``visibility_gauge``).
    """
    out = {}
    for name, p in params.items():
        e = effect(name)
        if not e.per_frame or e.gauge == "none" or not np.any(good):
            out[name] = p
        elif e.gauge == "shift":
            out[name] = p - np.median(p[good], axis=0) + e.neutral
        elif name == "visibility_loss" and visibility_gauge == "max":
            out[name] = p / np.quantile(p[good], visibility_quantile, axis=0)
        else:
            out[name] = p / np.median(p[good], axis=0)
    return out
