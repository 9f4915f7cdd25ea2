"""``sample_motion``: part of the sample moved during the scan; its pixels' frames disagree.

Localised, not per-frame: the pixels are left out of the fit (as the motion mask of the paper's
Sec. II-E leaves them out of a reconstruction's vibration fit).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage

from ..catalogue import Effect
from ..mask import motion_score
from ..observations import Observations
from ..stats import binomial_log_tail, chi2_quantile
from .base import Context, EffectBase, Finding, Hypothesis, Option, Params, Policy, State, Test, Unexplained

#: The largest share of the scored pixels that a moving part of the sample may cover: a misfit spread wider is
#: not sample motion (a blanket mask hides a misfit of the whole detector), and is reported where it is.
MAX_SHARE = 0.1
#: A moving part of the sample is one region: grown by :data:`REACH` pixels (steps along rows and columns), the
#: flagged pixels' largest group must hold at least this share of them. Measured (seed 11): a heart that moves, 256,
#: 215 and 18 pixels flagged at amplitudes 0.3, 0.1 and 0.05, one group each; the edges of ribs and lungs under a
#: parallax the model reads between rows (beam_path, kappa 0.02), 88 pixels in 10 groups, the largest 21. Three or
#: more moving parts of like size are reported as unexplained pixels too.
MIN_GROUPED = 0.5
REACH = 2


#: Why flagged pixels are no moving part of a sample (empty where they may be one).
Reasons = tuple[str, ...]


def motion_test(obs: Observations, params: Params, *, p_pixel: float = 1e-6, min_pixels: int = 5) -> Test[Reasons]:
    """Pixels whose frames disagree beyond noise and remaining vibration misfit, in clusters.

    The per-pixel score is :func:`dfxcorr.mask.motion_score` at the current model (a reduced
    chi-square once what the fringe sensitivity explains is divided out); a pixel is flagged when that
    score is in the chi-square tail beyond ``p_pixel``, and counts only in a cluster of three or more.

    Returns
    -------
    Test
        Statistic: chi-square in excess of its dof over the flagged pixels; dof: flagged pixels; log_p:
        binomial (that many pixels below ``p_pixel`` by chance); ``flagged`` (H, W) bool; payload: why the flagged
        pixels are no moving part of a sample, more than :data:`MAX_SHARE` of those scored or scattered
        (:func:`grouped`), and then not material.
    """
    score = motion_score(obs, params)
    dof = np.maximum(obs.segment_sum(obs.use, dtype=np.int64) - 3, 1)
    ok = np.isfinite(score)
    # the chi-square tail beyond p_pixel as a critical value per degree of freedom (a few distinct ones): the
    # log-tail of every pixel would take 0.3 s a round on a 512 x 1536 detector
    dofs, at = np.unique(dof, return_inverse=True)
    critical = chi2_quantile(p_pixel, dofs, upper=True)[at.reshape(dof.shape)]
    flag = obs.to_image(ok & (np.nan_to_num(score) * dof > critical), fill=False).astype(bool)
    labels, count = ndimage.label(flag)
    if count:
        # a moving sample covers neighbouring pixels; isolated tail pixels are noise or outliers
        sizes = ndimage.sum(flag, labels, index=np.arange(1, count + 1))
        flag = np.isin(labels, 1 + np.flatnonzero(sizes >= 3))
    k = int(flag.sum())
    excess = obs.to_image(np.nan_to_num(score - 1) * dof, fill=0.0)
    log_p = binomial_log_tail(k, int(ok.sum()), p_pixel) if k >= min_pixels else 0.0
    stat = float(excess[flag].sum())
    share = grouped(flag)
    checks = ((f"more than {100 * MAX_SHARE:.0f} % of the pixels", k > MAX_SHARE * ok.sum()),
              (f"scattered (the largest group holds {100 * share:.0f} % of them)", share < MIN_GROUPED))
    reasons = tuple(why for why, holds in checks if holds)
    return Test(stat, k, float(np.exp(log_p)), log_p, reasons, explains=stat, material=not reasons, flagged=flag)


def grouped(flag: np.ndarray) -> float:
    """The share of the flagged pixels (H, W) in their largest group once each is grown by :data:`REACH` pixels (1
    where none is flagged)."""
    if not flag.any():
        return 1.0
    labels, count = ndimage.label(ndimage.binary_dilation(flag, iterations=REACH))
    return float(np.bincount(labels[flag], minlength=count + 1).max() / flag.sum())


def where_pixels(mask: np.ndarray) -> str:
    """'N pixels in rows a-b, columns c-d' of a detector mask."""
    rows, cols = np.nonzero(mask)
    return (f"{rows.size} pixels in rows {rows.min()}-{rows.max()}, columns {cols.min()}-{cols.max()}"
            if rows.size else "nowhere")


def _flagged(test: Test[Reasons]) -> np.ndarray:
    if test.flagged is None:
        raise ValueError("a motion test flags pixels")
    return test.flagged


class SampleMotion(EffectBase[Reasons]):
    entry = Effect("sample_motion", None, False, (), 0.0, "none",
                   "part of the sample moved during the scan: pixels whose frames disagree")
    policy = Policy(localised=True, pixelwise=True, astray_check=True)
    files = ("motion_mask.tif",)

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test[Reasons] | None:
        if state.hypothesis.motion.any():
            return None
        d = ctx.cfg["diagnose"]
        return motion_test(state.obs, state.params, p_pixel=d["motion_p"], min_pixels=d["min_pixels"])

    def trial(self, ctx: Context, state: State, test: Test[Reasons]) -> Hypothesis:
        # the rim of a moving region is partly affected too
        return state.hypothesis.but(motion=ndimage.binary_dilation(_flagged(test), iterations=1))

    def accepted(self, ctx: Context, before: State, after: State, test: Test[Reasons]) -> Finding:
        motion = after.hypothesis.motion
        pixels = int(motion.sum())

        def write(path: Path) -> None:
            import tifffile

            tifffile.imwrite(path, motion.astype(np.uint8))

        return Finding(where_pixels(_flagged(test)), f"{pixels} pixels", {"pixels": pixels},
                       options=(Option("mask.enabled", "true"),), files={self.files[0]: write})

    def unexplained(self, test: Test[Reasons]) -> Unexplained:
        """The ``unexplained`` entry of pixels that disagree although masking them did not explain the misfit."""
        mask = _flagged(test)
        why = ("masking them does not explain the misfit" if test.material else
               "; ".join(test.payload) + ": no moving part of a sample")
        return Unexplained("pixel", test.statistic, test.dof, test.p_value, where_pixels(mask),
                           f"{int(mask.sum())} pixels whose frames disagree beyond noise, in clusters; {why}")


EFFECT = SampleMotion()
