"""Stage 1, load: the dfxcorr scan file (``spec/scan-format.md``), read with every check and written atomically.

Reading refuses anything the format forbids with a :class:`ScanFormatError` whose message names the
dataset. The package's modules: :mod:`.types` (the scan and its reference), :mod:`.validate` (the file's
layout before any read), :mod:`.read` and :mod:`.write` (atomic outputs, scan files).
"""
from .read import read_reference, read_scan
from .types import (
    FORMAT,
    FORMAT_VERSION,
    FrameSource,
    H5Frames,
    Reference,
    Scan,
    ScanFormatError,
    SteppingReference,
    frame_rows,
    lit_rows,
)
from .validate import Layout, validate_file
from .write import CHUNK_ROWS, TEMP_NAME_OVERHEAD, atomic_folder, atomic_path, h5_output, write_scan

__all__ = ["CHUNK_ROWS", "FORMAT", "FORMAT_VERSION", "TEMP_NAME_OVERHEAD", "FrameSource", "H5Frames", "Layout",
           "Reference", "Scan", "ScanFormatError", "SteppingReference", "atomic_folder", "atomic_path", "frame_rows",
           "h5_output", "lit_rows", "read_reference", "read_scan", "validate_file", "write_scan"]
