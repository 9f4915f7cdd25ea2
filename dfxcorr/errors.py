"""The one base class of every refusal: the CLI turns a :class:`DfxcorrError` into one line and exit code 2."""
from __future__ import annotations

from pathlib import Path


class DfxcorrError(Exception):
    """Input, configuration or output that dfxcorr refuses; the message names the file, dataset or key."""


class OutputExistsError(DfxcorrError, FileExistsError):
    """An output file exists and overwriting was not asked for."""

    def __init__(self, path):
        super().__init__(f"{path} exists; use --overwrite to replace it")
        self.path = Path(path)
