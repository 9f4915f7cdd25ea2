"""Command-line interface: thin wrappers over the library, one clear line and a non-zero exit on bad input."""
from __future__ import annotations

import functools
import logging
import os
import shlex
import signal
import sys
import threading
import time
from pathlib import Path

import click
import numpy as np

from . import __version__
from . import config as C
from .errors import DfxcorrError, WriteError

log = logging.getLogger(__name__)

#: Exit code for refused input (bad file, bad configuration, existing output).
EXIT_INPUT = 2


def _exit_input(exc: Exception) -> None:
    """Exit with :data:`EXIT_INPUT`; without the interpreter's teardown after a failed HDF5 write.

    After a failed write (a full disk) HDF5 cannot release the file: its flushes at teardown fail again, print
    tracebacks and end in a segmentation fault. The temporary file is removed by then; logs are flushed first.
    """
    import h5py

    if isinstance(exc, WriteError) or h5py.h5f.get_obj_ids(types=h5py.h5f.OBJ_FILE):
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(EXIT_INPUT)
    sys.exit(EXIT_INPUT)


def friendly(func):
    """Turn the library's refusals into one line on stderr and exit code 2."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except DfxcorrError as exc:
            click.echo(f"error: {exc}", err=True)
            _exit_input(exc)
        except OSError as exc:
            click.echo(f"error: {exc.strerror or exc}: {exc.filename or ''}".rstrip(": "), err=True)
            _exit_input(exc)
        except SystemError as exc:
            # a signal handler's SystemExit raised while a compiled (numba) kernel returned comes wrapped
            stop: BaseException | None = exc
            while isinstance(stop, SystemError):
                stop = stop.__cause__ or stop.__context__
            if isinstance(stop, SystemExit):
                raise stop from None
            raise

    return wrapper


_LOG_FORMAT = logging.Formatter("%(asctime)s %(levelname)-7s %(message)s", datefmt="%H:%M:%S")


def _setup_logging(verbose: int, quiet: bool) -> None:
    level = logging.WARNING if quiet else (logging.DEBUG if verbose > 1 else logging.INFO)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_LOG_FORMAT)
    logging.basicConfig(level=level, handlers=[handler], force=True)
    if verbose < 2:
        logging.getLogger("dfxcorr").setLevel(level)


def _terminate(signum, frame):
    """SIGTERM (a batch system's time limit) ends the run like Ctrl-C: the writers remove their temporary files."""
    click.echo(f"error: stopped by {signal.Signals(signum).name}; files not completed were removed", err=True)
    raise SystemExit(128 + signum)


def _install_signal_handlers() -> None:
    if threading.current_thread() is not threading.main_thread():  # only the main thread may set handlers
        return
    for sig in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(sig) is signal.SIG_DFL:  # keep what nohup or a caller chose
            signal.signal(sig, _terminate)


def _guard(outputs, *, inputs=(), overwrite: bool = False) -> None:
    """Check every output of the command (and the log file) against its inputs, then open the log file.

    The log file is opened only here, after the check, so that it can never append to an input.
    """
    from .check import check_outputs

    log_file = (click.get_current_context().find_root().obj or {}).get("log_file")
    check_outputs(outputs, inputs=inputs, overwrite=overwrite, appended=[log_file] if log_file else [])
    if log_file:
        handler = logging.FileHandler(log_file, encoding="utf-8")
        handler.setFormatter(_LOG_FORMAT)
        logging.getLogger().addHandler(handler)


def _command_line() -> str:
    # arguments that are not UTF-8 (surrogate-escaped) are recorded with backslash escapes
    return "dfxcorr " + " ".join(shlex.quote(os.fsencode(a).decode("utf-8", "backslashreplace"))
                                 for a in sys.argv[1:])


config_options = [
    click.option("-c", "--config", "config_files", multiple=True, type=click.Path(dir_okay=False),
                 help="YAML configuration (repeatable; later files win)."),
    click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE",
                 help="Override one option (repeatable), e.g. --set fit.subsample=10."),
]


def with_config(func):
    for opt in reversed(config_options):
        func = opt(func)
    return func


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="dfxcorr")
@click.option("-v", "--verbose", count=True, help="More log output (-vv: debug).")
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors.")
@click.option("--log-file", type=click.Path(dir_okay=False),
              help="Also append the log to this file (its folder must exist; never one of the inputs).")
@click.pass_context
def main(ctx, verbose, quiet, log_file):
    """Correct grating-vibration artefacts in scanning Talbot-Lau X-ray interferometry.

    Typical use: dfxcorr reconstruct scan.h5 -o result.h5 --tiff out/ --preview
    """
    _setup_logging(verbose, quiet)
    _install_signal_handlers()
    ctx.obj = {"log_file": log_file}


def reconstruct_options(func):
    """The options of ``reconstruct``, shared with ``check``, which checks the same run."""
    func = click.option("--overwrite", is_flag=True, help="Replace existing outputs.")(func)
    func = click.option("--preview", is_flag=True,
                        help="Also write <output stem>_preview.png (uncorrected and corrected images) and "
                             "<output stem>_fit.png.")(func)
    func = click.option("--dicom-sidecar", type=click.Path(dir_okay=False),
                        help="DICOM: patient and study attributes (YAML or JSON of DICOM keywords); none "
                             "are invented.")(func)
    func = click.option("--dicom", "dicom_dir", type=click.Path(file_okay=False),
                        help="Also write the images as DICOM here: one study, three series (needs pydicom).")(func)
    func = click.option("--tiff", "tiff_dir", type=click.Path(file_okay=False),
                        help="Also write float32 TIFFs here.")(func)
    func = click.option("--method", type=click.Choice(C.METHODS),
                        help="Vibration estimator (overrides fit.method).")(func)
    func = with_config(func)
    func = click.option("-o", "--output", type=click.Path(dir_okay=False),
                        help="Result HDF5 file (default: <scan stem>_result.h5 in the current directory).")(func)
    return click.argument("scan", type=click.Path(dir_okay=False))(func)


def _prepare_reconstruct(scan, output, config_files, sets, method, tiff_dir, preview, overwrite, dicom):
    """Check a reconstruction's outputs and configuration before any work.

    ``dicom`` holds the options dicom_dir and dicom_sidecar. Returns the output, the
    configuration, the outputs and the DICOM export's keywords (None without --dicom).
    """
    from . import dicom as D

    out = Path(output) if output else Path(f"{Path(scan).stem}_result.h5")
    dicom_dir, sidecar = dicom["dicom_dir"], dicom["dicom_sidecar"]
    if sidecar and not dicom_dir:
        raise D.DicomError("--dicom-sidecar needs --dicom DIR")
    if dicom_dir:
        D.require_pydicom()
    outputs = _reconstruct_outputs(out, tiff_dir=tiff_dir, preview=preview, dicom_dir=dicom_dir)
    cfg = C.load(config_files, list(sets) + ([f"fit.method={method}"] if method else [])
                 + (["retrieve.uncorrected=true"] if preview else []))
    _guard(outputs, inputs=[scan, *config_files, *C.input_files(cfg), *([sidecar] if sidecar else [])],
           overwrite=overwrite)
    export = {"out_dir": dicom_dir, "sidecar": D.read_sidecar(sidecar) if sidecar else None} if dicom_dir else None
    return out, cfg, outputs, export


def _reconstruct_outputs(out: Path, *, tiff_dir=None, preview=False, dicom_dir=None) -> list[Path]:
    from .dicom import dicom_paths
    from .export import tiff_paths

    outputs = [out] + (tiff_paths(tiff_dir, out.stem) if tiff_dir else [])
    outputs += dicom_paths(dicom_dir, out.stem) if dicom_dir else []
    return outputs + ([out.with_name(f"{out.stem}_preview.png"), out.with_name(f"{out.stem}_fit.png")]
                      if preview else [])


@main.command()
@reconstruct_options
@friendly
def reconstruct(scan, output, config_files, sets, method, tiff_dir, preview, overwrite, **dicom):
    """Reconstruct vibration-corrected images from SCAN (dfxcorr scan format)."""
    from . import check, pipeline
    from .io import read_scan

    out, cfg, outputs, dicom_export = _prepare_reconstruct(scan, output, config_files, sets, method, tiff_dir,
                                                           preview, overwrite, dicom)
    # the header is not held through the run: its reference maps take 29 MiB at full resolution
    check.plan(read_scan(scan, allow_external=cfg["load"]["allow_external"], header_only=True), cfg, name=scan,
               outputs=outputs)
    t0 = time.perf_counter()
    result = pipeline.reconstruct(scan, cfg, command_line=_command_line())
    _write_outputs(result, out, tiff_dir=tiff_dir, preview=preview, dicom=dicom_export, overwrite=overwrite)
    misfit = " (outside what noise allows: run dfxcorr diagnose)" if result.misfit else ""
    click.echo(f"{out}: reduced chi-square {result.reduced_chi2:.4f}{misfit}, {time.perf_counter() - t0:.1f} s")


@main.command("check")
@reconstruct_options
@friendly
def check_cmd(scan, output, config_files, sets, method, tiff_dir, preview, overwrite, **dicom):
    """Check that `dfxcorr reconstruct` with the same arguments would run, in seconds, computing nothing.

    Validates SCAN, the configuration against it (subsampling, column offset, mask dilation, effects this
    acquisition cannot determine, judged as reconstruct judges them) and every output, and prints what
    reconstruct would do and the memory it will need. Exit code 0: it would run; 2: it would refuse.
    """
    from . import check
    from .io import read_scan

    _, cfg, outputs, _ = _prepare_reconstruct(scan, output, config_files, sets, method, tiff_dir, preview, overwrite,
                                              dicom)
    scan_read = read_scan(scan, allow_external=cfg["load"]["allow_external"])
    click.echo(check.plan(scan_read, cfg, name=scan, outputs=outputs, pilot=True).summary())
    faults = check.detector_faults(scan_read, cfg)
    faults.require_data()
    click.echo(faults.summary() if faults.any else "detector faults: none (no saturated sample, no empty or repeated "
                                                   "frame)")
    click.echo("ok: reconstruct would run")


def _write_outputs(result, out: Path, *, tiff_dir=None, preview=False, dicom=None, overwrite=False) -> list[Path]:
    """Write the files :func:`_reconstruct_outputs` lists (``dicom``: keywords of the DICOM export, or None)."""
    from . import export, plots

    export.write_result_h5(out, result, overwrite=overwrite, compression=_compression(result.config))
    written = [out]
    if tiff_dir:
        written += export.write_tiffs(tiff_dir, result, stem=out.stem, overwrite=overwrite)
    if dicom:
        from .dicom import write_dicom

        written += write_dicom(result, stem=out.stem, result_file=out.name, overwrite=overwrite, **dicom)
    if preview:
        written.append(plots.write_preview(out.with_name(f"{out.stem}_preview.png"), result, overwrite=overwrite))
        written.append(plots.write_fit_plot(out.with_name(f"{out.stem}_fit.png"), result, overwrite=overwrite))
    for p in written:
        log.info("wrote %s", p)
    return written


def _compression(cfg: dict):
    c = cfg["export"]["compression"]
    return None if c == "none" else c


@main.command("dicom")
@click.argument("result_file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", "output_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for <result stem>_transmission.dcm, _dark_field.dcm and _differential_phase.dcm.")
@click.option("--sidecar", type=click.Path(dir_okay=False),
              help="Patient and study attributes (YAML or JSON of DICOM keywords); none are invented.")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@friendly
def dicom_cmd(result_file, output_dir, sidecar, overwrite):
    """Write the images of RESULT_FILE as DICOM for a PACS: one study, three series (needs pydicom).

    Physical values are recoverable from the stored pixels (Rescale Slope and Intercept); NaN pixels
    hold the PixelPaddingValue 0. The same result and sidecar give the same UIDs every time.
    """
    from . import dicom as D

    D.require_pydicom()
    paths = D.dicom_paths(output_dir, Path(result_file).stem)
    _guard(paths, inputs=[result_file, *([sidecar] if sidecar else [])], overwrite=overwrite)
    attributes = D.read_sidecar(sidecar) if sidecar else None
    written = D.write_dicom(result_file, output_dir, sidecar=attributes, overwrite=overwrite)
    click.echo(f"wrote {', '.join(str(p) for p in written)}")


@main.command()
@click.argument("config_file", required=False, type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Scan file to write.")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE", help="Override one option.")
@click.option("--truth", type=click.Path(dir_okay=False), help="Truth file (default: <output stem>.truth.npz).")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@friendly
def simulate(config_file, output, sets, truth, overwrite):
    """Simulate a scan (the paper's simulation study by default) and write it with its truth."""
    from .io import atomic_path
    from .sim import simulate as S

    out = Path(output)
    truth_path = Path(truth) if truth else out.with_name(f"{out.stem}.truth.npz")
    _guard([out, truth_path], inputs=[config_file] if config_file else [], overwrite=overwrite)
    cfg = C.load([config_file] if config_file else [], sets, schema=S.SCHEMA)
    scan, true = S.simulate_file(cfg, out, overwrite=overwrite)
    with atomic_path(truth_path, overwrite=overwrite) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **true)
    click.echo(f"{out}: {scan.shape[0]} frames of {scan.shape[1]} x {scan.shape[2]}; truth in {truth_path}")


@main.command()
@click.argument("scan", type=click.Path(dir_okay=False))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for diagnosis.json, report.md and pictures.")
@with_config
@click.option("--base", type=click.Choice(["configured", "none"]), default="configured", show_default=True,
              help="Start from the configured model, or from plain retrieval without per-frame terms.")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@friendly
def diagnose(scan, out_dir, config_files, sets, base, overwrite):
    """Find where SCAN and the model disagree, name the missing physics, add it and refit."""
    from . import check
    from .analysis.diagnose import diagnose as run
    from .analysis.report import FIXED_FILES, write_report
    from .io import read_scan

    out = Path(out_dir)
    cfg = C.load(config_files, sets)
    # every file of a fixed name the report may write: the iterative workflow feeds pixel_noise.tif and
    # position_errors.txt back, and a run must not replace the map it reads
    _guard([out / name for name in FIXED_FILES],
           inputs=[scan, *config_files, *C.input_files(cfg)], overwrite=overwrite)
    check.check_folder(out)  # the report replaces its folder as a unit
    # plain retrieval (--base none) fits no configured effect
    header = read_scan(scan, allow_external=cfg["load"]["allow_external"], header_only=True)
    check.plan(header, C.merge(cfg, {"fit": {"method": "none"}}) if base == "none" else cfg,
               name=scan, diagnose=True)
    diag = run(scan, cfg, base=base)
    write_report(diag, out, overwrite=overwrite)
    found = [e.name for e in diag.effects if e.detected]
    click.echo(f"{out / 'report.md'}: reduced chi-square {diag.initial_chi2:.4f} -> {diag.final_chi2:.4f}; "
               f"detected: {', '.join(found) or 'nothing'}")


@main.group("import")
def import_group():
    """Convert recordings from other layouts into the dfxcorr scan format."""


def _floats(text, name):
    from .importer import StackImportError

    try:
        return [float(p) for p in text.split(",")] if text else None
    except ValueError:
        raise StackImportError(f"--{name} {text!r}: expected comma-separated numbers") from None


def _dims(shape):
    from .importer import StackImportError

    if not shape:
        return None
    try:
        return tuple(int(p) for p in shape.lower().split("x"))
    except ValueError:
        raise StackImportError(f"--shape {shape!r}: expected ROWSxCOLS, e.g. 195x487") from None


@import_group.command("stepping")
@click.option("--sample", required=True, help="Sample series: glob, one file per step or one stack (.npy, .tif, raw).")
@click.option("--reference", required=True, help="Reference (flat-field) series of the unloaded interferometer.")
@click.option("--dark", help="Dark frame(s) of the sample series (averaged).")
@click.option("--reference-dark", help="Dark frame(s) of the reference series (default: --dark).")
@click.option("--steps-per-period", type=float, help="Nominal steps: 2 pi k / steps-per-period.")
@click.option("--phases", help="Nominal step phases in rad, comma-separated (instead of --steps-per-period).")
@click.option("--reference-phases", help="Step phases of the reference series if they differ (comma-separated).")
@click.option("--shape", help="Raw files: frame shape ROWSxCOLS.")
@click.option("--dtype", help="Raw files: numpy dtype with byte order, e.g. '<u2'.")
@click.option("--offset", type=int, default=0, show_default=True, help="Raw files: header bytes to skip.")
@click.option("--gain", type=float, default=1.0, show_default=True, help="Detector units per photon.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Scan file to write.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output.")
@friendly
def import_stepping_cmd(sample, reference, dark, reference_dark, steps_per_period, phases, reference_phases, shape,
                        dtype, offset, gain, output, overwrite):
    """Import a phase-stepping recording (sample and reference series), losslessly."""
    from .importer import import_stepping, input_files

    _guard([output], inputs=input_files(sample, reference, dark, reference_dark), overwrite=overwrite)
    scan = import_stepping(output, sample=sample, reference=reference, dark=dark, reference_dark=reference_dark,
                           steps_per_period=steps_per_period, phases=_floats(phases, "phases"),
                           reference_phases=_floats(reference_phases, "reference-phases"), shape=_dims(shape),
                           dtype=dtype, offset=offset, gain=gain, overwrite=overwrite)
    click.echo(f"{output}: {scan.shape[0]} steps of {scan.shape[1]} x {scan.shape[2]} ({scan.data.dtype}), "
               f"reference {scan.reference.data.shape[0]} steps")


@import_group.command("scanning")
@click.option("--frames", required=True, help="Frames in acquisition order: glob, one file per frame or one stack "
                                               "(.npy, .tif, raw).")
@click.option("--positions", required=True, type=click.Path(dir_okay=False),
              help="Motor log: top edge of the active area per frame, one number per line or a CSV with a header.")
@click.option("--position-units", type=click.Choice(["pixel", "mm"]), default="pixel", show_default=True,
              help="Units of the log (mm needs --pixel-size).")
@click.option("--position-column", help="Column of a CSV log.")
@click.option("--reference-stepping", help="Phase-stepping series of the unloaded interferometer on the detector.")
@click.option("--steps-per-period", type=float, help="Its nominal steps: 2 pi k / steps-per-period.")
@click.option("--reference-phases", help="Its step phases in rad, comma-separated (instead of --steps-per-period).")
@click.option("--reference", "reference_file", type=click.Path(dir_okay=False),
              help="Take /entry/reference of this scan file instead.")
@click.option("--dark", help="Dark frame(s) (averaged).")
@click.option("--reference-dark", help="Dark frame(s) of the reference series (default: --dark).")
@click.option("--active-first-row", type=int, help="First detector row of the active area in the reference frames "
                                                   "(default: found from the flux).")
@click.option("--active-rows", type=int, help="Height of the active area in rows (with --active-first-row).")
@click.option("--shape", help="Raw files: frame shape ROWSxCOLS.")
@click.option("--dtype", help="Raw files: numpy dtype with byte order, e.g. '<u2'.")
@click.option("--offset", type=int, default=0, show_default=True, help="Raw files: header bytes to skip.")
@click.option("--gain", type=float, default=1.0, show_default=True, help="Detector units per photon.")
@click.option("--pixel-size", type=float, help="Pixel pitch in m (e.g. 75e-6).")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Scan file to write.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output.")
@friendly
def import_scanning_cmd(frames, positions, position_units, position_column, reference_stepping, steps_per_period,
                        reference_phases, reference_file, dark, reference_dark, active_first_row, active_rows, shape,
                        dtype, offset, gain, pixel_size, output, overwrite):
    """Import a scanning acquisition (frames and a motor log), losslessly, one frame at a time."""
    from .importer import import_scanning, input_files

    _guard([output], inputs=input_files(frames, positions, reference_stepping, reference_file, dark, reference_dark),
           overwrite=overwrite)
    scan = import_scanning(output, frames=frames, positions=positions, position_units=position_units,
                           position_column=position_column, reference_stepping=reference_stepping,
                           steps_per_period=steps_per_period,
                           reference_phases=_floats(reference_phases, "reference-phases"), reference=reference_file,
                           dark=dark, reference_dark=reference_dark, active_first_row=active_first_row,
                           active_rows=active_rows, shape=_dims(shape), dtype=dtype, offset=offset, gain=gain,
                           pixel_size=pixel_size, overwrite=overwrite)
    click.echo(f"{output}: {scan.shape[0]} frames of {scan.shape[1]} x {scan.shape[2]} ({scan.data.dtype}), "
               f"active area {scan.active_rows} rows")


@main.command()
@click.argument("output_dir", type=click.Path(file_okay=False), default="dfxcorr-demo")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@friendly
def demo(output_dir, overwrite):
    """Simulate a small scan, reconstruct it and write images, pictures and a summary (under a minute)."""
    from .sim.demo import demo_paths, run_demo

    _guard(demo_paths(Path(output_dir)).values(), overwrite=overwrite)
    summary = run_demo(Path(output_dir), overwrite=overwrite, command_line=_command_line())
    click.echo(summary)


@main.command("config")
@click.option("--defaults", "show_defaults", is_flag=True, help="Print the commented default configuration.")
@click.option("--schema", type=click.Choice(["reconstruct", "simulate"]), default="reconstruct", show_default=True,
              help="Which configuration.")
@click.option("--check", "check_files", multiple=True, type=click.Path(dir_okay=False),
              help="Validate these YAML files and print the resolved configuration.")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE", help="Override one option.")
@friendly
def config_cmd(show_defaults, schema, check_files, sets):
    """Show the default configuration, or validate and resolve configuration files."""
    from .sim import simulate as S

    _guard([], inputs=check_files)
    sch = S.SCHEMA if schema == "simulate" else C.SCHEMA
    if show_defaults or not (check_files or sets):
        title = ("dfxcorr simulate this.yaml -o scan.h5" if schema == "simulate"
                 else "dfxcorr reconstruct SCAN -c this.yaml")
        click.echo(C.commented_defaults(sch, title=title))
        return
    click.echo(C.dump(C.load(check_files, sets, schema=sch)), nl=False)


@main.command()
@click.argument("scan", type=click.Path(dir_okay=False))
@click.option("-o", "--output", "output_dir", required=True, type=click.Path(file_okay=False),
              help="Directory for the per-method results, the pictures and the table.")
@click.option("--truth", type=click.Path(dir_okay=False),
              help="Ground truth (.npz of dfxcorr simulate): adds RMSE of parameters and images.")
@click.option("--methods", default="none,correlation,alternating,ml", show_default=True,
              help="Comma-separated estimators (fit.method values).")
@with_config
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@friendly
def compare(scan, output_dir, truth, methods, config_files, sets, overwrite):
    """Run every vibration estimator on SCAN and compare them: results, pictures and a table."""
    from . import check
    from .analysis import compare as CMP
    from .io import read_scan

    methods = CMP.parse_methods(methods)
    cfg = C.load(config_files, sets)
    _guard(CMP.comparison_paths(Path(output_dir), methods).values(), inputs=[scan, *config_files,
           *C.input_files(cfg)] + ([truth] if truth else []), overwrite=overwrite)
    header = read_scan(scan, allow_external=cfg["load"]["allow_external"], header_only=True)
    for m in methods:
        check.plan(header, C.merge(cfg, {"fit": {"method": m}}), name=scan)
    true = CMP.load_truth(truth, header.shape) if truth else None
    data = read_scan(scan, allow_external=cfg["load"]["allow_external"])
    cfg = C.merge(cfg, {"retrieve": {"uncorrected": False}})
    results, runtimes = CMP.run_methods(scan, cfg, methods=methods, command_line=_command_line())
    paths = CMP.write_comparison(output_dir, data, results, runtimes, truth=true, source=scan, overwrite=overwrite)
    click.echo(paths["table_md"].read_text(), nl=False)
    click.echo(f"wrote {len(paths)} files to {output_dir}")


@main.command()
@click.argument("scans", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", "output_dir", required=True, type=click.Path(file_okay=False),
              help="Directory for nps.png, nps.csv and nps.json.")
@click.option("--methods", default="none,correlation,ml", show_default=True,
              help="Comma-separated estimators (fit.method values).")
@click.option("--bins", type=click.IntRange(4, 1000),
              help="Radial frequency bins between 0 and 0.5 cycles/pixel (default: rings a quarter of the "
                   "fringe frequency wide).")
@with_config
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@friendly
def nps(scans, output_dir, methods, bins, config_files, sets, overwrite):
    """Noise power spectra of the dark-field images of blank SCANS (no sample), per estimator."""
    from . import check
    from .analysis import compare as CMP
    from .io import read_scan

    methods = CMP.parse_methods(methods)
    cfg = C.load(config_files, sets)
    _guard(CMP.nps_paths(Path(output_dir)).values(), inputs=[*scans, *config_files, *C.input_files(cfg)],
           overwrite=overwrite)
    for scan in scans:
        header = read_scan(scan, allow_external=cfg["load"]["allow_external"], header_only=True)
        for m in methods:
            check.plan(header, C.merge(cfg, {"fit": {"method": m}}), name=scan)
    study = CMP.nps_study(scans, cfg, methods=methods, bins=bins, command_line=_command_line())
    paths = CMP.write_nps(output_dir, study, overwrite=overwrite)
    ff = study["fringe_frequency"]
    click.echo(f"fringe frequency {ff:.4f} cycles/pixel (first harmonic {2 * ff:.4f})")
    for m, p in CMP.fringe_power(study).items():
        click.echo(f"{m}: NPS at the fringe {p['fringe']:.3g}, at the harmonic {p['first_harmonic']:.3g}, "
                   f"elsewhere {p['other']:.3g} (pixel^2)")
    click.echo(f"wrote {', '.join(str(p) for p in paths.values())}")


@main.command()
@click.argument("scan_list", type=click.Path(dir_okay=False))
@click.option("-o", "--output", "output_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for the results (<scan stem>.h5) and logs (<scan stem>.log).")
@with_config
@click.option("--jobs", type=click.IntRange(min=1), default=1, show_default=True,
              help="Scans processed at once (each gets an equal share of the cores).")
@click.option("--array-index", type=click.IntRange(min=1), envvar="SLURM_ARRAY_TASK_ID",
              help="Process only the scan on this line of SCAN_LIST (from 1, as sed -n Np) and exit with its "
                   "status; default: $SLURM_ARRAY_TASK_ID.")
@friendly
def batch(scan_list, output_dir, config_files, sets, jobs, array_index):
    """Reconstruct every scan listed in SCAN_LIST (one path per line), one process per scan.

    Finished results are skipped, so a stopped batch resumes where it was; a result of another configuration or of
    a scan that changed since is re-run. A failed scan does not stop the others; the summary at the end lists
    every scan with its status, time and reduced chi-square (marked misfit where noise cannot explain it).
    """
    from . import batch as B

    C.load(config_files, sets)  # refuse a bad configuration once, before any scan runs
    entries = B.read_list(scan_list)
    _guard([], inputs=[scan_list, *config_files, *(text for _, text in entries)])
    if array_index is not None:
        entries = B.select_line(entries, array_index, list_name=scan_list)
    out_dir = Path(output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    todo = B.plan(entries, out_dir)
    done = [0]

    def report(outcome):
        done[0] += 1
        extra = (f", reduced chi-square {outcome.reduced_chi2:.4f}{' (misfit)' if outcome.misfit else ''}"
                 if outcome.reduced_chi2 is not None else "")
        line = f"[{done[0]}/{len(todo)}] {outcome.job.scan}: {outcome.status} ({outcome.seconds:.1f} s{extra})"
        log.info("%s%s", line, "".join(f": {t}" for t in (outcome.note, outcome.error) if t))

    outcomes = B.run_batch(todo, config_files=config_files, sets=sets, n_jobs=jobs, on_done=report)
    click.echo(B.summary(outcomes))
    if any(o.status == "failed" for o in outcomes):
        sys.exit(1)


if __name__ == "__main__":  # pragma: no cover
    main()
