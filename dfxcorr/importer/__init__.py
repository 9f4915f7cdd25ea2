"""Import of recordings (series of .npy, TIFF or headerless raw frames) into a scan file.

Two layouts: a phase-stepping recording (:func:`import_stepping`), the special case of
``spec/scan-format.md`` with A = H, all positions 0 and ``scan/phase_step`` holding the nominal step phases,
its reference stored as the stepping series of the unloaded interferometer (``/entry/reference/stepping``);
and a scanning acquisition (:func:`import_scanning`): frames plus a motor log of the interferometer position,
with a reference stepping series cropped to the active area or the reference of another scan file. The import
is lossless: counts are written exactly as read. Frame dtypes the format does not allow are converted to the
smallest allowed type that holds every value of the source type exactly (see :func:`frame_dtype`), or refused.
Every file's size is checked from its header before its data is read.

Modules: :mod:`.formats` (the file readers and :class:`Series`), :mod:`.common` (what both imports share),
:mod:`.stepping` and :mod:`.scanning`.
"""
from .common import input_files, nominal_steps
from .formats import Series, StackImportError, frame_dtype, read_stack
from .scanning import active_area, import_scanning, read_positions
from .stepping import import_stepping

__all__ = ["Series", "StackImportError", "active_area", "frame_dtype", "import_scanning", "import_stepping",
           "input_files", "nominal_steps", "read_positions", "read_stack"]
