#!/usr/bin/env python3
"""What ``diagnose`` costs against ``reconstruct`` of the same scan: wall time and peak memory, and where the time goes.

Each command runs in a process of its own (peak resident memory from getrusage); the scans are made here
(the shared 11-step recording, imported; a 5-step 512 x 1536 flat-panel stepping simulation; the paper's
study at 1 mm), the clinical ones are read from ``--dir`` (made there by ``scripts/benchmark.py clinical --dir``:
195 frames of 1440 x 1440 and of 2880 x 2880; the binned one with Compton scatter, s = 0.1, is made there by this
script). Writes docs/diagnose-cost.json and prints a table.

Each command runs ``--runs`` times (alternated with the other); the run of median time counts.

Usage: python scripts/diagnose_cost.py [--cases real stepping paper clinical-binned clinical-full
       clinical-binned-scatter] [--dir /tmp/dfx-bench] [--runs 3] [--out docs/]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Runs one command on one scan in this process and prints its seconds, peak memory and stage timings. The peak is
#: the kernel's high-water mark of this process's own memory (VmHWM): getrusage's ru_maxrss survives fork and exec,
#: so a child of this script started at the size of its parent (measured: 599 MB reported for a child of 14 MB).
CHILD = """
import json, sys, time
from dfxcorr import config as C
from dfxcorr.pipeline import reconstruct
from dfxcorr.analysis.diagnose import diagnose
command, path, base = sys.argv[1:4]
t0 = time.perf_counter()
if command == "reconstruct":
    timings = reconstruct(path, C.defaults(), progress=False).timings
else:
    timings = diagnose(path, C.defaults(), base=base).timings
peak_mb = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:")) / 1024
print(json.dumps({"seconds": time.perf_counter() - t0, "peak_mb": peak_mb, "timings": timings}))
"""


def make(case: str, folder: Path, clinical: Path | None = None) -> tuple[Path, str]:
    """The scan file of a case, and the diagnosis's base model (the clinical ones are read from ``clinical``)."""
    from dfxcorr import config as C
    from dfxcorr.io import write_scan
    from dfxcorr.sim import simulate as S

    if case == "clinical-binned-scatter":
        # the binned clinical scan with Compton scatter (s = 0.1 of the primary, 50 mm kernel), made here once
        path = (clinical or folder) / f"{case}.h5"
        if not path.exists():
            cfg = C.load([str(ROOT / "configs" / "clinical-binned.yaml")], ["effects.scatter=0.1"], schema=S.SCHEMA)
            S.simulate_file(cfg, path)
        return path, "configured"
    if case.startswith("clinical-"):
        path = (clinical or folder) / f"{case}.h5"
        if not path.exists():
            raise SystemExit(f"{path} is missing: make it with python scripts/benchmark.py clinical --dir "
                             f"{clinical or folder}")
        return path, "configured"
    path = folder / f"{case}.h5"
    if case == "real":
        from dfxcorr.importer import import_stepping

        data = ROOT.parent / "shared" / "data" / "real" / "tum-ipp-stepping"
        import_stepping(path, sample=str(data / "data_stepping_*.npy"), reference=str(data / "flat_stepping_*.npy"),
                        steps_per_period=11)
        return path, "configured"
    if case == "stepping":
        cfg = C.load([], [f"{k}={v}" for k, v in {**S.FLAT_PANEL_STEPPING, "simulate.pixel_mm": 0.3,
                                                   "simulate.height_mm": 153.6, "simulate.width_mm": 460.8}.items()],
                     schema=S.SCHEMA)
        base = "none"
    else:
        cfg = C.load([str(ROOT / "configs" / "paper-simulation.yaml")], schema=S.SCHEMA)
        base = "configured"
    scan, _ = S.simulate(cfg)
    write_scan(path, scan)
    return path, base


def measure(command: str, path: Path, base: str) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, command, str(path), base], check=True, capture_output=True,
                         text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="*", default=["real", "stepping", "paper"],
                    choices=["real", "stepping", "paper", "clinical-binned", "clinical-full",
                             "clinical-binned-scatter"])
    ap.add_argument("--dir", type=Path, default=None, help="where the clinical scans are")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    ap.add_argument("--runs", type=int, default=3,
                    help="runs of each command, alternated; the medians count (one reconstruct of a clinical scan "
                         "varied by 20 %% from run to run)")
    args = ap.parse_args()
    if args.runs < 1:
        ap.error("--runs must be at least 1")
    from dfxcorr.analysis.compare import machine

    rows = {"machine": machine(), "cases": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for case in args.cases:
            path, base = make(case, Path(tmp), args.dir)
            runs = [(measure("reconstruct", path, base), measure("diagnose", path, base)) for _ in range(args.runs)]
            # the run of median time stands for each command (its memory and stage timings with it)
            rec, diag = (sorted((r[i] for r in runs), key=lambda m: m["seconds"])[len(runs) // 2] for i in (0, 1))
            stages: dict[str, float] = {}
            for name, seconds in diag["timings"].items():
                # 'test <effect>' keys stay as they are: each effect's share of the rounds' tests (already counted
                # in 'tests': the stages do not add up to the whole)
                kind = ("tests" if name.endswith(": tests") else name.split(": fit")[0].split(": ")[-1]
                        if ": fit" in name else name)
                kind = "trial fits" if kind.startswith("trial") else ("fits" if kind.startswith("round") else kind)
                stages[kind] = stages.get(kind, 0.0) + seconds
            rows["cases"][case] = {"reconstruct_s": rec["seconds"], "diagnose_s": diag["seconds"],
                                   "time_ratio": diag["seconds"] / rec["seconds"], "reconstruct_mb": rec["peak_mb"],
                                   "diagnose_mb": diag["peak_mb"], "memory_ratio": diag["peak_mb"] / rec["peak_mb"],
                                   "diagnose_stages_s": stages, "machine": rows["machine"],
                                   "runs_s": {"reconstruct": [round(r[0]["seconds"], 2) for r in runs],
                                              "diagnose": [round(r[1]["seconds"], 2) for r in runs]},
                                   "load_average_after": round(os.getloadavg()[0], 2)}
            print(case, json.dumps(rows["cases"][case]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    out = args.out / "diagnose-cost.json"
    # the cases not run this time keep their last measurement, and every case its place in the file
    kept = json.loads(out.read_text())["cases"] if out.exists() else {}
    rows["cases"] = {**kept, **rows["cases"]}
    out.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
