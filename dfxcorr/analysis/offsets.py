"""Where the flat field was read: ``reference_offset`` (one global shift) and ``position_error`` (one per frame).

Both read the flat-field maps of a frame at u - delta instead of u (``spec/diagnosis.md``). Every
derivative with respect to delta here is a finite difference of the one alignment
(:meth:`dfxcorr.align.LitStore.shifted`, i.e. :func:`dfxcorr.align.interpolate_rows`) pushed through
the one model (:mod:`dfxcorr.model`): no second copy of either.

``reference_offset`` is estimated from the differential-phase image, not from the likelihood. Where
the flat-field phase is linear along the scan, a global offset shifts every exposure of a pixel by
the same k delta (k = d phi^f / du of that pixel): the pixel's phase image absorbs it exactly and the
likelihood does not change. It is identifiable in the likelihood only through the flat field's
departure from linearity along u, which is small in real flat fields (the chi-square moves by noise).
The image however steps by -(jump of k) delta at every boundary of the grating tiles, where the
sample has no reason to step. :func:`offset_test` fits that step pattern, one parameter against all
boundaries and rows, and tests it against noise.
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from .. import model as M
from ..pipeline import Prepared
from ..retrieve import retrieve


def realign(prep: Prepared, like: M.Observations, shift: np.ndarray | float) -> M.Observations:
    """Observations of the samples of ``like`` with the flat field read at u - shift (rows; scalar or (J,)).

    ``like`` must come from ``prep`` (same rows and columns); its ``use``, noise model and region of
    interest (v^f = 0 outside) are kept, so that the realigned samples are the same samples.
    """
    store = prep.store.shifted(shift)
    rows = (int(like.row[0]), int(like.row[-1]) + 1)
    obs = store.observations(prep.reference, columns=like.columns, rows=rows, gain=like.gain,
                             electronic=like.electronic, dtype=like.counts.dtype)
    obs.noise = like.noise
    obs.vf = np.where(like.vf > 0, obs.vf, 0).astype(obs.vf.dtype, copy=False)
    obs.use = like.use.copy()
    return obs


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * a))


def _third_difference(a: np.ndarray) -> np.ndarray:
    """a[c+2] - 3 a[c+1] + 3 a[c] - a[c-1] along columns, shape (R, C - 3): zero for any quadratic in c."""
    return a[:, 3:] - 3 * a[:, 2:-1] + 3 * a[:, 1:-2] - a[:, :-3]


def phase_variance(images: M.Images, dispersion: float = 1.0) -> np.ndarray:
    """Variance (rad^2) of each pixel's phase phi = atan2(s, c) from the inverse normal matrix, (R, C)."""
    c, s = images.coef[..., 1], images.coef[..., 2]
    inv = images.inverse
    if inv is None:
        raise ValueError("the phase variance needs the inverse normal matrices (solve_images(..., keep_inverse=True))")
    with np.errstate(divide="ignore", invalid="ignore"):
        var = (s ** 2 * inv[..., 1, 1] + c ** 2 * inv[..., 2, 2] - 2 * c * s * inv[..., 1, 2]) / (c ** 2 + s ** 2) ** 2
    return np.where(images.valid, var * dispersion, np.nan)


def offset_test(prep: Prepared, obs: M.Observations, params: dict, shift: np.ndarray | float = 0.0, *,
                step: float = 0.5, clip: float = 5.0, min_precision: float = 0.1) -> dict:
    """Test for, and estimate, a reference offset from the steps of the differential-phase image.

    With the flat field read at u - delta for every frame, the retrieved phase image is
    phi_hat = phi - s delta, s = d phi_hat / d delta the pixel's sensitivity (its flat field's k =
    d phi^f / du averaged over its frames, less what the per-frame parameters absorb); s is the
    central difference of two retrievals with the flat field read ``step`` rows either way. The third
    difference along columns, D3, annihilates any sample structure quadratic over four columns, and
    s's smooth part; it leaves the jumps of k at the tile boundaries. delta is the weighted least-squares
    fit of D3(phi_hat) = -D3(s) delta over all rows and boundaries, weights the inverse noise variances
    of D3(phi_hat) (pixels independent); stencils beyond ``clip`` standard deviations from the fit (edges
    in the sample) are left out, iteratively. Its variance is exact for independent pixel noise
    (the estimator is linear in the phase image), scaled by the residual dispersion of all stencils
    where that exceeds 1: stencils away from the boundaries measure the noise.

    Parameters
    ----------
    prep : Prepared
    obs : Observations
        Every column of the detector (contiguous), as prepared, at the current alignment.
    params : dict
        Current effect parameters.
    shift : float or ndarray, shape (J,)
        Rows by which ``obs`` is already read off ``prep``'s alignment.
    step : float
        Rows of the finite difference.
    clip : float
        Outlier threshold (standard deviations).
    min_precision : float
        The offset is identifiable where its standard error is below this (rows): the flat field's k
        must jump between columns (tiled gratings); a smooth flat field has no boundary to step at.

    Returns
    -------
    dict
        'statistic' (z^2), 'dof' (1), 'p_value', 'log_p', 'identifiable', 'excess', 'explains', 'value'
        (delta beyond ``shift``, rows), 'sigma' (its standard error).
    """
    rec = retrieve(obs, params)
    images = M.solve_images(obs, M.design(obs, params), rec.weights, keep_inverse=True)
    phi, var = images.phi, phase_variance(images, max(rec.reduced_chi2, 1.0))
    plus, minus = (retrieve(realign(prep, obs, shift + d), params).images for d in (step, -step))
    sens = _wrap(plus.phi - minus.phi) / (2 * step)
    ok4 = images.valid & plus.valid & minus.valid & np.isfinite(var)
    ok = ok4[:, 3:] & ok4[:, 2:-1] & ok4[:, 1:-2] & ok4[:, :-3]
    f_phi = np.where(ok, _wrap(_third_difference(np.where(ok4, phi, 0.0))), 0.0)
    f_s = np.where(ok, _third_difference(np.where(ok4, sens, 0.0)), 0.0)
    v = np.nan_to_num(var)
    f_var = np.where(ok, v[:, 3:] + 9 * v[:, 2:-1] + 9 * v[:, 1:-2] + v[:, :-3], np.inf)
    keep, delta = ok.copy(), 0.0
    for _ in range(5):
        w = np.where(keep, 1.0 / f_var, 0.0)
        info = float(np.sum(w * f_s ** 2))
        if info <= 0:
            break
        delta = -float(np.sum(w * f_phi * f_s)) / info
        e = np.where(ok, (f_phi + f_s * delta) / np.sqrt(f_var), 0.0)
        new = ok & (np.abs(e) < clip)
        if np.array_equal(new, keep):
            break
        keep = new
    w = np.where(keep, 1.0 / f_var, 0.0)
    info = float(np.sum(w * f_s ** 2))
    if info <= 0:
        return {"statistic": 0.0, "dof": 1, "p_value": 1.0, "log_p": 0.0, "identifiable": False, "excess": 1,
                "explains": 0.0, "value": 0.0, "sigma": np.inf}
    # the estimator's coefficients on the phase image: the adjoint of the stencil applied to -w D3(s) / info
    a = -w * f_s / info
    coef = np.zeros_like(phi)
    for at, factor in ((3, 1.0), (2, -3.0), (1, 3.0), (0, -1.0)):
        coef[:, at:at + a.shape[1]] += factor * a
    sigma2 = float(np.sum(coef ** 2 * v))
    dispersion = max(float(np.sum(w * (f_phi + f_s * delta) ** 2) / max(int(keep.sum()) - 1, 1)), 1.0)
    sigma = np.sqrt(sigma2 * dispersion)
    stat = delta ** 2 / sigma ** 2
    return {"statistic": stat, "dof": 1, "p_value": float(stats.chi2.sf(stat, 1)),
            "log_p": float(stats.chi2.logsf(stat, 1)), "identifiable": bool(np.sqrt(sigma2) < min_precision),
            "excess": 0, "explains": stat, "value": delta, "sigma": float(sigma)}


def _shift_derivative(prep: Prepared, obs: M.Observations, params: dict, images: M.Images, shift: np.ndarray,
                      step: float) -> np.ndarray:
    """dIbar/d delta_j at every sample (K, C): images and parameters fixed, central difference of the alignment."""
    out = []
    for d in (step, -step):
        o = realign(prep, obs, shift + d)
        out.append(M.expected(o, M.design(o, params), images))
    return (out[0] - out[1]) / (2 * step)


def position_test(prep: Prepared, obs: M.Observations, params: dict, shift: np.ndarray, *,
                  dispersion: float = 1.0, step: float = 0.25, min_precision: float = 1.0, prior: float = 1.0) -> dict:
    """Per-frame score test for position errors, and one Gauss-Newton step of their estimate.

    Frame j's score U_j = sum w r dIbar/d delta_j and information I_j = sum w (dIbar/d delta_j)^2, each
    with the frame's own model parameters profiled out (the Schur complement of the frame's block:
    a delta_j that a phase offset or tilt would mimic is not a position error); the images are held
    fixed, which overstates I_j and keeps the test conservative. The common mode (one shift of all
    frames, the reference offset's business and nearly absorbed by the images) is projected out:
    S = (sum U_j^2 / I_j - (sum U_j)^2 / sum I_j) / dispersion, chi-square with (frames - 1) dof.

    Parameters
    ----------
    prep : Prepared
    obs : Observations
        The fit's samples, at the alignment ``shift`` relative to ``prep``.
    params : dict
        Current effect parameters.
    shift : ndarray, shape (J,)
        Rows by which ``obs`` is already read off ``prep``'s alignment.
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
    dict
        'statistic', 'dof', 'p_value', 'log_p', 'identifiable', 'excess', 'explains', 'frames'
        (per-frame share of the statistic), 'step' (J,) Gauss-Newton step of delta, 'param_step' (dict:
        the accompanying step of the model's per-frame parameters).
    """
    rec = retrieve(obs, params)
    images, w = rec.images, rec.weights
    r = obs.counts - rec.expected
    dsg = M.design(obs, params)
    D = [_shift_derivative(prep, obs, params, images, shift, step)]
    names = [(n, m) for n in params if M.effect(n).per_frame for m in range(M.effect(n).size)]
    D += [F for n in params if M.effect(n).per_frame for F in M.sample_derivatives(obs, dsg, images, n)]
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
    param_step: dict = {}
    for k, (n, m) in enumerate(names, start=1):
        param_step.setdefault(n, np.zeros_like(params[n]))[:, m] = sol[:, k]
    return {"statistic": stat, "dof": dof, "p_value": float(stats.chi2.sf(stat, dof)) if dof else 1.0,
            "log_p": float(stats.chi2.logsf(stat, dof)) if dof else 0.0,
            "identifiable": bool(dof and precision < min_precision), "excess": 0, "explains": stat * dispersion,
            "frames": per, "step": np.where(use, sol[:, 0], 0.0), "param_step": param_step}


def estimate_position_errors(prep: Prepared, obs: M.Observations, params: dict, shift: np.ndarray, *,
                             iterations: int = 10, tol: float = 0.01) -> tuple[np.ndarray, dict]:
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
        t = position_test(prep, realign(prep, obs, shift + delta), params, shift + delta)
        delta = delta + t["step"]
        for n, dp in t["param_step"].items():
            params[n] = params[n] + dp
        if np.max(np.abs(t["step"])) < tol:
            break
    return delta, params
