"""Run the command line in a forked child under an address-space cap (never in the pytest process itself).

The cap is the child's address space at the fork (the interpreter, numpy, numba and BLAS threads already
reserve much of it) plus a budget; a run that tries to read what a hostile file declares rather than what
it holds hits the cap and shows up as a MemoryError.
"""
from __future__ import annotations

import multiprocessing
import os
import resource
import traceback
from dataclasses import dataclass

from click.testing import CliRunner

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
