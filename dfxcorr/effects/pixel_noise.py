"""``pixel_noise``: the noise variance differs from pixel to pixel (module-boundary pixels of hybrid detectors, say).

variance_i = f_i * g * mean (+ electronic), f a per-pixel factor map, one factor per pixel class. Read from
``load.pixel_noise`` (a TIFF of factors, such as the ``pixel_noise.tif`` that the diagnosis writes), it
scales each pixel's noise variance in the fit's and the retrieval's weights.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .. import model as M
from ..catalogue import Effect
from ..errors import DfxcorrError
from ..noise import pearson
from ..observations import Observations
from ..preparation import Correctable
from ..stats import digitize, holm, normal_log_tail, ranges
from .base import Consistency, Context, EffectBase, Finding, Hypothesis, Option, Params, Policy, State, Test, chi2_test
from .residuals import fit_counts, line_consistency, pixel_chi2, squared_residuals


@dataclass(frozen=True)
class Classes:
    """A pixel-noise test's payload: the factor map (H, W), relative to the current factors, and its classes
    (each a dict of 'columns', 'rows', 'pixels', 'factor', 'dof')."""

    map: np.ndarray
    classes: tuple[dict[str, Any], ...]


def read_pixel_noise(path: str | Path | None, shape: tuple[int, int]) -> np.ndarray | None:
    """The variance factor map of ``load.pixel_noise`` (a TIFF of shape (H, W), e.g. diagnose's pixel_noise.tif).

    Raises
    ------
    PixelNoiseError
        If the file cannot be read, or its shape or values do not fit (positive and finite, one per pixel).
    """
    if path is None:
        return None
    import tifffile

    try:
        f = np.asarray(tifffile.imread(path), dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise PixelNoiseError(f"{path}: cannot read the pixel noise map of load.pixel_noise ({exc})") from None
    if f.shape != tuple(shape):
        raise PixelNoiseError(f"{path}: load.pixel_noise map has shape {f.shape}, the detector {tuple(shape)}")
    if not np.all(np.isfinite(f) & (f > 0)):
        raise PixelNoiseError(f"{path}: load.pixel_noise map holds values that are not positive and finite")
    return f


class PixelNoiseError(DfxcorrError, ValueError):
    """A pixel noise map (``load.pixel_noise``) that does not fit the scan."""



def pixel_noise_test(obs: Observations, params: Params, images: M.Images, *, alpha: float, counts: np.ndarray,
                     exclude: np.ndarray | None = None, fitted: np.ndarray | None = None) -> Test[Classes]:
    """Pixel classes whose noise variance differs from the rest: found by detector column and row, factor per class.

    Per pixel, the Pearson chi-square X_i of its samples under the current noise model, each sample's z^2
    divided by the regular pixels' dispersion at its expected count (12 bins: a variance misfit that follows
    the count, a detector nonlinearity say, is no pixel class), and its degrees of freedom n_i - 3 (3 image
    unknowns). Per detector column (and row) the sum X against c times its dof,
    c the overall dispersion: z = (X - c dof) / (c sqrt(V)), V the variance of the summed z^2 (2 + g / mu
    per sample: scaled Poisson noise); columns and rows significant after Holm (alpha over all of them)
    are anomalous, and grouped by their variance ratio (:func:`_variance_groups`: lines whose ratios agree
    within noise). Classes: pixels sharing (column group, row group), group 0 regular; the regular class is
    the reference. Each other class gets the factor
    f = (X / dof of the class) / (X / dof of the regular class), so that its reduced chi-square becomes that
    of the rest (a global gain stays detector_gain's); where no pixel is regular (every row anomalous, say)
    the factors are against the stated noise model. Statistic: the Gaussian likelihood ratio of a
    variance scale per class, sum dof (f - 1 - ln f), chi-square with one dof per class.

    ``fitted`` (C,) marks the columns the per-frame parameters were fitted on: their residuals are smaller
    (the parameters took some of their variance, and of any misfit), so their dispersion reference is that
    of the regular fitted columns, per count bin like the rest.

    The samples are summed per pixel and count bin a run of columns at a time (the expected counts from
    ``images`` and the model at ``params``), so that every column's temporaries are never held at once; the
    count bins' edges are quantiles of ``counts`` (the fit's columns' expected counts: the bins need not see
    every sample). ``exclude`` (H, W): pixels left out.

    Returns
    -------
    Test
        Payload 'map' (H, W) factors (relative to the current ones), 'classes' (list of dict: 'columns', 'rows',
        'pixels', 'factor').
    """
    C = obs.columns.size
    kind = np.zeros(C, int) if fitted is None else np.asarray(fitted, int)
    # a variance misfit that depends on the expected count (detector nonlinearity, say) is not a pixel class:
    # z^2 is measured against the regular pixels' dispersion at the same count (12 bins of equal size)
    edges = np.quantile(counts, np.linspace(0, 1, 13)[1:-1])
    R = obs.starts.size
    # per pixel and count bin: the sum of z^2 and the number of samples (float32: a few samples each)
    Z, N = np.zeros((R, C, edges.size + 1), np.float32), np.zeros((R, C, edges.size + 1), np.float32)
    kv_sum = np.zeros((R, C))
    for cols, sub, ibar, sel, z2 in squared_residuals(obs, params, images, exclude):
        kv_sum[:, cols] = sub.segment_sum(np.where(sel, 2.0 + sub.sample_gain()
                                                   / np.maximum(sub.photons(ibar), 1e-3), 0.0))
        # one bincount per sum over (pixel, count bin) cells, not a segment sum per bin
        cell = ((sub.pixel[:, None] * cols.size + np.arange(cols.size)) * (edges.size + 1)
                + digitize(ibar, edges)).ravel()
        for out, values in ((Z, z2), (N, sel)):
            out[:, cols] = np.bincount(cell, weights=values.ravel(), minlength=R * cols.size * (edges.size + 1)
                                       ).reshape(R, cols.size, edges.size + 1)
    n = N.sum(axis=2)
    dof = np.maximum(n - 3, 0.0)
    share = dof / np.maximum(n, 1)  # a sample's share of its pixel's dof
    # from here on N holds the samples' share of the dof per cell (in place: the (R, C, bins) sums are the test's
    # largest arrays)
    N *= share[..., None].astype(np.float32)
    V = np.where(dof > 0, kv_sum * dof / np.maximum(n, 1), 0.0)
    img = {k: obs.to_image(v, fill=0.0) for k, v in (("dof", dof), ("V", V))}
    H, W = obs.shape[1:]
    fmap = np.ones((H, W))
    none = Test(0.0, 0, 1.0, 0.0, Classes(fmap, ()))
    if img["dof"].sum() <= 0:
        return none
    groups = [np.zeros(W, int), np.zeros(H, int)]
    # the dispersion of the regular pixels, the anomalous columns and rows found against it: repeated until
    # they stay the same (anomalous lines would otherwise pull the reference and make the rest look anomalous)
    for _ in range(5):
        regular = (groups[1][:, None] == 0) & (groups[0][None, :] == 0)
        # per count bin (columns fitted or not) the regular pixels' sum of z^2 against their share of the dof
        per_count = np.ones((2, edges.size + 1))
        # regular = regular rows x regular columns: the cells summed over the rows (float32, a few hundred each),
        # then over the columns of each kind in float64
        rows = (groups[1][obs.rows] == 0).astype(np.float32)
        by_column = [np.tensordot(rows, A, 1).astype(np.float64) for A in (Z, N)]
        for k in (0, 1):
            cols = ((groups[0][obs.columns] == 0) & (kind == k)).astype(np.float64)
            num, den = cols @ by_column[0], cols @ by_column[1]
            per_count[k] = np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)
        scale = (1.0 / per_count[kind]).astype(np.float32)[None]
        # a run of rows at a time: the scaled sums of every pixel at once would be one more (R, C, bins) array
        X = np.concatenate([(Z[r] * scale).sum(axis=2, dtype=np.float64)
                            for r in np.array_split(np.arange(R), max(R // 64, 1))])
        img["X"] = obs.to_image(np.where(dof > 0, X, 0.0), fill=0.0)
        c = _dispersion(img, regular)
        tests, lines = [], []
        for axis in (0, 1):
            # a column's sum over the regular rows, a row's over the regular columns
            keep = (groups[1][:, None] == 0) if axis == 0 else (groups[0][None, :] == 0)
            Xa, Da, Va = (np.where(keep, img[k], 0.0).sum(axis=axis) for k in ("X", "dof", "V"))
            ok = Da > 0
            z = np.where(ok, (Xa - c * Da) / (c * np.sqrt(np.where(ok, Va, 1.0))), 0.0)
            lines.append((Xa, Da, Va))
            log_p = np.log(2) + normal_log_tail(np.abs(z))
            tests += [(float(log_p[i]), axis, i) for i in np.flatnonzero(ok)]
        significant = holm([t[0] for t in tests], alpha)
        new = []
        for axis in (0, 1):
            idx = np.array([i for (_, a, i), s in zip(tests, significant, strict=True) if a == axis and s], int)
            Xa, Da, Va = lines[axis]
            new.append(_variance_groups(Xa[idx], Da[idx], Va[idx], idx, c=c, size=(W, H)[axis]))
        if all(np.array_equal(a, b) for a, b in zip(new, groups, strict=True)):
            break
        groups = new
    label = groups[1][:, None] * (groups[0].max() + 1) + groups[0][None, :]
    regular = label == 0
    if regular.all():
        return none
    c0 = _dispersion(img, regular)
    classes, stat = [], 0.0
    for k in np.unique(label[~regular]):
        m = label == k
        d = img["dof"][m].sum()
        if d <= 0:
            continue
        f = img["X"][m].sum() / d / c0
        fmap[m] = f
        stat += float(d * (f - 1 - np.log(f)))
        r_idx, c_idx = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        classes.append({"rows": ranges(r_idx, limit=8), "columns": ranges(c_idx, limit=8),
                        "pixels": int(m.sum()), "factor": float(f), "dof": float(d)})
    if not classes:
        return none
    return chi2_test(stat, len(classes), Classes(fmap, tuple(classes)), explains=stat)


def _dispersion(img: dict[str, Any], regular: np.ndarray) -> float:
    """Reduced chi-square of the regular pixels; 1 (the stated noise model) when every line is anomalous."""
    dof = img["dof"][regular].sum()
    return float(img["X"][regular].sum() / dof) if dof > 0 else 1.0


def _variance_groups(X: np.ndarray, dof: np.ndarray, V: np.ndarray, idx: np.ndarray, *, c: float, size: int,
                     z_split: float = 5.0) -> np.ndarray:
    """Group anomalous detector lines (columns or rows) whose variance ratios agree: 0 regular, 1, 2, ... groups.

    The lines ``idx`` (their chi-square sums X, dof and variances V), sorted by their ratio X / (c dof), join
    the current group while they lie within ``z_split`` standard deviations of its pooled ratio.
    """
    out = np.zeros(size, int)
    if idx.size == 0:
        return out
    ratio = X / (c * dof)
    order = np.argsort(ratio)
    g, Xg, Dg, Vg = 0, 0.0, 0.0, 0.0
    for i in order:
        if g and abs(ratio[i] - Xg / (c * Dg)) > z_split * np.sqrt(V[i] / dof[i] ** 2 + Vg / Dg ** 2):
            g, Xg, Dg, Vg = g + 1, 0.0, 0.0, 0.0
        g = max(g, 1)
        out[idx[i]] = g
        Xg, Dg, Vg = Xg + X[i], Dg + dof[i], Vg + V[i]
    return out


def class_chi2(obs: Observations, ibar: np.ndarray, valid: np.ndarray, classes: np.ndarray) -> dict[int, float]:
    """Reduced chi-square per pixel class: sum of Pearson residuals over sum of (samples - 3) per pixel.

    ``classes`` (H, W) int labels; returns label -> reduced chi-square (under the noise model of ``obs``).
    """
    sel = obs.use & obs.gather_valid(valid)
    n = obs.segment_sum(sel.astype(float))
    X = obs.to_image(obs.segment_sum(np.where(sel, pearson(obs, ibar), 0.0)), fill=0.0)
    dof = obs.to_image(np.maximum(n - 3, 0.0), fill=0.0)
    return {int(k): float(X[classes == k].sum() / dof[classes == k].sum()) for k in np.unique(classes)
            if dof[classes == k].sum() > 0}




class PixelNoise(EffectBase[Classes]):
    entry = Effect("pixel_noise", None, False, (), 1.0, "none",
                   "the noise variance differs from pixel to pixel: variance_i = f_i * g * mean (+ electronic)")
    # a variance pattern before a global gain: its factors are relative to the regular pixels, so a gain fitted
    # first would be pulled by the anomalous ones
    policy = Policy(order=0, noise_model=True, pixelwise=True)
    files = ("pixel_noise.tif",)

    def configured(self, cfg: dict[str, Any], *, n_frames: int, detector: tuple[int, int]) -> Any:
        return read_pixel_noise(cfg["load"]["pixel_noise"], detector)

    def apply(self, data: Correctable, setting: Any) -> Correctable:
        return replace(data, noise=replace(data.noise, factors=setting))

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test[Classes] | None:
        from scipy import ndimage

        return pixel_noise_test(state.obs, state.params, state.rec.images, alpha=ctx.cfg["diagnose"]["alpha"],
                                counts=fit_counts(state), fitted=ctx.fitted,
                                exclude=ndimage.binary_dilation(flagged))

    def consistency(self, ctx: Context, before: State, state: State) -> Consistency | None:
        # the classes' factors in the trial's model: each class must have one factor along its lines
        # (:func:`line_consistency`: its strata's factors against the class's own departure from 1)
        factors = state.hypothesis.noise.factors
        if factors is None:
            return None
        X, dof, _ = pixel_chi2(state.obs, state.params, state.rec.images)
        return line_consistency(factors, X, dof)

    def trial(self, ctx: Context, state: State, test: Test[Classes]) -> Hypothesis:
        noise = state.hypothesis.noise
        # the test's factors are relative to the current ones
        factors = test.payload.map * (1.0 if noise.factors is None else noise.factors)
        return state.hypothesis.but(noise=replace(noise, factors=factors))

    def accepted(self, ctx: Context, before: State, after: State, test: Test[Classes]) -> Finding:
        classes = test.payload.classes
        factors = after.hypothesis.noise.factors
        files = {}
        if factors is not None:
            def write(path: Path) -> None:
                import tifffile

                tifffile.imwrite(path, factors.astype(np.float32))

            files = {self.files[0]: write}
        return Finding("; ".join(f"rows {c['rows']} x columns {c['columns']}" for c in classes[:3]),
                       ", ".join(f"f = {c['factor']:.3g} ({c['pixels']} pixels)" for c in classes),
                       {"classes": list(classes)}, options=(Option("load.pixel_noise", self.files[0], file=True),),
                       files=files)


EFFECT = PixelNoise()
