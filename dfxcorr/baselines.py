"""The two published estimators the paper compares against, for ``fit.method`` alternating and correlation.

``alternating`` (paper refs. [19]-[21]: Okada et al. 1991, Marschner et al. 2016, Seifert et al. 2016)
minimises the same cost as the maximum-likelihood fit, sum w (I - Ibar)^2, by block-coordinate
descent: (a) the images for fixed per-frame parameters (closed form, paper eqs. 8-9), (b) the per-frame
parameters for fixed images. With the images fixed the cost separates over frames, so (b) is a small
Gauss-Newton problem per frame, solved for all frames at once.

``correlation`` (paper ref. [18], Seifert et al. 2019, as described in the paper's Sec. III-D.2) does
not use the likelihood: for every frame and detector column it finds the grating position p at which
the flat-field pattern tf (1 + vf cos(phif + p)) correlates best with the measured counts along the
column's lit rows, then fits a polynomial in x to these column-wise positions per frame with a robust
(bisquare) loss. It has no visibility term.

Both return a :class:`dfxcorr.fit.FitResult` with the gauge of paper eq. 22 (:func:`dfxcorr.fit.fix_gauge`).
"""
from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
from scipy import sparse

from . import model as M
from .catalogue import PAPER_MODEL, effect, neutral_params
from .config import ConfigError
from .fit import FitResult, initial_weights, uncertainty
from .frames import fix_gauge, well_determined, wrap_phases
from .noise import noise_weights
from .observations import Observations

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------------
# Alternating optimisation
# --------------------------------------------------------------------------------------------------


def fit_alternating(obs: Observations, *, effects=PAPER_MODEL, start: dict | None = None,
                    weights: np.ndarray | None = None, maxiter: int = 300, gtol: float = 1e-3,
                    inner: int = 2, reweight: int = 1, visibility_gauge: str = "max",
                    visibility_quantile: float = 0.99, gauge_fraction: float = 0.5,
                    on_iteration: Callable[[str, float], None] | None = None) -> FitResult:
    """Estimate per-frame effect parameters by alternating between images and per-frame parameters.

    Parameters
    ----------
    obs : Observations
        Samples entering the fit.
    effects : sequence of str
        Catalogue effects of the model; those without a mean channel are ignored.
    start : dict, optional
        Starting parameters (default neutral).
    weights : ndarray, shape (K, C), optional
        Inverse variances (1 / counts^2); default :func:`dfxcorr.fit.initial_weights`, as for the ML fit.
    maxiter : int
        Alternations (image solve + parameter update) per stage.
    gtol : float
        Stop when the largest gradient component of the reduced cost, divided by the square root of
        its Gauss-Newton curvature, is below this (the ML fit's criterion in its preconditioned variables).
    inner : int
        Gauss-Newton (Levenberg-Marquardt) steps on the per-frame parameters per alternation.
    reweight : int
        Further stages with weights recomputed from the fitted model (as ``fit.reweight`` of the ML fit).
    visibility_gauge, visibility_quantile, gauge_fraction
        As for :func:`dfxcorr.fit.fit_vibrations`.
    on_iteration : callable, optional
        Called with (stage, cost) after every alternation.
    **_
        Options of the ML fit that do not apply (circular mean, staging, preconditioning).

    Returns
    -------
    FitResult
        ``cost`` holds sum w (I - Ibar)^2 at the closed-form images after each alternation, the value
        the ML fit records per L-BFGS iteration.
    """
    names = [n for n in effects if effect(n).channel is not None]
    params = neutral_params(names, obs.n_frames)
    if start:
        params.update({k: np.array(v, dtype=np.float64) for k, v in start.items() if k in params})
    if weights is None:
        weights = initial_weights(obs, params)
    costs, stage_of, messages, converged = [], [], [], True
    for label in ["all"] + ["reweight"] * reweight:
        if not names:
            break
        if label == "reweight":
            dsg = M.design(obs, params)
            weights = noise_weights(obs, M.expected(obs, dsg, M.solve_images(obs, dsg, weights)))
        cb = None if on_iteration is None else (lambda c, _l=label: on_iteration(_l, c))
        params, c, converged = alternate(obs, names, params, weights, maxiter=maxiter, gtol=gtol, inner=inner,
                                         on_iteration=cb)
        costs += c
        stage_of += [label] * len(c)
        messages.append(f"{label}: {'converged' if converged else 'iteration limit reached'} after {len(c)} "
                        f"alternations")
        log.debug(messages[-1])
    params = wrap_phases(params, obs)
    good = well_determined(obs, gauge_fraction)
    params = fix_gauge(params, good, visibility_gauge=visibility_gauge, visibility_quantile=visibility_quantile)
    return FitResult(params=params, uncertainty=uncertainty(obs, params, weights), cost=np.asarray(costs),
                     stage=stage_of, iterations=len(costs), converged=converged, messages=messages,
                     well_determined=good)


def alternate(obs: Observations, names, params: dict, weights: np.ndarray, *, maxiter: int = 300,
              gtol: float = 1e-3, inner: int = 2, on_iteration=None) -> tuple[dict, list[float], bool]:
    """One stage of alternating minimisation of sum w (I - Ibar)^2 at fixed weights.

    Parameters
    ----------
    obs : Observations
    names : sequence of str
        Effects whose parameters are free (per-frame ones are updated frame by frame, global ones
        as one further block).
    params : dict
        Starting values of every effect in the model.
    weights : ndarray, shape (K, C)
    maxiter : int
        Alternations.
    gtol : float
        Convergence threshold (see :func:`fit_alternating`).
    inner : int
        Gauss-Newton steps per block and alternation.
    on_iteration : callable, optional
        Called with the cost after every alternation.

    Returns
    -------
    params : dict
    costs : list of float
        Cost at the closed-form images after each alternation.
    converged : bool
    """
    blocks = [b for b in ([n for n in names if effect(n).per_frame], [n for n in names if not effect(n).per_frame])
              if b]
    costs: list[float] = []
    for it in range(maxiter + 1):
        dsg = M.design(obs, params)
        images = M.solve_images(obs, dsg, weights)
        largest = 0.0
        for b, block in enumerate(blocks):
            # the last pass only measures the cost of the parameters of the last alternation
            params, scaled, cost = update_block(obs, block, params, images, weights,
                                                steps=inner if it < maxiter else 0, dsg=dsg if b == 0 else None)
            largest = max(largest, scaled)
            if b == 0 and it:
                # the cost of the parameters of the previous alternation at their closed-form images
                costs.append(cost)
                if on_iteration is not None:
                    on_iteration(cost)
        # the first block's gradient is taken at the closed-form images, so it is the reduced cost's
        # (envelope theorem, eq. 25); that is the ML fit's stopping criterion
        if it == maxiter:
            break
        if it and largest < gtol:
            return params, costs, True
    return params, costs, False


def update_block(obs: Observations, names, params: dict, images: M.Images, weights: np.ndarray, *,
                 steps: int = 2, damping: float = 1e-3, dsg: M.Design | None = None) -> tuple[dict, float, float]:
    """Levenberg-Marquardt steps on one block of parameters with the images held fixed.

    For per-frame effects each frame is its own small problem (the cost separates over frames at fixed
    images): the normal matrices of all frames are built at once and each frame's step is accepted
    or rejected on its own cost. Global effects form a single problem.

    Parameters
    ----------
    obs : Observations
    names : sequence of str
        All per-frame or all global effects.
    params : dict
    images : Images
        Held fixed.
    weights : ndarray, shape (K, C)
    steps : int
        Gauss-Newton steps.
    damping : float
        Initial Levenberg-Marquardt damping (relative to the diagonal of the normal matrix).
    dsg : Design, optional
        The design at ``params``, if already evaluated.

    Returns
    -------
    params : dict
        Updated copy.
    scaled_gradient : float
        Largest |d cost / d p| / sqrt(d^2 cost / d p^2) (Gauss-Newton curvature) at the starting point.
    cost : float
        sum w (I - Ibar)^2 at the starting point.
    """
    per_frame = effect(names[0]).per_frame
    n_groups = obs.n_frames if per_frame else 1
    group = obs.frame if per_frame else np.zeros(obs.frame.size, dtype=np.int64)

    def group_sum(a):
        return np.bincount(group, weights=a.sum(axis=1), minlength=n_groups)

    sizes = [effect(n).size for n in names]
    lower = np.concatenate([np.full(s, -np.inf if effect(n).lower is None else effect(n).lower)
                            for n, s in zip(names, sizes, strict=True)])

    def pack(p):
        return np.concatenate([p[n].reshape(n_groups, -1) for n in names], axis=1)

    def unpack(theta):
        out, i = dict(params), 0
        for n, s in zip(names, sizes, strict=True):
            out[n] = theta[:, i:i + s].reshape(params[n].shape)
            i += s
        return out

    theta = pack(params)
    mu = np.full(n_groups, damping)
    dsg = M.design(obs, params) if dsg is None else dsg
    resid = obs.counts - M.expected(obs, dsg, images)
    cost = group_sum(weights * resid ** 2)
    start_cost = float(cost.sum())
    scaled = 0.0
    for step in range(steps):
        F = [f for n in names for f in M.sample_derivatives(obs, dsg, images, n)]
        P = len(F)
        H = np.empty((n_groups, P, P))
        for a in range(P):
            wFa = weights * F[a]
            for b in range(a, P):
                H[:, a, b] = H[:, b, a] = group_sum(wFa * F[b])
        # half the negative gradient of the cost
        g = np.stack([group_sum(weights * resid * f) for f in F], axis=-1)
        d = np.einsum("gii->gi", H)
        has = d > 0
        if step == 0:
            scaled = float(np.max(np.abs(g[has]) * 2 / np.sqrt(2 * d[has]), initial=0.0))
        # components without data (frames that light nothing) keep their value: identity rows
        A = H + (mu[:, None] * np.where(has, d, 1.0))[:, :, None] * np.eye(P)
        A[~has] = 0.0
        A.transpose(0, 2, 1)[~has] = 0.0
        A[..., np.arange(P), np.arange(P)] = np.where(has, A[..., np.arange(P), np.arange(P)], 1.0)
        delta = np.linalg.solve(A, np.where(has, g, 0.0)[..., None])[..., 0]
        trial = np.maximum(theta + delta, lower)
        tdsg = M.design(obs, unpack(trial))
        tresid = obs.counts - M.expected(obs, tdsg, images)
        tcost = group_sum(weights * tresid ** 2)
        ok = tcost <= cost
        theta = np.where(ok[:, None], trial, theta)
        mu = np.where(ok, mu / 3.0, mu * 4.0)
        cost = np.where(ok, tcost, cost)
        if step + 1 < steps:
            if ok.all():
                dsg, resid = tdsg, tresid
            else:
                dsg = M.design(obs, unpack(theta))
                resid = obs.counts - M.expected(obs, dsg, images)
    return unpack(theta), scaled, start_cost


# --------------------------------------------------------------------------------------------------
# Correlation with virtual flat-field patterns and a robust polynomial fit
# --------------------------------------------------------------------------------------------------


def fit_correlation(obs: Observations, *, effects=PAPER_MODEL, grid: int = 360, bisquare: float = 4.685,
                    min_rows: int = 3, irls_iterations: int = 200, gauge_fraction: float = 0.5) -> FitResult:
    """Estimate grating phase per frame from column-wise correlation with the flat field (paper ref. [18]).

    Parameters
    ----------
    obs : Observations
        Samples entering the fit; ``obs.use`` excludes samples (motion mask).
    effects : sequence of str
        The phase effects among them (phase_offset: x^0, tilt: x^1, curvature: x^2) set the terms of the
        polynomial; every other effect is left out (not estimated; visibility_loss in particular, the
        method has no visibility term).
    grid : int
        Trial grating positions over one period (2 pi / grid apart), refined by parabolic interpolation.
    bisquare : float
        Tuning constant of the bisquare loss, in robust standard deviations (1.4826 MAD) of the
        column-wise positions about the fit.
    min_rows : int
        Columns with fewer lit rows in a frame give no position.
    irls_iterations : int
        Iteratively reweighted least-squares iterations of the robust fit.
    gauge_fraction : float
        As for :func:`dfxcorr.fit.fit_vibrations`.
    **_
        Options of the likelihood fits that do not apply.

    Returns
    -------
    FitResult
        Only the phase effects in ``params``; ``uncertainty`` is the standard error of the robust fit
        (inf for frames with fewer usable columns than polynomial terms); no cost history.

    Raises
    ------
    ConfigError
        If ``effects`` holds no phase effect.
    """
    # the method fits each frame's column positions with powers of x: a term along the rows is not one of them
    phase = [n for n in effects if effect(n).channel == "phase" and not any(effect(n).row_powers)]
    if not phase:
        raise ConfigError("fit.method=correlation estimates grating positions only: enable vibration.phase_offset, "
                          "vibration.tilt or vibration.curvature")
    skipped = [n for n in effects if effect(n).channel is not None and n not in phase]
    if skipped:
        log.info("the correlation method does not estimate %s (left neutral)", ", ".join(skipped))
    powers = [effect(n).powers[0] for n in phase]
    positions, valid = column_positions(obs, grid=grid, min_rows=min_rows)
    coef, sigma, converged = robust_polyfit(obs.x, positions, valid, powers=powers, tuning=bisquare,
                                            iterations=irls_iterations)
    params = {n: coef[:, [m]] for m, n in enumerate(phase)}
    unc = {n: sigma[:, [m]] for m, n in enumerate(phase)}
    params = wrap_phases(params, obs)
    good = well_determined(obs, gauge_fraction)
    params = fix_gauge(params, good)
    n_fit = int(np.isfinite(sigma[:, 0]).sum())
    return FitResult(params=params, uncertainty=unc, cost=np.zeros(0), stage=[], iterations=0,
                     converged=converged, messages=[f"correlation: {n_fit} of {obs.n_frames} frames fitted"],
                     well_determined=good)


def _frame_matrix(obs: Observations) -> sparse.csr_matrix:
    """(J, K) indicator of the blocks of each frame: sums over a frame's blocks per column as a product."""
    K = obs.frame.size
    return sparse.csr_matrix((np.ones(K), (obs.frame, np.arange(K))), shape=(obs.n_frames, K))


def column_positions(obs: Observations, *, grid: int = 360, min_rows: int = 3,
                     chunk: int = 2_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Grating position per frame and column that maximises the correlation with the flat-field pattern.

    The virtual pattern for grating position p is tf (1 + vf cos(phif + p)) = a + b cos p + c sin p with
    a = tf, b = tf vf cos phif, c = -tf vf sin phif, so its Pearson correlation with the counts I along
    a column's lit rows follows for every p from the moments of (I, a, b, c) over those rows.

    Parameters
    ----------
    obs : Observations
    grid : int
        Trial positions 2 pi k / grid; the best one is refined by a parabola through its neighbours.
    min_rows : int
        Fewest lit (and used) rows for a position.
    chunk : int
        Frames are processed in groups of about this many (frame, column, trial) values.

    Returns
    -------
    positions : ndarray, shape (J, C)
        Grating position (rad) in (-pi, pi]; 0 where not valid.
    valid : ndarray of bool, shape (J, C)
        Enough rows, and neither the counts nor the pattern constant along them.
    """
    S = _frame_matrix(obs)
    u = obs.use.astype(np.float64)
    counts = obs.counts
    dsg = M.design(obs, {})
    basis = (dsg.A, dsg.Bc, dsg.Bs)
    n = S @ u
    nz = np.maximum(n, 1.0)

    def mean(a):
        return (S @ (u * a)) / nz

    def cov(a, b):
        return mean(a * b) - mean(a) * mean(b)

    var_i = cov(counts, counts)
    c_i = np.stack([cov(counts, a) for a in basis], axis=-1)                       # (J, C, 3)
    sig = np.stack([np.stack([cov(a, b) for b in basis], -1) for a in basis], -1)  # (J, C, 3, 3)
    p = 2 * np.pi * np.arange(grid) / grid
    e = np.stack([np.ones(grid), np.cos(p), np.sin(p)])                      # (3, G)
    J, C = n.shape
    score = np.empty((J, C, grid))
    step = max(1, chunk // max(C * grid, 1))
    for lo in range(0, J, step):
        hi = min(J, lo + step)
        num = c_i[lo:hi] @ e
        var_p = np.einsum("jcab,ag,bg->jcg", sig[lo:hi], e, e)
        with np.errstate(divide="ignore", invalid="ignore"):
            score[lo:hi] = num / np.sqrt(np.maximum(var_p, 0.0))
    best = np.argmax(np.where(np.isfinite(score), score, -np.inf), axis=-1)
    f0, fm, fp = (np.take_along_axis(score, ((best + k) % grid)[..., None], -1)[..., 0] for k in (0, -1, 1))
    curv = fm - 2 * f0 + fp
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(curv < 0, 0.5 * (fm - fp) / curv, 0.0)
    positions = np.angle(np.exp(1j * (p[best] + np.clip(shift, -0.5, 0.5) * 2 * np.pi / grid)))
    scale = np.abs(sig[..., 0, 0]) + np.abs(sig[..., 1, 1]) + np.abs(sig[..., 2, 2])
    valid = (n >= min_rows) & (var_i > 0) & np.isfinite(f0) & (scale > 1e-12 * np.max(scale, initial=0.0))
    return np.where(valid, positions, 0.0), valid


def robust_polyfit(x: np.ndarray, y: np.ndarray, valid: np.ndarray, *, powers, tuning: float = 4.685,
                   iterations: int = 200, floor: float = 1e-6, tol: float = 1e-9
                   ) -> tuple[np.ndarray, np.ndarray, bool]:
    """Per-row bisquare (Tukey) fit of a polynomial in x to phases, by iteratively reweighted least squares.

    The data are phases: each iteration moves every value by a multiple of 2 pi to the branch nearest
    the current fit, starting from the row's circular mean.

    Parameters
    ----------
    x : ndarray, shape (C,)
        Abscissae (lateral coordinate, -1..1).
    y : ndarray, shape (J, C)
        Phases (rad).
    valid : ndarray of bool, shape (J, C)
        Values that take part.
    powers : sequence of int
        Powers of x in the polynomial (one coefficient each).
    tuning : float
        Bisquare constant c: weights (1 - (r / (c s))^2)^2 for |r| < c s, else 0, with s = 1.4826 MAD.
    iterations : int
        IRLS iterations at most.
    floor : float
        Smallest robust scale s (rad); keeps exact data from dividing by zero.
    tol : float
        Stop when no coefficient changes by more than this (rad).

    Returns
    -------
    coef : ndarray, shape (J, len(powers))
        0 for rows with fewer valid values than coefficients.
    sigma : ndarray, shape (J, len(powers))
        Standard errors s_w sqrt(diag (X^T W X)^-1), s_w^2 = sum w r^2 / (sum w - P); inf where not fitted.
    converged : bool
    """
    P = len(powers)
    J = y.shape[0]
    if P == 0:
        return np.zeros((J, 0)), np.zeros((J, 0)), True
    X = np.stack([x ** k for k in powers], axis=-1)                           # (C, P)
    fitted = valid.sum(axis=1) > P
    centre = np.angle(np.sum(np.where(valid, np.exp(1j * y), 0.0), axis=1))
    fit = np.broadcast_to(centre[:, None], y.shape)
    w = valid.astype(np.float64)
    coef = np.zeros((J, P))
    converged = False
    for _ in range(iterations):
        target = fit + np.angle(np.exp(1j * (y - fit)))
        N = np.einsum("jc,ca,cb->jab", w, X, X)
        N[~fitted] = np.eye(P)
        rhs = np.einsum("jc,ca,jc->ja", w, X, target)
        new = np.where(fitted[:, None], np.linalg.solve(N, rhs[..., None])[..., 0], 0.0)
        change = np.max(np.abs(new - coef), initial=0.0)
        coef = new
        fit = coef @ X.T
        r = np.where(valid, target - fit, np.nan)
        s = np.full(J, floor)
        s[fitted] = np.maximum(1.4826 * np.nanmedian(np.abs(r[fitted]), axis=1), floor)
        z = np.nan_to_num(r / (tuning * s[:, None]), nan=np.inf)
        w = np.where(np.abs(z) < 1, (1 - z ** 2) ** 2, 0.0)
        if change < tol:
            converged = True
            break
    N = np.einsum("jc,ca,cb->jab", w, X, X)
    dof = w.sum(axis=1) - P
    ok = fitted & (dof > 0) & (np.abs(np.linalg.det(N)) > 0)
    N[~ok] = np.eye(P)
    s2 = np.where(ok, np.sum(w * np.nan_to_num(r) ** 2, axis=1) / np.where(ok, dof, 1.0), np.inf)
    sigma = np.sqrt(s2[:, None] * np.einsum("jaa->ja", np.linalg.inv(N)))
    return np.where(fitted[:, None], coef, 0.0), np.where(ok[:, None], sigma, np.inf), converged
