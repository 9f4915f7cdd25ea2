#!/usr/bin/env python3
"""Speed of the compiled kernels (dfxcorr.kernels) against the memory-bandwidth floor, measured in one run.

Reports, for the paper study's observations (209 frames of 450 x 510, every column) and the fit
columns of a clinical detector (195 frames, active area 440 rows, every 20th of 2880 columns,
synthetic samples), both in float32 as a reconstruction holds them:
- ns per (pixel, frame) sample of one cost+gradient evaluation (the paper model's channels) and of
  one retrieval pass as the pipeline's blocked retrieval runs it (two solves, the second with the model's
  weights, and the Pearson chi-square; no expected counts written), wall time and process CPU time
  (the CPU time is what counts on cores shared with other work),
- the floor of each pass: the bytes it must stream / the np.copyto bandwidth measured here (the passes read the
  samples' fringe as its quadratures, Observations.fringe: no pass evaluates a trigonometric function per sample),
- the cost of making those quadratures once, at alignment (numpy's cos and sin in the samples' dtype),
- each pass on one thread over every row and over a slab of rows held in cache, repeated: how much of its time is
  memory and how much arithmetic (arithmetic_share),
then the wall time of the whole vibration fit stage of ``reconstruct`` on the paper study with
``fit.subsample=1`` and the default (auto), and the first-call compile cost of the kernels (fresh
numba cache, in a subprocess) against a cached start. Writes docs/bench-kernels.json.

Usage: python scripts/bench_kernels.py [--repeat 5] [--skip-fit] [--out docs/]
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

from dfxcorr import config as C
from dfxcorr import kernels as K
from dfxcorr import model as M
from dfxcorr import pipeline
from dfxcorr.align import build_observations
from dfxcorr.catalogue import PAPER_MODEL, neutral_params
from dfxcorr.noise import noise_weights
from dfxcorr.observations import Observations, quadratures
from dfxcorr.reference import resolve_reference
from dfxcorr.sim import simulate as S

ROOT = Path(__file__).resolve().parents[1]


def copy_bandwidth(*, nbytes: int = 1 << 28, repeat: int = 5) -> float:
    """Bytes per second that np.copyto moves (read + write) on this machine, best of ``repeat``."""
    src = np.ones(nbytes // 8)
    dst = np.empty_like(src)
    best = min(_seconds(lambda: np.copyto(dst, src)) for _ in range(repeat))
    return 2 * src.nbytes / best


def _seconds(f) -> float:
    t0 = time.perf_counter()
    f()
    return time.perf_counter() - t0


def _timed(f, repeat: int) -> tuple[float, float]:
    """Best wall and best process CPU seconds (all threads) of ``repeat`` calls."""
    walls, cpus = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        f()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return min(walls), min(cpus)


def clinical_observations(rng, *, frames: int = 195, height: int = 2880, width: int = 2880, active: int = 440,
                          every: int = 20) -> Observations:
    """Synthetic fit observations of a clinical detector: each frame lights ``active`` rows, every n-th column."""
    start = np.round(np.linspace(0, height - active, frames)).astype(int)
    row = (start[:, None] + np.arange(active)[None, :]).ravel()
    frame = np.repeat(np.arange(frames), active)
    order = np.argsort(row, kind="stable")
    row, frame = row[order], frame[order]
    columns = np.arange(0, width, every)
    Kb, Cc = row.size, columns.size
    tf = rng.uniform(1.5e4, 2.5e4, (Kb, Cc))
    vf = rng.uniform(0.25, 0.35, (Kb, Cc))
    phif = 2 * np.pi * 2.0 * (row[:, None] / active + columns[None, :] / width) + frame[:, None] * 0.3
    counts = rng.poisson(tf * (1 + 0.8 * vf * np.cos(phif)))
    f32 = np.float32
    fc, fs = quadratures(tf.astype(f32), vf.astype(f32), phif.astype(f32))
    return Observations(counts.astype(f32), tf.astype(f32), fc, fs,
                        np.zeros((Kb, Cc), f32), np.ones((Kb, Cc), bool), row, frame, columns,
                        (frames, height, width))


def paper_observations() -> tuple:
    """The paper study's scan (configs/paper-simulation.yaml) and its observations on every column."""
    scan, _ = S.simulate(C.load([ROOT / "configs" / "paper-simulation.yaml"], [], schema=S.SCHEMA))
    return scan, build_observations(scan, resolve_reference(scan), dtype=np.float32)


def pass_numbers(obs: Observations, bandwidth: float, *, repeat: int) -> dict:
    """ns per sample of a cost+gradient evaluation and a retrieval pass, and their bandwidth floors."""
    params = neutral_params(PAPER_MODEL, obs.n_frames)
    rng = np.random.default_rng(0)
    params["phase_offset"] += rng.normal(0, 0.1, params["phase_offset"].shape)
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    # in the samples' dtype, as the fit holds them (fit._Problem)
    weights = np.asarray(noise_weights(obs, obs.counts), dtype=obs.counts.dtype)
    n = obs.counts.size
    K.reduced_cost(obs, ch, weights)

    def retrieval():
        return K.retrieve(obs, ch, iterations=2, keep_expected=False)

    # as the alignment makes them, from the flat field's visibility and phase at each sample
    vf, phif = obs.vf, obs.phif
    fringe, fringe_cpu = _timed(lambda: quadratures(obs.tf, vf, phif), repeat)
    retrieval()
    cost, cost_cpu = _timed(lambda: K.reduced_cost(obs, ch, weights, channels=("phase", "visibility")), repeat)
    ret, ret_cpu = _timed(retrieval, repeat)
    # bytes each pass must stream once: the samples it reads (the blocked retrieval writes none)
    fc, fs = obs.fringe
    read_cost = sum(a.itemsize for a in (obs.counts, obs.tf, fc, fs, obs.dark, weights))
    read_ret = sum(a.itemsize for a in (obs.counts, obs.tf, fc, fs, obs.dark, obs.use))
    return {"samples": int(n), "blocks": int(obs.frame.size), "columns": int(obs.columns.size),
            "frames": int(obs.n_frames), "rows": int(obs.rows.size),
            "cost_gradient": {"ns_per_sample": round(cost / n * 1e9, 2), "seconds": round(cost, 4),
                              "cpu_ns_per_sample": round(cost_cpu / n * 1e9, 2),
                              "bytes_per_sample": read_cost,
                              "floor_ns_per_sample": round(read_cost / bandwidth * 1e9, 2)},
            "retrieval": {"ns_per_sample": round(ret / n * 1e9, 2), "seconds": round(ret, 4),
                          "cpu_ns_per_sample": round(ret_cpu / n * 1e9, 2),
                          "bytes_per_sample": read_ret,
                          "floor_ns_per_sample": round(read_ret / bandwidth * 1e9, 2)},
            "fringe": {"ns_per_sample": round(fringe / n * 1e9, 2),
                       "cpu_ns_per_sample": round(fringe_cpu / n * 1e9, 2)}}


@numba.njit
def _repeat(reps, kernel, *args):
    """``reps`` calls of the compiled ``kernel``, from compiled code (no Python dispatch between them)."""
    for _ in range(reps):
        kernel(*args)


def arithmetic_share(obs: Observations, *, repeat: int, slab_bytes: int = 1 << 22) -> dict:
    """Single-thread ns per sample of the two passes' compiled kernels, called as reduced_cost and retrieve call them,
    over every row (the samples streamed from memory) and over a slab of middle rows whose samples take at most
    ``slab_bytes`` (Observations.of_rows), repeated so that it stays in the last-level cache; the two alternated,
    best of ``repeat`` each. Where the two are close, a pass is bound by its arithmetic, not by memory."""
    params = neutral_params(PAPER_MODEL, obs.n_frames)
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    weights = np.asarray(noise_weights(obs, obs.counts), dtype=obs.counts.dtype)
    n_c, rows = obs.columns.size, obs.rows.size
    turning, vis = K._turning(obs, ch.phase), K._c(ch.vis, np.float64)
    cost_out = (np.empty(n_c), *(np.empty((obs.n_frames, n_c)) for _ in range(3)), np.empty((3, n_c)),
                np.empty((2, n_c)))
    need = np.isin(list(K.CHANNEL_IDS), ["phase", "visibility"])
    per_row = obs.counts.size / rows * sum(a.itemsize for a in (obs.counts, obs.tf, obs.fc, obs.fs, obs.dark, weights))
    slab = max(1, int(slab_bytes // per_row))
    first = (rows - slab) // 2
    parts = {"streamed": (obs, weights),
             "in_cache": (obs.of_rows(first, first + slab), weights[obs.block_range(first, first + slab)])}

    def cost(reps, sub, w):
        _repeat(reps, K._cost_rows, sub.counts, sub.tf, sub.fc, sub.fs, sub.dark, w, sub.frame, sub.y, sub.x,
                K._bounds(sub), 0, sub.rows.size, *turning, vis, ch.dose, ch.background, ch.harmonic, np.eye(2), False,
                need, K.TILE, *cost_out)

    def retrieval(reps, sub, _):
        n = sub.rows.size
        _repeat(reps, K._retrieve, sub.counts, sub.tf, sub.fc, sub.fs, sub.dark, sub.dark, sub.use,
                np.zeros((0, 0), sub.tf.dtype), sub.frame, sub.y, sub.x, K._bounds(sub), np.array([0, n]), *turning,
                vis, ch.dose, ch.background, ch.harmonic, np.ones((n, n_c)), 0.0, 2, True, False, False, False, False,
                -(-n_c // -(-n_c // K.TILE)), np.empty((0, n_c), sub.tf.dtype))
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    out: dict = {"slab_rows": slab, "slab_bytes": slab_bytes}
    try:
        for name, run in (("cost_gradient", cost), ("retrieval", retrieval)):
            reps = {where: max(1, obs.counts.size // sub.counts.size) for where, (sub, _) in parts.items()}
            best = dict.fromkeys(parts, np.inf)
            for sub, w in parts.values():
                run(1, sub, w)
            for _ in range(repeat):
                for where, (sub, w) in parts.items():
                    seconds = _seconds(functools.partial(run, reps[where], sub, w))
                    best[where] = min(best[where], seconds / reps[where] / sub.counts.size)
            out[name] = {f"{where}_ns_per_sample": round(best[where] * 1e9, 2) for where in parts}
    finally:
        numba.set_num_threads(threads)
    return out


def fit_times(scan) -> dict:
    """Wall time of reconstruct's stages with every column and every 20th column in the fit."""
    out = {}
    for name, sets in (("subsample=1", ["fit.subsample=1"]), ("default (subsample auto)", [])):
        t0, c0 = time.perf_counter(), time.process_time()
        result = pipeline.reconstruct(scan, C.load([], sets), progress=False)
        out[name] = {"seconds": round(time.perf_counter() - t0, 2), "cpu_seconds": round(time.process_time() - c0, 2),
                     "stages": {k: round(v, 2) for k, v in result.timings.items()},
                     "iterations": int(result.cost.size), "reduced_chi2": round(result.reduced_chi2, 4)}
        print(name, json.dumps(out[name]), flush=True)
    return out


COMPILE_PROBE = """
import time, numpy as np
t0 = time.perf_counter()
from dfxcorr import fisher_pixels as FP, kernels as K, model as M
from dfxcorr.catalogue import PAPER_MODEL
from dfxcorr.noise import noise_weights
from dfxcorr.observations import Observations, quadratures
rng = np.random.default_rng(0)
row = np.repeat(np.arange(8), 4); frame = np.tile(np.arange(4), 8); shape = (8, 4, 6)
a = lambda lo, hi: rng.uniform(lo, hi, (32, 6))
f = lambda v: np.asarray(v, np.float32)  # a reconstruction's observations are float32
tf = f(a(900, 1100))
obs = Observations(f(a(500, 900)), tf, *quadratures(tf, f(a(0.2, 0.4)), f(a(-3, 3))), f(np.zeros((32, 6))),
                   np.ones((32, 6), bool), row, frame, np.arange(6), (4, 8, 6))
K.set_threads()
ch = M.channels({}, x=obs.x, n_frames=4)
w = noise_weights(obs, obs.counts)
K.reduced_cost(obs, ch, np.asarray(w, np.float32))
r = K.retrieve(obs, ch, weights=w, keep_inverse=True)
FP.fisher(obs, ch, w, r["coef"], r["inverse"], M.component_table(PAPER_MODEL)[:3])
print(time.perf_counter() - t0)
"""


def compile_cost() -> dict:
    """Seconds from import to the first result of each kernel: fresh numba cache, then cached."""
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(ROOT)}
        runs = [float(subprocess.run([sys.executable, "-c", COMPILE_PROBE], env=env, check=True, capture_output=True,
                                     text=True).stdout.split()[-1]) for _ in range(2)]
    return {"first_run_seconds": round(runs[0], 1), "cached_run_seconds": round(runs[1], 1)}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--skip-fit", action="store_true", help="leave out the reconstruct timings")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    threads = K.set_threads()
    out = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.system()}, "
                      f"python {platform.python_version()}, numba {numba.__version__} ({threads} threads)",
           "load_average_at_start": [round(v, 2) for v in os.getloadavg()]}
    bandwidth = copy_bandwidth()
    out["copy_bandwidth_GB_per_s"] = round(bandwidth / 1e9, 2)
    print(json.dumps(out), flush=True)
    out["compile"] = compile_cost()
    print("compile", json.dumps(out["compile"]), flush=True)
    scan, obs = paper_observations()
    out["paper_every_column"] = pass_numbers(obs, bandwidth, repeat=args.repeat)
    out["paper_every_column"]["single_thread"] = arithmetic_share(obs, repeat=args.repeat)
    print("paper", json.dumps(out["paper_every_column"]), flush=True)
    del obs
    clinical = clinical_observations(np.random.default_rng(1))
    out["clinical_fit_columns"] = pass_numbers(clinical, bandwidth, repeat=args.repeat)
    out["clinical_fit_columns"]["single_thread"] = arithmetic_share(clinical, repeat=args.repeat)
    print("clinical", json.dumps(out["clinical_fit_columns"]), flush=True)
    del clinical
    if not args.skip_fit:
        out["reconstruct_paper_study"] = fit_times(scan)
    out["load_average_at_end"] = [round(v, 2) for v in os.getloadavg()]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench-kernels.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
