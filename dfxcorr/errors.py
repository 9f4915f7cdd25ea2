"""The one base class of every refusal: the CLI turns a :class:`DfxcorrError` into one line and exit code 2."""
from __future__ import annotations

import os
import stat
from pathlib import Path


class DfxcorrError(Exception):
    """Input, configuration or output that dfxcorr refuses; the message names the file, dataset or key."""


class OutputExistsError(DfxcorrError, FileExistsError):
    """An output file exists and overwriting was not asked for."""

    def __init__(self, path):
        super().__init__(f"{path} exists; use --overwrite to replace it")
        self.path = Path(path)


class WriteError(DfxcorrError, OSError):
    """An output could not be written (a full disk, a quota); the message names it."""


class InputFileError(DfxcorrError, OSError):
    """An input that is not a regular file (a FIFO, a device, a folder): reading it could block or never end."""


def require_regular_file(path, what: str = "input") -> None:
    """Refuse an existing ``path`` that is not a regular file (symbolic links followed), before anything opens it.

    Opening a FIFO for reading waits for a writer, for ever if none comes; a device can be endless. A path that
    does not exist is left to the reader, which names it.
    """
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return
    if not stat.S_ISREG(mode):
        kind = "a folder" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else "not a regular file"
        name = os.fsencode(path).decode("utf-8", "backslashreplace")
        raise InputFileError(f"{name}: the {what} is {kind}; give a regular file")


#: Detector units per photon that any X-ray detector may record (photon counters 1, integrating flat panels
#: 1e-2-1e2): a stated gain outside is a typing or unit error. Far outside, the fit's float32 noise weights
#: overflow (at 1e-100 its least-squares solve does not converge).
GAIN_RANGE = (1e-6, 1e6)


def gain_problem(gain: float) -> str | None:
    """Why a stated gain (detector units per photon) is not physical, or None: the one rule for every source."""
    lo, hi = GAIN_RANGE
    return None if lo <= gain <= hi else (f"must be a finite number in [{lo:g}, {hi:g}] detector units per photon "
                                          f"(photon counters record 1)")
