"""Command-line interface: thin wrappers over the library, one clear line and a non-zero exit on bad input."""
from __future__ import annotations

import functools
import logging
import shlex
import sys
import time
from pathlib import Path

import click
import numpy as np

from . import __version__
from . import config as C
from .errors import DfxcorrError

log = logging.getLogger("dfxcorr")

#: Exit code for refused input (bad file, bad configuration, existing output).
EXIT_INPUT = 2


def friendly(func):
    """Turn the library's refusals into one line on stderr and exit code 2."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except DfxcorrError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(EXIT_INPUT)
        except OSError as exc:
            click.echo(f"error: {exc.strerror or exc}: {exc.filename or ''}".rstrip(": "), err=True)
            sys.exit(EXIT_INPUT)

    return wrapper


def _setup_logging(verbose: int, quiet: bool, log_file: str | None) -> None:
    level = logging.WARNING if quiet else (logging.DEBUG if verbose > 1 else logging.INFO)
    handlers = [logging.StreamHandler(sys.stderr)]
    if log_file:
        handlers.append(logging.FileHandler(log_file))
    logging.basicConfig(level=level, handlers=handlers, force=True,
                        format="%(asctime)s %(levelname)-7s %(message)s", datefmt="%H:%M:%S")
    if verbose < 2:
        logging.getLogger("dfxcorr").setLevel(level)


def _command_line() -> str:
    return "dfxcorr " + " ".join(shlex.quote(a) for a in sys.argv[1:])


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
@click.option("--log-file", type=click.Path(dir_okay=False), help="Also write the log to this file.")
def main(verbose, quiet, log_file):
    """Correct grating-vibration artefacts in scanning Talbot-Lau X-ray interferometry.

    Typical use: dfxcorr reconstruct scan.h5 -o result.h5 --tiff out/ --preview
    """
    _setup_logging(verbose, quiet, log_file)


@main.command()
@click.argument("scan", type=click.Path(dir_okay=False))
@click.option("-o", "--output", type=click.Path(dir_okay=False),
              help="Result HDF5 file (default: <scan stem>_result.h5 in the current directory).")
@with_config
@click.option("--method", type=click.Choice(["ml", "alternating", "correlation", "none"]),
              help="Vibration estimator (overrides fit.method).")
@click.option("--tiff", "tiff_dir", type=click.Path(file_okay=False), help="Also write float32 TIFFs here.")
@click.option("--preview", is_flag=True, help="Also write a PNG with uncorrected and corrected images.")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@friendly
def reconstruct(scan, output, config_files, sets, method, tiff_dir, preview, overwrite):
    """Reconstruct vibration-corrected images from SCAN (dfxcorr scan format)."""
    from . import export, pipeline

    sets = list(sets) + ([f"fit.method={method}"] if method else [])
    cfg = C.load(config_files, sets)
    out = Path(output) if output else Path(f"{Path(scan).stem}_result.h5")
    export.check_output(out, overwrite=overwrite)
    t0 = time.perf_counter()
    result = pipeline.reconstruct(scan, cfg, command_line=_command_line())
    _write_outputs(result, out, tiff_dir=tiff_dir, preview=preview, overwrite=overwrite)
    click.echo(f"{out}: reduced chi-square {result.reduced_chi2:.4f}, {time.perf_counter() - t0:.1f} s")


def _write_outputs(result, out: Path, *, tiff_dir=None, preview=False, overwrite=False) -> list[Path]:
    from . import export, plots

    export.write_result_h5(out, result, overwrite=overwrite, compression=_compression(result.config))
    written = [out]
    if tiff_dir:
        written += export.write_tiffs(tiff_dir, result, stem=out.stem, overwrite=overwrite)
    if preview:
        written.append(plots.write_preview(out.with_name(f"{out.stem}_preview.png"), result, overwrite=overwrite))
        written.append(plots.write_fit_plot(out.with_name(f"{out.stem}_fit.png"), result, overwrite=overwrite))
    for p in written:
        log.info("wrote %s", p)
    return written


def _compression(cfg: dict):
    c = cfg["export"]["compression"]
    return None if c == "none" else c


@main.command()
@click.argument("config_file", required=False, type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Scan file to write.")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE", help="Override one option.")
@click.option("--truth", type=click.Path(dir_okay=False), help="Truth file (default: <output stem>.truth.npz).")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@friendly
def simulate(config_file, output, sets, truth, overwrite):
    """Simulate a scan (the paper's simulation study by default) and write it with its truth."""
    from . import export
    from .sim import simulate as S
    from .io import atomic_path

    cfg = C.load([config_file] if config_file else [], sets, schema=S.SCHEMA)
    out = Path(output)
    truth_path = Path(truth) if truth else out.with_name(f"{out.stem}.truth.npz")
    for p in (out, truth_path):
        export.check_output(p, overwrite=overwrite)
    scan, true = S.simulate_file(cfg, out)
    with atomic_path(truth_path) as tmp, open(tmp, "wb") as fh:
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
    from .analysis.diagnose import diagnose as run, write_report
    from .export import check_output

    cfg = C.load(config_files, sets)
    out = Path(out_dir)
    for name in ("diagnosis.json", "report.md", "residuals.png"):
        check_output(out / name, overwrite=overwrite)
    diag = run(scan, cfg, base=base)
    write_report(diag, out, overwrite=overwrite)
    found = [e.name for e in diag.effects if e.detected]
    click.echo(f"{out / 'report.md'}: reduced chi-square {diag.initial_chi2:.4f} -> {diag.final_chi2:.4f}; "
               f"detected: {', '.join(found) or 'nothing'}")


@main.group("import")
def import_group():
    """Convert recordings from other layouts into the dfxcorr scan format."""


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
    from .importer import StackImportError, import_stepping

    def floats(text, name):
        try:
            return [float(p) for p in text.split(",")] if text else None
        except ValueError:
            raise StackImportError(f"--{name} {text!r}: expected comma-separated numbers") from None

    dims = None
    if shape:
        try:
            dims = tuple(int(p) for p in shape.lower().split("x"))
        except ValueError:
            raise StackImportError(f"--shape {shape!r}: expected ROWSxCOLS, e.g. 195x487") from None
    scan = import_stepping(output, sample=sample, reference=reference, dark=dark, reference_dark=reference_dark,
                           steps_per_period=steps_per_period, phases=floats(phases, "phases"),
                           reference_phases=floats(reference_phases, "reference-phases"), shape=dims, dtype=dtype,
                           offset=offset, gain=gain, overwrite=overwrite)
    click.echo(f"{output}: {scan.shape[0]} steps of {scan.shape[1]} x {scan.shape[2]} ({scan.data.dtype}), "
               f"reference {scan.reference.data.shape[0]} steps")


@main.command()
@click.argument("output_dir", type=click.Path(file_okay=False), default="dfxcorr-demo")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@friendly
def demo(output_dir, overwrite):
    """Simulate a small scan, reconstruct it and write images, pictures and a summary (under a minute)."""
    from .sim.demo import run_demo

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

    sch = S.SCHEMA if schema == "simulate" else C.SCHEMA
    if show_defaults or not (check_files or sets):
        title = "dfxcorr simulate this.yaml -o scan.h5" if schema == "simulate" else "dfxcorr reconstruct SCAN -c this.yaml"
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
    from .analysis import compare as CMP
    from . import export
    from .io import read_scan

    cfg = C.load(config_files, sets)
    methods = CMP.parse_methods(methods)
    for p in CMP.comparison_paths(Path(output_dir), methods).values():
        export.check_output(p, overwrite=overwrite)
    data = read_scan(scan)
    try:
        true = CMP.load_truth(truth, data.shape) if truth else None
    except CMP.TruthError as exc:
        raise click.BadParameter(str(exc), param_hint="--truth") from None
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
    from .analysis import compare as CMP
    from . import export

    cfg = C.load(config_files, sets)
    methods = CMP.parse_methods(methods)
    for p in CMP.nps_paths(Path(output_dir)).values():
        export.check_output(p, overwrite=overwrite)
    study = CMP.nps_study(scans, cfg, methods=methods, bins=bins, command_line=_command_line())
    paths = CMP.write_nps(output_dir, study, overwrite=overwrite)
    ff = study["fringe_frequency"]
    click.echo(f"fringe frequency {ff:.4f} cycles/pixel (first harmonic {2 * ff:.4f})")
    for m, p in CMP.fringe_power(study).items():
        click.echo(f"{m}: NPS at the fringe {p['fringe']:.3g}, at the harmonic {p['harmonic']:.3g}, "
                   f"elsewhere {p['other']:.3g} (pixel^2)")
    click.echo(f"wrote {', '.join(str(p) for p in paths.values())}")


if __name__ == "__main__":  # pragma: no cover
    main()
