"""Stage 6, export: the results file of ``spec/results-format.md``, TIFFs, a preview and a fit plot.

Every writer refuses to replace an existing file unless asked to (:class:`OutputExistsError`), and
writes to a temporary name in the target directory that is renamed into place only once complete,
so an interrupted run never leaves a truncated output behind.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import yaml

from .catalogue import CATALOGUE
from .errors import DfxcorrError, OutputExistsError
from .io import atomic_path, h5_output
from .result import Result, chi2_limits, paper_params

FORMAT = "dfxcorr-result"
FORMAT_VERSION = 1
PROVENANCE_KEYS = ("program", "version", "date", "command_line", "input_file", "input_sha256",
                   "external_files")

#: Results-file names of the paper's parameters -> catalogue effect names.
SPEC_EFFECTS = {"phase_offset": "phase_offset", "tilt": "tilt", "visibility": "visibility_loss"}

_STR = h5py.string_dtype("utf-8")


class ResultFormatError(DfxcorrError, ValueError):
    """A file given as a result that is not a dfxcorr results file."""


def check_output(path, *, overwrite: bool) -> None:
    """Refuse an output path before any work starts.

    Parameters
    ----------
    path : str or Path
        Output file to be written.
    overwrite : bool
        Allow replacing an existing file.

    Raises
    ------
    OutputExistsError
        If ``path`` exists and ``overwrite`` is False.
    IsADirectoryError
        If ``path`` is a directory (never replaced).
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a directory, not an output file")
    if path.exists() and not overwrite:
        raise OutputExistsError(path)


# --------------------------------------------------------------------------------------------------
# Per-frame parameters as written
# --------------------------------------------------------------------------------------------------


@dataclass
class VibrationDataset:
    """One dataset of /entry/dfxcorr/vibration."""

    name: str            # dataset name
    effect: str          # catalogue name
    value: np.ndarray
    sigma: np.ndarray | None
    estimated: bool
    per_frame: bool


def _squeeze(a: np.ndarray) -> np.ndarray:
    """(J, 1) -> (J,); anything else as is."""
    return a[:, 0] if a.ndim == 2 and a.shape[1] == 1 else a


def _n_frames(result: Result) -> int:
    for d in (result.params, result.uncertainty):
        for name, a in d.items():
            e = CATALOGUE.get(name)
            if e is not None and e.per_frame:
                return int(np.shape(a)[0])
    raise ValueError("cannot tell the number of frames: result.params holds no per-frame effect "
                     "(pass neutral parameters with estimated=False instead)")


def vibration_datasets(result: Result) -> list[VibrationDataset]:
    """The spec's three parameters (neutral where not estimated), then every further effect."""
    n_frames = _n_frames(result)
    neutral = paper_params({}, n_frames)
    out = []
    for name, eff in SPEC_EFFECTS.items():
        estimated = eff in result.params and bool(result.estimated.get(eff, True))
        if estimated:
            value = np.asarray(result.params[eff], dtype=np.float64).reshape(n_frames, -1)[:, 0]
            sigma = result.uncertainty.get(eff)
            sigma = None if sigma is None else np.asarray(sigma, np.float64).reshape(n_frames, -1)[:, 0]
        else:
            value, sigma = neutral[eff][:, 0], None
        out.append(VibrationDataset(name, eff, value, sigma, estimated, True))
    for eff, value in result.params.items():
        if eff in SPEC_EFFECTS.values():
            continue
        value = np.asarray(value, np.float64)
        sigma = result.uncertainty.get(eff)
        e = CATALOGUE.get(eff)
        per_frame = e.per_frame if e is not None else value.ndim >= 1 and value.shape[0] == n_frames
        out.append(VibrationDataset(eff, eff, _squeeze(value),
                          None if sigma is None else _squeeze(np.asarray(sigma, np.float64)),
                          bool(result.estimated.get(eff, True)), per_frame))
    return out


def units(effect: str) -> str | None:
    """Unit of an effect's parameters (None: dimensionless, or not of the catalogue)."""
    e = CATALOGUE.get(effect)
    return e.unit or None if e is not None else None


# --------------------------------------------------------------------------------------------------
# HDF5
# --------------------------------------------------------------------------------------------------


def _filters(compression: str) -> dict:
    """HDF5 filter options of a compressed dataset: the byte shuffle first (the bytes of a float's exponent, then of
    its mantissa, compress as runs), and gzip at level 1: the float32 images of a full-resolution clinical scan
    (2880 x 2880) are written 2.5x faster than at gzip's default level 4 unshuffled, and are 13% smaller (both are
    standard HDF5 filters)."""
    return {"compression": compression, "shuffle": True, **({"compression_opts": 1} if compression == "gzip" else {})}


def _dataset(group, name, data, *, dtype=None, compression=None, units=None, **attrs):
    data = np.asarray(data, dtype=dtype)
    if data.dtype.kind in "OUS":
        data = np.asarray(data, dtype=object).astype(str).astype(object)
        dtype, compression = _STR, None
    kwargs = _filters(compression) if compression and data.ndim and data.size > 1 else {}
    ds = group.create_dataset(name, data=data, dtype=dtype or data.dtype, **kwargs)
    if units:
        ds.attrs["units"] = units
    ds.attrs.update(attrs)
    return ds


def _string(group, name, text):
    return group.create_dataset(name, data=str(text), dtype=_STR)


def _write_tree(group, tree: dict, compression):
    for name, value in tree.items():
        if isinstance(value, dict):
            _write_tree(group.create_group(name), value, compression)
        elif isinstance(value, str):
            _string(group, name, value)
        else:
            _dataset(group, name, value, compression=compression)


def write_result_h5(path, result: Result, *, overwrite: bool = False, compression: str | None = "gzip") -> None:
    """Write the results file of ``spec/results-format.md``.

    Parameters
    ----------
    path : str or Path
        Output file (parent directories are created).
    result : Result
        What the reconstruction produced.
    overwrite : bool
        Replace an existing file.
    compression : str or None
        HDF5 filter for the array datasets ('gzip', 'lzf' or None).

    Raises
    ------
    OutputExistsError
        If ``path`` exists and ``overwrite`` is False.

    Notes
    -----
    The file is written under a temporary name in the same directory and renamed at the end; on any
    failure the temporary file is removed and ``path`` is left as it was.
    """
    check_output(path, overwrite=overwrite)
    vibration = vibration_datasets(result)
    with h5_output(path, overwrite=overwrite) as f:
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = np.int64(FORMAT_VERSION)
        entry = f.create_group("entry")
        entry.attrs["NX_class"] = "NXentry"
        entry.attrs["default"] = "dfxcorr/results"
        proc = entry.create_group("dfxcorr")
        proc.attrs["NX_class"] = "NXprocess"
        for key in PROVENANCE_KEYS:
            _string(proc, key, result.provenance.get(key, ""))
        _string(proc, "configuration", yaml.safe_dump(result.config, sort_keys=False))

        res = proc.create_group("results")
        res.attrs["NX_class"] = "NXdata"
        res.attrs["signal"] = "transmission"
        for name in Result.IMAGES:
            _dataset(res, name, result.image(name), dtype=np.float32, compression=compression,
                     units="rad" if name == "differential_phase" else None)
        if result.pixel_size is not None:
            for axis, size in zip("yx", result.pixel_size, strict=True):
                _dataset(res, f"{axis}_pixel_size", float(size), dtype=np.float64, units="m")

        vib = proc.create_group("vibration")
        unc = vib.create_group("uncertainty")
        for p in vibration:
            e = CATALOGUE.get(p.effect)
            attrs = {"estimated": np.int64(p.estimated), "effect": p.effect}
            if e is not None:
                attrs["components"] = list(e.components)
            _dataset(vib, p.name, p.value, dtype=np.float64, units=units(p.effect), **attrs)
            if p.estimated and p.sigma is not None:
                _dataset(unc, p.name, p.sigma, dtype=np.float64, units=units(p.effect))

        fit = proc.create_group("fit")
        _dataset(fit, "mask", result.fit_mask, dtype=np.uint8, compression=compression)
        _dataset(fit, "motion_mask", result.motion_mask, dtype=np.uint8, compression=compression)
        _dataset(fit, "cost", np.ravel(result.cost), dtype=np.float64)
        _dataset(fit, "stage", np.array([str(s) for s in result.cost_stage], dtype=object))
        _dataset(fit, "reduced_chi2", float(result.reduced_chi2), dtype=np.float64)
        lo, hi = chi2_limits(result.dof)
        _dataset(fit, "dof", int(result.dof), dtype=np.int64)
        _dataset(fit, "misfit", np.uint8(result.misfit), dtype=np.uint8, low=lo, high=hi,
                 description="1: reduced_chi2 lies outside [low, high], what noise allows with dof degrees of "
                             "freedom; the model does not fit this scan (dfxcorr diagnose)")
        _string(fit, "method", result.method)

        tim = proc.create_group("timings")
        for stage, seconds in result.timings.items():
            _dataset(tim, stage, float(seconds), dtype=np.float64, units="s")

        if result.uncorrected is not None:
            unc_img = proc.create_group("uncorrected")
            for name, image in result.uncorrected.items():
                _dataset(unc_img, name, image, dtype=np.float32, compression=compression,
                         units="rad" if name == "differential_phase" else None)
        if result.extra:
            _write_tree(proc.create_group("extra"), result.extra, compression)


def _read_string(ds) -> str:
    return ds.asstr()[()]


def read_result_h5(path) -> dict:
    """Read a results file back into plain Python objects.

    Parameters
    ----------
    path : str or Path
        A file written by :func:`write_result_h5`.

    Returns
    -------
    dict
        'transmission', 'dark_field', 'differential_phase' (float32 arrays), 'vibration' and
        'uncertainty' (dataset name -> array), 'estimated' (dataset name -> bool), 'mask',
        'motion_mask', 'cost', 'stage', 'reduced_chi2' (float), 'misfit' (bool; None in files written before it
        was recorded), 'method', 'configuration' (dict, the
        parsed YAML), 'provenance' (dict of str), 'timings' (dict of float), 'uncorrected' (dict or
        None), 'pixel_size' ((y, x) in m, or None) and 'format_version'.

    Raises
    ------
    ResultFormatError
        If the file is not a dfxcorr results file.
    """
    with h5py.File(path, "r") as f:
        fmt = f.attrs.get("format")
        if isinstance(fmt, bytes):
            fmt = fmt.decode()
        if fmt != FORMAT:
            raise ResultFormatError(f"{path} is not a {FORMAT} file (format attribute {fmt!r})")
        proc = f["entry/dfxcorr"]
        res = proc["results"]
        out = {name: res[name][()] for name in Result.IMAGES}
        out["pixel_size"] = (tuple(float(res[f"{axis}_pixel_size"][()]) for axis in "yx")
                             if "y_pixel_size" in res and "x_pixel_size" in res else None)
        vib = proc["vibration"]
        out["vibration"] = {k: ds[()] for k, ds in vib.items() if isinstance(ds, h5py.Dataset)}
        out["estimated"] = {k: bool(vib[k].attrs.get("estimated", 1)) for k in out["vibration"]}
        out["uncertainty"] = {k: ds[()] for k, ds in vib["uncertainty"].items()} if "uncertainty" in vib else {}
        fit = proc["fit"]
        out["mask"] = fit["mask"][()]
        out["motion_mask"] = fit["motion_mask"][()] if "motion_mask" in fit else None
        out["cost"] = fit["cost"][()]
        out["stage"] = list(fit["stage"].asstr()[()]) if "stage" in fit else []
        out["reduced_chi2"] = float(fit["reduced_chi2"][()])
        out["misfit"] = bool(fit["misfit"][()]) if "misfit" in fit else None
        out["method"] = _read_string(fit["method"]) if "method" in fit else ""
        out["configuration"] = yaml.safe_load(_read_string(proc["configuration"]))
        out["provenance"] = {k: _read_string(proc[k]) if k in proc else "" for k in PROVENANCE_KEYS}
        out["timings"] = {k: float(ds[()]) for k, ds in proc["timings"].items()} if "timings" in proc else {}
        out["uncorrected"] = ({k: ds[()] for k, ds in proc["uncorrected"].items()}
                              if "uncorrected" in proc else None)
        out["format_version"] = int(f.attrs["format_version"])
    return out


# --------------------------------------------------------------------------------------------------
# TIFF
# --------------------------------------------------------------------------------------------------


def tiff_paths(directory, stem: str) -> list[Path]:
    """The files :func:`write_tiffs` writes: one TIFF per image (in ``Result.IMAGES`` order), then the YAML."""
    directory = Path(directory)
    return [directory / f"{stem}_{name}.tif" for name in Result.IMAGES] + [directory / f"{stem}.yaml"]


def write_tiffs(directory, result: Result, *, stem: str, overwrite: bool = False) -> list[Path]:
    """Write one float32 TIFF per image and the resolved configuration beside them.

    Parameters
    ----------
    directory : str or Path
        Target directory (created if needed).
    result : Result
        What the reconstruction produced.
    stem : str
        File names are ``<stem>_transmission.tif``, ``<stem>_dark_field.tif``,
        ``<stem>_differential_phase.tif`` and ``<stem>.yaml``.
    overwrite : bool
        Replace existing files.

    Returns
    -------
    list of Path
        The files written, images first.

    Raises
    ------
    OutputExistsError
        If any of the files exists and ``overwrite`` is False (checked before anything is written).
    """
    import tifffile

    *names, config = tiff_paths(directory, stem)
    images = dict(zip(names, Result.IMAGES, strict=True))
    for path in [*images, config]:
        check_output(path, overwrite=overwrite)
    for path, name in images.items():
        with atomic_path(path, overwrite=overwrite) as tmp, open(tmp, "wb") as fh:
            tifffile.imwrite(fh, np.asarray(result.image(name), dtype=np.float32), photometric="minisblack")
    with atomic_path(config, overwrite=overwrite) as tmp:
        tmp.write_text(yaml.safe_dump(result.config, sort_keys=False))
    return [*images, config]


# --------------------------------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------------------------------


