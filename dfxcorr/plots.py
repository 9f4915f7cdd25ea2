"""Pictures: every matplotlib figure dfxcorr draws (previews, fit plots, comparisons, spectra, diagnosis).

matplotlib is imported on first use, on the Agg backend, so that the pipeline never needs a display
and a run without pictures never imports it.
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .catalogue import CATALOGUE
from .export import VibrationDataset, check_output, units, vibration_datasets
from .io import atomic_path
from .result import Result


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed), imported only when a picture is drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, *, overwrite: bool = False) -> Path:
    """Write a figure as PNG atomically and close it (replacing an existing file only with ``overwrite``)."""
    try:
        with atomic_path(path, overwrite=overwrite) as tmp, open(tmp, "wb") as fh:
            fig.savefig(fh, format="png", dpi=150)
    finally:
        pyplot().close(fig)
    return Path(path)


def display_image(name: str, image) -> np.ndarray:
    """The field's display convention: t as is, dark field as -ln v, phi as is."""
    a = np.asarray(image, dtype=np.float64)
    if name == "dark_field":
        with np.errstate(divide="ignore", invalid="ignore"):
            a = -np.log(a)
    return np.where(np.isfinite(a), a, np.nan)


def display_window(name: str, a: np.ndarray) -> tuple[float, float]:
    """1st-99th percentile, symmetric about 0 for the differential phase."""
    finite = a[np.isfinite(a)]
    if finite.size == 0:
        return (-1.0, 1.0) if name == "differential_phase" else (0.0, 1.0)
    lo, hi = np.percentile(finite, [1, 99])
    if name == "differential_phase":
        hi = max(abs(lo), abs(hi))
        lo = -hi
    if hi <= lo:
        lo, hi = lo - 0.5 * (abs(lo) or 1.0), hi + 0.5 * (abs(hi) or 1.0)
    return float(lo), float(hi)


IMAGE_LABELS = {"transmission": "transmission t", "dark_field": "dark field −ln v",
                "differential_phase": "differential phase φ (rad)"}


def write_preview(path, result: Result, *, overwrite: bool = False, title: str | None = None) -> Path:
    """Picture of the three images, uncorrected above corrected.

    Parameters
    ----------
    path : str or Path
        Output PNG.
    result : Result
        What the reconstruction produced; with ``result.uncorrected`` set, a row of images retrieved
        with neutral per-frame parameters is shown above the corrected ones.
    overwrite : bool
        Replace an existing file.
    title : str, optional
        Figure title (default: the input file's name).

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    Transmission is shown as is, dark field as -ln v, differential phase in a window symmetric about
    zero, all in gray; non-finite pixels (never illuminated) in blue. Both panels of an image share the
    window of the corrected image (its 1st-99th percentile), so residual stripes compare directly.
    """
    check_output(path, overwrite=overwrite)
    plt = pyplot()
    rows: list[tuple[str, Callable[[str], Any]]] = [("corrected", result.image)]
    if result.uncorrected is not None:
        rows.insert(0, ("uncorrected", result.uncorrected.get))
    h, w = np.shape(result.transmission)
    panel_w = 4.6
    panel_h = float(np.clip(panel_w * 0.8 * h / max(w, 1), 1.4, 5.5))
    fig, axes = plt.subplots(len(rows), 3, figsize=(3 * panel_w, len(rows) * (panel_h + 0.7) + 0.5),
                             squeeze=False, layout="constrained")
    cmap = plt.get_cmap("gray").with_extremes(bad="#6f8fbf")
    for col, name in enumerate(Result.IMAGES):
        vmin, vmax = display_window(name, display_image(name, result.image(name)))
        for row, (kind, get) in enumerate(rows):
            ax = axes[row, col]
            image = get(name)
            label = "corrected (" + result.method + ")" if kind == "corrected" else kind
            ax.set_title(f"{IMAGE_LABELS[name]}: {label}", fontsize=10)
            ax.set_xticks([])
            ax.set_yticks([])
            if image is None:
                ax.set_axis_off()
                continue
            im = ax.imshow(display_image(name, image), cmap=cmap, vmin=vmin, vmax=vmax, aspect="auto",
                           interpolation="nearest")
            fig.colorbar(im, ax=ax, shrink=0.9)
    fig.suptitle(title if title is not None else Path(result.provenance.get("input_file", "")).name or "dfxcorr")
    window = "both panels of an image share" if len(rows) == 2 else "window:"
    fig.supxlabel(f"{window} the corrected image's 1st-99th percentile; blue: no data", fontsize=9)
    return save_figure(fig, path, overwrite=overwrite)


def write_fit_plot(path, result: Result, *, overwrite: bool = False) -> Path:
    """Picture of the fitted per-frame parameters and the cost history.

    Parameters
    ----------
    path : str or Path
        Output PNG.
    result : Result
        What the reconstruction produced.
    overwrite : bool
        Replace an existing file.

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    One panel per per-frame effect (phase_offset, tilt, visibility, then any other), one line per
    component, with one-sigma error bars where the uncertainty is finite. The y range follows the
    values, so a frame without information (huge uncertainty) cannot flatten the others. The last
    panel is the cost per iteration, coloured by fit stage, on a log scale when all costs are positive.
    """
    check_output(path, overwrite=overwrite)
    plt = pyplot()
    params = [p for p in vibration_datasets(result) if p.per_frame]
    n = len(params) + 1
    ncols = 2 if n > 1 else 1
    nrows = -(-n // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(6.5 * ncols, 2.8 * nrows), squeeze=False,
                             layout="constrained")
    axes = axes.ravel()
    for ax, p in zip(axes, params, strict=False):  # the axes after the parameters hold the cost
        _plot_param(ax, p)
    _plot_cost(axes[len(params)], result)
    for ax in axes[n:]:
        ax.set_axis_off()
    fig.suptitle(f"vibration fit ({result.method}), reduced χ² = {result.reduced_chi2:.3g}")
    return save_figure(fig, path, overwrite=overwrite)


def _plot_param(ax, p: VibrationDataset):
    values = p.value.reshape(p.value.shape[0], -1)
    sigma = None if p.sigma is None else p.sigma.reshape(values.shape)
    frames = np.arange(values.shape[0])
    e = CATALOGUE.get(p.effect)
    names = (e.components if e is not None and len(e.components) == values.shape[1]
             else [str(k) for k in range(values.shape[1])])
    span = np.nanmax(values) - np.nanmin(values) if np.isfinite(values).any() else 0.0
    cap = span if span > 0 else 1.0
    lo, hi = [], []
    for k in range(values.shape[1]):
        v = values[:, k]
        s = None if sigma is None else np.where(np.isfinite(sigma[:, k]), sigma[:, k], np.nan)
        ax.errorbar(frames, v, yerr=s, fmt=".-", ms=3, lw=0.8, elinewidth=0.6, capsize=0,
                    label=names[k] if values.shape[1] > 1 else None)
        s_c = np.zeros_like(v) if s is None else np.nan_to_num(np.minimum(s, cap))
        lo.append(np.nanmin(v - s_c))
        hi.append(np.nanmax(v + s_c))
    if np.isfinite(lo).all() and np.isfinite(hi).all():
        pad = 0.05 * (max(hi) - min(lo)) or 0.05 * (abs(max(hi)) or 1.0)
        ax.set_ylim(min(lo) - pad, max(hi) + pad)
    unit = units(p.effect)
    ax.set_ylabel(p.name + (f" ({unit})" if unit else ""))
    ax.set_xlabel("frame")
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_title(p.name if p.estimated else f"{p.name} (not estimated)", fontsize=10)
    ax.grid(alpha=0.3)
    if values.shape[1] > 1:
        ax.legend(fontsize=8)


def _plot_cost(ax, result: Result):
    cost = np.ravel(np.asarray(result.cost, dtype=np.float64))
    stages = [str(s) for s in result.cost_stage]
    if len(stages) != cost.size:
        stages = [""] * cost.size
    iterations = np.arange(cost.size)
    for stage in dict.fromkeys(stages):
        sel = np.array([s == stage for s in stages], dtype=bool)
        ax.plot(iterations[sel], cost[sel], ".-", ms=3, lw=0.8, label=stage or None)
    if cost.size and np.all(cost > 0):
        ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_ylabel("cost")
    ax.set_title("cost history", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    if any(stages):
        ax.legend(fontsize=8, title="stage", title_fontsize=8)


def plot_images(path, rows: list[tuple[str, dict]], *, names=Result.IMAGES, window_row: int = 0,
                crop: tuple[slice, slice] | None = None, title: str = "", overwrite: bool = False) -> Path:
    """Images of several methods side by side, one shared gray window per image kind.

    Parameters
    ----------
    path : str or Path
        Output PNG.
    rows : list of (label, images)
        images: 'transmission', 'dark_field', 'differential_phase' -> (H, W).
    names : sequence of str
        Which images to show (columns); with a single name the methods are laid out in one row.
    window_row : int
        Row whose 1st-99th percentile sets the window of each image kind (the truth, if shown).
    crop : (slice, slice), optional
        Region to show (rows, columns).
    title : str
    overwrite : bool

    Returns
    -------
    Path
    """
    check_output(path, overwrite=overwrite)
    plt = pyplot()
    crop = crop or (slice(None), slice(None))
    shown = [(label, {n: display_image(n, images[n])[crop] for n in names}) for label, images in rows]
    windows = {n: display_window(n, shown[window_row][1][n]) for n in names}
    h, w = shown[0][1][names[0]].shape
    single = len(names) == 1
    nr, nc = (1, len(shown)) if single else (len(shown), len(names))
    panel_w = 4.0 if single else 4.2
    panel_h = float(np.clip(panel_w * h / max(w, 1), 1.5, 6.0))
    fig, axes = plt.subplots(nr, nc, figsize=(nc * panel_w + 0.8, nr * (panel_h + 0.45) + 0.7), squeeze=False,
                             layout="constrained")
    cmap = plt.get_cmap("gray").with_extremes(bad="#6f8fbf")
    for i, (label, images) in enumerate(shown):
        for k, n in enumerate(names):
            ax = axes[0, i] if single else axes[i, k]
            im = ax.imshow(images[n], cmap=cmap, vmin=windows[n][0], vmax=windows[n][1], interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if single:
                ax.set_title(label, fontsize=10)
            else:
                if i == 0:
                    ax.set_title(IMAGE_LABELS[n], fontsize=10)
                if k == 0:
                    ax.set_ylabel(label, fontsize=10)
            if single and i == 0:
                ax.set_ylabel(IMAGE_LABELS[n], fontsize=10)
            if i == len(shown) - 1:
                fig.colorbar(im, ax=ax, shrink=0.85, location="right" if single else "bottom")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.supxlabel(f"windows: 1st-99th percentile of '{rows[window_row][0]}'; blue: no data", fontsize=8)
    return save_figure(fig, path, overwrite=overwrite)


def plot_convergence(path, histories: dict[str, tuple[np.ndarray, list]], *, reference: float | None = None,
                     whole: bool = True, title: str = "", overwrite: bool = False) -> Path:
    """Cost per iteration of several fits: the whole history, and the approach to the optimum.

    Parameters
    ----------
    path : str or Path
        Output PNG.
    histories : dict
        Label -> (cost per iteration (N,), fit stage of each iteration (N,) or empty).
    reference : float, optional
        Optimum for the right panel (e.g. from a long run); default: the lowest cost shown there.
    whole : bool
        Also show the left panel (the whole history).
    title : str
    overwrite : bool

    Returns
    -------
    Path

    Notes
    -----
    Left: every iteration, stage changes dotted. Right: cost minus ``reference`` on a log scale, for
    the iterations before the first 'reweight' stage, where every fit minimises the same cost (the
    same data weights), so that the curves are comparable.
    """
    check_output(path, overwrite=overwrite)
    plt = pyplot()
    fig, axes = plt.subplots(1, 2 if whole else 1, figsize=(12 if whole else 7, 4.6), squeeze=False,
                             layout="constrained")
    ax, ax2 = (axes[0, 0], axes[0, 1]) if whole else (None, axes[0, 0])
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    same = {}
    for (label, (cost, stages)), color in zip(histories.items(), colors, strict=False):
        cost = np.asarray(cost, dtype=np.float64)
        stages = list(stages) if len(stages) == cost.size else [""] * cost.size
        it = np.arange(1, cost.size + 1)
        if ax is not None:
            ax.plot(it, cost, "-", color=color, lw=1.2, label=label)
            for i in range(cost.size):
                if i == 0 or stages[i] != stages[i - 1]:
                    if i:
                        ax.axvline(it[i] - 0.5, color=color, ls=":", lw=0.8)
                    ax.annotate(stages[i], (it[i], 0.98), xycoords=("data", "axes fraction"), fontsize=7,
                                color=color, rotation=90, va="top", xytext=(2, 0), textcoords="offset points")
        n = stages.index("reweight") if "reweight" in stages else cost.size
        same[label] = (it[:n], cost[:n], color)
    shown = [c for _, c, _ in same.values() if c.size]
    ref = reference if reference is not None else (min(c.min() for c in shown) if shown else 0.0)
    for label, (it, cost, color) in same.items():
        excess = cost - ref
        ax2.plot(it, np.where(excess > 0, excess, np.nan), "-", color=color, lw=1.4, label=label)
    if ax is not None:
        ax.set_yscale("log")
        ax.set_ylabel("cost Σ w (I − Ī)²")
        ax.set_title("whole fit (dotted: next stage)", fontsize=10)
    ax2.set_yscale("log")
    ax2.set_ylabel("cost − optimum")
    ax2.set_title(f"approach to the optimum {ref:.8g}" + (" (before reweighting)" if any(
        "reweight" in list(s) for _, s in histories.values()) else ""), fontsize=10)
    for a in axes[0]:
        a.set_xlabel("iteration")
        a.grid(alpha=0.3, which="both")
        if histories:
            a.legend(fontsize=9)
    if title:
        fig.suptitle(title, fontsize=11)
    return save_figure(fig, path, overwrite=overwrite)


def plot_diagnosis(diag, path: Path, *, overwrite: bool = False) -> None:
    """Residual maps before and after, and the residual per frame, x, fringe phase and expected count."""
    plt = pyplot()
    fig = plt.figure(figsize=(13, 8.5), layout="constrained")
    grid = fig.add_gridspec(2, 4)
    top = np.nanpercentile(diag.before.pixel, 99)
    for k, (res, title) in enumerate(((diag.before, "before"), (diag.after, "after"))):
        ax = fig.add_subplot(grid[0, 2 * k:2 * k + 2])
        im = ax.imshow(res.pixel, cmap="magma", vmin=0, vmax=max(top, 2))
        ax.set_title(f"residual per pixel, {title} (model: "
                     f"{', '.join(diag.base_model if k == 0 else diag.final_model) or 'none'})"
                     + (f"\ntested pixel by pixel: {diag.band}" if diag.band else ""), fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.8)
    panels = [("frame", None, "frame"), ("x", "x_value", "lateral coordinate x"),
              ("phase", "phase_value", "fringe phase (rad)"), ("count", "count_value", "expected count")]
    for k, (attr, xattr, label) in enumerate(panels):
        ax = fig.add_subplot(grid[1, k])
        for res, style, title in ((diag.before, "-", "before"), (diag.after, "-", "after")):
            y = getattr(res, attr)
            x = np.arange(y.size) if xattr is None else getattr(res, xattr)
            ax.plot(x, y, style, marker="." if xattr else None, label=title)
        ax.axhline(1.0, color="k", lw=0.8, ls=":")
        if attr == "count":
            ax.set_xscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("mean squared standardized residual")
        ax.legend(fontsize=8)
    save_figure(fig, path, overwrite=overwrite)


def plot_effect(change: dict, path: Path, *, overwrite: bool = False) -> Path:
    """What adding one effect changed (``dfxcorr diagnose``): images, residual maps and its estimate.

    Parameters
    ----------
    change : dict
        From the diagnosis: 'name', 'reduced_chi2' (before, after), 'before' and 'after' (detector
        images 'differential_phase', 'dark_field', 'residual', each (H, W)), 'per_frame' ((J, n) or
        None) and 'components' (n names).
    path : Path
        Output PNG.
    """
    plt = pyplot()
    fig, axes = plt.subplots(3, 3, figsize=(13, 11), layout="constrained")
    before, after = change["before"], change["after"]
    for row, name in enumerate(("differential_phase", "dark_field")):
        a, b = display_image(name, before[name]), display_image(name, after[name])
        lo, hi = display_window(name, a)
        diff = b - a
        lim = float(np.nanpercentile(np.abs(diff), 99.5)) if np.isfinite(diff).any() else 1.0
        for col, (img, title, window, cmap) in enumerate((
                (a, "before", (lo, hi), "gray"), (b, "after", (lo, hi), "gray"),
                (diff, "after - before", (-max(lim, 1e-12), max(lim, 1e-12)), "RdBu_r"))):
            ax = axes[row, col]
            im = ax.imshow(img, cmap=cmap, vmin=window[0], vmax=window[1], interpolation="nearest")
            ax.set_title(f"{IMAGE_LABELS[name]}, {title}", fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.8)
    top = max(2.0, float(np.nanpercentile(before["residual"], 99)))
    for col, (res, title) in enumerate(((before["residual"], "before"), (after["residual"], "after"))):
        ax = axes[2, col]
        im = ax.imshow(res, cmap="magma", vmin=0, vmax=top, interpolation="nearest")
        ax.set_title(f"residual per pixel (1 = noise), {title}", fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.8)
    ax = axes[2, 2]
    values = change.get("per_frame")
    if values is not None:
        for m, comp in enumerate(change["components"]):
            ax.plot(np.arange(values.shape[0]), values[:, m], ".-", ms=3, lw=0.8, label=comp)
        ax.set_xlabel("frame")
        ax.set_ylabel(f"{change['name']} estimate")
        ax.grid(alpha=0.3)
        if values.shape[1] > 1:
            ax.legend(fontsize=8)
    else:
        ax.axis("off")
        ax.text(0.5, 0.5, f"{change['name']}: no per-frame parameter", ha="center", va="center", fontsize=10)
    chi_b, chi_a = change["reduced_chi2"]
    fig.suptitle(f"adding {change['name']}: reduced chi-square {chi_b:.4f} -> {chi_a:.4f}", fontsize=11)
    return save_figure(fig, path, overwrite=overwrite)


def plot_signatures(signatures: list, path: Path, *, n_frames: int, n_rows: int, overwrite: bool = False) -> Path:
    """The residual signatures of the final fit, significant bins marked (``dfxcorr diagnose``).

    Parameters
    ----------
    signatures : list of dict
        As returned by :func:`dfxcorr.analysis.diagnose.signatures`.
    path : Path
        Output PNG (checked by the caller).
    n_frames, n_rows : int
        Size of the (frame, row) map.
    """
    plt = pyplot()
    panels = [s for s in signatures if s["kind"] != "level"]
    cols = 4
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.0 * rows), layout="constrained", squeeze=False)
    for ax, sig in zip(axes.ravel(), panels, strict=False):
        std = sig["bins"]
        flag = "UNEXPLAINED" if sig["significant"] else "noise"
        ax.set_title(f"{sig['axis']} ({sig['kind']}): chi2 {sig['statistic']:.4g} / {sig['dof']} dof,\n"
                     f"p = {sig['p_value']:.2g}, {flag}", fontsize=8, color="C3" if sig["significant"] else "k")
        if sig["axis"] == "frame_row":
            image = np.full((n_frames, n_rows), np.nan)
            image[sig["frame"], sig["row"]] = std
            lim = max(3.0, float(np.nanpercentile(np.abs(std), 99.5)))
            im = ax.imshow(image.T, cmap="RdBu_r", vmin=-lim, vmax=lim, aspect="auto", interpolation="nearest")
            ax.set_xlabel("frame")
            ax.set_ylabel("detector row")
            fig.colorbar(im, ax=ax, shrink=0.8, label="standardized bin sum")
            continue
        x = sig["bin_value"]
        strong = np.abs(std) > 3
        ax.plot(x, std, ".-", ms=3, lw=0.8, color="0.3")
        ax.plot(x[strong], std[strong], "o", ms=4, color="C3", label="|bin| > 3 sigma")
        for level in (-3, 3):
            ax.axhline(level, color="k", lw=0.6, ls=":")
        ax.axhline(0, color="k", lw=0.6)
        if sig["axis"] == "count":
            ax.set_xscale("log")
        ax.set_xlabel({"frame": "frame", "row": "detector row", "column": "detector column",
                       "phase": "fringe phase theta + phi (rad)", "count": "expected count"}[sig["axis"]])
        ax.set_ylabel("standardized bin excess")
        if strong.any():
            ax.legend(fontsize=7)
    for ax in axes.ravel()[len(panels):]:
        ax.set_visible(False)
    return save_figure(fig, path, overwrite=overwrite)


def plot_nps(path, study: dict, *, title: str = "", overwrite: bool = False) -> Path:
    """Binned radial NPS per method (mean ± std over scans), fringe frequency and first harmonic marked.

    Parameters
    ----------
    path : str or Path
        Output PNG (checked by the caller).
    study : dict
        As returned by :func:`dfxcorr.analysis.compare.nps_study`.
    title : str
    """
    f, ff = study["frequency"], study["fringe_frequency"]
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.6), layout="constrained")
    for m in study["mean"]:
        ax.errorbar(f, study["mean"][m], yerr=study["std"][m], fmt=".-", ms=4, lw=1.1, capsize=2, label=m)
    for k, label in ((1, "fringe frequency"), (2, "first harmonic")):
        ax.axvline(k * ff, color="0.4", ls="--" if k == 1 else ":", lw=1)
        ax.annotate(f"{label}\n{k * ff:.3f} /px", (k * ff, 1), xycoords=("data", "axes fraction"), fontsize=8,
                    xytext=(3, -22 * k), textcoords="offset points", color="0.3")
    ax.set_yscale("log")
    ax.set_xlim(0, 0.5)
    ax.set_xlabel("radial spatial frequency (cycles/pixel)")
    ax.set_ylabel("NPS of the dark-field image (pixel²)")
    n = len(study["scans"])
    ax.set_title(title or f"binned radial NPS of blank-scan dark-field images, {n} scan{'s' * (n > 1)}"
                 + (" (mean ± std)" if n > 1 else ""), fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=9, title="method")
    return save_figure(fig, path, overwrite=overwrite)
