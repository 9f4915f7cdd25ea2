"""``sample_motion``: part of the sample moved during the scan; its pixels' frames disagree.

Localised, not per-frame: the pixels are left out of the fit (as the motion mask of the paper's
Sec. II-E leaves them out of a reconstruction's vibration fit).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage, stats

from ..catalogue import Effect
from ..mask import motion_score
from ..observations import Observations
from .base import Context, EffectBase, Hypothesis, State, Test, Writer

#: The largest share of the scored pixels that a moving part of the sample may cover: a misfit spread wider is
#: not sample motion (a blanket mask hides a misfit of the whole detector), and is reported where it is.
MAX_SHARE = 0.1


def motion_test(obs: Observations, params: dict, *, p_pixel: float = 1e-6, min_pixels: int = 5) -> Test:
    """Pixels whose frames disagree beyond noise and remaining vibration misfit, in clusters.

    The per-pixel score is :func:`dfxcorr.mask.motion_score` at the current model (a reduced
    chi-square once what the fringe sensitivity explains is divided out); a pixel is flagged when that
    score is in the chi-square tail beyond ``p_pixel``, and counts only in a cluster of three or more.

    Returns
    -------
    Test
        Statistic: chi-square in excess of its dof over the flagged pixels; dof: flagged pixels; log_p:
        binomial (that many pixels below ``p_pixel`` by chance); payload 'mask' (H, W) bool. Not material where
        the flagged pixels are more than :data:`MAX_SHARE` of those scored.
    """
    score = motion_score(obs, params)
    dof = np.maximum(obs.segment_sum(obs.use, dtype=np.int64) - 3, 1)
    ok = np.isfinite(score)
    # the chi-square tail beyond p_pixel as a critical value per degree of freedom (a few distinct ones): the
    # log-tail of every pixel was 0.3 s a round on a 512 x 1536 detector
    dofs, at = np.unique(dof, return_inverse=True)
    critical = stats.chi2.isf(p_pixel, dofs)[at.reshape(dof.shape)]
    flag = obs.to_image(ok & (np.nan_to_num(score) * dof > critical), fill=False).astype(bool)
    labels, count = ndimage.label(flag)
    if count:
        # a moving sample covers neighbouring pixels; isolated tail pixels are noise or outliers
        sizes = ndimage.sum(flag, labels, index=np.arange(1, count + 1))
        flag = np.isin(labels, 1 + np.flatnonzero(sizes >= 3))
    k = int(flag.sum())
    excess = obs.to_image(np.nan_to_num(score - 1) * dof, fill=0.0)
    log_p = float(stats.binom.logsf(k - 1, int(ok.sum()), p_pixel)) if k >= min_pixels else 0.0
    stat = float(excess[flag].sum())
    return Test(stat, k, float(np.exp(log_p)), log_p, explains=stat, material=k <= MAX_SHARE * ok.sum(),
                payload={"mask": flag})


def where_pixels(mask: np.ndarray) -> str:
    """'N pixels in rows a-b, columns c-d' of a detector mask."""
    rows, cols = np.nonzero(mask)
    return (f"{rows.size} pixels in rows {rows.min()}-{rows.max()}, columns {cols.min()}-{cols.max()}"
            if rows.size else "nowhere")


class SampleMotion(EffectBase):
    entry = Effect("sample_motion", None, False, (), 0.0, "none",
                   "part of the sample moved during the scan: pixels whose frames disagree")
    role = "pixels"
    files = ("motion_mask.tif",)

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test | None:
        if state.hypothesis.motion.any():
            return None
        d = ctx.cfg["diagnose"]
        return motion_test(state.obs, state.params, p_pixel=d["motion_p"], min_pixels=d["min_pixels"])

    def trial(self, ctx: Context, state: State, test: Test) -> Hypothesis:
        # the rim of a moving region is partly affected too
        return state.hypothesis.but(motion=ndimage.binary_dilation(test.payload["mask"], iterations=1))

    def accepted(self, ctx: Context, before: State, after: State, test: Test) -> dict:
        return {"pixels": int(after.hypothesis.motion.sum())}

    def where(self, test: Test, obs: Observations) -> str:
        return where_pixels(test.payload["mask"])

    def estimate(self, extra: dict, params: dict, good: np.ndarray) -> str:
        return f"{extra['pixels']} pixels"

    def unexplained(self, test: Test) -> dict:
        """The ``unexplained`` entry of pixels that disagree although masking them did not explain the misfit."""
        why = "masking them does not explain the misfit" if test.material else \
            f"more than {100 * MAX_SHARE:.0f} % of the pixels: no moving part of a sample"
        return {"axis": "pixel", "statistic": test.statistic, "dof": test.dof, "p_value": test.p_value,
                "where": where_pixels(test.payload["mask"]),
                "description": f"{int(test.payload['mask'].sum())} pixels whose frames disagree beyond noise, in "
                               f"clusters; {why}"}

    def settings(self, cfg: dict, final: Hypothesis, extra: dict | None, out_dir: Path) -> list[str]:
        return ["mask.enabled=true"] if extra is not None else []

    def artefacts(self, final: Hypothesis, extra: dict | None, cfg: dict) -> dict[str, Writer]:
        if extra is None:
            return {}

        def write(path: Path) -> None:
            import tifffile

            tifffile.imwrite(path, final.motion.astype(np.uint8))

        return {self.files[0]: write}


EFFECT = SampleMotion()
