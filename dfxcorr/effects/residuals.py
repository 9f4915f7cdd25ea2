"""Per-pixel residuals of a fit that several effects' tests read: squared Pearson residuals a run of columns at a
time, per-pixel chi-squares, and whether a class of pixels has one variance factor along the detector's lines."""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import numpy as np

from .. import engine as E
from .. import model as M
from ..chunks import row_counts
from ..noise import pearson
from ..observations import Noise, Observations
from ..stats import bonferroni, one_way_anova
from .base import Consistency, Params, State


def fit_counts(state: State) -> np.ndarray:
    """The expected counts of the fit's used, solved samples in the region of interest on the columns held for the
    per-pixel tests (``state.obs``): where bins of expected count are cut from, without every column's."""
    obs, rec = state.fit_obs, state.fit_rec
    solved = obs.use & obs.in_roi & obs.gather_valid(rec.images.valid)
    held = solved & np.isin(obs.columns, state.obs.columns)[None, :]
    # a band narrower than the fit's column step holds none of its columns (a full-resolution clinical scan's band of
    # 93 columns, the fit's every 434th): the bins from every column of the fit
    return rec.expected[held if held.any() else solved]


def image_leverage(state: State) -> np.ndarray:
    """The leverage of each of the fit's own samples in its pixel's images (:func:`dfxcorr.model.leverage`), shape
    (K, C): made once per fit (the residual signatures and the noise model's fit read it)."""
    return state.cached(_image_leverage)


def _image_leverage(state: State) -> np.ndarray:
    obs, rec = state.fit_obs, state.fit_rec
    return M.leverage(obs, M.design(obs, state.params), rec.images, rec.weights)


def squared_residuals(obs: Observations, params: Params, images: M.Images, exclude: np.ndarray | None = None, *,
                      samples: float = 2.5e5
                      ) -> Iterator[tuple[np.ndarray, Observations, np.ndarray, np.ndarray, np.ndarray]]:
    """A run of about ``samples`` samples' columns at a time (:func:`dfxcorr.engine.expected_by_columns`): its
    positions, samples, expected counts (from ``images`` and the model at ``params``), the samples that count (used,
    of solved pixels, not in ``exclude`` (H, W)) and their squared Pearson residuals (0 elsewhere). Runs of a
    quarter of the model's usual size: the per-pixel tests read them beside per-pixel sums of every held column,
    at the diagnosis's peak memory."""
    for cols, sub, im, ibar in E.expected_by_columns(obs, params, images, samples=samples):
        sel = sub.use & im.valid[sub.pixel]
        if exclude is not None:
            sel &= ~sub.pixel_mask(exclude)
        yield cols, sub, ibar, sel, np.where(sel, pearson(sub, ibar), 0.0)


def pixel_chi2(obs: Observations, params: Params, images: M.Images, *, under: Noise | None = None
               ) -> tuple[np.ndarray, np.ndarray, float]:
    """Per pixel, the Pearson chi-square of its samples under the noise model of ``obs`` and its degrees of
    freedom (samples - 3), detector images (H, W), 0 where nothing counts; and the whole chi-square of the same
    residuals under the noise model ``under`` (nan without it), in the same pass over the samples."""
    X, n = np.zeros((obs.starts.size, obs.columns.size)), np.zeros((obs.starts.size, obs.columns.size))
    total = 0.0 if under is not None else np.nan
    for cols, sub, ibar, sel, z2 in squared_residuals(obs, params, images):
        X[:, cols], n[:, cols] = sub.segment_sum(z2), row_counts(sub, sel)
        if under is not None:
            total += float(np.sum(pearson(sub.with_noise(under), ibar), where=sel))
    return obs.to_image(X, fill=0.0), obs.to_image(np.maximum(n - 3, 0.0), fill=0.0), total


def reduced_map(X: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """Reduced chi-square of each pixel, X / dof from its chi-square X and degrees of freedom (samples - 3; any shape,
    the same), NaN where it has none."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(dof > 0, X / dof, np.nan)


def line_consistency(factors: np.ndarray, X: np.ndarray, dof: np.ndarray, *, strata: int = 6,
                     min_pixels: int = 24) -> Consistency | None:
    """Whether each pixel class of a factor map has one variance factor along its detector lines.

    A class of pixels whose noise differs (module boundaries, a bad readout line) has it wherever the line runs;
    a moving part of the sample, or a localised artefact, raises the variance of a patch, which the class's
    lines only cross. Per class (pixels of one factor other than 1) and per axis, its pixels in ``strata`` groups
    of equal size by detector row (and by column), a one-way analysis of variance of the per-pixel reduced
    chi-square X / dof (weights dof) at the fit with the factors in the model.

    Parameters
    ----------
    factors, X, dof : ndarray, shape (H, W)
        The variance factor of each pixel in the model, its chi-square and degrees of freedom.

    Returns
    -------
    Consistency or None
        The strongest over classes and axes (Bonferroni): axis 'pixel', the strata's own factors f_s - 1 against
        the class's f - 1, ``along`` the lines. None without a class to test.
    """
    found = {}
    index = np.indices(factors.shape)
    for f in np.unique(factors[(factors != 1.0) & (dof > 0)]):
        m = (factors == f) & (dof > 0)
        if m.sum() < min_pixels:
            continue
        y, w = X[m] / dof[m], dof[m]
        for name, where in (("rows", index[0][m]), ("columns", index[1][m])):
            order = np.argsort(where, kind="stable")
            group = np.empty(order.size, int)
            group[order] = np.arange(order.size) * strata // order.size
            F, d1, _, log_p, means, pooled = one_way_anova(y, w, group, strata)
            sizes = tuple(float(v) for v in (f * means / pooled - 1.0) / (f - 1.0))
            found[f"{f:.6g} {name}"] = Consistency(F * d1, d1, float(np.exp(log_p)), log_p, "pixel", sizes,
                                                   along="rows" if name == "rows" else "columns")
    if not found:
        return None
    keys = list(found)
    i, log_p = bonferroni([found[k].log_p for k in keys])
    return replace(found[keys[i]], p_value=min(1.0, len(keys) * found[keys[i]].p_value), log_p=log_p)
