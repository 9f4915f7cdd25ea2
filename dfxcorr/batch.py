"""Batches of scans: one independent process per scan, resumable, locally or as a SLURM job array.

A list file holds one scan path per line. Each scan is reconstructed by its own ``dfxcorr
reconstruct`` process into ``OUTDIR/<scan stem>.h5`` with its log beside it (``<stem>.log``). A
result that already exists is complete (results are written atomically), so a batch that was stopped
is resumed by running it again: a result is kept where its provenance names the same scan contents
(SHA-256) and its configuration is the batch's, and re-run (replaced) where either changed. One
failed scan never stops the others. A result whose reduced chi-square lies outside what noise allows
is done, but flagged in the summary.

On a cluster the same list is a job array: ``--array-index N`` (default ``SLURM_ARRAY_TASK_ID``)
processes the scan on line N of the list (counted from 1 as ``sed -n Np`` does) and exits with its
status, so the scheduler sees which task failed (``scripts/slurm-array.sh``).
"""
from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import h5py
import yaml

from . import config as C
from .errors import DfxcorrError, require_regular_file

log = logging.getLogger(__name__)


class BatchError(DfxcorrError):
    """A list file or output folder that a batch cannot use."""


@dataclass(frozen=True)
class Job:
    """One scan of a batch.

    Attributes
    ----------
    line : int
        Line of the list file (from 1).
    scan : Path
    result : Path
        ``OUTDIR/<stem>.h5``.
    log : Path
        ``OUTDIR/<stem>.log``.
    """

    line: int
    scan: Path
    result: Path
    log: Path


@dataclass(frozen=True)
class Outcome:
    """What became of one job: status 'done', 'skipped' (result existed) or 'failed'.

    ``misfit``: the result's reduced chi-square lies outside what noise allows; ``note``: why a result that existed
    was re-run.
    """

    job: Job
    status: str
    seconds: float = 0.0
    reduced_chi2: float | None = None
    error: str = ""
    misfit: bool = False
    note: str = ""


def read_list(path: str | os.PathLike) -> list[tuple[int, str]]:
    """Lines of a list file as (line number from 1, text); blank lines and ``#`` comments are kept out.

    Raises
    ------
    BatchError
        If the file cannot be read as UTF-8 text or names no scan.
    """
    path = Path(path)
    require_regular_file(path, "scan list")
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise BatchError(f"{path}: cannot read the scan list ({exc})") from None
    entries = [(n, text.strip()) for n, text in enumerate(lines, start=1)
               if text.strip() and not text.lstrip().startswith("#")]
    if not entries:
        raise BatchError(f"{path}: the scan list names no scan")
    return entries


def plan(entries: list[tuple[int, str]], out_dir: str | os.PathLike) -> list[Job]:
    """Jobs for the listed scans, results named by the scan file's stem.

    Raises
    ------
    BatchError
        If two scans share a stem (their results would collide) or a scan is listed twice.
    """
    out_dir = Path(out_dir)
    jobs: list[Job] = []
    seen: dict[str, int] = {}
    for line, text in entries:
        scan = Path(text)
        stem = scan.stem
        if stem in seen:
            raise BatchError(f"lines {seen[stem]} and {line} of the scan list both give results named {stem}.h5; "
                             f"rename one scan or run them in separate output folders")
        seen[stem] = line
        jobs.append(Job(line=line, scan=scan, result=out_dir / f"{stem}.h5", log=out_dir / f"{stem}.log"))
    return jobs


def select_line(entries: list[tuple[int, str]], index: int, *,
                list_name: str = "the scan list") -> list[tuple[int, str]]:
    """The entry on line ``index`` (from 1, as ``sed -n Np``), for one task of a job array.

    Raises
    ------
    BatchError
        If that line is missing, blank or a comment.
    """
    for line, text in entries:
        if line == index:
            return [(line, text)]
    raise BatchError(f"array index {index}: line {index} of {list_name} names no scan")


def is_complete(path: Path) -> bool:
    """True if ``path`` is a dfxcorr results file (written atomically, so present means complete)."""
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
    except (OSError, ValueError):
        return False
    return (fmt.decode() if isinstance(fmt, bytes) else fmt) == "dfxcorr-result"


def result_chi2(path: Path) -> tuple[float | None, bool]:
    """Reduced chi-square stored in a results file (None if it cannot be read), and whether it is marked a misfit."""
    try:
        with h5py.File(path, "r") as f:
            fit = f["entry/dfxcorr/fit"]
            return float(fit["reduced_chi2"][()]), bool(fit["misfit"][()]) if "misfit" in fit else False
    except (OSError, KeyError, ValueError, TypeError):
        return None, False


def changed(job: Job, cfg: dict) -> str:
    """Why the existing result of ``job`` is not the one this batch would write ('' where it is): its scan's
    contents (the SHA-256 its provenance holds) or its resolved configuration differ."""
    from .pipeline import sha256

    try:
        with h5py.File(job.result, "r") as f:
            proc = f["entry/dfxcorr"]
            digest = proc["input_sha256"].asstr()[()]
            stored = yaml.safe_load(proc["configuration"].asstr()[()])
    except (OSError, KeyError, ValueError, TypeError, yaml.YAMLError):
        return "its provenance cannot be read"
    if stored != cfg:
        return "the configuration changed"
    if digest != sha256(job.scan):
        return "the scan changed"
    return ""


def threads_per_job(n_jobs: int, *, cores: int | None = None) -> int:
    """Cores each of ``n_jobs`` concurrent processes may use (SLURM_CPUS_PER_TASK, else the machine's)."""
    total = cores or int(os.environ.get("SLURM_CPUS_PER_TASK") or 0) or os.cpu_count() or 1
    return max(1, total // max(n_jobs, 1))


def command(job: Job, *, config_files=(), sets=(), overwrite: bool = False) -> list[str]:
    """The ``dfxcorr reconstruct`` command line of one job (the same entry point as a user would type)."""
    exe = shutil.which("dfxcorr")
    base = [exe] if exe else [sys.executable, "-c", "from dfxcorr.cli import main; main()"]
    cmd = base + ["--log-file", str(job.log), "reconstruct", str(job.scan), "-o", str(job.result)]
    cmd += ["--overwrite"] if overwrite else []
    for c in config_files:
        cmd += ["-c", str(c)]
    for s in sets:
        cmd += ["--set", s]
    return cmd


def run_job(job: Job, *, config_files=(), sets=(), threads: int = 1) -> Outcome:
    """Reconstruct one scan in its own process; a finished result of the same scan and configuration is skipped,
    one of another scan or configuration re-run (:func:`changed`).

    The child's standard error (one line on refusal, a traceback on a crash) is appended to the job's
    log, and its last line becomes the outcome's error.
    """
    note = ""
    if is_complete(job.result):
        note = changed(job, C.load(config_files, sets))
        if not note:
            chi2, misfit = result_chi2(job.result)
            return Outcome(job, "skipped", reduced_chi2=chi2, misfit=misfit)
        log.info("%s: re-run, %s since %s was written", job.scan, note, job.result)
        note = f"re-run: {note}"
    env = dict(os.environ, NUMBA_NUM_THREADS=str(threads), OMP_NUM_THREADS=str(threads),
               SLURM_CPUS_PER_TASK=str(threads))
    t0 = time.perf_counter()
    proc = subprocess.run(command(job, config_files=config_files, sets=sets, overwrite=bool(note)), env=env,
                          stdin=subprocess.DEVNULL, capture_output=True, text=True, errors="replace", check=False)
    seconds = time.perf_counter() - t0
    if proc.returncode == 0:
        chi2, misfit = result_chi2(job.result)
        return Outcome(job, "done", seconds, chi2, misfit=misfit, note=note)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    error = lines[-1] if lines else f"exit code {proc.returncode}"
    if job.log.parent.is_dir():
        with open(job.log, "a", encoding="utf-8") as fh:
            fh.write(proc.stderr)
    return Outcome(job, "failed", seconds, error=f"{error} (exit code {proc.returncode})", note=note)


def run_batch(jobs: list[Job], *, config_files=(), sets=(), n_jobs: int = 1, on_done=None) -> list[Outcome]:
    """Run every job, ``n_jobs`` processes at a time, in list order of completion reporting.

    Parameters
    ----------
    jobs : list of Job
    config_files, sets
        Passed to every ``dfxcorr reconstruct`` as ``-c`` and ``--set``.
    n_jobs : int
        Scans processed at once; each gets an equal share of the cores.
    on_done : callable, optional
        Called with each :class:`Outcome` as it finishes (progress lines).

    Returns
    -------
    list of Outcome
        In the order of ``jobs``.
    """
    threads = threads_per_job(n_jobs)

    def one(job):
        outcome = run_job(job, config_files=config_files, sets=sets, threads=threads)
        if on_done is not None:
            on_done(outcome)
        return outcome

    with ThreadPoolExecutor(max_workers=max(1, n_jobs)) as pool:
        return list(pool.map(one, jobs))


def summary(outcomes: list[Outcome]) -> str:
    """A plain-text table: scan, status, time (s), reduced chi-square (marked 'misfit' where it lies outside what
    noise allows), and the error or why an existing result was re-run."""
    rows = [("scan", "status", "time_s", "reduced_chi2", "notes")]
    for o in outcomes:
        chi2 = "-" if o.reduced_chi2 is None else f"{o.reduced_chi2:.4f}" + (" misfit" if o.misfit else "")
        rows.append((str(o.job.scan), o.status, f"{o.seconds:.1f}" if o.status != "skipped" else "-", chi2,
                     "; ".join(t for t in (o.note, o.error) if t)))
    widths = [max(len(r[k]) for r in rows) for k in range(4)]
    lines = ["  ".join(r[k].ljust(widths[k]) for k in range(4)) + ("  " + r[4] if r[4] else "") for r in rows]
    counts = {s: sum(o.status == s for o in outcomes) for s in ("done", "skipped", "failed")}
    misfits = sum(o.misfit for o in outcomes if o.status != "failed")
    lines.append(f"{len(outcomes)} scans: {counts['done']} done, {counts['skipped']} skipped, "
                 f"{counts['failed']} failed" + (f"; {misfits} marked misfit (reduced chi-square outside what "
                                                 f"noise allows: run dfxcorr diagnose on it)" if misfits else ""))
    return "\n".join(line.rstrip() for line in lines)
