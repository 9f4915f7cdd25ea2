"""Side-by-side comparison of the vibration estimators, and noise power spectra of blank scans.

``dfxcorr compare`` runs every estimator (``fit.method`` none, correlation, alternating, ml) on one scan
and writes their results, a picture of their images, their cost histories and a table (reduced
chi-square, runtime and, given a ground truth, RMSE of vibration parameters and images).

``dfxcorr nps`` measures what vibrations leave in the dark-field image of scans without a sample
(paper Sec. III-D.4, Fig. 11): the binned radial noise power spectrum per method, mean and standard
deviation over scans, with the fringe frequency and its first harmonic marked.
"""
from __future__ import annotations

import json
import logging
import os
import platform
import time
import zipfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .. import config as C
from .. import export, pipeline, plots
from ..effects import REGISTRY
from ..errors import DfxcorrError
from ..io import Scan, atomic_path
from ..preparation import Prepared, prepare
from ..result import Result, paper_params
from .evaluate import frames_lighting, image_rmse, vibration_rmse

log = logging.getLogger(__name__)

#: Estimators in the order they are compared: every ``fit.method``, from no correction to this paper's.
METHODS = tuple(reversed(C.METHODS))
#: Estimators of the noise power spectra by default (the paper's Fig. 11).
NPS_METHODS = ("none", "correlation", "ml")


class TruthError(DfxcorrError, ValueError):
    """A ground-truth file that does not fit the scan."""


class SpectrumError(DfxcorrError, ValueError):
    """A scan whose dark-field image has nothing to take a noise power spectrum of."""


def parse_methods(text: str) -> tuple[str, ...]:
    """Comma-separated ``fit.method`` values -> tuple, each validated (ConfigError names a bad one)."""
    methods = tuple(m.strip() for m in text.split(",") if m.strip())
    if not methods:
        raise C.ConfigError("--methods: name at least one method")
    for m in methods:
        C.validate_value("fit", "method", m)
    return methods


def machine() -> str:
    """One line describing where the numbers were measured: CPU, cores, memory, system, versions."""
    cpu, mem = platform.processor() or platform.machine(), ""
    if os.path.exists("/proc/cpuinfo"):
        with open("/proc/cpuinfo") as fh:
            cpu = next((line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")), cpu)
        with open("/proc/meminfo") as fh:
            kib = next((int(line.split()[1]) for line in fh if line.startswith("MemTotal")), 0)
        mem = f", {kib / 2 ** 20:.0f} GiB"
    return (f"{cpu}, {os.cpu_count()} cores{mem}, {platform.system()}, python {platform.python_version()}, "
            f"numpy {np.__version__}")


# --------------------------------------------------------------------------------------------------
# Running the estimators
# --------------------------------------------------------------------------------------------------


#: Configuration sections that :func:`dfxcorr.preparation.prepare` reads.
PREPARATION_SECTIONS = ("load", "reference", "align")


def run_methods(scan: Scan | str | Path | Prepared, cfg: dict[str, Any], *, methods: Sequence[str] = METHODS,
                method_sets: dict[str, Any] | None = None,
                command_line: str = "") -> tuple[dict[str, Result], dict[str, float]]:
    """Reconstruct one scan with each estimator.

    Parameters
    ----------
    scan : Scan, path or Prepared
        Prepared once for all methods that share the ``load``, ``reference`` and ``align`` options; a
        path is recorded (with its checksum) in each result's provenance.
    cfg : dict
        Resolved configuration shared by all methods (``fit.method`` is set per method).
    methods : sequence of str
    method_sets : dict, optional
        Method -> list of further ``section.key=value`` overrides for that method only.
    command_line : str
        Recorded in each result's provenance.

    Returns
    -------
    results : dict
        Method -> Result.
    runtimes : dict
        Method -> wall-clock seconds of the reconstruction (s).
    """
    results, runtimes = {}, {}
    prepared: dict[str, tuple[Prepared, float]] = {}
    for method in methods:
        cfg_m = C.merge(cfg, {"fit": {"method": method}})
        for item in (method_sets or {}).get(method, []):
            cfg_m = C.merge(cfg_m, C.parse_set(item), origin=f"{method}: {item}")
        log.info("method %s ...", method)
        # methods that share the preparation options share the prepared scan; each is charged its time
        key = json.dumps({k: cfg_m[k] for k in PREPARATION_SECTIONS}, sort_keys=True)
        if key not in prepared:
            t0 = time.perf_counter()
            prep = scan if isinstance(scan, Prepared) else prepare(scan, cfg_m, effects=REGISTRY.values())
            prepared[key] = prep, time.perf_counter() - t0
        prep, prep_seconds = prepared[key]
        t0 = time.perf_counter()
        results[method] = pipeline.reconstruct(prep, cfg_m, command_line=command_line)
        runtimes[method] = time.perf_counter() - t0 + prep_seconds
        log.info("method %s: %.1f s, reduced chi-square %.4f", method, runtimes[method],
                 results[method].reduced_chi2)
    return results, runtimes


def load_truth(path: str | Path, shape: tuple[Any, ...]) -> dict[str, Any]:
    """Read a truth file (``dfxcorr simulate``; ``image_*`` (H, W), ``vib_*`` (J,)) and check it fits the scan.

    Parameters
    ----------
    path : str or Path
    shape : tuple
        (J, H, W) of the scan.

    Raises
    ------
    TruthError
        If the file cannot be read as an .npz archive of plain arrays (pickled objects are never loaded),
        an array would expand beyond what the scan's images and frames need, an image is missing, an image
        or per-frame array has the wrong shape, or holds values that are not finite real numbers.
    """
    J, H, W = shape
    # a member's size is known from the archive's directory before it is read (a zip bomb is not expanded)
    limit = 16 * (H * W + 8 * J) + (1 << 20)
    try:
        with open(path, "rb") as fh:
            f = np.load(fh, allow_pickle=False)
            if isinstance(f, np.lib.npyio.NpzFile) and f.zip is not None:
                big = [i.filename for i in f.zip.infolist() if i.file_size > limit]
                if big:
                    raise TruthError(f"{path}: {big[0]} expands beyond {limit} bytes, more than the scan's "
                                     f"{H} x {W} images need")
            truth = {k: f[k] for k in f.files} if isinstance(f, np.lib.npyio.NpzFile) else None
    except TruthError:
        raise
    except OSError as exc:
        raise TruthError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except (ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise TruthError(f"{path}: not a truth file of dfxcorr simulate ({C.show(str(exc), quote=False)})") from None
    if truth is None:
        raise TruthError(f"{path}: a single array, not the .npz archive of dfxcorr simulate")
    for k in (k for k in truth if k.startswith("image_")):
        if truth[k].shape != (H, W):
            raise TruthError(f"{path}: {k} has shape {truth[k].shape}, the scan's images are {(H, W)}")
    missing = [f"image_{k}" for k in Result.IMAGES if f"image_{k}" not in truth]
    if missing:
        raise TruthError(f"{path} holds no {' / '.join(missing)} (dfxcorr simulate writes every image)")
    for k in (k for k in truth if k.startswith("vib_")):
        if truth[k].shape[:1] != (J,) or truth[k].size == 0:
            raise TruthError(f"{path}: {k} has shape {truth[k].shape}, expected one value per frame of the scan's "
                             f"{J}")
    for k in (k for k in truth if k.startswith(("image_", "vib_"))):
        if truth[k].dtype.kind not in "biuf" or not np.all(np.isfinite(truth[k])):
            raise TruthError(f"{path}: {k} holds values that are not finite real numbers ({truth[k].dtype})")
    return truth


def comparison_table(results: dict[str, Result], runtimes: dict[str, float], *, scan: Scan,
                     truth: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """One row per method: reduced chi-square, runtime and, with a truth, RMSE of parameters and images.

    Parameters
    ----------
    results, runtimes
        As returned by :func:`run_methods`.
    scan : Scan
        Supplies the geometry: vibration RMSEs are over frames lighting at least half the active area
        (:func:`dfxcorr.analysis.evaluate.frames_lighting`), in the median gauge.
    truth : dict, optional
        See :func:`load_truth`.

    Returns
    -------
    list of dict
        Keys 'method', 'reduced_chi2', 'runtime_s', 'fit_s', 'iterations', and with a truth
        'rmse_<effect>' (rad, v^s dimensionless) and 'rmse_<image>'; parameters a method does not
        estimate count at their neutral value.
    """
    rows = []
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    for method, res in results.items():
        row = {"method": method, "reduced_chi2": float(res.reduced_chi2), "runtime_s": float(runtimes[method]),
               "fit_s": float(res.timings.get("fit", 0.0)), "iterations": int(np.size(res.cost))}
        if truth is not None:
            vib = vibration_rmse(paper_params(res.params, scan.shape[0]), truth, good)
            row.update({f"rmse_{k}": v for k, v in vib.items()})
            row.update({f"rmse_{k}": v for k, v in image_rmse({k: res.image(k) for k in Result.IMAGES},
                                                               truth).items()})
        rows.append(row)
    return rows


_HEAD = {"method": "method", "reduced_chi2": "reduced χ²", "runtime_s": "runtime (s)", "fit_s": "fit (s)",
         "iterations": "iterations", "rmse_phase_offset": "RMSE φ0 (rad)", "rmse_tilt": "RMSE φ1 (rad)",
         "rmse_visibility_loss": "RMSE v^s", "rmse_curvature": "RMSE φ2 (rad)", "rmse_dose": "RMSE dose",
         "rmse_transmission": "RMSE t", "rmse_dark_field": "RMSE v", "rmse_differential_phase": "RMSE φ (rad)"}


def table_markdown(rows: list[dict[str, Any]]) -> str:
    """A markdown table of :func:`comparison_table` rows (columns in the order of the first row)."""
    keys = list(rows[0])
    out = ["| " + " | ".join(_HEAD.get(k, k) for k in keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        cells = [r[k] if isinstance(r[k], str) else (f"{r[k]:d}" if isinstance(r[k], int) else f"{r[k]:.4g}")
                 for k in keys]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------------
# The compare command
# --------------------------------------------------------------------------------------------------


def comparison_paths(out_dir: Path, methods: Iterable[str]) -> dict[str, Path]:
    """Every file :func:`write_comparison` writes, by role."""
    out = {m: out_dir / f"{m}.h5" for m in methods}
    out.update(images=out_dir / "images.png", convergence=out_dir / "convergence.png",
               table_md=out_dir / "table.md", table_json=out_dir / "table.json")
    return out


def write_comparison(out_dir: str | Path, scan: Scan, results: dict[str, Result], runtimes: dict[str, float], *,
                     truth: dict[str, Any] | None = None, source: str = "", result_files: bool = True,
                     overwrite: bool = False) -> dict[str, Path]:
    """Write per-method results, the images and convergence pictures, and the table (markdown + JSON).

    Parameters
    ----------
    out_dir : str or Path
    scan : Scan
    results, runtimes
        As returned by :func:`run_methods`.
    truth : dict, optional
        See :func:`load_truth`.
    source : str
        Name of the scan for titles and the table.
    result_files : bool
        Also write each method's results file (``<method>.h5``).
    overwrite : bool

    Returns
    -------
    dict
        Role -> path, as :func:`comparison_paths` (without the results files unless written).
    """
    out_dir = Path(out_dir)
    paths = comparison_paths(out_dir, results if result_files else ())
    for p in paths.values():
        export.check_output(p, overwrite=overwrite)
    for method, res in results.items() if result_files else ():
        c = res.config["export"]["compression"]
        export.write_result_h5(paths[method], res, overwrite=overwrite, compression=None if c == "none" else c)
    rows = [(m, {k: r.image(k) for k in Result.IMAGES}) for m, r in results.items()]
    if truth is not None:
        rows.insert(0, ("truth", {k: truth[f"image_{k}"] for k in Result.IMAGES}))
    # the windows of the best-corrected images (noise included), as in the reconstruct preview
    labels = [label for label, _ in rows]
    window_row = labels.index("ml") if "ml" in labels else len(rows) - 1
    J, H, W = scan.shape
    plots.plot_images(paths["images"], rows, window_row=window_row, overwrite=overwrite,
                title=f"{Path(source).name or 'scan'}: {J} frames of {H} x {W}")
    hist = {m: (r.cost, r.cost_stage) for m, r in results.items() if np.size(r.cost)}
    plots.plot_convergence(paths["convergence"], hist, overwrite=overwrite,
                     title="cost per iteration (the ML fit's includes its weak prior on the per-frame parameters)")
    table = comparison_table(results, runtimes, scan=scan, truth=truth)
    header = (f"Scan {Path(source).name or '(in memory)'}: {J} frames of {H} x {W}; measured on {machine()}.\n"
              + ("RMSE over frames lighting at least half the active area, median gauge; parameters a method "
                 "does not estimate count at their neutral value.\n" if truth is not None else "") + "\n")
    export_text(paths["table_md"], header + table_markdown(table), overwrite=overwrite)
    export_text(paths["table_json"], json.dumps({"scan": str(source), "shape": [J, H, W], "machine": machine(),
                                                 "methods": table}, indent=2), overwrite=overwrite)
    return paths


def export_text(path: Path, text: str, *, overwrite: bool = False) -> Path:
    """Write a text file (refusing to replace one unless asked, complete or not at all)."""
    export.check_output(path, overwrite=overwrite)
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(text)
    return path


# --------------------------------------------------------------------------------------------------
# Noise power spectra
# --------------------------------------------------------------------------------------------------


def radial_nps(image: np.ndarray, *, mask: np.ndarray | None = None, bins: int = 32
               ) -> tuple[np.ndarray, np.ndarray]:
    """Binned radial noise power spectrum of an image.

    The image minus its mean over ``mask`` (zero outside it), over the bounding box of ``mask``, is
    multiplied by a separable Hann window; the periodogram |FFT|^2 / sum(window^2 mask) is averaged in
    rings of radial frequency. White noise of variance s^2 gives s^2 at every frequency.

    Parameters
    ----------
    image : ndarray, shape (H, W)
    mask : ndarray of bool, shape (H, W), optional
        Pixels that count (default: the finite ones).
    bins : int
        Rings of equal width from 0 to 0.5 cycles/pixel.

    Returns
    -------
    frequency : ndarray, shape (bins,)
        Ring centres (cycles/pixel).
    nps : ndarray, shape (bins,)
        Mean power in each ring (image units^2 pixel^2); NaN for rings without a frequency sample.
    """
    image = np.asarray(image, dtype=np.float64)
    mask = np.isfinite(image) if mask is None else (np.asarray(mask, bool) & np.isfinite(image))
    if not mask.any():
        raise ValueError("no pixel to take a noise power spectrum of")
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    m = mask[box]
    d = np.where(m, image[box] - image[mask].mean(), 0.0)
    win = np.outer(np.hanning(d.shape[0] + 2)[1:-1], np.hanning(d.shape[1] + 2)[1:-1])
    power = np.abs(np.fft.fft2(d * win)) ** 2 / np.sum(win ** 2 * m)
    fr = np.hypot(*np.meshgrid(np.fft.fftfreq(d.shape[0]), np.fft.fftfreq(d.shape[1]), indexing="ij"))
    edges = np.linspace(0.0, 0.5, bins + 1)
    sel = (fr > 0) & (fr <= 0.5)
    which = np.clip(np.digitize(fr[sel], edges) - 1, 0, bins - 1)
    n = np.bincount(which, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        nps = np.bincount(which, weights=power[sel], minlength=bins) / n
    return 0.5 * (edges[1:] + edges[:-1]), np.where(n > 0, nps, np.nan)


def fringe_frequency(phase: np.ndarray) -> float:
    """Spatial frequency of the moiré fringes along the scan direction.

    Parameters
    ----------
    phase : ndarray, shape (A, W)
        Flat-field phase (rad, may be wrapped) of the active area, rows along the scan direction.

    Returns
    -------
    float
        median |d phi^f / du| / 2 pi over the map (cycles per detector row).
    """
    grad = np.diff(np.unwrap(np.asarray(phase, dtype=np.float64), axis=0), axis=0)
    return float(np.median(np.abs(grad)) / (2 * np.pi))


def nps_study(scans: Sequence[Scan | str | Path], cfg: dict[str, Any], *, methods: Sequence[str] = NPS_METHODS,
              method_sets: dict[str, Any] | None = None, bins: int | None = None,
              command_line: str = "") -> dict[str, Any]:
    """Noise power spectra of the dark-field images of blank scans, per method.

    Parameters
    ----------
    scans : sequence of Scan or path
        Scans without a sample; paths are read one at a time.
    cfg : dict
        Resolved configuration shared by all methods.
    methods : sequence of str
    method_sets : dict, optional
        Method -> further ``section.key=value`` overrides for that method only.
    bins : int, optional
        Radial bins (see :func:`radial_nps`); default: rings a quarter of the fringe frequency f of the
        first scan wide (round(2 / f)), so that f and 2 f are resolved at any pitch.
    command_line : str

    Returns
    -------
    dict
        'frequency' (bins,) cycles/pixel; 'nps' method -> (n_scans, bins) (dark-field units^2 pixel^2);
        'mean', 'std' method -> (bins,); 'fringe_frequency' (cycles/pixel, median over scans);
        'scans' (names); 'runtime_s' method -> total seconds.
    """
    cfg = C.merge(cfg, {"retrieve": {"uncorrected": False}})
    spectra: dict[str, list[Any]] = {m: [] for m in methods}
    runtime = {m: 0.0 for m in methods}
    fringes: list[Any] = []
    names: list[str] = []
    freq = None
    for item in scans:
        prep = prepare(item, cfg, effects=REGISTRY.values())
        names.append(str(item) if not isinstance(item, Scan) else f"scan {len(names)}")
        fringes.append(fringe_frequency(prep.reference.phase))
        # rings a quarter of the fringe frequency wide, within the command line's bounds (no fringe: 32)
        bins = bins or (int(np.clip(round(2 / fringes[0]), 4, 1000)) if fringes[0] > 0 else 32)
        results, runtimes = run_methods(prep, cfg, methods=methods, method_sets=method_sets,
                                        command_line=command_line)
        for m, res in results.items():
            if not np.any(np.isfinite(res.dark_field)):
                raise SpectrumError(f"{names[-1]}: the dark-field image of method {m} has no finite pixel (no "
                                    f"pixel's phase varies over its frames)")
            freq, p = radial_nps(res.dark_field, bins=bins)
            spectra[m].append(p)
            runtime[m] += runtimes[m]
    nps = {m: np.array(v) for m, v in spectra.items()}
    return {"frequency": freq, "nps": nps, "mean": {m: v.mean(axis=0) for m, v in nps.items()},
            "std": {m: v.std(axis=0, ddof=1) if v.shape[0] > 1 else np.zeros(v.shape[1]) for m, v in nps.items()},
            "fringe_frequency": float(np.median(fringes)), "scans": names, "runtime_s": runtime}


def nps_paths(out_dir: Path) -> dict[str, Path]:
    """Every file :func:`write_nps` writes, by role."""
    return {"png": out_dir / "nps.png", "csv": out_dir / "nps.csv", "json": out_dir / "nps.json"}


def write_nps(out_dir: str | Path, study: dict[str, Any], *, title: str = "", overwrite: bool = False
              ) -> dict[str, Path]:
    """Picture (mean ± std per method, fringe frequency and first harmonic marked), CSV and JSON of a study.

    Returns
    -------
    dict
        Role -> path, as :func:`nps_paths`.
    """
    paths = nps_paths(Path(out_dir))
    for p in paths.values():
        export.check_output(p, overwrite=overwrite)
    f, ff = study["frequency"], study["fringe_frequency"]
    plots.plot_nps(paths["png"], study, title=title, overwrite=overwrite)
    head = ["frequency_cycles_per_pixel"] + [f"{m}_{s}" for m in study["mean"] for s in ("mean", "std")]
    cols = [f] + [study[s][m] for m in study["mean"] for s in ("mean", "std")]
    lines = [",".join(head)] + [",".join(f"{v:.6g}" for v in row) for row in zip(*cols, strict=True)]
    export_text(paths["csv"], "\n".join(lines) + "\n", overwrite=overwrite)
    doc = {"scans": study["scans"], "fringe_frequency": ff, "first_harmonic": 2 * ff, "machine": machine(),
           "runtime_s": study["runtime_s"], "frequency": f.tolist(),
           "mean": {m: v.tolist() for m, v in study["mean"].items()},
           "std": {m: v.tolist() for m, v in study["std"].items()},
           "power_near_fringe": fringe_power(study)}
    export_text(paths["json"], json.dumps(doc, indent=2), overwrite=overwrite)
    return paths


def fringe_power(study: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Power left at the fringe frequency and its first harmonic, per method.

    Parameters
    ----------
    study : dict
        As returned by :func:`nps_study`.

    Returns
    -------
    dict
        Method -> {'fringe', 'first_harmonic': mean NPS of the rings holding f and 2 f; 'other': median of
        the rings more than 1.5 ring widths from both} (pixel^2).
    """
    f, ff = study["frequency"], study["fringe_frequency"]
    step = f[1] - f[0]
    at = [int(np.argmin(np.abs(f - k * ff))) for k in (1, 2)]
    far = (np.abs(f - ff) > 1.5 * step) & (np.abs(f - 2 * ff) > 1.5 * step)
    return {m: {"fringe": float(v[at[0]]), "first_harmonic": float(v[at[1]]), "other": float(np.nanmedian(v[far]))}
            for m, v in study["mean"].items()}
