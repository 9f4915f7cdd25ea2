#!/usr/bin/env python3
"""The measurement pages, generated from the JSON that the measuring scripts write into docs/.

Reads docs/paper-study.json (scripts/paper_study.py), docs/benchmark.json (scripts/benchmark.py),
docs/bench-baseline.json (scripts/bench_baseline.py), docs/bench-kernels.json (scripts/bench_kernels.py),
docs/real-ipp.json (scripts/real_ipp.py), docs/diagnosis-study.json (scripts/diagnose_study.py),
docs/diagnose-cost.json (scripts/diagnose_cost.py), docs/scatter-twin.json (scripts/scatter_twin.py),
docs/parallax.json (scripts/parallax.py), docs/uncertainty-columns.json (scripts/uncertainty_columns.py) and the
evaluation's docs/table-*.json and docs/fig*.json (scripts/paper_figures.py), and writes
- docs/measurements.md: every measurement with its machine, load and the script that makes it;
- the table between the ``measured`` markers of README.md: one row per case, the same numbers.
Text that explains a result lives here as prose; every number comes from the JSON. Run it after any of
those scripts; ``--check`` only reports whether the pages are in step (exit code 1 if not). Uses the
standard library only.

Usage: python scripts/docs_pages.py [--docs docs/] [--readme README.md] [--check]
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
#: The README's generated table sits between these two lines.
BEGIN, END = "<!-- measured: begin (scripts/docs_pages.py writes this table) -->", "<!-- measured: end -->"
PAGE = "measurements.md"


def read(docs: Path, name: str) -> dict:
    """A JSON file of docs/, or {} where it is absent (its section is then left out)."""
    path = docs / name
    return json.loads(path.read_text()) if path.is_file() else {}


def g(x: float, digits: int = 2) -> str:
    """A number to ``digits`` significant digits, without exponent for ordinary sizes."""
    return f"{x:.{digits}g}" if 1e-4 <= abs(x) < 1e6 or x == 0 else f"{x:.{digits}e}"


def pulls_text(case: dict) -> str:
    """The pulls of phi0 / phi1 of a benchmark case (RMS of error / reported standard error), where recorded."""
    p = case.get("pulls")
    return f"; pulls {p['phase_offset']:.2f} / {p['tilt']:.2f}" if p else ""


def rmse3(r: dict) -> str:
    """phi0 / phi1 / v^s RMSE of a ``rmse`` mapping."""
    return " / ".join(f"{r[k]:.2g}" for k in ("phase_offset", "tilt", "visibility_loss"))


def load_text(load: list | float | None) -> str:
    if load is None:
        return "-"
    return f"{load[0]:.1f}" if isinstance(load, list) else f"{load:.1f}"


def table(head: list[str], rows: list[list[Any]]) -> list[str]:
    return (["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
            + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows])


def span(values: list[float], fmt: str, unit: str = "") -> str:
    """'lo-hi' of ``values`` in ``fmt`` with ``unit`` after it; one value where both read the same."""
    lo, hi = fmt.format(min(values)), fmt.format(max(values))
    return (lo if lo == hi else f"{lo}-{hi}") + unit


def fmt_estimate(r: dict) -> str:
    """A concealed-effect run's estimate against the truth (a row of docs/diagnosis-study.json)."""
    e = r.get("estimate")
    if not e:
        return "-"
    if "rmse" in e:
        return f"RMSE {e['rmse']:.3g} (truth std {e['truth_std']:.3g})"
    if "a2" in e:
        return f"a2 {e['a2']:.4f} ({e['a2_truth']:.4f}), beta {e['beta']:.2f} ({e['beta_truth']:.2f})"
    if "misclassified" in e:
        return f"f {e['factor']:.3g} ({e['truth']:.3g}), {100 * e['misclassified']:.1f} % of pixels misclassified"
    if "pixels" in e:
        return f"{e['pixels']} pixels ({e['true_pixels']} moving, {100 * e['in_region']:.0f} % of them)"
    est, tru = e["estimate"], e["truth"]
    if isinstance(est, list):
        return ", ".join(f"{a:.3g} ({b:.3g})" for a, b in zip(est, tru, strict=True))
    return f"{est:.4g} ({tru:.4g})"


def fmt_images(r: dict) -> str:
    """Phase / dark-field RMSE against the truth before -> after the effect was added."""
    if "images_before" not in r:
        return "-"
    b, a = r["images_before"], r["images_after"]
    return f"{b['phase_rmse']:.3f} -> {a['phase_rmse']:.3f} / {b['dark_field_rmse']:.3f} -> {a['dark_field_rmse']:.3f}"


def amps(r: dict) -> str:
    """The amplitudes of a combination's run, 'a + b'."""
    return " + ".join(f"{v:g}" for v in r["amplitude"].values())


def axes(r: dict) -> str:
    """The unexplained axes of a run, each once, in order."""
    return ", ".join(dict.fromkeys(r["unexplained"])) or "-"


def columns_text(text: str) -> str:
    """'72 columns (every 20-th column ...' -> '72 (every 20th)'."""
    n, rest = text.split(" columns", 1)
    step = rest.split("every ", 1)[1].split("-th", 1)[0] if "every " in rest else "1"
    return n if step == "1" else f"{n} (every {step}th)"


def linear_slope(values: list[float]) -> float:
    """Least-squares slope of ``values`` against their index."""
    n = len(values)
    mx, my = (n - 1) / 2, sum(values) / n
    return sum((i - mx) * (v - my) for i, v in enumerate(values)) / sum((i - mx) ** 2 for i in range(n))


def median(values: list[float]) -> float:
    s = sorted(values)
    return (s[(len(s) - 1) // 2] + s[len(s) // 2]) / 2


# ---------------------------------------------------------------------------------------------------------------
# docs/measurements.md


INTRO = """\
# Measurements

Generated by `scripts/docs_pages.py` from the JSON files in this folder, which the scripts named in each section
write; do not edit by hand. Every figure states the machine it was measured on (all: 2 shared cores) and, where
the script records it, the load average: the machine was shared, so wall times vary with the load, while
accuracies, iteration counts and ratios measured in one alternated run are the robust numbers."""

PAPER_STUDY = """\
Simulated with `configs/paper-simulation.yaml` (FORBILD-like thorax, 30 exposures per pixel, seed {seed}) and
reconstructed at `fit.subsample=20`; the RMSE of the per-frame parameters is taken in the median gauge over
the {frames} frames lighting at least half the active area. The v^s gauge sets the 99th percentile of v^s over
the well-determined frames to 1, the paper's max v^s = 1 made robust to a stray frame (`fit.visibility_gauge`,
`fit.visibility_quantile`); with the median gauge of eq. 22 the dark-field image would be scaled by the
median of the true v^s, about 0.86. The default configuration fits more columns than this and reaches
the Cramer-Rao level: see the next section."""

SPEED = """\
Whole `dfxcorr reconstruct` processes under `/usr/bin/time -v` (wall time, CPU time and peak resident memory,
start-up included) on the clinical scanner's geometry (`configs/clinical.yaml`: 195 frames of 2880 x 2880 uint16,
active area 440 rows; `configs/clinical-binned.yaml`: 1440 x 1440), simulated by the script, with the RMSE of
phi0 / phi1 / v^s against the truth and the pulls of phi0 / phi1 (RMS of error / reported standard error: 1 where
the error bars a user reads are right; pooled over noise realisations in the next section). The frames stay in
the file and only their lit rows are held (`retrieve.block_mb` bounds the retrieval's blocks, `fit.max_samples` the
fit)."""

PAPER_CASES = """\
The paper's study, reconstructed in memory at the defaults and at other settings (one process, the scan
simulated once). The optimiser and preconditioner comparisons use every 4th column, where L-BFGS without
preconditioning still finishes in seconds. The parallax rows set `geometry.parallax` on this scan, which has none
(their reduced chi-square is the misfit of a wrong setting); with every column, against `every column`, they show
what the coupled rows cost."""

BASELINE = """\
The same scan as separate processes, dfxcorr at commit `{this}` against its own first version (commit `{ref}`: the
paper's method in numpy/scipy, before the compiled kernels; installed in its own virtual environment), runs
alternated, medians of {runs}. An old record of the project's own progress: the speed anchor is the section
after it."""

KERNELS = """\
Nanoseconds per (pixel, frame) sample of one cost-and-gradient evaluation and of one retrieval pass (CPU time of
all threads, and wall time), in float32 as a reconstruction holds the samples, against the floor of the bytes each
pass must stream at the copy bandwidth measured in the same run ({bandwidth:g} GB/s). Neither pass evaluates a
trigonometric function per sample: they read each sample's flat field as its transmission and the fringe's
quadratures, which the alignment makes once in place of its visibility and phase ({fringe} ns per sample, numpy's
single-precision cos and sin), turned by the phase channel with products alone. What the fit saves beyond that is
cost evaluations ({evaluations} per scan at the defaults, above)."""

ARITHMETIC = """\
The same kernels on one thread, over every row (the samples streamed from memory) and over a slab of middle rows
(at most {slab} MiB of samples, in the last-level cache), run again and again, the two alternated, best of each.
The slab changes the time by {change}:
{verdict} (a cost evaluation turns, solves and differentiates each sample; a retrieval solves each pixel twice,
reweighting in between, and sums its Pearson residuals). Within 3x of the floor would need that arithmetic
{need_cost} (cost) and {need_ret} (retrieval) faster than it runs from cache."""

ANCHOR = """\
The same scan as separate processes (start-up included), this version at its defaults against the paper's method
written plainly in numpy/scipy (`../shared/bench/reference_cli.py`, its fit on every 20th column), runs
alternated, medians of {runs}."""

DESIGN = """\
Design choices, each measured against its alternative in the same run (the comparisons above, and
`scripts/paper_figures.py fig6` below): Gauss-Newton steps on the profiled Fisher information against
L-BFGS alone; whitening by the whole profiled Fisher information against its diagonal (the paper's eq. 34)
and against no preconditioning; and fitting a subset of columns against every column. Iterations and cost
evaluations are logged by every reconstruction (`vibration fit: ... iterations, ... evaluations`)."""

REAL = """\
`../shared/data/real/tum-ipp-stepping`: {steps} steps of {rows} x {cols} counts from a photon-counting hybrid
pixel detector, imported losslessly as {dtype}. The step errors that the maximum-likelihood fit estimates form a
clean ramp: a stepping calibration error, the real step {excess:.1f} % longer than 2 pi / {steps}. The per-step
dose of the reference is flat to {dose:.0e}; dose is identifiable here only because pixels outside the gratings
carry no fringe ({outside} such pixels, outside the gratings and in module gaps, are found from the reference
visibility and are NaN in the images)."""

REAL_DIAGNOSIS = """\
`dfxcorr diagnose` of the sample series (report: `docs/real-ipp-diagnosis/`) starts at a reduced chi-square of
{initial:.4f}, adds {added} and ends at {final:.4f}, with {unexplained}. The noise is sub-Poisson, but not
uniformly: the hybrid detector's module boundaries are three-pixel-wide strips whose centre pixel carries about a
third of the Poisson variance and its neighbours two thirds (counts shared among inter-chip pixels). The classes
are found from the residuals themselves (detector columns and rows whose variance departs from the rest, grouped
by their variance ratio); the fit's and the retrieval's weights then use each pixel's factor (`load.pixel_noise`,
the `pixel_noise.tif` the report writes). The classes and their variance factors f:"""

DIAGNOSIS = """\
Each catalogue effect is simulated in a small scan ({pixel_mm:g} mm pixels, seed 11) at a realistic amplitude
and left out of the model (the paper's model, minus the effect where it is one of the paper's three); then the
amplitude is weakened until it is no longer named first. `reference_offset` and `position_error` are simulated
with tiled gratings and a flat field that is not linear along the scan (with a smooth flat field they are
absorbed by `phase_offset` and `curvature`); `electronic_noise` on a flat panel (2000 counts in the open beam, a
dark of 100, read noise not stated). Estimate: against the truth in brackets (per-frame effects: RMSE in the
effect's gauge, the first and last tenth of the frames left out). Images: RMSE of the differential phase (rad)
and of the dark field -ln v against the truth, before -> after the effect was added (the diagnosis's own fits).
Every row, with every amplitude and its cost: `docs/diagnosis-study.md`. Machine: {machine}."""

DIAGNOSIS_HOW = """\
How the decisions are made, and what the study's other cases show:

- **Each trial is judged on its own signatures.** The level of the residuals against the stated noise model is
  the noise model's signature, never a mean effect's. The noise model's gain and electronic variance are fitted
  together from the fit's own columns (where the per-frame parameters' leverage is known) and each is tested with
  the other profiled, so a gain error is not named electronic noise nor the other way round. Where the file holds
  the readout of rows that no frame lights at that time (a flat panel reads every row), those rows measure the
  electronic variance directly. Every trial of a mean, alignment or pixel effect settles the noise effects
  already in the model again on its own fit, so the decisions do not depend on the order in which a round tries
  the candidates (`diagnose.order`).
- **No proxies.** A catalogue effect has one size across the recording. Before a mean effect is added, its trial
  fit is tested for that: an efficient-score test of the alternative that its size differs between strata of the
  pixels (six by expected count, six by detector row). A candidate is refused as a proxy where that test is
  significant and its sizes span more than `diagnose.proxy_spread` times the shared fit's; its signature is then
  reported unexplained along that axis. `pixel_noise` and the gain are held to the same rule along the detector's
  rows and columns. `sample_motion` is localised: flagged pixels over 10 % of those scored, or scattered (grown by 2
  pixels along rows and columns, their largest group holds less than half of them), are no moving part of a sample
  and are reported as unexplained pixels. Where the final reduced chi-square stays above 2 the report says
  that the misfit is gross and names no physics for it.
- **Not identifiable is not the same as absent.** A significant effect that the acquisition cannot identify gets
  a trial refit first; if it explains the misfit and no identifiable effect explains as much, the report says so,
  names nothing in its place and lists the misfit as unexplained.
- **Background** needs a flat field that varies along the scan (in the study t^f changes by 30 % over the active
  area); with a uniform one it is reported not identifiable."""

COST = """\
Each command in a process of its own (its own peak resident memory, VmHWM), warm numba cache, the cases one
after another (the load average after each in the table); diagnose against reconstruct of the same scan, each run
three times alternated, the run of median time counting. Where the time goes, from each case's `test <effect>`
and `trial fits` timings (summed over the diagnosis's rounds) and the replication of its findings on halves of
the detector: the largest shares below.

The stepping case is above 5x because its reconstruction is little more than a closed-form retrieval: the fit of
5 frames' phase offset and tilt takes under a second on every column (0.1 s on the 32 columns that
`fit.target_uncertainty=0.0025` keeps, when the whole reconstruction takes 0.7 s and the ratio is about 17x),
while the diagnosis tests every catalogue effect in each round (four rounds there, three effects added), and
every test reads every sample at least once, so a round's tests alone take longer than the reconstruction.

On a scan larger than `diagnose.max_held_samples` the per-pixel tests (sample motion, pixel noise, reference
offset, the residual maps) see a band of contiguous columns in the middle of the detector, while the fit and the
residual signatures keep columns spread over the whole detector (`diagnose.max_samples`). Pixels outside the
band are not tested for motion nor for a noise class of their columns (row classes carry across); a moving part
of the sample there shows as an unexplained signature, not as `sample_motion` (a reconstruction's own motion mask
covers every pixel). The log, `report.md`, `residuals.png` and `diagnosis.json` (`tested_columns`) say which
columns were tested; `diagnose.max_held_samples` widens the band for whoever can spend the time and memory."""

EVALUATION = """\
`--method alternating` is alternating minimisation of the same cost (the paper's refs. [19]-[21]): closed-form
images, then Levenberg-Marquardt steps per frame. `--method correlation` is ref. [18] as Sec. III-D.2 describes
it: per-column correlation with virtual flat-field patterns, then a bisquare polynomial fit per frame, with no
visibility term. `--method none` applies no correction. The full page, with where the outcome differs from the
paper and why: `docs/evaluation.md`."""

IDENTIFIABILITY = """\
`dfxcorr/identify.py` counts the directions of an effect's parameters that carry no Fisher information once the
images are profiled out, beyond the effect's exact gauge. This reproduces the paper's Sec. II-F (per-frame
visibility loss in phase stepping: 4 extra null directions), and finds more. Per-step dose in a stepping series
where every pixel is modulated is not identifiable together with the step phases: the per-step vector
d_j (1, cos psi_j, sin psi_j) lies on a cone and the images absorb its Lorentz boosts, which gives 2 extra null
directions (a dose modulation in step with the phase). Pixels without fringe (outside the gratings) have
transmission as their only unknown and break the symmetry, so dfxcorr keeps them in the fit as dose monitors and
leaves them out of the images. An additive background is likewise not identifiable when t^f does not vary along
the scan. When the missing physics is itself not identifiable (real per-step visibility loss in stepping data),
its misfit remains, and with tilt in the model a weakly identifiable proxy such as dose can take up part of it:
the report then lists the true cause as not identifiable and the proxy as detected."""


def rounds_text(section: dict) -> str:
    """How a benchmark section's times were taken: the fastest of several rounds of every case in turn."""
    n = section.get("rounds", 1)
    return (f" Each case's time is its fastest of {n} rounds of every case in turn (the machine's speed drifts by"
            " 10-25 % within an hour; in turn, every case meets it alike)." if n > 1 else "")


def paper_study_section(p: dict) -> list[str]:
    if not p:
        return []
    dfv, img = p["dark_field_vs_true_parameters"], p["image_rmse_vs_truth"]
    r = p["rmse_vibration"]
    u, c, t = img["uncorrected"], img["corrected"], img["true parameters"]
    rows = [
        ["RMSE phi0 (rad)", "<= 0.004", f"{r['phase_offset']:.2g}"],
        ["RMSE phi1 (rad)", "<= 0.004", f"{r['tilt']:.2g}"],
        ["RMSE v^s", "<= 0.003", f"{r['visibility_loss']:.2g}"],
        ["dark field against the one retrieved with the true parameters: RMS difference / photon-noise RMS",
         "<= 0.15", f"{dfv['ratio']:.2g} ({dfv['rms_difference']:.2g} / {dfv['photon_noise_rms']:.3g})"],
        ["the same per pixel, in units of each pixel's photon noise (RMS z)", "<= 0.15",
         f"{dfv['per_pixel_rms_z']:.3g} (mean {dfv['per_pixel_mean_z']:.2g}: the v^s gauge, "
         f"{100 * (dfv['visibility_gauge_ratio'] - 1):.2f} % off the simulator's max = 1)"],
        ["reduced chi-square of the final model", "~1", f"{p['reduced_chi2']:.4f}"],
        ["image RMSE against the truth: uncorrected -> corrected (with the true parameters)", "",
         f"t {u['transmission']:.2g} -> {c['transmission']:.2g} ({t['transmission']:.2g}); "
         f"v {u['dark_field']:.3g} -> {c['dark_field']:.3g} ({t['dark_field']:.3g}); "
         f"phi {u['differential_phase']:.3g} -> {c['differential_phase']:.3g} ({t['differential_phase']:.3g})"],
    ]
    size = " x ".join(str(s) for s in p["size"])
    return ["", f"## The paper's simulation study ({size}, {p['pixel_mm']:g} mm pixels)", "",
            "`scripts/paper_study.py` -> `docs/paper-study.json`, `docs/paper-study.png`.", "",
            PAPER_STUDY.format(seed=p["seed"], frames=p["well_determined_frames"]), "",
            *table(["measure", "goal", "measured"], rows), "",
            "![uncorrected and corrected images of the simulated thorax](paper-study.png)", "",
            "The uncorrected dark-field and differential-phase images carry the vibration fringes; the corrected "
            "ones do not."]


def speed_section(bench: dict, base: dict, kern: dict) -> list[str]:
    out: list[str] = []
    clinical = bench.get("clinical", {})
    if clinical:
        rows = []
        for name, c in clinical["cases"].items():
            st = c["stages"]
            sets = f" ({', '.join(c['sets'])})" if c.get("sets") else ""
            rows.append([f"{name} {' x '.join(str(s) for s in c['size'])}{sets}", columns_text(c["columns"]),
                         f"{c['seconds']:g} s ({c['cpu_seconds']:g} s CPU)", f"{c['peak_rss_mb']} MB",
                         rmse3(c["rmse"]) + pulls_text(c), f"{c['iterations']} / {c['evaluations']}",
                         ", ".join(f"{k} {v:g}" for k, v in sorted(st.items(), key=lambda kv: -kv[1]) if v >= 0.1),
                         load_text(c.get("load_average"))])
        out += ["", "## Speed and memory", "", "### Clinical scans", "",
                "`scripts/benchmark.py clinical` -> `docs/benchmark.json`. Machine: " + clinical["machine"] + ".", "",
                SPEED + rounds_text(clinical), "",
                *table(["scan (defaults unless set)", "columns fitted", "wall time", "peak memory",
                        "RMSE phi0 / phi1 / v^s; pulls",
                        "iterations / cost evaluations", "stages (s)", "load"], rows)]
    paper = bench.get("paper", {})
    if paper:
        rows = [[name, columns_text(c["columns"]), f"{c['seconds']:g}", f"{c['stages']['fit']:g}",
                 f"{c['iterations']} / {c['evaluations']}", rmse3(c["rmse"]) + pulls_text(c),
                 f"{c['reduced_chi2']:.4f}", load_text(c.get("load_average"))] for name, c in paper["cases"].items()]
        out += ["", "### The paper's study: settings and optimisers", "",
                "`scripts/benchmark.py paper` -> `docs/benchmark.json`. Machine: " + paper["machine"] + ".", "",
                PAPER_CASES + rounds_text(paper), "",
                *table(["case", "columns fitted", "seconds", "fit (s)", "iterations / evaluations",
                        "RMSE phi0 / phi1 / v^s; pulls", "reduced chi2", "load"], rows)]
    if base:
        ref = base["reference"]
        rows = []
        for case, s in base["summary"].items():
            med, rss = s["median_seconds"], s["peak_rss_mib"]
            rows.append([case, f"{med['this checkout']:g} s, {rss['this checkout']} MiB",
                         f"{med[ref]:g} s, {rss[ref]} MiB", f"{s['ratio_this_over_ref']:.2f}"])
        runs = len(next(iter(base["runs"].values()))["this checkout"])
        out += ["", "### Against an earlier dfxcorr", "",
                "`scripts/bench_baseline.py` -> `docs/bench-baseline.json`. Machine: " + base["machine"] + ".", "",
                BASELINE.format(this=base["commit"][:7], ref=ref[:7], runs=runs), "",
                *table(["case", f"`{base['commit'][:7]}`", f"`{ref[:7]}`", "time ratio"], rows)]
    anc = bench.get("anchor")
    if anc:
        runs = anc["runs"]
        rows = []
        for who, label in (("dfxcorr", "this version, defaults"), ("anchor", "plain numpy/scipy, fit.subsample=20")):
            rmse = " / ".join(g(median([r["rmse"][k] for r in runs[who]]))
                              for k in ("phase_offset", "tilt", "visibility_loss"))
            cpu = median([r["cpu_seconds"] for r in runs[who]])
            rows.append([label, f"{anc['median_seconds'][who]:g} s", f"{cpu:g} s",
                         f"{max(r['peak_rss_mb'] for r in runs[who])} MB", rmse,
                         load_text(runs[who][-1].get("load_average"))])
        out += ["", "### Against the speed anchor", "",
                "`scripts/benchmark.py targets` -> `docs/benchmark.json`. Machine: " + anc["machine"] + ".", "",
                ANCHOR.format(runs=len(runs["dfxcorr"])), "",
                *table(["process", "wall time", "CPU time", "peak memory", "RMSE phi0 / phi1 / v^s", "load"], rows), "",
                f"Time ratio: {anc['ratio']:.2f}."]
    demo = bench.get("demo")
    if demo:
        out += ["", "### `dfxcorr demo`", "",
                "`scripts/benchmark.py demo` -> `docs/benchmark.json`, at load "
                f"{load_text(demo['load_average_at_start'])}: "
                f"{demo['cold']['seconds']:g} s ({demo['cold']['peak_rss_mb']} MB) with an empty numba cache, where "
                f"the kernels are compiled first; {demo['warm']['seconds']:g} s ({demo['warm']['peak_rss_mb']} MB) "
                "with the cache."]
    if kern:
        rows = []
        for key, label in (("paper_every_column", "paper study, every column"),
                           ("clinical_fit_columns", "clinical scan, the fit's columns")):
            k = kern[key]
            cg, rt = k["cost_gradient"], k["retrieval"]
            rows.append([label, *(f"{p['cpu_ns_per_sample']:g} / {p['ns_per_sample']:g} (floor "
                                  f"{p['floor_ns_per_sample']:g})" for p in (cg, rt)),
                         f"{k['fringe']['cpu_ns_per_sample']:g}"])
        pk = kern["paper_every_column"]["fringe"]
        evaluations = "-"
        if paper:
            evaluations = str(paper["cases"]["default"]["evaluations"])
        out += ["", "### Kernels", "",
                "`scripts/bench_kernels.py` -> `docs/bench-kernels.json`. Machine: " + kern["machine"]
                + f", load {load_text(kern['load_average_at_start'])}.", "",
                KERNELS.format(bandwidth=kern["copy_bandwidth_GB_per_s"], fringe=pk["cpu_ns_per_sample"],
                               evaluations=evaluations), "",
                *table(["samples", "cost + gradient (ns: CPU / wall)", "retrieval (ns: CPU / wall)",
                        "fringe quadratures, once (ns CPU)"], rows), "",
                *arithmetic_rows(kern), "",
                f"Compiling the kernels in a fresh numba cache: {kern['compile']['first_run_seconds']:g} s; loading "
                f"them from the cache: {kern['compile']['cached_run_seconds']:g} s."]
    if out:
        out += ["", DESIGN]
    return out


def arithmetic_rows(kern: dict) -> list[str]:
    """The kernels' single-thread times streamed and from cache (bench_kernels.py's arithmetic_share), if measured."""
    cases = [(label, kern[key]) for key, label in (("paper_every_column", "paper study, every column"),
                                                   ("clinical_fit_columns", "clinical scan, the fit's columns"))
             if "single_thread" in kern[key]]
    if not cases:
        return []
    rows, changes, need = [], [], {"cost_gradient": [], "retrieval": []}
    for label, k in cases:
        one = k["single_thread"]
        cells = [label + f" (slab of {one['slab_rows']} rows)"]
        for name in ("cost_gradient", "retrieval"):
            streamed, cached = one[name]["streamed_ns_per_sample"], one[name]["in_cache_ns_per_sample"]
            cells.append(f"{streamed:g} / {cached:g}")
            changes.append(cached / streamed - 1)
            need[name].append(cached / (3 * k[name]["floor_ns_per_sample"]))
        rows.append(cells)
    # what holding the samples in cache takes off a pass is the share memory has in it
    share = max(0.0, -100 * min(changes))
    verdict = (f"memory takes at most {share:.0f} % of either pass, so both are bound by their arithmetic"
               if share < 50 else f"memory takes up to {share:.0f} % of a pass, the rest is their arithmetic")
    slab = {one["single_thread"].get("slab_bytes", 1 << 22) for _, one in cases}
    text = ARITHMETIC.format(slab="/".join(f"{b / 2 ** 20:g}" for b in sorted(slab)),
                             change=f"{100 * min(changes):+.0f} % to {100 * max(changes):+.0f} %", verdict=verdict,
                             need_cost=span(need["cost_gradient"], "{:.1f}", "x"),
                             need_ret=span(need["retrieval"], "{:.1f}", "x"))
    return [text, "", *table(["samples", "cost + gradient, one thread: streamed / in cache (ns)",
                              "retrieval, one thread: streamed / in cache (ns)"], rows)]


def real_section(real: dict) -> list[str]:
    if not real:
        return []
    steps, rows, cols = real["shape"]
    errors = real["reference_step_errors_rad"]
    excess = 100 * linear_slope(errors) / (2 * math.pi / steps)
    dose = max(abs(d - 1) for d in real["reference_dose"]) if real.get("reference_dose") else float("nan")
    ref, smp = real["reference_chi2"], real["sample_chi2"]
    chi = [["reference (flat) series, grating area", f"{ref['nominal_steps']:.4f}", f"{ref['estimated_steps']:.4f}"],
           ["sample series, `reconstruct` (per-step phase_offset and tilt)", f"{smp['nominal_steps_everywhere']:.4f}",
            f"{smp['ml_phase_offset_tilt']:.4f}"]]
    sample_errors = real["sample_phase_offset_rad"]
    out = ["", "## A real phase-stepping recording", "",
           "`scripts/real_ipp.py` -> `docs/real-ipp.json`, `docs/real-ipp.png`, `docs/real-ipp-diagnosis/`.", "",
           REAL.format(steps=steps, rows=rows, cols=cols, dtype=real["dtype"], excess=excess, dose=dose,
                       outside=real["pixels_outside_gratings"]), "",
           *table(["reduced chi-square", "nominal steps (2 pi k / " + str(steps) + ")", "estimated step errors"], chi),
           "",
           f"Step errors: reference {errors[0]:+.3f} ... {errors[-1]:+.3f} rad, sample {sample_errors[0]:+.3f} ... "
           f"{sample_errors[-1]:+.3f} rad over the {steps} steps.", "",
           "![real recording: nominal against estimated steps](real-ipp.png)"]
    diag = real.get("diagnosis")
    if diag:
        named = [e for e in diag["effects"] if e.get("detected")]
        classes = [c for e in named for c in e.get("classes", [])]
        unexplained = ("nothing unexplained" if not diag["unexplained"] else
                       "unexplained: " + ", ".join(dict.fromkeys(u["axis"] for u in diag["unexplained"])))
        out += ["", REAL_DIAGNOSIS.format(initial=diag["reduced_chi2"]["initial"],
                                          final=diag["reduced_chi2"]["final"],
                                          added=", ".join(f"`{e['name']}`" for e in named) or "nothing",
                                          unexplained=unexplained), ""]
        out += table(["rows", "columns", "pixels", "f"],
                     [[c["rows"], c["columns"], c["pixels"], f"{c['factor']:.3g}"] for c in classes])
        rest = [e for e in diag["effects"] if not e.get("detected") and e.get("dof")]
        out += ["", "The other effects tested in the first round: "
                + "; ".join(f"{e['name']} p = {e['p_value']:.2g}" + ("" if e["identifiable"] else " (not identifiable)")
                            for e in rest) + "."]
    return out


def next_smaller(rows: list[dict], limit: float | None) -> str:
    """What the first amplitude past the detection limit gave (rows in the study's order: strongest first)."""
    at = [i for i, r in enumerate(rows) if r["amplitude"] == limit]
    if not at or at[-1] + 1 >= len(rows):
        return "found at every amplitude tried"
    r = rows[at[-1] + 1]
    if r["first"]:
        what = f"{r['first']} named instead"
    elif r["unexplained"]:
        what = f"nothing named, {axes(r)} unexplained"
    else:
        what = "nothing detected"
    return f"{r['amplitude']:g}: {what} (chi2 {r['final_chi2']:.4f})"


def diagnosis_section(study: dict) -> list[str]:
    if not study:
        return []
    by_effect: dict[str, list[dict]] = {}
    for r in study["concealed"]:
        by_effect.setdefault(r["effect"], []).append(r)
    rows = []
    for effect, runs in by_effect.items():
        top, limit = runs[0], study["limits"].get(effect)
        found = (f"{top['amplitude']:.6g}: {', '.join(top['found']) or 'nothing'}, "
                 f"{top['initial_chi2']:.4f} -> {top['final_chi2']:.4f}"
                 + (f", unexplained ({axes(top)})" if top["unexplained"] else ""))
        rows.append([effect, found, fmt_estimate(top), fmt_images(top),
                     "not found" if limit is None else f"{limit:g}", next_smaller(runs, limit)])
    clean = study["clean"]
    alarms = sum(bool(r["found"] or r["unexplained"]) for r in clean)
    uncat = study.get("uncatalogued", [])
    pairs = study.get("pairs", [])
    first = sum(runs[0]["first"] == effect for effect, runs in by_effect.items())
    costs = [r["cost_vs_reconstruct"] for r in study["concealed"] + clean + uncat + pairs]
    out = ["", "## Diagnosis on concealed effects", "",
           "`scripts/diagnose_study.py` -> `docs/diagnosis-study.json`, `docs/diagnosis-study.md`; the same cases "
           "are tests in `tests/analysis/` and `tests/effects/`.", "",
           DIAGNOSIS.format(pixel_mm=study["pixel_mm"], machine=study["machine"]), "",
           *table(["effect", "realistic amplitude: found, reduced chi2 initial -> final", "estimate (truth)",
                   "images: phase / dark-field RMSE before -> after", "weakest amplitude named first",
                   "next weaker"], rows), "",
           f"{first} of {len(by_effect)} effects are named first at their realistic amplitude. False alarms: "
           f"{alarms} of {len(clean)} clean scans with any detection or unexplained signature "
           f"({'; '.join(sorted(set(r['scan'] for r in clean)))}).", ""]
    if uncat:
        out += ["Detector effects in no catalogue (`simulate.UNCATALOGUED`) must end in `unexplained` with at most "
                "the noise model named on the way: "
                + "; ".join(f"{r['effect']} {r['amplitude']:g}: {', '.join(r['found']) or 'nothing'} named, "
                            f"{axes(r)} unexplained ({'as required' if r['ok'] else 'NOT as required'})"
                            for r in uncat) + ".", ""]
    if pairs:
        combos: dict[str, list[dict]] = {}
        for r in pairs:
            combos.setdefault(r["effect"], []).append(r)
        parts = []
        for name, runs in combos.items():
            ok = [r for r in runs if r["ok"]]
            text = f"{name} down to {amps(ok[-1])}" if ok else f"{name}: not at {amps(runs[0])}"
            if ok and len(ok) == len(runs):
                text += " (every level tried)"
            parts.append(text)
        out += [f"Two or three effects concealed at once, each named once and nothing else: {'; '.join(parts)}.",
                ""]
    out += [f"A diagnosis of these small scans took {min(costs):.1f} to {max(costs):.1f} times a `reconstruct` of "
            f"the same scan (median {median(costs):.1f}).", "", DIAGNOSIS_HOW]
    return out


def cost_section(cost: dict) -> list[str]:
    if not cost:
        return []
    labels = {"real": "shared 11-step recording", "paper": "paper's study 209 x 450 x 510",
              "stepping": "5-step 512 x 1536 flat-panel stepping, `--base none`",
              "clinical-binned": "clinical binned 195 x 1440 x 1440",
              "clinical-full": "clinical full resolution 195 x 2880 x 2880",
              "clinical-binned-scatter": "clinical binned with Compton scatter, s = 0.1"}
    rows, where = [], []
    for name, c in cost["cases"].items():
        rows.append([labels.get(name, name),
                     f"{c['time_ratio']:.2f}x ({c['diagnose_s']:.1f} s against {c['reconstruct_s']:.1f} s)",
                     f"{c['memory_ratio']:.2f}x ({c['diagnose_mb']:.0f} MB against {c['reconstruct_mb']:.0f} MB)",
                     load_text(c.get("load_average_after"))])
        parts = {("replication" if k.startswith("replication") else k.removeprefix("test ")): v
                 for k, v in c["diagnose_stages_s"].items()
                 if k.startswith(("test ", "replication")) or k == "trial fits"}
        top = sorted(parts.items(), key=lambda kv: -kv[1])[:4]
        where.append(f"- {labels.get(name, name)}: " + ", ".join(f"{k} {v:.1f} s" for k, v in top if v >= 0.05))
    return ["", "## What the diagnosis costs", "",
            "`scripts/diagnose_cost.py` -> `docs/diagnose-cost.json`. Machine: " + cost["machine"] + ".", "",
            COST, "",
            *table(["scan", "time: diagnose / reconstruct", "peak memory: diagnose / reconstruct",
                    "load after"], rows), "",
            "Where the time goes:", "", *where]


SCATTER_TWIN = """\
A small scan with physical Compton scatter (the simulator's superposition of the primary, nothing renormalised) is
diagnosed and reconstructed with the recommended settings, and with the simulator's exact scatter field as the
known offset; its twin, the same seeds without scatter, at the defaults. Error: RMS of ln v against the truth
(median difference removed). The shot-noise prediction is the Cramer-Rao ratio of ln v's variance with the scatter's
photons in each sample's Poisson variance to that without, from the noise-free counts (the script's docstring
derives it): what a correction that knew the scatter exactly would reach. Its levels sit slightly below the
measured errors (the twin's column: the differential phase is left out of the prediction)."""


def scatter_twin_section(twin: dict) -> list[str]:
    if not twin:
        return []
    runs, rows = twin["runs"], []
    for r in runs:
        e, q, pp = r["dark_field_error"], r["ratio_to_twin"], r["scatter_to_primary_per_pixel"]
        est, found = r["estimate"], ", ".join(r["found"]) or "nothing"
        if est:
            found += f"; s {est['s']:.4f} +- {est['s_se']:.4f}, {est['width_mm']:g} mm"
        rows.append([r["seed"], found, f"{q['recommended']:.2f}x ({e['recommended']:.4f})",
                     f"{q['exact_field']:.2f}x ({e['exact_field']:.4f})", f"{r['shot_noise_prediction']['ratio']:.2f}x",
                     f"{q['uncorrected']:.2f}x", f"{e['twin']:.4f} ({r['shot_noise_prediction']['twin_error']:.4f})",
                     f"{r['scatter_to_primary_in_band']:.3f}; {pp['p10']:.2f} / {pp['p50']:.2f} / {pp['p90']:.2f}"])
    apart = max(abs(r["dark_field_error"]["recommended"] / r["dark_field_error"]["exact_field"] - 1) for r in runs)
    return ["", "## Physical scatter against its scatter-free twin", "",
            f"`scripts/scatter_twin.py` -> `docs/scatter-twin.json`. Machine: {twin['machine']}.", "",
            f"Scatter s = {twin['scatter']:g} per unit primary under a {twin['width_mm']:g} mm kernel, "
            f"{twin['pixel_mm']:g} mm pixels, scan {' x '.join(str(n) for n in runs[0]['shape'])}.",
            SCATTER_TWIN, "",
            f"Goal: the recommended reconstruction's dark-field error within {twin['goal_ratio']:g}x of the twin's. "
            f"Measured {span([r['ratio_to_twin']['recommended'] for r in runs], '{:.2f}', 'x')}; with the exact "
            f"field {span([r['ratio_to_twin']['exact_field'] for r in runs], '{:.2f}', 'x')} (the recommended "
            f"settings within {100 * apart:.1f} % of it); predicted from the scatter's shot noise alone "
            f"{span([r['shot_noise_prediction']['ratio'] for r in runs], '{:.2f}', 'x')}.", "",
            *table(["seed", "diagnosis", "recommended: dark-field error / twin's", "exact field", "shot-noise "
                    "prediction", "uncorrected", "twin's error (predicted)", "scatter / primary: band; pixels "
                    "p10 / p50 / p90"], rows)]


PARALLAX = """
Each kappa's scan (a source that travels with the gratings; the simulator evaluates the phantom where each frame
sees it) is diagnosed, then reconstructed at the defaults and with the recommended `geometry.parallax`; its twin
(the same seeds, no parallax) at the defaults. Errors against the truth where the sample transmits more than 5 %:
transmission, ln dark field and differential phase (offsets removed). The images live on the pixel grid: what a
pixel sees between two rows is their interpolation, while the sample's edges move across it by fractions of a row.
The floor below is what that interpolation misses of the exactly displaced phantom, in photon-noise units at the
scan's flux: no model on the pixel grid returns such a scan to the noise, and the same error biases kappa. The images
are held where each pixel sees the sample with the active area centred on it, and resampled to the detector's rows
for the result: the last column compares the transmission on that grid with the phantom evaluated there, and that
exact phantom, resampled to rows as the result is, with the truth (an error of the resampling alone)."""


def parallax_section(par: dict) -> list[str]:
    if not par:
        return []
    rows = []
    for r in par["runs"]:
        d = r["diagnose"]
        kappa = f"{d['kappa']:.4f} +- {d['se']:.4f}" if d["se"] is not None else "-"

        def cell(rec: dict) -> str:
            e = rec["errors"]
            return (f"{rec['reduced_chi2']:.3f}; {e['transmission']:.4f} / {e['ln_dark_field']:.3f} / "
                    f"{e['differential_phase']:.3f}; {rec['vibration_rmse']['phase_offset']:.4f} "
                    f"({rec['vibration_pulls']['phase_offset']:.2f}); {rec['seconds']:.0f} s")

        grid = r.get("transmission_at_true_kappa")
        rows.append([f"{r['kappa']:g}", ", ".join(d["found"]) or "nothing", kappa,
                     f"{d['reduced_chi2'][0]:.3f} -> {d['reduced_chi2'][1]:.3f}", ", ".join(d["unexplained"]) or "-",
                     cell(r["defaults"]), cell(r["recommended"]), cell(r["twin"]),
                     f"{grid['on_grid']:.4f} / {grid['resampled_truth']:.4f}" if grid else "-"])
    floor = ", ".join(f"{k} row: {v:.2f}" for k, v in par["interpolation_z2"].items())
    if "interpolation_z2_cubic" in par:
        floor += " (linear, the model's); with cubic convolution between four rows " + ", ".join(
            f"{k} row: {v:.2f}" for k, v in par["interpolation_z2_cubic"].items())
    scale = [f"Displacements of up to 0.3 rows as the interpolation between rows predicts them, against the exact "
             f"pixels: x{par['interpolation_scale']['linear']:.3f} (linear, the model's: a kappa whose displacements "
             f"stay within a fraction of a row is found about that factor low), "
             f"x{par['interpolation_scale']['cubic convolution']:.3f} with cubic convolution."
             ] if "interpolation_scale" in par else []
    if "cells_z2" in par:
        scale.append("Images finer than the pixel grid, m cells per row, each pixel the mean of the cells under it "
                     "where the frame sees it, fitted to every displacement of -0.3 to 0.3 rows at once (m = 1 is "
                     "the model's reading between rows): mean z^2 " + ", ".join(
                         f"m = {m}: {v:.3f}" for m, v in par["cells_z2"].items()) + ".")
    return ["", "## Beam paths that change during the scan", "",
            f"`scripts/parallax.py` -> `docs/parallax.json`. Machine: {par['machine']}. {par['pixel_mm']:g} mm "
            f"pixels, scan {' x '.join(str(n) for n in par['runs'][0]['shape'])}, flux {par['flux']:g}.", PARALLAX, "",
            f"Interpolation floor (mean z^2 of the transmission alone, per displacement): {floor}.", *scale, "",
            *table(["kappa", "diagnosis names", "kappa found", "diagnosis chi-square", "unexplained",
                    "defaults: chi-square; errors t / ln v / phi; phi0 RMSE (pull); time", "recommended", "twin",
                    "t error at the true kappa: on the images' grid / the exact phantom there, resampled to rows"],
                   rows)]


def uncertainty_columns_section(rec: dict) -> list[str]:
    """The between-rows uncertainty from standing columns against every column's (scripts/uncertainty_columns.py)."""
    if not rec:
        return []
    rows, times = [], []
    for name, r in rec["scans"].items():
        scan = f"{name}, {' x '.join(str(n) for n in r['shape'])}"
        for effect, q in r["ratio"].items():
            rows.append([scan, effect, f"{r['standing_columns']} of {r['columns']}", f"{q['median']:.4f}",
                         f"{q['min']:.4f}-{q['max']:.4f}", f"{q['rms_deviation']:.4f}",
                         f"{q['frames']} ({q.get('finite_in_one_only', 0)})"])
        times.append(f"{scan}: {r['seconds']['standing']:.2f} s from the standing columns, "
                     f"{r['seconds']['every column']:.2f} s from every column"
                     + (f" (load {r['load_average']:g})" if "load_average" in r else ""))
    return ["", "### The uncertainty between rows from standing columns", "",
            f"`scripts/uncertainty_columns.py` -> `docs/uncertainty-columns.json`. Machine: {rec['machine']}. "
            f"Simulated with kappa = {rec['parallax']:g} and reconstructed with it: each frame's standard error "
            "from the columns spread by their information, each standing for its stratum, over that from every "
            "column (frames finite in both; in brackets, those finite in only one).", "",
            *table(["scan", "effect", "columns", "median", "range", "rms deviation from 1", "frames"], rows), "",
            "Seconds of one computation each: " + "; ".join(times) + "."]


def evaluation_section(docs: Path) -> list[str]:
    tab = read(docs, "table-1mm.json")
    if not tab:
        return []
    rows = [[m["method"], f"{m['reduced_chi2']:.4g}", f"{m['rmse_phase_offset']:.2g}", f"{m['rmse_tilt']:.2g}",
             f"{m['rmse_visibility_loss']:.2g}", f"{m['rmse_dark_field']:.3g}"] for m in tab["table-1mm"]]
    out = ["", "## Baselines and the paper's evaluation", "",
           "`scripts/paper_figures.py` -> `docs/table-*.json`, `docs/fig*.json` and their pictures.", "",
           EVALUATION, "",
           f"The paper's study at {tab['pixel_mm']:g} mm (RMSE against the truth, frames lighting at least half the "
           "active area):", "",
           *table(["method", "reduced chi2", "RMSE phi0 (rad)", "RMSE phi1 (rad)", "RMSE v^s", "RMSE dark field"],
                  rows), ""]
    items = []
    f6, f62 = read(docs, "fig6-1mm.json"), read(docs, "fig6-2.5mm.json")
    if f6:
        m = f6["methods"]
        pre, plain, alt = (m.get(k, {}).get("iterations_to_excess_1") for k in
                           ("ML, preconditioned (eq. 34)", "ML, not preconditioned", "alternating"))
        text = (f"**Fig. 6** (every column): to come within 1 of the optimum, ML takes {pre} iterations "
                f"preconditioned (eq. 34) and {plain} without; alternating takes {alt}.")
        prof = [v for k, v in f62.get("methods", {}).items() if "profiled" in k]
        diag = f62.get("methods", {}).get("ML, preconditioned (eq. 34)")
        if prof and diag:
            text += (f" At 2.5 mm, whitening by the whole profiled Fisher information (the default) takes "
                     f"{prof[0]['iterations_to_excess_1']} against the diagonal's {diag['iterations_to_excess_1']}.")
        items.append(text)
    f7 = read(docs, "fig7-1mm.json")
    if f7:
        items.append("**Fig. 7**: dark-field RMSE " + " -> ".join(f"{v:.3g} ({k})" for k, v in
                                                                  f7["dark_field_rmse"].items()) + ".")
    f8 = read(docs, "fig8-1mm.json")
    if f8:
        v = f8["vibration_rmse"]
        items.append(f"**Fig. 8**: the correlation method's phi0 error on the thorax is "
                     f"{v['thorax, correlation']['phase_offset']:.2g} rad against ML's "
                     f"{v['thorax, ml']['phase_offset']:.2g}; on a sample of constant attenuation "
                     f"{v['constant attenuation, correlation']['phase_offset']:.2g} rad.")
    f11 = read(docs, "fig11-1mm.json")
    if f11:
        p = f11["fig11-nps-1mm"]["power"]
        items.append("**Fig. 11**: in the noise power spectra of blank dark-field images (`dfxcorr nps`), ML is at "
                     f"the level of the other frequencies at the fringe frequency f and at 2f "
                     f"({p['ml']['fringe']:.2g} and {p['ml']['harmonic']:.2g} against {p['ml']['other']:.2g}); "
                     f"correlation leaves {p['correlation']['fringe'] / p['ml']['fringe']:.0f} and "
                     f"{p['correlation']['harmonic'] / p['ml']['harmonic']:.0f} times ML's power there.")
    out += [f"- {t}" for t in items]
    shared = _shared_table(docs)
    if shared:
        ml = [m for m in shared["methods"] if m["method"] == "ml"][0]
        out += ["", f"The independent simulator's thorax ({shared['scan'].split(' (')[0]}) loads as it is; the same "
                "comparison "
                f"there: ML at RMSE {ml['rmse_phase_offset']:.2g} / {ml['rmse_tilt']:.2g} / "
                f"{ml['rmse_visibility_loss']:.2g}, reduced chi-square {ml['reduced_chi2']:.4f} "
                "(`docs/table-shared-thorax-2.5mm/`)."]
    return out


def _shared_table(docs: Path) -> dict:
    path = docs / "table-shared-thorax-2.5mm" / "table.json"
    return json.loads(path.read_text()) if path.is_file() else {}


PULLS = """\
The pull of a frame is its phi0 (or phi1) error against the truth over the standard error the fit reports, the
truth carried into the estimate's gauge by their median difference over the frames lighting half the active area;
the RMS of the pulls is 1 where the error bars are right. Each put in its own median gauge instead (as the RMSE
figures of these pages are), both medians fall on one frame, whose error every other frame then carries: pulls of
1.16-1.38 on these scans, from the comparison, not from the error bars. Neighbouring frames share pixels, so their
errors are correlated and one scan's RMS varies between noise realisations: each case is simulated with several
seeds and the pulls are pooled over all their frames."""


def pulls_section(rec: dict) -> list[str]:
    if not rec:
        return []
    rows = []
    for case, settings in rec["cases"].items():
        for label, r in settings.items():
            per = ", ".join(f"{p['phase_offset']:.2f} / {p['tilt']:.2f}" for p in r["per_seed"])
            rmse = " / ".join(f"{median([e[k] for e in r['rmse']]):.5f}" for k in ("phase_offset", "tilt"))
            rows.append([case, label, f"{r['pooled']['phase_offset']:.2f} / {r['pooled']['tilt']:.2f}", per, rmse])
    return ["", "### Error bars: pulls over noise realisations", "",
            f"`scripts/pulls.py` -> `docs/pulls.json`. Machine: {rec['machine']}. Seeds {rec['seeds']}.", "",
            PULLS, "",
            *table(["case", "setting", "pooled pulls phi0 / phi1", "per seed", "median RMSE phi0 / phi1 (rad)"], rows)]


def measurements(docs: Path) -> str:
    """The text of docs/measurements.md."""
    bench, base = read(docs, "benchmark.json"), read(docs, "bench-baseline.json")
    kern = read(docs, "bench-kernels.json")
    lines = [INTRO]
    lines += paper_study_section(read(docs, "paper-study.json"))
    lines += speed_section(bench, base, kern)
    lines += pulls_section(read(docs, "pulls.json"))
    lines += real_section(read(docs, "real-ipp.json"))
    lines += diagnosis_section(read(docs, "diagnosis-study.json"))
    lines += cost_section(read(docs, "diagnose-cost.json"))
    lines += scatter_twin_section(read(docs, "scatter-twin.json"))
    lines += parallax_section(read(docs, "parallax.json"))
    lines += uncertainty_columns_section(read(docs, "uncertainty-columns.json"))
    lines += evaluation_section(docs)
    lines += ["", "## Identifiability, found rather than assumed", "", IDENTIFIABILITY]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------------------------
# README.md's table


def readme_table(docs: Path) -> str:
    """The rows of README.md's table of what dfxcorr achieves, from the same JSON."""
    bench = read(docs, "benchmark.json")
    real, study = read(docs, "real-ipp.json"), read(docs, "diagnosis-study.json")
    cost = read(docs, "diagnose-cost.json")
    rows = []
    paper = bench.get("paper", {}).get("cases", {})
    if "default" in paper:
        d = paper["default"]
        speed, script = f"{d['seconds']:g} s in memory", "`benchmark.py paper`"
        anc = bench.get("anchor")
        if anc:
            mine = anc["runs"]["dfxcorr"]
            speed = (f"{anc['median_seconds']['dfxcorr']:g} s, {max(r['peak_rss_mb'] for r in mine)} MB "
                     f"({anc['ratio']:.2f}x the time of the plain numpy/scipy method, load "
                     f"{load_text(mine[-1].get('load_average'))})")
            script += ", `benchmark.py targets`"
        every = paper.get("every column")
        level = "every column's: the Cramer-Rao level"
        if every and any(d["rmse"][k] > 1.1 * every["rmse"][k] for k in ("phase_offset", "tilt")):
            level = f"fit.target_uncertainty; every column: {rmse3(every['rmse'])}, the Cramer-Rao level"
        rows.append(["paper's study, 209 x 450 x 510, defaults", f"RMSE phi0 / phi1 / v^s {rmse3(d['rmse'])} "
                     f"({level}){pulls_text(d)}, reduced chi2 {d['reduced_chi2']:.4f}", speed, script])
    clinical_cases = bench.get("clinical", {}).get("cases", {})
    for name, c in clinical_cases.items():
        size = " x ".join(str(s) for s in c["size"])
        scan = c.get("scan", name)
        if scan != name and not c.get("accuracy_counts", False):
            # another case's scan with a setting it was simulated without: its accuracy says nothing, its cost does
            base_case = clinical_cases.get(scan)
            if base_case:
                rows.append([f"clinical {scan}, {size}, with {', '.join(c.get('sets', []))} (its scan has "
                             "none: what the setting costs)", "-",
                             f"{c['seconds']:g} s against {base_case['seconds']:g} s "
                             f"(x{c['seconds'] / base_case['seconds']:.2f}), {c['peak_rss_mb']} MB",
                             "`benchmark.py clinical`"])
            continue
        setting = f"with {', '.join(c['sets'])}" if c.get("sets") else "defaults"
        rows.append([f"clinical {'full resolution' if scan == 'full' else scan}, {size}, {setting}",
                     f"RMSE {rmse3(c['rmse'])}{pulls_text(c)}",
                     f"{c['seconds']:g} s, {c['peak_rss_mb']} MB (load {load_text(c.get('load_average'))})",
                     "`benchmark.py clinical`"])
    if real:
        diag = real.get("diagnosis", {})
        named = ", ".join(e["name"] for e in diag.get("effects", []) if e.get("detected")) or "nothing"
        rc = cost.get("cases", {}).get("real")
        rows.append([f"real {real['shape'][0]}-step recording, {real['shape'][1]} x {real['shape'][2]}",
                     f"reduced chi2 {real['sample_chi2']['nominal_steps_everywhere']:.4f} (nominal steps) -> "
                     f"{real['sample_chi2']['ml_phase_offset_tilt']:.4f} (per-step errors fitted); `diagnose` names "
                     f"{named}: {diag['reduced_chi2']['initial']:.4f} -> {diag['reduced_chi2']['final']:.4f}",
                     "-" if not rc else f"reconstruct {rc['reconstruct_s']:.1f} s, {rc['reconstruct_mb']:.0f} MB",
                     "`real_ipp.py`"])
    if study:
        tops: dict[str, dict] = {}
        for r in study["concealed"]:
            tops.setdefault(r["effect"], r)
        at_realistic = sum(r["first"] == e for e, r in tops.items())
        alarms = sum(bool(r["found"] or r["unexplained"]) for r in study["clean"])
        combos: dict[str, dict] = {}
        for r in study.get("pairs", []):
            combos.setdefault(r["effect"], r)
        combos_ok = [r for r in combos.values() if r["ok"]]
        costs = [r["cost_vs_reconstruct"] for key in ("concealed", "clean", "uncatalogued", "pairs")
                 for r in study.get(key, [])]
        rows.append([f"diagnosis study, {study['pixel_mm']:g} mm scans with one effect left out of the model",
                     f"{at_realistic} of {len(tops)} catalogue effects named first at a realistic amplitude "
                     "(detection limits in docs/measurements.md); "
                     f"{alarms} false alarms on {len(study['clean'])} clean scans; "
                     f"{len(combos_ok)} of {len(combos)} combinations of two or three effects named exactly at "
                     "realistic amplitudes",
                     f"`diagnose` {min(costs):.1f}-{max(costs):.1f}x a `reconstruct` (median {median(costs):.1f})",
                     "`diagnose_study.py`"])
    if cost:
        cases = cost["cases"]
        goal = [c for n, c in cases.items() if n != "clinical-binned-scatter"]
        t = [c["time_ratio"] for c in goal]
        m = [c["memory_ratio"] for c in goal]
        rows.append([f"`diagnose` against `reconstruct`, {len(goal)} scans (recording, paper, stepping, clinical)",
                     "", f"{min(t):.2f}-{max(t):.2f}x the time, {min(m):.2f}-{max(m):.2f}x the peak memory",
                     "`diagnose_cost.py`"])
    machine = bench.get("clinical", {}).get("machine") or bench.get("paper", {}).get("machine", "")
    return "\n".join(table(["case", "accuracy", "speed and memory", "script (`scripts/`)"], rows)
                     + ["", f"Machine: {machine}; loads and every other measurement: `docs/measurements.md`."])


def with_readme_table(readme: str, docs: Path) -> str:
    """README.md's text with its generated table replaced."""
    if BEGIN not in readme or END not in readme:
        raise SystemExit(f"README.md lacks the markers {BEGIN!r} and {END!r}")
    head, rest = readme.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{BEGIN}\n{readme_table(docs)}\n{END}{tail}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--docs", type=Path, default=ROOT / "docs")
    ap.add_argument("--readme", type=Path, default=ROOT / "README.md")
    ap.add_argument("--check", action="store_true", help="write nothing; exit code 1 if a page is out of step")
    args = ap.parse_args()
    pages = {args.docs / PAGE: measurements(args.docs),
             args.readme: with_readme_table(args.readme.read_text(), args.docs)}
    stale = [path for path, text in pages.items() if not path.is_file() or path.read_text() != text]
    if args.check:
        for path in stale:
            print(f"{path}: out of step with the JSON in {args.docs}; run scripts/docs_pages.py", file=sys.stderr)
        return 1 if stale else 0
    for path in stale:
        path.write_text(pages[path])
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
