#!/usr/bin/env python3
"""The real phase-stepping recording of ../shared/data/real/tum-ipp-stepping, end to end.

Imports the 11 + 11 numpy files, retrieves the flat field with nominal steps and with estimated step
errors, reconstructs the sample series without and with per-step phase_offset and tilt, diagnoses
it, and writes docs/real-ipp.json, docs/real-ipp.png and docs/real-ipp-diagnosis/.

Usage: python scripts/real_ipp.py [--data ../shared/data/real/tum-ipp-stepping] [--out docs/]
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from dfxcorr import config as C
from dfxcorr import pipeline, plots
from dfxcorr.analysis.diagnose import diagnose
from dfxcorr.analysis.report import write_report
from dfxcorr.importer import import_stepping
from dfxcorr.reference import fit_reference

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "real" / "tum-ipp-stepping")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ipp.h5"
        scan = import_stepping(path, sample=str(args.data / "data_stepping_*.npy"),
                               reference=str(args.data / "flat_stepping_*.npy"), steps_per_period=11)
        nominal = fit_reference(scan.reference, effects=())
        stepped = fit_reference(scan.reference, effects=("phase_offset", "dose"))
        none = pipeline.reconstruct(path, C.load([], ["fit.method=none"]))
        nominal_steps = pipeline.reconstruct(path, C.load([], ["fit.method=none", "reference.step_errors=false",
                                                               "reference.dose=false"]))
        ml = pipeline.reconstruct(path, C.defaults(), command_line="scripts/real_ipp.py")
        diag = diagnose(path, C.defaults())
    # a fresh folder: a picture of an effect an earlier run detected must not stay beside this run's report
    report = args.out / "real-ipp-diagnosis"
    if report.exists():
        shutil.rmtree(report)
    write_report(diag, report)
    ml.uncorrected = {k: nominal_steps.image(k) for k in ml.IMAGES}
    plots.write_preview(args.out / "real-ipp.png", ml, overwrite=True,
                         title="real stepping recording (11 steps, 195 x 487): nominal steps (top) vs estimated step "
                               "errors (bottom)")
    numbers = {
        "shape": list(scan.shape), "dtype": str(scan.data.dtype),
        "reference_chi2": {"nominal_steps": nominal.reduced_chi2["nominal"],
                           "estimated_steps": stepped.reduced_chi2.get("fitted")},
        "reference_step_errors_rad": stepped.params["phase_offset"][:, 0].round(4).tolist(),
        "reference_dose": stepped.params["dose"][:, 0].round(5).tolist() if "dose" in stepped.params else None,
        "sample_chi2": {"nominal_steps_everywhere": nominal_steps.reduced_chi2,
                        "estimated_reference_steps_only": none.reduced_chi2, "ml_phase_offset_tilt": ml.reduced_chi2},
        "sample_phase_offset_rad": ml.params["phase_offset"][:, 0].round(4).tolist(),
        "sample_tilt_rad": ml.params["tilt"][:, 0].round(4).tolist(),
        "pixels_outside_gratings": int(np.isnan(ml.dark_field).sum()),
        "diagnosis": diag.to_json(),
    }
    (args.out / "real-ipp.json").write_text(json.dumps(numbers, indent=2, default=float))
    print(json.dumps({k: v for k, v in numbers.items() if k != "diagnosis"}, indent=2))
    print("detected:", [e.name for e in diag.effects if e.detected], diag.initial_chi2, "->", diag.final_chi2)


if __name__ == "__main__":
    main()
