#!/usr/bin/env python3
"""Wall time and memory of ``reconstruct``: the paper's study, or the clinical scanner's files.

Target ``paper`` (default) simulates the paper's study (209 frames of 450 x 510) in memory once, then
reconstructs it
- with the defaults, with every column and with every 20th column (``fit.subsample=20``): what subsampling saves,
- on every 4th column: with the Gauss-Newton steps, with L-BFGS instead (``fit.optimizer=lbfgs``), with the
  paper's diagonal preconditioner (``fit.preconditioner=diagonal``): what whitening by the whole profiled Fisher
  information saves, and without preconditioning (``fit.precondition=false``): what eq. 34 saves,
- with a parallax set (``geometry.parallax=0.02``: the samples read the images between rows, one block-tridiagonal
  solve per column), at the defaults (the plan counts the coupled rows' cost) and with every column (against
  ``every column``: what the coupled rows cost),
and reports seconds per stage, iterations, cost evaluations and the ratios.

Target ``clinical`` simulates (once, into ``--dir``; never into the repository) the clinical scanner at
full resolution (configs/clinical.yaml: 195 frames of 2880 x 2880 uint16, 3.2 GB) and binned
(configs/clinical-binned.yaml: 1440 x 1440), then runs ``dfxcorr reconstruct`` on each file in a
subprocess under ``/usr/bin/time -v`` for wall time and peak resident memory, and the phi0 / phi1 /
v^s RMSE against the truth (median gauge over frames lighting half the active area) and their pulls (RMS of
error / reported standard error, 1 where the error bars are right), with the fit's
iterations and cost evaluations from its log; and the binned scan again with a parallax set
(``binned-parallax``: ``geometry.parallax=0.02``); with ``--repeat`` the cases in turn, that many rounds, the fastest
run of each counting. Targets: full resolution under 30 s and 1.6 GB,
binned under 10 s, both within 0.004 rad; with a parallax within 2x of without.

Target ``demo`` runs ``dfxcorr demo`` in a subprocess with an empty numba cache (compilation included),
then again with that cache (warm): targets under 60 s and 20 s.

Both print the machine and write its section of docs/benchmark.json (the other section is kept).

Target ``targets`` measures the speed anchor in the same run: it simulates the paper's study into ``--dir``
(once), then runs ``dfxcorr reconstruct`` at its defaults and the plain numpy/scipy method
(``../shared/bench/reference_cli.py``, fit on every 20th column) on that file alternately, ``--runs`` times
each, as separate processes (wall time and peak memory of the whole process, start-up included), with their
phi0 / phi1 RMSE; writes the ``anchor`` section of docs/benchmark.json and prints every target with the figure
measured for it, its prediction where the run states one, and the machine (the clinical rows from
docs/benchmark.json as ``clinical`` measured them, the kernels' from docs/bench-kernels.json,
scripts/bench_kernels.py).

Usage: python scripts/benchmark.py [paper] [--pixel-mm 1.0] [--repeat 1] [--out docs/]
       python scripts/benchmark.py clinical --dir /tmp/dfx-bench [--cases binned full] [--set k=v ...] [--repeat 1]
       python scripts/benchmark.py demo --dir /tmp/dfx-bench [--out docs/]
       python scripts/benchmark.py targets --dir /tmp/dfx-bench [--runs 3] [--out docs/]
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from dfxcorr import config as C
from dfxcorr import pipeline
from dfxcorr.analysis.compare import machine
from dfxcorr.analysis.evaluate import frames_lighting, vibration_pulls, vibration_rmse
from dfxcorr.export import SPEC_EFFECTS, read_result_h5
from dfxcorr.io import read_scan
from dfxcorr.sim import simulate as S

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_baseline import head_commit  # noqa: E402  (a sibling script, not a package)

ROOT = Path(__file__).resolve().parents[1]

#: The optimiser comparisons run on every 4th column (127; the defaults take all 510, where L-BFGS without
#: preconditioning needs minutes), against Gauss-Newton on the same columns.
CASES = {"default": [], "every column": ["fit.subsample=1"], "every 20th column": ["fit.subsample=20"],
         "every 4th column": ["fit.subsample=4"],
         "L-BFGS (fit.optimizer=lbfgs)": ["fit.subsample=4", "fit.optimizer=lbfgs"],
         "diagonal preconditioning (eq. 34)": ["fit.subsample=4", "fit.optimizer=lbfgs", "fit.preconditioner=diagonal"],
         "no preconditioning": ["fit.subsample=4", "fit.optimizer=lbfgs", "fit.precondition=false"],
         "parallax (geometry.parallax=0.02)": ["geometry.parallax=0.02"],
         "parallax, every column": ["geometry.parallax=0.02", "fit.subsample=1"]}
#: The fit's log line with its iterations and cost evaluations (dfxcorr.pipeline.run_fit).
FIT_LINE = re.compile(r"vibration fit: (\d+) iterations, (\d+) evaluations of the cost over (\d+) samples")
#: The log line of the chosen columns (dfxcorr.planning.plan_columns).
PLAN_LINE = re.compile(r"vibration fit columns: (.*)")
CLINICAL = {"binned": ROOT / "configs" / "clinical-binned.yaml", "full": ROOT / "configs" / "clinical.yaml"}
#: Clinical cases that reconstruct another case's scan with settings of their own: the binned scan with a parallax set
#: (what the coupled rows cost against ``binned``: a bound of 2x), and the full-resolution fit holding 4x the samples
#: of the defaults (within 1.6 GB). The third entry: whether the case's accuracy means anything (the scan has no
#: parallax, so its RMSE with one set does not).
CLINICAL_SETS = {"binned-parallax": ("binned", ["geometry.parallax=0.02"], False),
                 "full-4x-samples": ("full", ["fit.max_samples=28000000"], True)}
#: The speed anchor: the paper's method written plainly in numpy/scipy (not part of the project).
ANCHOR = ROOT.parent / "shared" / "bench" / "reference_cli.py"


def measured(cmd: list[str], *, env: dict | None = None) -> tuple[float, float, str]:
    """Run a command; its wall time (s), peak resident memory (MB, from /usr/bin/time -v if present) and stderr."""
    t0 = time.perf_counter()
    if shutil.which("time") or Path("/usr/bin/time").exists():
        proc = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True, check=False, env=env)
        wall = time.perf_counter() - t0
        if proc.returncode:
            sys.exit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
        rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr).group(1))
        return wall, rss_kb / 1024, proc.stderr
    import resource
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    wall = time.perf_counter() - t0
    if proc.returncode:
        sys.exit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    # peak of the largest child so far: run one measured command per process
    return wall, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, proc.stderr


def cpu_seconds(time_text: str) -> float | None:
    """User + system CPU seconds of a process from /usr/bin/time -v's report (None without it): on cores shared with
    other work the wall time says more about the neighbours than about the program."""
    found = [re.search(rf"{what} time \(seconds\): ([\d.]+)", time_text) for what in ("User", "System")]
    return round(sum(float(m.group(1)) for m in found if m), 1) if all(found) else None


def fit_counts(log_text: str) -> dict:
    """Iterations, cost evaluations, fit samples and the chosen columns from a reconstruct log."""
    out: dict = {}
    if m := FIT_LINE.search(log_text):
        out.update(iterations=int(m.group(1)), evaluations=int(m.group(2)), fit_samples=int(m.group(3)))
    if m := PLAN_LINE.search(log_text):
        out["columns"] = m.group(1)
    return out


def clinical(args) -> dict:
    """Simulate (if missing) and reconstruct the clinical scans; wall time, peak memory and RMSE per case: the cases
    in turn, ``--repeat`` rounds of them (the fastest run of each counts)."""
    folder = scratch(args.dir)
    out: dict[str, dict] = {}
    for _ in range(args.repeat):
        for case in args.cases:
            entry = clinical_case(case, folder, args.set)
            if case not in out or entry["seconds"] < out[case]["seconds"]:
                out[case] = {**out.get(case, {}), **entry}
    for case, entry in out.items():
        print(case, json.dumps(entry), flush=True)
    return out


def clinical_case(case: str, folder: Path, settings: list[str]) -> dict:
    """One reconstruction of a clinical case (its scan simulated first where missing)."""
    exe = [sys.executable, "-c", "from dfxcorr.cli import main; main()"]
    of, own, accurate = CLINICAL_SETS.get(case, (case, [], True))
    scan_path, result_path = folder / f"clinical-{of}.h5", folder / f"clinical-{case}.result.h5"
    truth_path = folder / f"clinical-{of}.truth.npz"
    entry: dict = {"scan": of, "accuracy_counts": accurate}
    if not (scan_path.exists() and truth_path.exists()):
        print(f"simulating {scan_path} ...", flush=True)
        wall, rss, _ = measured([*exe, "simulate", str(CLINICAL[of]), "-o", str(scan_path), "--truth",
                                 str(truth_path), "--overwrite"])
        entry["simulate"] = {"seconds": round(wall, 1), "peak_rss_mb": round(rss)}
    scan = read_scan(scan_path)
    entry["size"] = list(scan.shape)
    entry["file_gb"] = round(scan_path.stat().st_size / 1e9, 2)
    sets = [x for s in [*settings, *own] for x in ("--set", s)]
    wall, rss, log_text = measured([*exe, "reconstruct", str(scan_path), "-o", str(result_path), "--overwrite", *sets])
    res = read_result_h5(result_path)
    # the file names effects as the results spec does (visibility), one value per frame
    params = {SPEC_EFFECTS.get(k, k): np.asarray(v).reshape(scan.shape[0], -1) for k, v in res["vibration"].items()}
    unc = {SPEC_EFFECTS.get(k, k): np.asarray(v).reshape(scan.shape[0], -1) for k, v in res["uncertainty"].items()}
    truth = dict(np.load(truth_path))
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    entry.update(seconds=round(wall, 1), cpu_seconds=cpu_seconds(log_text), peak_rss_mb=round(rss),
                 stages={k: round(v, 2) for k, v in res["timings"].items()},
                 reduced_chi2=round(res["reduced_chi2"], 4),
                 rmse={k: round(v, 5) for k, v in vibration_rmse(params, truth, good).items()},
                 pulls={k: round(v, 2) for k, v in vibration_pulls(params, unc, truth, good).items()},
                 sets=[*settings, *own], load_average=[round(v, 2) for v in os.getloadavg()], **fit_counts(log_text))
    return entry


def scratch(path: Path) -> Path:
    """``path`` resolved and created, refused inside the repository (the scans are gigabytes)."""
    folder = path.resolve()
    if folder == ROOT or ROOT in folder.parents:
        sys.exit(f"--dir {folder} is inside the repository; give a scratch folder such as /tmp/dfx-bench")
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def vibrations(path: Path, n_frames: int) -> dict:
    """The per-frame estimates of a result file (dfxcorr's or the anchor's, both write entry/dfxcorr/vibration),
    by the catalogue's names, each (J, 1)."""
    with h5py.File(path, "r") as f:
        g = f["entry/dfxcorr/vibration"]
        return {SPEC_EFFECTS.get(k, k): np.asarray(g[k]).reshape(n_frames, -1) for k in g
                if isinstance(g[k], h5py.Dataset)}


def anchor(args) -> dict:
    """dfxcorr at its defaults and the anchor on the paper's study, alternately: seconds, memory, RMSE, ratio."""
    if not ANCHOR.exists():
        sys.exit(f"{ANCHOR} is absent: the anchor is measured where ../shared/bench holds it")
    folder = scratch(args.dir)
    scan_path, truth_path = folder / "paper-study.h5", folder / "paper-study.truth.npz"
    exe = [sys.executable, "-c", "from dfxcorr.cli import main; main()"]
    if not (scan_path.exists() and truth_path.exists()):
        print(f"simulating {scan_path} ...", flush=True)
        measured([*exe, "simulate", str(ROOT / "configs" / "paper-simulation.yaml"), "-o", str(scan_path),
                  "--truth", str(truth_path), "--overwrite"])
    scan = read_scan(scan_path)
    truth = dict(np.load(truth_path))
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    commands = {"dfxcorr": lambda out: [*exe, "reconstruct", str(scan_path), "-o", str(out), "--overwrite"],
                "anchor": lambda out: [sys.executable, str(ANCHOR), str(scan_path), "-o", str(out)]}
    runs: dict = {who: [] for who in commands}
    # a first, untimed dfxcorr run: numba's cache filled for this checkout, as a user's second run finds it
    measured(commands["dfxcorr"](folder / "paper-study.dfxcorr.h5"))
    for _ in range(args.runs):
        for who, cmd in commands.items():
            out = folder / f"paper-study.{who}.h5"
            out.unlink(missing_ok=True)
            wall, rss, text = measured(cmd(out))
            runs[who].append({"seconds": round(wall, 2), "cpu_seconds": cpu_seconds(text), "peak_rss_mb": round(rss),
                              "rmse": {k: round(v, 5) for k, v in
                                       vibration_rmse(vibrations(out, scan.shape[0]), truth, good).items()},
                              "load_average": [round(v, 2) for v in os.getloadavg()], **fit_counts(text)})
            print(who, json.dumps(runs[who][-1]), flush=True)
    med = {who: float(np.median([r["seconds"] for r in rs])) for who, rs in runs.items()}
    return {"size": list(scan.shape), "runs": runs, "median_seconds": med,
            "ratio": round(med["dfxcorr"] / med["anchor"], 3)}


def demo(args) -> dict:
    """``dfxcorr demo`` with an empty numba cache (compilation included), then warm: wall seconds of each."""
    folder = args.dir.resolve()
    folder.mkdir(parents=True, exist_ok=True)
    exe = [sys.executable, "-c", "from dfxcorr.cli import main; main()"]
    out: dict = {"load_average_at_start": [round(v, 2) for v in os.getloadavg()]}
    with tempfile.TemporaryDirectory(dir=folder) as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        for label in ("cold", "warm"):
            wall, rss, text = measured([*exe, "-q", "demo", str(folder / "demo"), "--overwrite"], env=env)
            out[label] = {"seconds": round(wall, 1), "cpu_seconds": cpu_seconds(text), "peak_rss_mb": round(rss)}
            print("demo", label, json.dumps(out[label]), flush=True)
    out["load_average_at_end"] = [round(v, 2) for v in os.getloadavg()]
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("target", nargs="?", choices=("paper", "clinical", "demo", "targets"), default="paper")
    ap.add_argument("--pixel-mm", type=float, default=1.0, help="paper: pixel pitch of the simulated study (mm)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="paper, clinical: rounds of every case in turn (the fastest run of each case counts)")
    ap.add_argument("--runs", type=int, default=3, help="targets: alternated runs of dfxcorr and the anchor each")
    ap.add_argument("--dir", type=Path, default=Path("/tmp/dfx-bench"),
                    help="clinical, demo, targets: scratch folder (the scans, the demo's output)")
    ap.add_argument("--cases", nargs="+", choices=(*CLINICAL, *CLINICAL_SETS), default=[*CLINICAL, *CLINICAL_SETS],
                    help="clinical: which")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="clinical: reconstruct option (repeatable)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    info = machine()
    print(info, flush=True)
    doc_path = args.out / "benchmark.json"
    doc = json.loads(doc_path.read_text()) if doc_path.exists() else {}
    if "machine" in doc:  # the earlier layout held the paper target alone
        doc = {"paper": doc}
    if args.target == "targets":
        doc["anchor"] = {"machine": info, "commit": head_commit(), **anchor(args)}
        args.out.mkdir(parents=True, exist_ok=True)
        doc_path.write_text(json.dumps(doc, indent=2))
        targets(args.out)
        return
    if args.target == "clinical":
        doc["clinical"] = {"machine": info, "rounds": args.repeat, "cases": clinical(args)}
    elif args.target == "demo":
        doc["demo"] = {"machine": info, **demo(args)}
    else:
        doc["paper"] = paper(args, info)
    args.out.mkdir(parents=True, exist_ok=True)
    doc_path.write_text(json.dumps(doc, indent=2))


def targets(folder: Path) -> None:
    """Print each performance target with its measured figure, the machine and whether it is met (saved JSON)."""
    def load(name):
        path = folder / name
        return json.loads(path.read_text()) if path.exists() else {}

    bench, kern = load("benchmark.json"), load("bench-kernels.json")
    rows = []
    clin = bench.get("clinical", {}).get("cases", {})
    for case, label, seconds in (("full", "full resolution 195 x 2880 x 2880", 30),
                                 ("binned", "binned 1440 x 1440", 10)):
        if case in clin:
            c = clin[case]
            worst = max(c["rmse"]["phase_offset"], c["rmse"]["tilt"])
            memory = case != "full" or c["peak_rss_mb"] <= 1600
            rows.append((f"clinical {label} at defaults: phi0/phi1 RMSE <= 0.004 rad in < {seconds} s"
                         + (", peak <= 1.6 GB" if case == "full" else ""),
                         f"{worst:.4f} rad, {c['seconds']} s ({c.get('cpu_seconds')} s CPU), "
                         f"{c['peak_rss_mb'] / 1000:.2f} GB, "
                         f"{c.get('iterations')} iterations, {c.get('evaluations')} evaluations, load "
                         f"{c.get('load_average')}; predicted: {c.get('columns')}",
                         worst <= 0.004 and c["seconds"] < seconds and memory))
    if "full-4x-samples" in clin:
        c = clin["full-4x-samples"]
        rows.append(("clinical full resolution, the fit holding 4x the default samples "
                     f"({', '.join(c['sets'])}): peak <= 1.6 GB",
                     f"{c['peak_rss_mb'] / 1000:.2f} GB, {c['seconds']} s, {c.get('fit_samples')} samples fitted, "
                     "phi0 / phi1 / v^s RMSE "
                     + " / ".join(f"{c['rmse'][k]:.5f}" for k in ("phase_offset", "tilt", "visibility_loss")),
                     c["peak_rss_mb"] <= 1600))
    cases = bench.get("paper", {}).get("cases", {})
    # the coupled rows' cost: a parallax set against the same scan without, in memory (the paper study,
    # both in one run) and whole process (the binned clinical scan)
    pairs = [("paper study in memory", cases.get("parallax (geometry.parallax=0.02)"), cases.get("default")),
             ("binned clinical, whole process", clin.get("binned-parallax"), clin.get("binned"))]
    for label, with_, without in pairs:
        if with_ and without:
            ratio = with_["seconds"] / without["seconds"]
            rows.append((f"reconstruct with geometry.parallax=0.02 within 2x of without: {label}",
                         f"{with_['seconds']} / {without['seconds']} s, x{ratio:.2f}; stages {with_.get('stages')} "
                         f"against {without.get('stages')}", ratio <= 2.0))
    if "default" in cases and "every column" in cases:
        d, e = cases["default"], cases["every column"]
        ratio = max(d["rmse"][k] / e["rmse"][k] for k in ("phase_offset", "tilt"))
        rows.append(("paper study at defaults: the Cramer-Rao level (phi0/phi1 RMSE within 10 % of every column's)",
                     f"{d['rmse']['phase_offset']} / {d['rmse']['tilt']} rad against {e['rmse']['phase_offset']} / "
                     f"{e['rmse']['tilt']} (x{ratio:.2f}), {d['seconds']} s in memory, {d.get('iterations')} "
                     f"iterations, {d.get('evaluations')} evaluations", ratio <= 1.1))
    # the pulls pooled over noise realisations (scripts/pulls.py) where measured: one scan's vary much
    pooled = load("pulls.json").get("cases", {})
    pulls = ([(f"{name}, pooled over seeds {load('pulls.json')['seeds']}", c["defaults"]["pooled"])
              for name, c in pooled.items()] or
             [(name, c["pulls"]) for name, c in (("paper study", cases.get("default", {})),
                                                 *((f"clinical {k}", v) for k, v in clin.items())) if "pulls" in c])
    if pulls:
        worst = [c[k] for _, c in pulls for k in ("phase_offset", "tilt")]
        rows.append(("pulls of phi0 / phi1 at defaults (RMS of error / reported standard error) within 0.8-1.25",
                     "; ".join(f"{name} {c['phase_offset']} / {c['tilt']}" for name, c in pulls),
                     min(worst) >= 0.8 and max(worst) <= 1.25))
    anc = bench.get("anchor")
    if anc:
        med, runs = anc["median_seconds"], anc["runs"]

        def rmse(who: str) -> str:
            return " / ".join(f"{np.median([r['rmse'][k] for r in runs[who]]):.4f}" for k in ("phase_offset", "tilt"))

        current = anc.get("commit") == head_commit()
        every = cases.get("every column", {}).get("rmse")
        level = max(np.median([r["rmse"][k] for r in runs["dfxcorr"]]) / every[k]
                    for k in ("phase_offset", "tilt")) if every else None
        rows.append(("paper study at defaults: the Cramer-Rao level in <= 0.4 x the anchor's whole-process time "
                     "(alternated runs)",
                     f"{med['dfxcorr']:.1f} / {med['anchor']:.1f} s, ratio {anc['ratio']:.2f}; phi0/phi1 RMSE "
                     f"{rmse('dfxcorr')} rad" + ("" if level is None else f" (x{level:.2f} every column's)")
                     + f"; {runs['dfxcorr'][0].get('columns', '')}; load {runs['dfxcorr'][-1]['load_average']}"
                     + ("" if current else f" (measured at commit {anc.get('commit')}, not this one)"),
                     anc["ratio"] <= 0.4 and (level is None or level <= 1.1) if current else None))
        rows.append(("the plain numpy/scipy method at fit.subsample=20 (the anchor, same run)",
                     f"{med['anchor']:.1f} s, phi0/phi1 RMSE {rmse('anchor')} rad", None))
    if "demo" in bench:
        dm = bench["demo"]
        rows.append(("dfxcorr demo, empty numba cache < 60 s, warm < 20 s",
                     f"{dm['cold']['seconds']} / {dm['warm']['seconds']} s (load {dm['load_average_at_start']})",
                     dm["cold"]["seconds"] < 60 and dm["warm"]["seconds"] < 20))
    for key, label in (("paper_every_column", "paper study, every column"), ("clinical_fit_columns", "clinical fit")):
        if key in kern:
            k = kern[key]
            cpu = {p: k[p].get("cpu_ns_per_sample", k[p]["ns_per_sample"]) for p in ("cost_gradient", "retrieval")}
            worst = max(cpu[p] / k[p]["floor_ns_per_sample"] for p in cpu)
            one = k.get("single_thread")
            # what the passes take on one thread with their samples in cache: the arithmetic alone
            arithmetic = "" if one is None else (
                f"; one thread, streamed / in cache: {one['cost_gradient']['streamed_ns_per_sample']} / "
                f"{one['cost_gradient']['in_cache_ns_per_sample']} and {one['retrieval']['streamed_ns_per_sample']} / "
                f"{one['retrieval']['in_cache_ns_per_sample']} ns")
            rows.append((f"kernels within 3 x the memory floor ({label}): cost+gradient / retrieval, CPU ns "
                         "per sample",
                         f"{cpu['cost_gradient']} / {cpu['retrieval']} ns against "
                         f"{k['cost_gradient']['floor_ns_per_sample']} / {k['retrieval']['floor_ns_per_sample']} ns "
                         f"(x{worst:.1f}){arithmetic}",
                         worst <= 3))
    print("machine:", bench.get("clinical", {}).get("machine") or bench.get("paper", {}).get("machine"),
          "| kernels:", kern.get("machine"))
    for what, figure, met in rows:
        print(f"{what}\n    measured {figure}: {'-' if met is None else 'met' if met else 'NOT met'}")


def paper(args, info: dict) -> dict:
    """The paper's study in memory: seconds per stage, iterations and RMSE of the cases of :data:`CASES`."""
    sim = C.load([ROOT / "configs" / "paper-simulation.yaml"], [f"simulate.pixel_mm={args.pixel_mm}"],
                 schema=S.SCHEMA)
    scan, truth = S.simulate(sim)
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    out = {"machine": info, "size": list(scan.shape), "rounds": args.repeat, "cases": {}}
    records: list[str] = []
    handler = logging.Handler(level=logging.INFO)
    handler.emit = lambda record: records.append(record.getMessage())  # type: ignore[method-assign]
    logging.getLogger("dfxcorr").addHandler(handler)
    logging.getLogger("dfxcorr").setLevel(logging.INFO)
    # untimed: the first reconstruct of a process loads the compiled kernels from numba's cache (about 3 s)
    pipeline.reconstruct(scan, C.load([], []), progress=False)
    # the cases in turn, --repeat rounds of them (the fastest of each counts): a machine that speeds up or slows down
    # during the run changes every case alike, not the later ones
    best: dict[str, dict] = {}
    for _ in range(args.repeat):
        for name, sets in CASES.items():
            records.clear()
            t0 = time.perf_counter()
            result = pipeline.reconstruct(scan, C.load([], sets), progress=False)
            seconds = time.perf_counter() - t0
            if name not in best or seconds < best[name]["seconds"]:
                best[name] = {"seconds": round(seconds, 2),
                              "stages": {k: round(v, 2) for k, v in result.timings.items()},
                              **fit_counts("\n".join(records)), "reduced_chi2": round(result.reduced_chi2, 4),
                              "rmse": {k: round(v, 5) for k, v in vibration_rmse(result.params, truth, good).items()},
                              "pulls": {k: round(v, 2) for k, v in vibration_pulls(result.params, result.uncertainty,
                                                                                   truth, good).items()},
                              "load_average": [round(v, 2) for v in os.getloadavg()]}
    for name in CASES:
        out["cases"][name] = best[name]
        print(name, json.dumps(best[name]), flush=True)
    ref = out["cases"]["default"]
    out["ratios"] = {f"{k} / default": round(v["seconds"] / ref["seconds"], 2) for k, v in out["cases"].items()
                     if k != "default"}
    print(json.dumps(out["ratios"]))
    return out


if __name__ == "__main__":
    main()
