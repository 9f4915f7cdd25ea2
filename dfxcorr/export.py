"""Stage 6, export: the results file of ``spec/results-format.md``, TIFFs, a preview and a fit plot.

Every writer refuses to replace an existing file unless asked to (:class:`OutputExistsError`), and
writes to a temporary name in the target directory that is renamed into place only once complete,
so an interrupted run never leaves a truncated output behind.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import yaml

from .io import atomic_path
from .model import CATALOGUE
from .result import Result

FORMAT = "dfxcorr-result"
FORMAT_VERSION = 1
PROVENANCE_KEYS = ("program", "version", "date", "command_line", "input_file", "input_sha256")

#: Results-file names of the paper's parameters -> catalogue effect names.
SPEC_EFFECTS = {"phase_offset": "phase_offset", "tilt": "tilt", "visibility": "visibility_loss"}

_STR = h5py.string_dtype("utf-8")


class OutputExistsError(FileExistsError):
    """An output file exists and overwriting was not asked for."""

    def __init__(self, path):
        super().__init__(f"{path} exists; use --overwrite to replace it")
        self.path = Path(path)


def check_output(path, *, overwrite: bool) -> None:
    """Refuse an output path before any work starts.

    Parameters
    ----------
    path : str or Path
        Output file to be written.
    overwrite : bool
        Allow replacing an existing file.

    Raises
    ------
    OutputExistsError
        If ``path`` exists and ``overwrite`` is False.
    IsADirectoryError
        If ``path`` is a directory (never replaced).
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a directory, not an output file")
    if path.exists() and not overwrite:
        raise OutputExistsError(path)


# --------------------------------------------------------------------------------------------------
# Per-frame parameters as written
# --------------------------------------------------------------------------------------------------


@dataclass
class _Param:
    """One dataset of /entry/dfxcorr/vibration."""

    name: str            # dataset name
    effect: str          # catalogue name
    value: np.ndarray
    sigma: np.ndarray | None
    estimated: bool
    per_frame: bool


def _squeeze(a: np.ndarray) -> np.ndarray:
    """(J, 1) -> (J,); anything else as is."""
    return a[:, 0] if a.ndim == 2 and a.shape[1] == 1 else a


def _n_frames(result: Result) -> int:
    for d in (result.params, result.uncertainty):
        for name, a in d.items():
            e = CATALOGUE.get(name)
            if e is not None and e.per_frame:
                return int(np.shape(a)[0])
    raise ValueError("cannot tell the number of frames: result.params holds no per-frame effect "
                     "(pass neutral parameters with estimated=False instead)")


def _vibration(result: Result) -> list[_Param]:
    """The spec's three parameters (neutral where not estimated), then every further effect."""
    n_frames = _n_frames(result)
    out = []
    for name, eff in SPEC_EFFECTS.items():
        estimated = eff in result.params and bool(result.estimated.get(eff, True))
        if estimated:
            value = np.asarray(result.params[eff], dtype=np.float64).reshape(n_frames, -1)[:, 0]
            sigma = result.uncertainty.get(eff)
            sigma = None if sigma is None else np.asarray(sigma, np.float64).reshape(n_frames, -1)[:, 0]
        else:
            value, sigma = np.full(n_frames, CATALOGUE[eff].neutral), None
        out.append(_Param(name, eff, value, sigma, estimated, True))
    for eff, value in result.params.items():
        if eff in SPEC_EFFECTS.values():
            continue
        value = np.asarray(value, np.float64)
        sigma = result.uncertainty.get(eff)
        e = CATALOGUE.get(eff)
        per_frame = e.per_frame if e is not None else value.ndim >= 1 and value.shape[0] == n_frames
        out.append(_Param(eff, eff, _squeeze(value),
                          None if sigma is None else _squeeze(np.asarray(sigma, np.float64)),
                          bool(result.estimated.get(eff, True)), per_frame))
    return out


def _units(effect: str) -> str | None:
    e = CATALOGUE.get(effect)
    if e is None:
        return None
    return {"phase": "rad", "background": "counts"}.get(e.channel)


# --------------------------------------------------------------------------------------------------
# HDF5
# --------------------------------------------------------------------------------------------------


def _dataset(group, name, data, *, dtype=None, compression=None, units=None, **attrs):
    data = np.asarray(data, dtype=dtype)
    if data.dtype.kind in "OUS":
        data = np.asarray(data, dtype=object).astype(str).astype(object)
        dtype, compression = _STR, None
    kwargs = {"compression": compression} if compression and data.ndim and data.size > 1 else {}
    ds = group.create_dataset(name, data=data, dtype=dtype or data.dtype, **kwargs)
    if units:
        ds.attrs["units"] = units
    ds.attrs.update(attrs)
    return ds


def _string(group, name, text):
    return group.create_dataset(name, data=str(text), dtype=_STR)


def _write_tree(group, tree: dict, compression):
    for name, value in tree.items():
        if isinstance(value, dict):
            _write_tree(group.create_group(name), value, compression)
        elif isinstance(value, str):
            _string(group, name, value)
        else:
            _dataset(group, name, value, compression=compression)


def write_result_h5(path, result: Result, *, overwrite: bool = False, compression: str | None = "gzip") -> None:
    """Write the results file of ``spec/results-format.md``.

    Parameters
    ----------
    path : str or Path
        Output file (parent directories are created).
    result : Result
        What the reconstruction produced.
    overwrite : bool
        Replace an existing file.
    compression : str or None
        HDF5 filter for the array datasets ('gzip', 'lzf' or None).

    Raises
    ------
    OutputExistsError
        If ``path`` exists and ``overwrite`` is False.

    Notes
    -----
    The file is written under a temporary name in the same directory and renamed at the end; on any
    failure the temporary file is removed and ``path`` is left as it was.
    """
    check_output(path, overwrite=overwrite)
    vibration = _vibration(result)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = np.int64(FORMAT_VERSION)
        entry = f.create_group("entry")
        entry.attrs["NX_class"] = "NXentry"
        entry.attrs["default"] = "dfxcorr/results"
        proc = entry.create_group("dfxcorr")
        proc.attrs["NX_class"] = "NXprocess"
        for key in PROVENANCE_KEYS:
            _string(proc, key, result.provenance.get(key, ""))
        _string(proc, "configuration", yaml.safe_dump(result.config, sort_keys=False))

        res = proc.create_group("results")
        res.attrs["NX_class"] = "NXdata"
        res.attrs["signal"] = "transmission"
        for name in Result.IMAGES:
            _dataset(res, name, result.image(name), dtype=np.float32, compression=compression,
                     units="rad" if name == "differential_phase" else None)

        vib = proc.create_group("vibration")
        unc = vib.create_group("uncertainty")
        for p in vibration:
            e = CATALOGUE.get(p.effect)
            attrs = {"estimated": np.int64(p.estimated), "effect": p.effect}
            if e is not None:
                attrs["components"] = list(e.components)
            _dataset(vib, p.name, p.value, dtype=np.float64, units=_units(p.effect), **attrs)
            if p.estimated and p.sigma is not None:
                _dataset(unc, p.name, p.sigma, dtype=np.float64, units=_units(p.effect))

        fit = proc.create_group("fit")
        _dataset(fit, "mask", result.fit_mask, dtype=np.uint8, compression=compression)
        _dataset(fit, "motion_mask", result.motion_mask, dtype=np.uint8, compression=compression)
        _dataset(fit, "cost", np.ravel(result.cost), dtype=np.float64)
        _dataset(fit, "stage", np.array([str(s) for s in result.cost_stage], dtype=object))
        _dataset(fit, "reduced_chi2", float(result.reduced_chi2), dtype=np.float64)
        _string(fit, "method", result.method)

        tim = proc.create_group("timings")
        for stage, seconds in result.timings.items():
            _dataset(tim, stage, float(seconds), dtype=np.float64, units="s")

        if result.uncorrected is not None:
            unc_img = proc.create_group("uncorrected")
            for name, image in result.uncorrected.items():
                _dataset(unc_img, name, image, dtype=np.float32, compression=compression,
                         units="rad" if name == "differential_phase" else None)
        if result.extra:
            _write_tree(proc.create_group("extra"), result.extra, compression)


def _read_string(ds) -> str:
    return ds.asstr()[()]


def read_result_h5(path) -> dict:
    """Read a results file back into plain Python objects.

    Parameters
    ----------
    path : str or Path
        A file written by :func:`write_result_h5`.

    Returns
    -------
    dict
        'transmission', 'dark_field', 'differential_phase' (float32 arrays), 'vibration' and
        'uncertainty' (dataset name -> array), 'estimated' (dataset name -> bool), 'mask',
        'motion_mask', 'cost', 'stage', 'reduced_chi2' (float), 'method', 'configuration' (dict, the
        parsed YAML), 'provenance' (dict of str), 'timings' (dict of float), 'uncorrected' (dict or
        None) and 'format_version'.

    Raises
    ------
    ValueError
        If the file is not a dfxcorr results file.
    """
    with h5py.File(path, "r") as f:
        fmt = f.attrs.get("format")
        if isinstance(fmt, bytes):
            fmt = fmt.decode()
        if fmt != FORMAT:
            raise ValueError(f"{path} is not a {FORMAT} file (format attribute {fmt!r})")
        proc = f["entry/dfxcorr"]
        out = {name: proc["results"][name][()] for name in Result.IMAGES}
        vib = proc["vibration"]
        out["vibration"] = {k: ds[()] for k, ds in vib.items() if isinstance(ds, h5py.Dataset)}
        out["estimated"] = {k: bool(vib[k].attrs.get("estimated", 1)) for k in out["vibration"]}
        out["uncertainty"] = {k: ds[()] for k, ds in vib["uncertainty"].items()} if "uncertainty" in vib else {}
        fit = proc["fit"]
        out["mask"] = fit["mask"][()]
        out["motion_mask"] = fit["motion_mask"][()] if "motion_mask" in fit else None
        out["cost"] = fit["cost"][()]
        out["stage"] = list(fit["stage"].asstr()[()]) if "stage" in fit else []
        out["reduced_chi2"] = float(fit["reduced_chi2"][()])
        out["method"] = _read_string(fit["method"]) if "method" in fit else ""
        out["configuration"] = yaml.safe_load(_read_string(proc["configuration"]))
        out["provenance"] = {k: _read_string(proc[k]) if k in proc else "" for k in PROVENANCE_KEYS}
        out["timings"] = {k: float(ds[()]) for k, ds in proc["timings"].items()} if "timings" in proc else {}
        out["uncorrected"] = ({k: ds[()] for k, ds in proc["uncorrected"].items()}
                              if "uncorrected" in proc else None)
        out["format_version"] = int(f.attrs["format_version"])
    return out


# --------------------------------------------------------------------------------------------------
# TIFF
# --------------------------------------------------------------------------------------------------


def write_tiffs(directory, result: Result, *, stem: str, overwrite: bool = False) -> list[Path]:
    """Write one float32 TIFF per image and the resolved configuration beside them.

    Parameters
    ----------
    directory : str or Path
        Target directory (created if needed).
    result : Result
        What the reconstruction produced.
    stem : str
        File names are ``<stem>_transmission.tif``, ``<stem>_dark_field.tif``,
        ``<stem>_differential_phase.tif`` and ``<stem>.yaml``.
    overwrite : bool
        Replace existing files.

    Returns
    -------
    list of Path
        The files written, images first.

    Raises
    ------
    OutputExistsError
        If any of the files exists and ``overwrite`` is False (checked before anything is written).
    """
    import tifffile

    directory = Path(directory)
    images = {directory / f"{stem}_{name}.tif": name for name in Result.IMAGES}
    config = directory / f"{stem}.yaml"
    for path in [*images, config]:
        check_output(path, overwrite=overwrite)
    for path, name in images.items():
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            tifffile.imwrite(fh, np.asarray(result.image(name), dtype=np.float32), photometric="minisblack")
    with atomic_path(config) as tmp:
        tmp.write_text(yaml.safe_dump(result.config, sort_keys=False))
    return [*images, config]


# --------------------------------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------------------------------


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed), imported only when a picture is drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path) -> Path:
    """Write a figure as PNG atomically and close it."""
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
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
    rows = [("corrected", result.image)]
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
    return save_figure(fig, path)


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
    params = [p for p in _vibration(result) if p.per_frame]
    n = len(params) + 1
    ncols = 2 if n > 1 else 1
    nrows = -(-n // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(6.5 * ncols, 2.8 * nrows), squeeze=False,
                             layout="constrained")
    axes = axes.ravel()
    for ax, p in zip(axes, params):
        _plot_param(ax, p)
    _plot_cost(axes[len(params)], result)
    for ax in axes[n:]:
        ax.set_axis_off()
    fig.suptitle(f"vibration fit ({result.method}), reduced χ² = {result.reduced_chi2:.3g}")
    return save_figure(fig, path)


def _plot_param(ax, p: _Param):
    values = p.value.reshape(p.value.shape[0], -1)
    sigma = None if p.sigma is None else p.sigma.reshape(values.shape)
    frames = np.arange(values.shape[0])
    e = CATALOGUE.get(p.effect)
    names = e.components if e is not None and len(e.components) == values.shape[1] else \
        [str(k) for k in range(values.shape[1])]
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
    units = _units(p.effect)
    ax.set_ylabel(p.name + (f" ({units})" if units else ""))
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
