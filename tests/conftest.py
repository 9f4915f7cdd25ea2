"""Shared helpers of the tests: small simulated scans, ../shared/data, tolerances, the capped command line.

Commands run in a forked child under an address-space cap (never in the pytest process itself): the cap is
the child's address space at the fork plus a budget, so a run that reads what a hostile file declares rather
than what it holds shows up as a MemoryError."""
from __future__ import annotations

import multiprocessing
import os
import resource
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dfxcorr import config as C
from dfxcorr import model as M
from dfxcorr import preparation
from dfxcorr.align import build_observations
from dfxcorr.catalogue import MEAN_EFFECTS, effect
from dfxcorr.effects import REGISTRY
from dfxcorr.io import Reference, Scan
from dfxcorr.sim import simulate as S

#: The project's root (the checkout these tests belong to).
ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"


def shared_path(*parts) -> Path:
    """A path under ../shared/data, skipping the test where it is absent (a fresh clone)."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"{p} is absent")
    return p


def real_ipp_scan(tmp_path) -> Path:
    """The shared real phase-stepping recording imported into ``tmp_path / 'ipp.h5'`` (skips where it is absent)."""
    from dfxcorr.importer import import_stepping

    folder = shared_path("real", "tum-ipp-stepping")
    import_stepping(tmp_path / "ipp.h5", sample=str(folder / "data_stepping_*.npy"),
                    reference=str(folder / "flat_stepping_*.npy"), steps_per_period=11)
    return tmp_path / "ipp.h5"


def prepare(scan, cfg: dict, **kw) -> preparation.Prepared:
    """:func:`dfxcorr.preparation.prepare` with every registered effect's configured correction, as reconstruct does."""
    return preparation.prepare(scan, cfg, effects=REGISTRY.values(), **kw)


def sim_config(**overrides) -> dict:
    """A small scan: 5 mm pixels (90 x 102), active area 15 rows moving 1 row per frame (104 frames).

    ``overrides`` are 'section.key' -> value (dots as double underscores in keyword form are not needed:
    pass a dict via **{"effects.dose": 0.02}).
    """
    cfg = C.defaults(S.SCHEMA)
    cfg["simulate"].update(pixel_mm=5.0, step_mm=5.0, seed=1)
    for key, value in overrides.items():
        section, name = key.split(".")
        cfg = C.merge(cfg, {section: {name: value}}, schema=S.SCHEMA)
    return cfg


@pytest.fixture
def small_scan():
    """Factory: (scan, truth) of :func:`sim_config` with overrides."""
    def make(**overrides):
        return S.simulate(sim_config(**overrides))
    return make


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def concealed(effect, *, seed=11, amplitude=None):
    key, realistic, _, extra, conceal = S.CONCEALED[effect]
    scan, truth = S.simulate(sim_config(**{**extra, key: realistic if amplitude is None else amplitude,
                                           "simulate.seed": seed}))
    return scan, truth, C.load([], conceal)


def chi2_tolerance(diag, cfg) -> float:
    """How far the final reduced chi-square may lie from 1 when the model is right.

    The fit runs on every n-th column (``diagnose.subsample``) and the chi-square is read on all of
    them: each fitted parameter's noise, worth 1 on the fitted columns, adds about n to the chi-square
    sum, a mean excess of n * n_params / dof. Around it the statistic scatters by sqrt(2 / dof): five
    of those.
    """
    last = diag.rounds[-1]
    dof = last["chi2_before"] / last["reduced_chi2_before"]
    n_params = sum(np.size(p) for p in diag.params.values())
    return cfg["diagnose"]["subsample"] * n_params / dof + 5 * np.sqrt(2 / dof)


def tiny_obs(rng, *, J=12, H=6, W=7, A=4):
    """Random flat field and counts on a small scan geometry (positions step by one row)."""
    ref = Reference(rng.uniform(500, 1500, (A, W)), rng.uniform(0.2, 0.5, (A, W)),
                    np.cumsum(rng.uniform(0.5, 1.5, (A, W)), axis=0))
    position = -A + 1.0 + np.arange(J) * (H + A - 2) / (J - 1)
    data = rng.poisson(800, (J, H, W)).astype(np.float64)
    return build_observations(Scan(data=data, position=position, reference=ref), ref)


def random_params(rng, J, names):
    p = {}
    for n in names:
        e = effect(n)
        shape = (J, e.size) if e.per_frame else (e.size,)
        scale = {"background": 20.0}.get(n, 0.05)
        p[n] = e.neutral + rng.normal(0, scale, shape)
    return p


ALL = [n for n in MEAN_EFFECTS]


#: Extra address space a run may take beyond what the process held at the fork; measured small runs take
#: under 200 MiB (see tests/test_hostile.py).
BUDGET = 512 << 20


@dataclass
class Outcome:
    exit_code: int
    stdout: str
    stderr: str
    traceback: str  # empty unless the command raised something other than SystemExit


def address_space() -> int:
    """Current virtual memory size of this process in bytes."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmSize in /proc/self/status")


def _child(send, func, budget):
    try:
        cap = address_space() + budget
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
        send.send(func())
    except BaseException:  # noqa: BLE001 -- anything escaping func is a finding of the test, reported to the parent
        send.send(Outcome(-1, "", "", traceback.format_exc()))
    finally:
        os._exit(0)


def run_capped(func, *, budget: int = BUDGET, timeout: float = 120):
    """``func()`` in a forked child whose address space may grow by ``budget`` bytes; returns its value."""
    ctx = multiprocessing.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(send, func, budget))
    proc.start()
    try:
        if not recv.poll(timeout):
            raise TimeoutError(f"capped child did not answer within {timeout} s")
        return recv.recv()
    finally:
        proc.join(10)
        if proc.is_alive():
            proc.kill()


def invoke(args) -> Outcome:
    """The dfxcorr command line, in-process (meant to run inside :func:`run_capped`)."""
    from dfxcorr.cli import main

    res = CliRunner().invoke(main, [str(a) for a in args])
    tb = ""
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        tb = "".join(traceback.format_exception(type(res.exception), res.exception, res.exception.__traceback__))
    return Outcome(res.exit_code, res.stdout, res.stderr, tb)


def cli_capped(*args, budget: int = BUDGET, timeout: float = 120) -> Outcome:
    """:func:`invoke` under the cap."""
    return run_capped(lambda: invoke(args), budget=budget, timeout=timeout)


def one_error_line(stderr: str, *words: str) -> bool:
    """True if ``stderr`` (log lines aside) holds exactly one ``error:`` line, naming ``words``, and no traceback."""
    errors = [ln for ln in stderr.splitlines() if ln.startswith("error:")]
    return (len(errors) == 1 and all(w in errors[0] for w in words) and "Traceback" not in stderr)


def random_images(rng, obs):
    """Images (t, c, s) with t in [0.2, 1], v in [0.3, 1], phi in [-1, 1] for every pixel of ``obs``."""
    R, C = obs.rows.size, obs.columns.size
    t, v, phi = rng.uniform(0.2, 1.0, (R, C)), rng.uniform(0.3, 1.0, (R, C)), rng.uniform(-1, 1, (R, C))
    return M.Images(np.stack([t, t * v * np.cos(phi), t * v * np.sin(phi)], -1), np.ones((R, C), bool))


def modelled_counts(rng, obs, params):
    """Poisson counts of the model at random images: data the model describes, with their noise."""
    return rng.poisson(M.expected(obs, M.design(obs, params), random_images(rng, obs))).astype(np.float64)
