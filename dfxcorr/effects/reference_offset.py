"""``reference_offset``: the whole interferometer sat delta rows off during the scan, relative to the reference scan.

Every frame reads the flat-field maps at u - delta (paper Sec. III-B: phase ramps at the G2 tile
boundaries). Every derivative with respect to delta here is a finite difference of the one alignment
(:func:`dfxcorr.align.realign`) pushed through the one model (:mod:`dfxcorr.model`): no second copy of either.

It is estimated from the differential-phase image, not from the likelihood. Where the flat-field phase
is linear along the scan, a global offset shifts every exposure of a pixel by the same k delta (k =
d phi^f / du of that pixel): the pixel's phase image absorbs it exactly and the likelihood does not
change. It is identifiable in the likelihood only through the flat field's departure from linearity
along u, which is small in real flat fields (the chi-square moves by noise). The image however steps by
-(jump of k) delta at every boundary of the grating tiles, where the sample has no reason to step.
:func:`offset_test` fits that step pattern, one parameter against all boundaries and rows, and tests it
against noise.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .. import model as M
from ..catalogue import Effect
from ..observations import Observations
from ..preparation import Correctable
from ..retrieve import per_dof, retrieve
from .base import Context, EffectBase, Estimate, Finding, Hypothesis, Option, Policy, Realign, State, Test, chi2_test


@dataclass(frozen=True)
class Offset:
    """An offset test's estimate beyond the current alignment and its standard error (rows)."""

    value: float
    sigma: float


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


def _realigned_images(realigned: Realign, obs: Observations, params: dict[str, Any], shift: np.ndarray | float, *,
                      keep_inverse: bool = False) -> tuple[M.Images, float]:
    """The images of the samples of ``obs`` with the flat field read ``shift`` rows off the prepared alignment, and
    their reduced chi-square, solved a run of columns at a time (a clinical scan's realigned samples at once would be
    most of its diagnosis's peak memory)."""
    # views of each run of columns: the realignment reads their samples anew and keeps only their masks
    parts = [retrieve(realigned(obs.subset(c, copy=False), shift), params, keep_inverse=keep_inverse,
                      keep_expected=False) for c in obs.column_chunks()]
    inverse = np.concatenate([p.images.inverse for p in parts], axis=1) if keep_inverse else None
    images = M.Images(np.concatenate([p.images.coef for p in parts], axis=1),
                      np.concatenate([p.images.valid for p in parts], axis=1), inverse)
    chi2 = per_dof(sum(p.chi2_sum for p in parts), sum(p.samples for p in parts), int(images.valid.sum()),
                   sum(np.size(p) for p in params.values()), 3)
    return images, chi2


def offset_test(realigned: Realign, obs: Observations, params: dict[str, Any], shift: np.ndarray | float = 0.0, *,
                step: float = 0.5, clip: float = 5.0, min_precision: float = 0.1) -> Test[Any]:
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
    realigned : callable
        (observations, shift) -> the same samples with the flat field read ``shift`` rows off the prepared
        alignment (:func:`dfxcorr.align.realign`).
    obs : Observations
        Contiguous columns of the detector (every one, or the diagnosis's band): their samples, at any alignment.
    params : dict
        Current effect parameters.
    shift : float or ndarray, shape (J,)
        Rows off the prepared alignment at which the flat field is read (the samples are realigned there, a run
        of columns at a time).
    step : float
        Rows of the finite difference.
    clip : float
        Outlier threshold (standard deviations).
    min_precision : float
        The offset is identifiable where its standard error is below this (rows): the flat field's k
        must jump between columns (tiled gratings); a smooth flat field has no boundary to step at.

    Returns
    -------
    Test
        Statistic z^2 with 1 dof; payload the offset beyond ``shift`` (rows) and its standard error.
    """
    # the compiled retrieval keeps the inverse normal matrices the phase variance needs (the numpy model's solve of
    # every column would take a quarter of the paper study's tests)
    images, chi2 = _realigned_images(realigned, obs, params, shift, keep_inverse=True)
    phi, var = images.phi, phase_variance(images, max(chi2, 1.0))
    plus, minus = (_realigned_images(realigned, obs, params, shift + d)[0] for d in (step, -step))
    sens = M.wrap_angle(plus.phi - minus.phi) / (2 * step)
    ok4 = images.valid & plus.valid & minus.valid & np.isfinite(var)
    ok = ok4[:, 3:] & ok4[:, 2:-1] & ok4[:, 1:-2] & ok4[:, :-3]
    f_phi = np.where(ok, M.wrap_angle(_third_difference(np.where(ok4, phi, 0.0))), 0.0)
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
        return Test(0.0, 1, 1.0, 0.0, Offset(0.0, np.inf), identifiable=False, excess=1)
    # the estimator's coefficients on the phase image: the adjoint of the stencil applied to -w D3(s) / info
    a = -w * f_s / info
    coef = np.zeros_like(phi)
    for at, factor in ((3, 1.0), (2, -3.0), (1, 3.0), (0, -1.0)):
        coef[:, at:at + a.shape[1]] += factor * a
    sigma2 = float(np.sum(coef ** 2 * v))
    dispersion = max(float(np.sum(w * (f_phi + f_s * delta) ** 2) / max(int(keep.sum()) - 1, 1)), 1.0)
    sigma = np.sqrt(sigma2 * dispersion)
    stat = delta ** 2 / sigma ** 2
    return chi2_test(stat, 1, Offset(delta, float(sigma)), identifiable=bool(np.sqrt(sigma2) < min_precision),
                     explains=stat)


class ReferenceOffset(EffectBase[Offset]):
    entry = Effect("reference_offset", None, False, ("delta",), 0.0, "none",
                   "the interferometer sat delta rows off during the scan: the flat field is read at u - delta",
                   unit="rows")
    # its statistic comes from the image, not the likelihood (which barely sees it); its step signature at the
    # tile boundaries is specific, while mean-effect proxies would soak up what it does to the fit
    policy = Policy(order=1, astray_check=True)

    def configured(self, cfg: dict[str, Any], *, n_frames: int, detector: tuple[int, int]) -> Any:
        return cfg["align"]["reference_offset"] or None

    def apply(self, data: Correctable, setting: Any) -> Correctable:
        return replace(data, shift=data.shift + setting)

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test[Offset] | None:
        # a phase-stepping recording has no scan positions to be off
        if ctx.stepping:
            return None
        return offset_test(ctx.realigner(state.hypothesis), state.obs, state.params, state.hypothesis.shift)

    def trial(self, ctx: Context, state: State, test: Test[Offset]) -> Hypothesis:
        realigned = ctx.realigner(state.hypothesis)
        found = state.hypothesis.shift + test.payload.value
        # one refinement at the corrected alignment: the step's sensitivity is a linearisation
        found = found + offset_test(realigned, state.obs, state.params, found).payload.value
        return state.hypothesis.but(shift=found)

    def accepted(self, ctx: Context, before: State, after: State, test: Test[Offset]) -> Finding:
        value = float(np.mean(after.hypothesis.shift - before.hypothesis.shift))
        # the configured offset stays in the recommended command
        offset = ctx.cfg["align"]["reference_offset"] + value
        return Finding("steps of the differential phase at the flat field's tile boundaries, all rows",
                       f"delta = {value:.3f} rows", {"value": value},
                       options=(Option("align.reference_offset", f"{offset:.4g}"),))

    def measure(self, ctx: Context, state: State) -> Estimate | None:
        # the offset this fit's alignment holds beyond the configured one, with the standard error its test gives
        t = offset_test(ctx.realigner(state.hypothesis), state.obs, state.params, state.hypothesis.shift)
        return Estimate(np.asarray(float(np.mean(state.hypothesis.shift)) + t.payload.value),
                        np.asarray(t.payload.sigma))


EFFECT = ReferenceOffset()
