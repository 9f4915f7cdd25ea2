"""Stage 4, the vibration fit: maximum-likelihood per-frame parameters by L-BFGS on the reduced cost.

The cost is the weighted least-squares approximation of the shot-noise log-likelihood (paper eqs. 6,
20) with the images solved in closed form for every trial of the per-frame parameters (eq. 23), so
L-BFGS only sees the per-frame parameters and the gradient follows from the envelope theorem
(eq. 25). L-BFGS works in variables whitened by the profiled Fisher information of the per-frame
parameters (its Cholesky factor; the paper rescales by the diagonal of the plain one, eqs. 27, 34,
which ``preconditioner='diagonal'`` keeps).

Against local minima (paper Sec. II-E) the fit runs in stages: first the phase effects with the
phase image held at its circular mean (eq. 36), then the phase effects with free images, then every
enabled effect (visibility loss is added only once the phases have mostly converged). A weak prior
around the neutral value keeps frames that light only a few rows sane; it is negligible wherever
the data say anything.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.linalg import solve_triangular
from scipy.optimize import minimize

from . import engine as E
from . import kernels as K
from . import model as M
from .catalogue import PAPER_MODEL, effect, neutral_params
from .frames import (
    catalogue_prior,
    empirical_prior,
    fix_gauge,
    rescue_frames,
    rows_in_use,
    well_determined,
    wrap_phases,
)
from .observations import Observations
from .subsets import column_information, standing_columns

log = logging.getLogger(__name__)


@dataclass
class FitResult:
    """What the vibration fit found.

    Attributes
    ----------
    params : dict
        Effect name -> parameters, gauge fixed (paper eq. 22).
    uncertainty : dict
        Effect name -> one-sigma uncertainty from the Fisher information, same shapes (inf where a
        frame carries no information); empty where the fit was asked not to compute it.
    cost : ndarray
        Cost after each iteration, all stages.
    stage : list of str
        Stage of each entry of ``cost``.
    iterations : int
        Accepted steps (Gauss-Newton) or iterations (L-BFGS), all stages.
    converged : bool
    messages : list of str
        The optimiser's last word per stage.
    well_determined : ndarray of bool, shape (J,)
        Frames lighting at least the configured fraction of the active area (used for the gauge).
    evaluations : int
        Passes of the cost kernel over the fit's samples, all stages.
    """

    params: dict[str, np.ndarray]
    uncertainty: dict[str, np.ndarray]
    cost: np.ndarray
    stage: list[str]
    iterations: int
    converged: bool
    messages: list[str] = field(default_factory=list)
    well_determined: np.ndarray | None = None
    evaluations: int = 0


#: Share of the diagonal preconditioner (eq. 34) added to the profiled Hessian: it bounds the steps of
#: parameters that the images take up almost entirely at the start (a frame lighting one or two rows),
#: whose profiled curvature there understates what the cost shows once the images settle (paper study,
#: every column: 0 -> 377 iterations, the 'all' stage at its limit; 0.01 -> 190; 0.1 -> 195; diagonal 426).
RIDGE = 0.01
#: Pixels (rows x columns) of the columns that enter the profiled Hessian (spread by their information, each standing
#: for a stratum of all: :func:`dfxcorr.subsets.information_columns`): the coupling it captures is that of frames
#: through the rows they share, which every column repeats, so a tall detector needs fewer columns (the paper study's
#: 450 rows: 64 columns; a binned clinical scan's 1440: 21, which took its refreshes 0.33 -> 0.06 s each for 54 -> 77
#: cost evaluations, the fit 13.3 -> 9.4 s on the 2-core machine under load 2.4). At least :data:`FACTOR_MIN_COLUMNS`.
FACTOR_PIXELS = 30_000
FACTOR_MIN_COLUMNS = 16
#: Columns, spread by their information, on which the uncertainty is computed where samples read between rows: that
#: Fisher information costs about 100 ns per sample (0.73 s on the paper study's 510 columns, 0.24 s on these).
#: Against every column's, each frame's standard error within 1.8 % (rms 0.2 %) there and 4.8 % (rms 0.5 %) on 204
#: columns (scripts/uncertainty_columns.py).
UNCERTAINTY_COLUMNS = 128
#: Above this many parameters the dense profiled Hessian (P x P, per thread in the Fisher kernel) is not
#: formed and the diagonal preconditions (a clinical scan has 585; a long scan with many effects could
#: need gigabytes).
FACTOR_MAX_PARAMETERS = 3000
PRECONDITIONERS = ("profiled", "diagonal")
#: Gauss-Newton steps predicted to lower the cost (a chi-square) by more than this are followed by a fresh
#: Hessian; smaller ones keep the last (paper study, every column: a threshold of 0 -> 1, 76 -> 17 Hessians, the
#: same minimum; 100 saved a few Hessians at full resolution but cost evaluations on a small scan, 93 -> 138).
#: 1 -> 10: a Hessian costs about three evaluations of the cost; binned clinical scan 34 -> 27 Fisher passes for
#: 71 -> 73 evaluations, process CPU 12.1 -> 11.5 s; paper study 6.7 -> 5.8 s at its defaults, 12.4 -> 11.4 s at
#: every column (100: 23 Fisher passes, 99 evaluations, 12.0 s binned). A step rejected on a Hessian from
#: an earlier point is retried on a fresh one before the damping grows: the steps of a small scan with many edge
#: frames need fresh curvature (tests/test_fit.py's 102 x 90 scan on every 2nd column: 78 evaluations with a
#: threshold of 1, 124 with 10; with the retry and :data:`STAGE_GTOL` 47, its last stage 50 -> 10).
REFRESH_DECREASE = 10.0
#: Gauss-Newton trial steps per stage before L-BFGS takes over: where the Gauss-Newton Hessian misses the
#: curvature (frames lighting a few rows, whose cost is not near-quadratic) the steps crawl, and L-BFGS learns
#: that curvature (a small scan of 17 columns with many edge frames crawled for 256 steps, each lowering the
#: cost by ~0.02; the paper study at every column converges in at most 15 per stage).
GAUSS_NEWTON_STEPS = 25
#: Convergence threshold of every stage but the last (a whitened gradient of 1: within about a standard deviation
#: of that stage's minimum). Such a stage only brings the parameters into the basin of the next one's minimum, and
#: what it hands on hardly depends on the last standard deviation: the phase stage's estimate is a start (with
#: visibility held at 1 its residuals are far above noise, so that the Gauss-Newton Hessian misses curvature there
#: and the steps converge only linearly: paper study, every column, 56 steps to the default gtol, 15 to this); the
#: weights of a reweighting and the empirical prior change by a small fraction of a sample's variance. The last
#: stage converges to ``gtol`` from there. Paper study at every column (fit.coarse 7): 75 -> 61 evaluations, 17 -> 9
#: of them over all columns; the estimates move by at most 1.4e-4 of their standard deviations.
STAGE_GTOL = 1.0
#: Smallest factor by which a well-predicted Gauss-Newton step shrinks the damping (Nielsen's rule uses 1/3): the
#: damping starts at :data:`RIDGE` and, near the minimum, only limits the steps of frames whose information is
#: far below it, which then crawl until it has shrunk (paper study at every column, evaluations of all stages:
#: 1/3 -> 73, 0.1 -> 64, 0.01 -> 59; the same minimum).
LAMBDA_SHRINK = 0.01


class _Problem:
    """Packs effect parameters into one preconditioned vector for scipy."""

    def __init__(self, obs: Observations, names: Iterable[str], params: dict[str, np.ndarray], weights: np.ndarray,
                 *, phase: float | None = None, precondition: bool = True, preconditioner: str = "profiled",
                 prior: dict | None = None, information: np.ndarray | None = None) -> None:
        if preconditioner not in PRECONDITIONERS:
            raise ValueError(f"preconditioner must be one of {', '.join(PRECONDITIONERS)}, got {preconditioner!r}")
        # the weights in the samples' dtype once, not converted at every evaluation (kernels.reduced_cost)
        self.obs, self.names, self.phase = obs, list(names), phase
        self.weights = weights.astype(K.weights_dtype(obs), copy=False)
        self.fixed = {k: v for k, v in params.items() if k not in self.names}
        self.shapes = [params[n].shape for n in self.names]
        self.theta0 = np.concatenate([params[n].ravel() for n in self.names])
        prior = prior or {}
        self.centre = np.concatenate([np.broadcast_to(prior[n][0], params[n].shape).ravel() if n in prior
                                      else np.zeros(params[n].size) for n in self.names])
        self.prior_w = np.concatenate([np.broadcast_to(prior[n][1], params[n].shape).ravel() ** -2.0 if n in prior
                                       else np.zeros(params[n].size) for n in self.names])
        self.scale = np.ones_like(self.theta0)
        #: passes of the cost kernel over the samples (cost and gradient, or the Fisher diagonal)
        self.evaluations = 0
        # the spread columns of the Hessian (:meth:`hessian`), by their number, and the columns' information they are
        # spread by (column_information; made at the first Hessian where not given)
        self._spread: dict[int, tuple[Observations, np.ndarray]] = {}
        self.information = information
        # z = chol^T (scale theta): chol is the Cholesky factor of the profiled Hessian divided by the diagonal
        # preconditioner's scales (eq. 34), or None
        self.chol: np.ndarray | None = None
        if precondition:
            self.scale = np.sqrt(self._curvature(params))
            if preconditioner == "profiled" and phase is None and self.theta0.size <= FACTOR_MAX_PARAMETERS:
                self.chol = self._profiled_factor(params)

    def to_z(self, theta: np.ndarray) -> np.ndarray:
        """The optimiser's variables of parameters ``theta``."""
        y = theta * self.scale
        return y if self.chol is None else self.chol.T @ y

    def to_theta(self, z: np.ndarray) -> np.ndarray:
        """Parameters of the optimiser's variables ``z``."""
        y = z if self.chol is None else solve_triangular(self.chol, z, trans="T", lower=True)
        return y / self.scale

    def hessian(self, params: dict[str, np.ndarray], *, columns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The reduced cost's Gauss-Newton Hessian in the order of ``theta``, and its plain diagonal.

        The Hessian is 2 x the profiled Fisher information (plain minus the share the images take up, as
        in :func:`uncertainty`) plus the prior's 2 / width^2, computed on at most ``columns`` columns spread by
        their information, each standing for a stratum of all (:func:`information_columns`; default:
        :func:`hessian_columns`).

        Returns
        -------
        hessian : ndarray, shape (P, P)
            Cost per parameter unit squared.
        plain : ndarray, shape (P,)
            Its diagonal without the profiled correction (2 x the plain Fisher diagonal, eq. 27, plus the prior).
        """
        if columns is None:
            columns = hessian_columns(self.obs)
        if columns not in self._spread:
            if self.information is None and self.obs.columns.size > columns:
                self.evaluations += 1
                self.information = column_information(self.obs, params, self.weights)
            obs, weights = standing_columns(self.obs, self.weights, self.information, most=columns)
            # the steps need a Hessian close to the reduced cost's, not its exact value (the gradient decides
            # where they end): where samples read between rows (a fraction of a row off their own), that of the
            # images solved per pixel, by the compiled kernels, rather than the block-tridiagonal solve's
            self._spread[columns] = (replace(obs, reading=None), weights)
        obs, weights = self._spread[columns]
        plain, corr = E.profiled_fisher(obs, _channels(obs, params), weights, self.names)
        offsets = np.cumsum([0] + [int(np.prod(shp)) for shp in self.shapes])
        where = {n: (o, shp) for n, o, shp in zip(self.names, offsets[:-1], self.shapes, strict=True)}
        order = np.array([where[n][0] + (np.ravel_multi_index((j, m), where[n][1]) if j >= 0 else m)
                          for n, j, m in M.fisher_index(self.names, self.obs.n_frames)])
        h = np.empty((order.size, order.size))
        h[np.ix_(order, order)] = 2.0 * (plain - corr)
        h[np.diag_indices_from(h)] += 2.0 * self.prior_w
        d = np.empty(order.size)
        d[order] = 2.0 * np.diag(plain)
        return h, d + 2.0 * self.prior_w

    def _profiled_factor(self, params: dict[str, np.ndarray]) -> np.ndarray | None:
        """Cholesky factor of the reduced cost's Gauss-Newton Hessian (:meth:`hessian`), divided by the diagonal scales.

        Whitening by it removes what the diagonal of eq. 34 leaves: the coupling of phase offset and tilt,
        and of frames through the images they share (frames that light few rows share their pixels with few
        others, so their plain diagonal overstates their information many times over). It is divided by
        ``outer(scale, scale)`` (the plain diagonal of eq. 34, so its own diagonal is the profiled share of
        the information, at most 1, plus :data:`RIDGE`). None where the matrix is not finite or the
        factorisation fails (the diagonal is used then).
        """
        h = self.hessian(params)[0] / np.outer(self.scale, self.scale)
        h[np.diag_indices_from(h)] += RIDGE
        if not np.all(np.isfinite(h)):
            log.debug("profiled Hessian not finite: diagonal preconditioning")
            return None
        try:
            return np.linalg.cholesky(h)
        except np.linalg.LinAlgError:
            log.debug("profiled Hessian not positive definite: diagonal preconditioning")
            return None

    def unpack(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        out, i = dict(self.fixed), 0
        for n, shp in zip(self.names, self.shapes, strict=True):
            size = int(np.prod(shp))
            out[n] = theta[i:i + size].reshape(shp)
            i += size
        return out

    def _channel_sums(self, params: dict[str, np.ndarray], *, square: bool) -> tuple[float, np.ndarray]:
        """Reduced cost and the per-parameter sums of the kernel (gradient, or sum w F^2 if ``square``)."""
        self.evaluations += 1
        cost, sums = E.parameter_sums(self.obs, _channels(self.obs, params), self.weights, self.names,
                                      phase=self.phase, square=square)
        return cost, np.concatenate([sums[n].ravel() for n in self.names])

    def _curvature(self, params: dict[str, np.ndarray]) -> np.ndarray:
        """Diagonal of the cost's Gauss-Newton Hessian (2 x Fisher information, paper eq. 27) plus the prior."""
        h = 2.0 * self._channel_sums(params, square=True)[1] + 2.0 * self.prior_w
        positive = h[h > 0]
        floor = 1e-12 * (positive.max() if positive.size else 1.0)
        return np.maximum(h, max(floor, 1e-300))

    def cost_gradient(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """Cost (with the prior) and its gradient in the parameters ``theta``."""
        cost, grad = self._channel_sums(self.unpack(theta), square=False)
        dev = theta - self.centre
        return cost + float(np.sum(self.prior_w * dev ** 2)), grad + 2.0 * self.prior_w * dev

    def evaluate(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """Cost and gradient in the optimiser's variables ``z``."""
        cost, grad = self.cost_gradient(self.to_theta(z))
        g = grad / self.scale
        if self.chol is not None:
            g = solve_triangular(self.chol, g, lower=True)
        return cost, g

    def lower(self) -> np.ndarray:
        """Physical lower bounds of the parameters (visibility and dose stay positive; -inf: none)."""
        return np.concatenate([np.full(int(np.prod(shp)), -np.inf if effect(n).lower is None else effect(n).lower)
                               for n, shp in zip(self.names, self.shapes, strict=True)])

    def bounds(self) -> list[tuple[float | None, None]] | None:
        """The lower bounds in the optimiser's variables: a box only under diagonal scaling (else None)."""
        if self.chol is not None:
            return None
        return [(lo if np.isfinite(lo) else None, None) for lo in self.lower() * self.scale]


def gauss_newton(prob: _Problem, *, maxiter: int, gtol: float, on_step: Callable[[float], None] | None = None
                 ) -> tuple[np.ndarray, str, bool]:
    """Levenberg-Marquardt steps on the profiled Gauss-Newton Hessian of the reduced cost.

    The reduced cost is a weighted least-squares problem in the per-frame parameters, and its
    Gauss-Newton Hessian is 2 x their profiled Fisher information (:meth:`_Problem.hessian`, from at
    most :data:`FACTOR_PIXELS` pixels of spread columns, refreshed after every accepted step that was predicted to
    lower the cost by more than :data:`REFRESH_DECREASE`: near the minimum the parameters hardly move and
    the Hessian hardly changes, while computing it costs a few cost evaluations, and before the damping grows
    after a step rejected on a Hessian from an earlier point). Each step solves
    (H_s + lambda I) d = -g in the variables scaled by the plain diagonal (eq. 34), H_s's diagonal being
    the profiled share of the information (at most 1); lambda starts at :data:`RIDGE`, shrinks after a
    step that the quadratic model predicted well and doubles (then quadruples...) after a rejected one
    (Nielsen's rule). A trial below a parameter's lower bound is rejected unevaluated. Convergence is
    the test of the whitened L-BFGS (:func:`minimise`), the gradient whitened by the Cholesky factor of
    H_s + lambda I below ``gtol`` in every component, with lambda at most :data:`RIDGE`: the smaller
    damping of the last steps makes it the step to the minimum in units of the parameters' standard
    deviations (times sqrt 2), also for frames whose profiled information is far below the ridge.

    Parameters
    ----------
    prob : _Problem
        Built without preconditioning (its own scaling is not used here).
    maxiter : int
        Trial steps at most.
    gtol : float
        Cost per standard deviation of a parameter.
    on_step : callable, optional
        Called with the cost after every accepted step.

    Returns
    -------
    theta : ndarray, shape (P,)
        The last accepted parameters.
    message : str
    converged : bool
        False where ``maxiter`` ran out or the damping grew without bound (no step lowers the cost).
    """
    theta = prob.theta0.copy()
    lower = prob.lower()
    cost, grad = prob.cost_gradient(theta)
    lam, grow = RIDGE, 2.0
    hs = scale = whiten = None
    current = False  # whether hs was computed at theta
    for _ in range(maxiter):
        if hs is None:
            h, plain = prob.hessian(prob.unpack(theta))
            current = True
            positive = plain[plain > 0]
            scale = np.sqrt(np.maximum(plain, 1e-12 * (positive.max() if positive.size else 1.0) + 1e-300))
            hs = h / np.outer(scale, scale)
            if not np.all(np.isfinite(hs)):
                return theta, "Gauss-Newton Hessian not finite", False
            try:
                whiten = np.linalg.cholesky(hs + RIDGE * np.eye(hs.shape[0]))
            except np.linalg.LinAlgError:
                return theta, "Gauss-Newton Hessian not positive definite", False
        gs = grad / scale
        try:
            factor = whiten if lam == RIDGE else np.linalg.cholesky(hs + lam * np.eye(hs.shape[0]))
        except np.linalg.LinAlgError:
            lam, grow = lam * grow, grow * 2.0
            continue
        gw = solve_triangular(factor, gs, lower=True)
        # the step in whitened units, damped at most by the ridge (a larger damping shortens it)
        worst = float(np.max(np.abs(gw if lam <= RIDGE else solve_triangular(whiten, gs, lower=True)), initial=0.0))
        if worst < gtol:
            return theta, "whitened gradient below gtol", True
        if lam > 1e12:
            return theta, "no Gauss-Newton step lowers the cost", False
        ds = -solve_triangular(factor, gw, trans="T", lower=True)
        trial = theta + ds / scale
        if np.any(trial < lower):
            lam, grow = lam * grow, grow * 2.0
            continue
        new_cost, new_grad = prob.cost_gradient(trial)
        predicted = -(gs @ ds + 0.5 * ds @ hs @ ds)
        log.debug("Gauss-Newton: cost %.9g -> %.9g (predicted %.3g), lambda %.2g, whitened gradient %.3g", cost,
                  new_cost, predicted, lam, worst)
        if new_cost < cost:
            rho = (cost - new_cost) / max(predicted, 1e-300)
            theta, cost, grad = trial, new_cost, new_grad
            current = False
            if predicted > REFRESH_DECREASE:
                hs = None
            lam, grow = max(lam * max(LAMBDA_SHRINK, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-9), 2.0
            if on_step is not None:
                on_step(cost)
        elif not current:
            hs = None
        else:
            lam, grow = lam * grow, grow * 2.0
    return theta, "iteration limit of the Gauss-Newton steps", False


#: Minimisers of the reduced cost (``fit.optimizer``).
OPTIMIZERS = ("gauss-newton", "lbfgs")


def minimise(obs: Observations, names: Sequence[str], params: dict[str, np.ndarray], weights: np.ndarray, *,
             phase: float | None = None, maxiter: int = 200, gtol: float = 1e-3, precondition: bool = True,
             preconditioner: str = "profiled", optimizer: str = "gauss-newton", prior: dict | None = None,
             on_iteration: Callable[[float], None] | None = None, information: np.ndarray | None = None
             ) -> tuple[dict[str, np.ndarray], list[float], str, bool, int]:
    """Minimise the reduced cost over the parameters of ``names``, the others held fixed.

    Parameters
    ----------
    obs : Observations
    names : sequence of str
        Effects whose parameters are free.
    params : dict
        Starting values of every effect in the model.
    weights : ndarray, shape (K, C)
        Fixed least-squares weights (inverse variances).
    phase : float, optional
        Hold the phase image at this constant (circular-mean stage; always L-BFGS).
    maxiter : int
    gtol : float
        Stop when the largest preconditioned gradient component falls below this (units of the
        cost per standard deviation of a parameter).
    precondition : bool
        Rescale by the Fisher information.
    preconditioner : {'profiled', 'diagonal'}
        Of L-BFGS. 'diagonal': the diagonal of the plain Fisher information (paper eq. 34); 'profiled':
        whiten by the whole profiled Fisher information (its Cholesky factor), so that L-BFGS also sees
        the coupling of the parameters, which the diagonal leaves it to learn (the phase-held stage uses
        the diagonal). Both reach the same minimum; the whitened variables have no box bounds, so where a
        parameter ends below its bound the stage is finished under the diagonal scaling, from the last
        iterate within the bounds and within the same ``maxiter``. Above
        :data:`FACTOR_MAX_PARAMETERS` parameters the diagonal is used.
    optimizer : {'gauss-newton', 'lbfgs'}
        'gauss-newton': :func:`gauss_newton` steps on the profiled Fisher information (a handful of cost
        evaluations), L-BFGS from where they stop if they do not converge within :data:`GAUSS_NEWTON_STEPS`
        (L-BFGS then has ``maxiter`` iterations); used unless the phase image is
        held, ``precondition`` is off or there are more than :data:`FACTOR_MAX_PARAMETERS` parameters.
        'lbfgs': L-BFGS alone (the same minimum).
    prior : dict, optional
        Effect name -> (centre, width): a Gaussian prior on each per-frame parameter, arrays
        broadcastable to the parameters (see :func:`catalogue_prior`, :func:`empirical_prior`).
    on_iteration : callable, optional
        Called with the cost after every iteration (accepted step).
    information : ndarray, shape (C,), optional
        Each column's information (:func:`dfxcorr.subsets.column_information`), which the profiled Hessian's
        columns are spread by; made at the first Hessian where not given.

    Returns
    -------
    params : dict
    costs : list of float
        After each iteration.
    message : str
    converged : bool
    evaluations : int
        Passes of the cost kernel over the samples (cost and gradient, or the Fisher diagonal).
    """
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {', '.join(OPTIMIZERS)}, got {optimizer!r}")
    costs: list[float] = []
    evaluations = 0

    def step(cost: float) -> None:
        costs.append(cost)
        if on_iteration is not None:
            on_iteration(cost)

    size = sum(int(np.size(params[n])) for n in names)
    gn: _Problem | None = None
    if optimizer == "gauss-newton" and phase is None and precondition and size <= FACTOR_MAX_PARAMETERS:
        gn = _Problem(obs, names, params, weights, precondition=False, prior=prior, information=information)
        theta, message, ok = gauss_newton(gn, maxiter=min(maxiter, GAUSS_NEWTON_STEPS), gtol=gtol,
                                          on_step=step)
        evaluations += gn.evaluations
        if ok:
            return gn.unpack(theta), costs, message, True, evaluations
        log.debug("Gauss-Newton stopped (%s) after %d steps: L-BFGS from there", message, len(costs))
        params = {**params, **gn.unpack(theta)}
    # the last iterate within the lower bounds (the whitened variables have no box bounds)
    feasible: list[np.ndarray] = []

    def callback(intermediate_result: Any) -> None:  # a scipy.optimize.OptimizeResult
        if prob.chol is not None:
            now = prob.to_theta(intermediate_result.x)
            if np.all(now >= lower):
                feasible[:] = [now]
        step(float(intermediate_result.fun))

    if information is None and gn is not None:
        information = gn.information
    prob = _Problem(obs, names, params, weights, phase=phase, precondition=precondition,
                    preconditioner=preconditioner, prior=prior, information=information)
    lower = prob.lower()
    if np.all(prob.theta0 >= lower):
        feasible.append(prob.theta0)
    res = minimize(prob.evaluate, prob.to_z(prob.theta0), jac=True, method="L-BFGS-B", bounds=prob.bounds(),
                   callback=callback, options={"maxiter": maxiter, "maxcor": 20, "ftol": 1e-15, "gtol": gtol})
    theta = prob.to_theta(res.x)
    evaluations += prob.evaluations
    if prob.chol is not None and np.any(theta < lower):
        # finish under the diagonal scaling, which keeps the bounds, from the last iterate within them (a
        # clipped end point could sit across a symmetry, e.g. v < 0 for a fringe shifted by pi)
        log.debug("%d parameters below their bounds: diagonal preconditioning from there", int(np.sum(theta < lower)))
        start = prob.unpack(feasible[-1] if feasible else np.maximum(theta, lower))
        prob = _Problem(obs, names, {**params, **start}, weights, phase=phase, precondition=precondition,
                        preconditioner="diagonal", prior=prior)
        res = minimize(prob.evaluate, prob.to_z(prob.theta0), jac=True, method="L-BFGS-B", bounds=prob.bounds(),
                       callback=callback, options={"maxiter": max(maxiter - len(costs), 1), "maxcor": 20,
                                                   "ftol": 1e-15, "gtol": gtol})
        theta = prob.to_theta(res.x)
        evaluations += prob.evaluations
    return prob.unpack(theta), costs, str(res.message), bool(res.success), evaluations


def fit_vibrations(obs: Observations, *, effects: Sequence[str] = PAPER_MODEL, start: dict | None = None,
                   weights: np.ndarray | None = None, circmean_iterations: int = 10, staged: bool = True,
                   maxiter: int = 300, gtol: float = 1e-3, precondition: bool = True,
                   preconditioner: str = "profiled", optimizer: str = "gauss-newton", prior: bool = True,
                   reweight: int = 1, visibility_gauge: str = "max", visibility_quantile: float = 0.99,
                   gauge_fraction: float = 0.5, coarse: int = 1, with_uncertainty: bool = True,
                   on_iteration: Callable[[str, float], None] | None = None) -> FitResult:
    """Estimate per-frame effect parameters by maximum likelihood (paper Sec. II-C to II-E).

    Parameters
    ----------
    obs : Observations
        Samples entering the fit (usually every n-th column, motion pixels with ``use = False``).
    effects : sequence of str
        Catalogue effects of the model; those without a mean channel are ignored here.
    start : dict, optional
        Starting parameters (default neutral).
    weights : ndarray, shape (K, C), optional
        Inverse variances; default: from the model without per-frame effects.
    circmean_iterations : int
        L-BFGS iterations with the phase image held at its circular mean (eq. 36); 0 skips.
    staged : bool
        Fit the phase effects first and add the others afterwards (paper Sec. II-E).
    maxiter : int
        Iterations per stage.
    gtol : float
        Convergence threshold on the preconditioned gradient.
    precondition : bool
        See :func:`minimise`.
    preconditioner : {'profiled', 'diagonal'}
        See :func:`minimise`.
    optimizer : {'gauss-newton', 'lbfgs'}
        See :func:`minimise`.
    prior : bool
        Keep frames with little data sane: a wide prior around the neutral values during the main
        stages, then an empirical one (median and robust spread of the well-determined frames) in a
        final stage that also searches the weakly determined frames globally (:func:`rescue_frames`).
    reweight : int
        Refits with weights recomputed from the fitted model.
    visibility_gauge : {'max', 'median'}
        Normalisation of visibility_loss: the ``visibility_quantile`` quantile (robust maximum, the
        paper's max v^s = 1 of Sec. III-A) or the median (eq. 22) of the well-determined frames set to 1.
    visibility_quantile : float
        Quantile used by the 'max' gauge.
    gauge_fraction : float
        Frames lighting at least this fraction of the active area's rows define the gauge.
    coarse : int
        Run every stage on every ``coarse``-th column first, then only the final ones on all columns from that
        estimate (with ``weights`` if given, else with those of its model, as a reweighting): Gauss-Newton reaches
        the same minimum from there in a few steps, so a fit of many columns costs a fit of a few and a few
        passes over all.
    with_uncertainty : bool
        Compute ``FitResult.uncertainty`` (a Fisher pass over every sample; the coarse first pass, whose estimate is
        only a start, does without).
    on_iteration : callable, optional
        Called with (stage, cost) after every iteration.

    Returns
    -------
    FitResult
    """
    names = [n for n in effects if effect(n).channel is not None]
    J = obs.n_frames
    costs, stage_of, messages, evaluations = [], [], [], 0
    if coarse > 1:
        keep = np.arange(coarse // 2, obs.columns.size, coarse)
        first = fit_vibrations(obs.subset(keep), effects=effects, start=start,
                               weights=None if weights is None else weights[:, keep],
                               circmean_iterations=circmean_iterations, staged=staged, maxiter=maxiter,
                               gtol=max(gtol, STAGE_GTOL),  # a start, like every stage but the last
                               precondition=precondition, preconditioner=preconditioner, optimizer=optimizer,
                               prior=prior, reweight=reweight, visibility_gauge=visibility_gauge,
                               visibility_quantile=visibility_quantile, gauge_fraction=gauge_fraction,
                               with_uncertainty=False, on_iteration=on_iteration)
        costs, stage_of, messages, evaluations = list(first.cost), list(first.stage), first.messages, first.evaluations
        # given weights stay; otherwise those of the coarse estimate's model, as a reweighting
        start, staged = first.params, False
    K.set_threads()
    params = neutral_params(names, J)
    if start:
        params.update({k: np.array(v, dtype=np.float64) for k, v in start.items() if k in params})
    # weights made here are the fit's own: a reweighting overwrites them rather than holding two sets
    own = weights is None
    if weights is None:
        weights = initial_weights(obs, params)
    phase_names = [n for n in names if effect(n).channel == "phase"]
    stages = []
    if staged and phase_names:
        if circmean_iterations > 0:
            stages.append(("circmean", phase_names, circmean_iterations))
        stages.append(("phase", phase_names, maxiter))
    stages.append(("all", names, maxiter))
    stages += [("reweight", names, maxiter)] * reweight
    converged = True
    wide = catalogue_prior(names) if prior else None
    good = well_determined(obs, gauge_fraction)
    weak = np.flatnonzero(~good & (rows_in_use(obs) > 0))
    refine = bool(prior and weak.size and np.any(good))
    # what the stages' Hessians spread their columns by, once (the columns' shares hardly move between stages)
    information = None
    hessians = precondition and (optimizer == "gauss-newton" or preconditioner == "profiled")
    size = sum(int(np.size(params[n])) for n in names)
    if hessians and obs.columns.size > hessian_columns(obs) and size <= FACTOR_MAX_PARAMETERS:
        information = column_information(obs, params, weights)
        evaluations += 1
    for i, (label, free, iters) in enumerate(stages):
        if not free:
            continue
        phase = None
        if label == "circmean":
            images = _solve(obs, params, weights)
            amp = np.where(images.valid, np.hypot(images.coef[..., 1], images.coef[..., 2]), 0.0)
            phase = M.circular_mean(images.phi, amp)
        if label == "reweight":
            weights = _model_weights(obs, params, weights, out=weights if own else None)
        cb: Callable[[float], None] | None = None if on_iteration is None else (
            lambda c, _l=label: on_iteration(_l, c))
        tol = max(gtol, STAGE_GTOL) if i + 1 < len(stages) or refine else gtol
        params, c, msg, ok, n_eval = minimise(obs, free, params, weights, phase=phase, maxiter=iters, gtol=tol,
                                              precondition=precondition, preconditioner=preconditioner,
                                              optimizer=optimizer, prior=wide, on_iteration=cb,
                                              information=information)
        log.debug("stage %s: %d iterations, %d evaluations, %s", label, len(c), n_eval, msg)
        evaluations += n_eval
        costs += c
        stage_of += [label] * len(c)
        messages.append(f"{label}: {msg}")
        if label != "circmean":
            converged = ok
    params = wrap_phases(params, obs)
    if refine:
        narrow = empirical_prior(params, good)
        if phase_names:
            params, moved = rescue_frames(obs, params, weights, weak, narrow)
            log.info("%d of %d weakly determined frames moved by the global search", moved, weak.size)
        cb = None if on_iteration is None else (lambda c: on_iteration("prior", c))
        params, c, msg, ok, n_eval = minimise(obs, names, params, weights, maxiter=maxiter, gtol=gtol,
                                              precondition=precondition, preconditioner=preconditioner,
                                              optimizer=optimizer, prior=narrow, on_iteration=cb,
                                              information=information)
        log.debug("stage prior: %d iterations, %d evaluations, %s", len(c), n_eval, msg)
        evaluations += n_eval
        costs += c
        stage_of += ["prior"] * len(c)
        messages.append(f"prior: {msg}")
        converged = ok
    params = fix_gauge(params, good, visibility_gauge=visibility_gauge, visibility_quantile=visibility_quantile)
    unc = uncertainty(obs, params, weights) if with_uncertainty else {}
    return FitResult(params=params, uncertainty=unc, cost=np.asarray(costs), stage=stage_of,
                     iterations=len(costs), converged=converged, messages=messages, well_determined=good,
                     evaluations=evaluations)


def pilot_uncertainty(obs: Observations, *, params: dict | None = None, effects: Sequence[str] = PAPER_MODEL,
                      gauge_fraction: float = 0.5) -> float:
    """Median one-sigma uncertainty of the phase effects that a fit of ``obs`` would report, before fitting.

    The profiled Fisher information (:func:`uncertainty`) at a pilot estimate of the parameters, with the
    weights of :func:`initial_weights`. At the neutral model instead, the images solved without the
    vibrations lose fringe amplitude and the prediction is pessimistic (binned clinical scan: 0.0025
    predicted, 0.0016 reported after the fit).

    Parameters
    ----------
    obs : Observations
        A few evenly spread columns.
    params : dict, optional
        Pilot estimate of some effects' parameters (e.g. :func:`dfxcorr.mask.pilot_vibrations`); the others
        neutral.
    effects : sequence of str
        The model (its phase effects are reported).
    gauge_fraction : float
        Frames lighting at least this fraction of the active area count (:func:`well_determined`).

    Returns
    -------
    float
        The larger of the medians of phase_offset (rad) and tilt (rad at the detector's edge) over the
        well-determined frames.
    """
    names, at = model_at(effects, params or {}, obs.n_frames)
    unc = uncertainty(obs, at, initial_weights(obs, at))
    good = well_determined(obs, gauge_fraction)
    return max(float(np.median(unc[n][good])) for n in names if effect(n).channel == "phase")


def model_at(effects: Sequence[str], params: dict, n_frames: int) -> tuple[list[str], dict[str, np.ndarray]]:
    """The model's effects with a mean channel, and their parameters: those of ``params`` given for them, the others
    neutral (:func:`dfxcorr.catalogue.neutral_params`)."""
    names = [n for n in effects if effect(n).channel is not None]
    return names, {**neutral_params(names, n_frames), **{k: v for k, v in params.items() if k in names}}


def hessian_columns(obs: Observations) -> int:
    """Columns the Gauss-Newton Hessian is computed on: :data:`FACTOR_PIXELS` pixels' worth, at least
    :data:`FACTOR_MIN_COLUMNS`."""
    return max(FACTOR_MIN_COLUMNS, FACTOR_PIXELS // max(obs.rows.size, 1))


def initial_weights(obs: Observations, params: dict) -> np.ndarray:
    """Inverse shot-noise variances from the model at ``params`` after one data-weighted solve (eq. 6), in the
    samples' dtype (the first solve is weighted from the data itself: no weights of the samples' size)."""
    return E.retrieve(obs, _channels(obs, params), keep_expected=False, next_weights=True)["weights"]


def _channels(obs: Observations, params: dict) -> M.Channels:
    """Channel values of ``params`` on the observations' (frame, column) grid."""
    return M.channels(params, x=obs.x, n_frames=obs.n_frames)


def _model_weights(obs: Observations, params: dict, weights: np.ndarray, *, out: np.ndarray | None = None
                   ) -> np.ndarray:
    """Inverse noise variances of the model solved with ``weights`` (the weights of a second solve), written into
    ``out`` where given (which may be ``weights``)."""
    return E.retrieve(obs, _channels(obs, params), weights=weights, keep_expected=False, next_weights=True,
                      out=out)["weights"]


def _solve(obs: Observations, params: dict, weights: np.ndarray) -> M.Images:
    """Closed-form images for fixed parameters and weights."""
    out = E.retrieve(obs, _channels(obs, params), weights=weights, keep_expected=False)
    return M.Images(out["coef"], out["valid"])


def uncertainty(obs: Observations, params: dict, weights: np.ndarray) -> dict[str, np.ndarray]:
    """One-sigma uncertainty of the effect parameters from the profiled Fisher information.

    The pseudo-inverse leaves out the gauge directions (a common shift or scale that the images take
    up), so the uncertainties are those of the gauge-fixed parameters. Frames without data get inf. Where the
    samples read between rows, on :data:`UNCERTAINTY_COLUMNS` columns standing for all (:func:`standing_columns`).
    """
    names = list(params)
    out = {n: np.full_like(params[n], np.inf) for n in names}
    if not names:
        return out
    if obs.reading is not None and obs.columns.size > UNCERTAINTY_COLUMNS:
        obs, weights = standing_columns(obs, weights, column_information(obs, params, weights),
                                        most=UNCERTAINTY_COLUMNS)
    plain, corr = E.profiled_fisher(obs, _channels(obs, params), weights, names)
    info, index = plain - corr, M.fisher_index(names, obs.n_frames)
    d = np.diag(info).copy()
    has = d > 1e-12 * max(d.max(), 1e-300)
    s = np.sqrt(d[has])
    sub = info[np.ix_(has, has)] / np.outer(s, s)
    var = np.diag(np.linalg.pinv(sub, rcond=1e-9, hermitian=True)) / s ** 2
    for (n, j, m), v in zip([ix for ix, h in zip(index, has, strict=True) if h], var, strict=True):
        out[n][(j, m) if j >= 0 else m] = np.sqrt(v) if v > 0 else np.inf
    return out
