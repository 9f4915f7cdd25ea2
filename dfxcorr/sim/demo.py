"""``dfxcorr demo``: simulate, reconstruct and show, with no input, in well under a minute."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .. import config as C
from .. import export, pipeline, plots
from ..analysis.evaluate import frames_lighting, image_rmse, vibration_rmse
from ..io import atomic_path, write_scan
from . import simulate as S

log = logging.getLogger(__name__)

#: The paper's simulation study at 2.5 mm pixels (180 x 204 detector, 209 frames, 30 per pixel).
DEMO_SIMULATION = {"simulate": {"pixel_mm": 2.5, "step_mm": 2.5, "seed": 7}}


def demo_paths(out_dir: Path) -> dict[str, Path]:
    """Every file :func:`run_demo` writes, by role."""
    paths = {k: out_dir / n for k, n in (("scan", "scan.h5"), ("truth", "scan.truth.npz"), ("result", "result.h5"),
                                           ("preview", "preview.png"), ("fit", "fit.png"), ("summary", "summary.md"))}
    paths.update({f"tiff{i}": p for i, p in enumerate(export.tiff_paths(out_dir / "tiff", "result"))})
    return paths


def run_demo(out_dir: Path, *, overwrite: bool = False, command_line: str = "dfxcorr demo") -> str:
    """Simulate the paper's study at a coarse pitch, reconstruct it, write everything to ``out_dir``.

    Returns
    -------
    str
        A summary for the terminal (also written to ``out_dir/summary.md``).
    """
    paths = demo_paths(out_dir)
    for p in paths.values():
        export.check_output(p, overwrite=overwrite)
    out_dir.mkdir(parents=True, exist_ok=True)
    sim_cfg = C.merge(C.defaults(S.SCHEMA), DEMO_SIMULATION, schema=S.SCHEMA)
    log.info("simulating the paper's study at 2.5 mm pixels")
    scan, truth = S.simulate(sim_cfg)
    write_scan(paths["scan"], scan, overwrite=overwrite)
    with atomic_path(paths["truth"], overwrite=overwrite) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **truth)
    cfg = C.load([], ["retrieve.uncorrected=true"])  # the summary compares with the uncorrected images
    result = pipeline.reconstruct(paths["scan"], cfg, command_line=command_line)
    export.write_result_h5(paths["result"], result, overwrite=overwrite)
    tiffs = export.write_tiffs(out_dir / "tiff", result, stem="result", overwrite=overwrite)
    preview = plots.write_preview(paths["preview"], result, overwrite=overwrite,
                                   title="dfxcorr demo: simulated thorax, 2.5 mm pixels")
    fitplot = plots.write_fit_plot(paths["fit"], result, overwrite=overwrite)
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    vib = vibration_rmse(result.params, truth, good)
    img = image_rmse({k: result.image(k) for k in result.IMAGES}, truth)
    assert result.uncorrected is not None
    img0 = image_rmse(result.uncorrected, truth)
    lines = ["# dfxcorr demo", "",
             f"Simulated {scan.shape[0]} frames of {scan.shape[1]} x {scan.shape[2]} pixels (seed "
             f"{sim_cfg['simulate']['seed']}), reconstructed in {sum(result.timings.values()):.1f} s; "
             f"reduced chi-square {result.reduced_chi2:.4f}.", "",
             "| vibration parameter | RMSE vs truth (median gauge, frames lighting >= half the active area) |",
             "|---|---|"]
    lines += [f"| {k} | {v:.4f} |" for k, v in vib.items()]
    lines += ["", "| image | RMSE uncorrected | RMSE corrected |", "|---|---|---|"]
    lines += [f"| {k} | {img0[k]:.4f} | {img[k]:.4f} |" for k in img]
    lines += ["", f"Files: {paths['scan'].name}, {paths['truth'].name}, {paths['result'].name}, "
              f"{preview.name}, {fitplot.name}, tiff/ ({len(tiffs)} files)."]
    text = "\n".join(lines) + "\n"
    with atomic_path(paths["summary"], overwrite=overwrite) as tmp:
        tmp.write_text(text)
    return text
