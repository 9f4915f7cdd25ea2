#!/usr/bin/env python3
"""How the fringe's interpolation between reference rows departs from the unwrapped phase's, on the project's scans.

The alignment (dfxcorr.align.LitStore.observations) interpolates t^f, v^f and the unwrapped phase linearly; the
compiled loops read each sample's fringe as its quadratures, made once (dfxcorr.observations.Observations.fringe),
so that they need no trigonometric call per sample. For the flat field and scan geometry of the paper study and
the clinical scanner (binned and full resolution), on every lit (row, frame) pair of every ``--every``-th column,
this prints and writes (docs/fringe-interpolation.json) the departure from the linear interpolation of the
unwrapped phase (``spec/scan-format.md`` allows both):
- of the unit phasor interpolated linearly and renormalised: phase difference, max and RMS;
- of the complex fringe t^f v^f exp(i phi^f) interpolated linearly (what a pixel straddling two reference rows
  integrates): phase difference, and the fringe amplitude's relative difference (second order in the phase step
  per row);
each also as the largest fringe difference in units of a sample's photon noise sqrt(t^f) (no sample in the beam),
beside the phase step between reference rows.

Usage: python scripts/fringe_interpolation.py [--every 32] [--out docs/]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dfxcorr import config as C
from dfxcorr.align import interpolate_rows, lit_blocks
from dfxcorr.sim import simulate as S
from dfxcorr.sim.flat import flat_field

ROOT = Path(__file__).resolve().parents[1]
SCANS = {"paper study": "paper-simulation.yaml", "clinical binned": "clinical-binned.yaml",
         "clinical full resolution": "clinical.yaml"}


def departures(config: Path, every: int) -> dict:
    """The departures of one scan's flat field and geometry (see the module's text)."""
    cfg = C.load([config], [], schema=S.SCHEMA)
    g = S.geometry(cfg)
    A, W, H = g["A"], g["W"], g["H"]
    ref = flat_field(cfg, A, W)
    _, _, u = lit_blocks(g["position"], A, H)
    cols = np.arange(every // 2, W, every)
    tf = interpolate_rows(ref.transmission, u, columns=cols)
    vf = interpolate_rows(ref.visibility, u, columns=cols)
    linear = tf * vf * np.exp(1j * interpolate_rows(np.unwrap(ref.phase, axis=0), u, columns=cols))
    unit = np.exp(1j * ref.phase)
    phasor = interpolate_rows(unit.real, u, columns=cols) + 1j * interpolate_rows(unit.imag, u, columns=cols)
    z = ref.transmission * ref.visibility * np.exp(1j * ref.phase)
    complex_ = interpolate_rows(z.real, u, columns=cols) + 1j * interpolate_rows(z.imag, u, columns=cols)
    noise = np.sqrt(tf)
    step = np.abs(np.diff(np.unwrap(ref.phase, axis=0), axis=0))

    def summary(f: np.ndarray, *, amplitude: bool) -> dict:
        dphi = np.angle(f * np.conj(linear))
        out = {"phase_max_rad": float(np.abs(dphi).max()), "phase_rms_rad": float(np.sqrt(np.mean(dphi ** 2))),
               "fringe_max_in_noise": float((np.abs(f - linear) / noise).max())}
        if amplitude:
            rel = np.abs(f) / np.abs(linear) - 1
            out |= {"amplitude_max_rel": float(np.abs(rel).max()), "amplitude_mean_rel": float(rel.mean())}
        return out

    return {"shape": [int(g["position"].size), int(H), int(W)], "active_rows": int(A), "columns": int(cols.size),
            "samples": int(u.size * cols.size), "phase_step_per_row_max_rad": float(step.max()),
            "phase_step_per_row_rms_rad": float(np.sqrt(np.mean(step ** 2))),
            "renormalised_phasor": summary(tf * vf * phasor / np.abs(phasor), amplitude=False),
            "complex_fringe": summary(complex_, amplitude=True)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--every", type=int, default=32, help="every n-th detector column")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    out = {}
    for name, file in SCANS.items():
        out[name] = departures(ROOT / "configs" / file, args.every)
        print(name, json.dumps(out[name]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "fringe-interpolation.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
