"""``position_error``: the recorded active-area position of frame j is off by delta_j rows (encoder error, jitter).

Its flat-field maps are read at u - delta_j; the true position is position[j] + delta_j. Derivatives with
respect to delta_j are finite differences of the one alignment (:func:`dfxcorr.align.realign`) pushed through
the one model.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .. import model as M
from ..align import read_position_errors
from ..catalogue import Effect, effect
from ..observations import Observations
from ..preparation import Correctable
from ..retrieve import retrieve
from ..stats import frames_where
from .base import (
    Context,
    EffectBase,
    Estimate,
    Finding,
    Hypothesis,
    Option,
    Params,
    Policy,
    Realign,
    State,
    Test,
    chi2_test,
)


@dataclass(frozen=True)
class Steps:
    """A position test's payload: the share of its statistic in each frame, the Gauss-Newton step of the position
    errors and its standard errors (J,) (rows), and the accompanying step of the model's per-frame parameters."""

    frames: np.ndarray
    step: np.ndarray
    se: np.ndarray
    param_step: Params


def _shift_derivative(realigned: Realign, obs: Observations, params: Params, images: M.Images, shift: np.ndarray,
                      step: float) -> np.ndarray:
    """dIbar/d delta_j at every sample (K, C): images and parameters fixed, central difference of the alignment."""
    out = []
    for d in (step, -step):
        o = realigned(obs, shift + d)
        out.append(M.expected(o, M.design(o, params), images))
    return (out[0] - out[1]) / (2 * step)


def position_test(realigned: Realign, obs: Observations, params: dict[str, Any], shift: np.ndarray, *,
                  dispersion: float = 1.0, step: float = 0.25, min_precision: float = 1.0, prior: float = 1.0
                  ) -> Test[Steps]:
    """Per-frame score test for position errors, and one Gauss-Newton step of their estimate.

    Frame j's score U_j = sum w r dIbar/d delta_j and information I_j = sum w (dIbar/d delta_j)^2, each
    with the frame's own model parameters profiled out (the Schur complement of the frame's block:
    a delta_j that a phase offset or tilt would mimic is not a position error); the images are held
    fixed, which overstates I_j and keeps the test conservative. The common mode (one shift of all
    frames, the reference offset's business and nearly absorbed by the images) is projected out:
    S = (sum U_j^2 / I_j - (sum U_j)^2 / sum I_j) / dispersion, chi-square with (frames - 1) dof.

    Parameters
    ----------
    realigned : callable
        (observations, shift) -> the same samples with the flat field read ``shift`` rows off the prepared
        alignment (:func:`dfxcorr.align.realign`).
    obs : Observations
        The fit's samples, at the alignment ``shift`` relative to ``prep``.
    params : dict
        Current effect parameters.
    shift : ndarray, shape (J,)
        Rows by which ``obs`` is already read off the prepared alignment.
    dispersion : float
        Pearson chi-square per degree of freedom of the current fit.
    step : float
        Rows of the finite difference.
    min_precision : float
        Identifiable when, in the median frame, delta_j's standard error with the frame's model
        parameters profiled is below this (rows).
    prior : float
        Width (rows) of a Gaussian prior on each delta_j in the step (not in the test).

    Returns
    -------
    Test
        Payload :class:`Steps`.
    """
    rec = retrieve(obs, params)
    images, w = rec.images, rec.weights
    r = obs.counts - rec.expected
    dsg = M.design(obs, params)
    D = [_shift_derivative(realigned, obs, params, images, shift, step)]
    names = [(n, m) for n in params if effect(n).per_frame for m in range(effect(n).size)]
    D += [F for n in params if effect(n).per_frame for F in M.sample_derivatives(obs, dsg, images, n)]
    G = np.stack(D, axis=-1)
    wG = w[..., None] * G
    p = G.shape[-1]
    J = obs.n_frames
    info = np.zeros((J, p, p))
    score = np.zeros((J, p))
    for a in range(p):
        score[:, a] = obs.frame_sum(np.sum(wG[..., a] * r, axis=1))
        for b in range(a, p):
            info[:, a, b] = info[:, b, a] = obs.frame_sum(np.sum(wG[..., a] * G[..., b], axis=1))
    sol = np.zeros((J, p))
    i_d, u_d = np.zeros(J), np.zeros(J)
    for j in range(J):
        if info[j, 0, 0] <= 0:
            continue
        # a prior of one row keeps frames that light a few rows from wandering (real errors are fractions of a row)
        sol[j] = np.linalg.lstsq(info[j] + np.diag(np.r_[dispersion / prior ** 2, np.zeros(p - 1)]), score[j],
                                 rcond=1e-10)[0]
        rest = info[j, 1:, 1:]
        cross = info[j, 0, 1:]
        proj = np.linalg.lstsq(rest, cross, rcond=1e-10)[0] if p > 1 else np.zeros(0)
        i_d[j] = info[j, 0, 0] - cross @ proj
        u_d[j] = score[j, 0] - proj @ score[j, 1:]
    use = i_d > 1e-12 * max(float(info[:, 0, 0].max()), 1e-300)
    per = np.where(use, u_d ** 2 / np.where(use, i_d, 1.0), 0.0) / dispersion
    common = float(u_d[use].sum() ** 2 / i_d[use].sum()) / dispersion if use.any() else 0.0
    stat = max(float(per.sum()) - common, 0.0)
    dof = max(int(use.sum()) - 1, 0)
    precision = float(np.sqrt(dispersion / np.median(i_d[use]))) if use.any() else np.inf
    param_step: Params = {}
    for k, (n, m) in enumerate(names, start=1):
        param_step.setdefault(n, np.zeros_like(params[n]))[:, m] = sol[:, k]
    se = np.where(use, np.sqrt(dispersion / np.where(use, i_d, 1.0)), np.inf)
    return chi2_test(stat, dof, Steps(per, np.where(use, sol[:, 0], 0.0), se, param_step),
                     identifiable=bool(dof and precision < min_precision), explains=stat * dispersion)


def estimate_position_errors(realigned: Realign, obs: Observations, params: dict[str, Any], shift: np.ndarray, *,
                             iterations: int = 10, tol: float = 0.01) -> tuple[np.ndarray, dict[str, Any]]:
    """Gauss-Newton on the per-frame position errors delta_j (rows), images profiled by re-solving them.

    Each iteration realigns the fit's samples with the current delta, re-solves the images and takes
    :func:`position_test`'s step for delta and the model's per-frame parameters together. No gauge is
    imposed here: a common shift of all frames is left where the likelihood puts it (where the flat
    field is linear along the scan the images absorb it and it does not move); reports fix the gauge
    as for phase_offset.

    Returns
    -------
    delta : ndarray, shape (J,)
        Position errors beyond ``shift`` (rows).
    params : dict
        The model's parameters after the steps.
    """
    delta = np.zeros(obs.n_frames)
    params = {k: v.copy() for k, v in params.items()}
    for _ in range(iterations):
        t = position_test(realigned, realigned(obs, shift + delta), params, shift + delta)
        delta = delta + t.payload.step
        for n, dp in t.payload.param_step.items():
            params[n] = params[n] + dp
        if np.max(np.abs(t.payload.step)) < tol:
            break
    return delta, params
class PositionError(EffectBase[Steps]):
    entry = Effect("position_error", None, True, ("delta",), 0.0, "shift",
                   "the recorded position of frame j is off by delta_j rows: its flat field is read at u - delta_j",
                   unit="rows")
    policy = Policy(astray_check=True, fresh_start=True)
    files = ("position_errors.txt",)

    def configured(self, cfg: dict[str, Any], *, n_frames: int, detector: tuple[int, int]) -> Any:
        path = cfg["align"]["position_errors"]
        return None if path is None else read_position_errors(path, n_frames)

    def apply(self, data: Correctable, setting: Any) -> Correctable:
        return replace(data, shift=data.shift + setting)

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test[Steps] | None:
        if ctx.stepping:
            return None
        return position_test(ctx.realigner(state.hypothesis), state.fit_obs, state.params, state.hypothesis.shift,
                             dispersion=max(state.reduced_chi2, 1e-6))

    def trial(self, ctx: Context, state: State, test: Test[Steps]) -> Hypothesis:
        delta, _ = estimate_position_errors(ctx.realigner(state.hypothesis), state.fit_obs, state.params,
                                            state.hypothesis.shift)
        return state.hypothesis.but(shift=state.hypothesis.shift + delta)

    def accepted(self, ctx: Context, before: State, after: State, test: Test[Steps]) -> Finding:
        delta = after.hypothesis.shift - before.hypothesis.shift
        # reported in the gauge of phase_offset (median zero over the well-determined frames); the file keeps
        # the shift itself, so that reconstruct reads the flat field where this fit did
        values = delta - np.median(delta[ctx.good_frames])
        configured = ctx.cfg["align"]["position_errors"]
        written = delta + (0.0 if configured is None else read_position_errors(configured, delta.size))

        def write(path: Path) -> None:
            np.savetxt(path, written, fmt="%.6f", header="position error delta_j of each frame (rows): dfxcorr "
                                                         "reconstruct --set align.position_errors=<this file>")

        return Finding(frames_where(test.payload.frames, after.fit_obs.n_frames),
                       f"std {np.std(values[ctx.good_frames]):.3g} rows", {"values": values.tolist()},
                       options=(Option("align.position_errors", self.files[0], file=True),),
                       files={self.files[0]: write}, per_frame=values[:, None])

    def measure(self, ctx: Context, state: State) -> Estimate | None:
        # each frame's position at this fit (its shift off the prepared alignment) and the standard error its
        # test gives there
        t = position_test(ctx.realigner(state.hypothesis), state.fit_obs, state.params, state.hypothesis.shift,
                          dispersion=max(state.reduced_chi2, 1e-6))
        return Estimate(state.hypothesis.shift + t.payload.step, t.payload.se)


EFFECT = PositionError()
