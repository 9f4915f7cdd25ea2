"""Reliability: inputs named by the configuration never replaced, no traceback and no hang on
hostile inputs (FIFOs, huge declarations, absurd numbers, a signal inside a compiled kernel), and ``check`` refusing
whatever ``reconstruct`` refuses before computing."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile
from click.testing import CliRunner

import dfxcorr
from dfxcorr import io
from dfxcorr.cli import main
from dfxcorr.io import Reference, Scan, write_scan
from dfxcorr.sim import simulate as S

from conftest import cli_capped, one_error_line, sim_config

DET = "entry/instrument/detector"
ROOT = Path(dfxcorr.__file__).resolve().parents[1]  # of the dfxcorr imported here, for the subprocesses


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def refused(res, *words):
    assert res.exit_code == 2, res.output
    assert one_error_line(res.stderr, *words), res.stderr


def tiny_scan(rng, J=12, H=8, W=5, A=3, position=None):
    ref = Reference(np.full((A, W), 100.0), np.full((A, W), 0.3), rng.uniform(0, 3, (A, W)))
    pos = np.linspace(-2, H - 1, J) if position is None else np.asarray(position, float)
    return Scan(data=rng.poisson(80, (J, H, W)).astype(np.uint16), position=pos, reference=ref)


@pytest.fixture(scope="module")
def scan_file(tmp_path_factory):
    """A small simulated scan (104 frames of 90 x 102)."""
    path = tmp_path_factory.mktemp("scan") / "scan.h5"
    io.write_scan(path, S.simulate(sim_config())[0])
    return path


def digest(path: Path) -> bytes:
    return path.read_bytes()


# --------------------------------------------------------------------------------------------------
# No input ever replaced: files the configuration names
# --------------------------------------------------------------------------------------------------


def test_output_never_replaces_the_pixel_noise_map(scan_file, tmp_path):
    pn = tmp_path / "pn.tif"
    tifffile.imwrite(pn, np.ones((90, 102), np.float32))
    before = digest(pn)
    refused(run("reconstruct", scan_file, "-o", pn, "--overwrite", "--set", f"load.pixel_noise={pn}"),
            "pn.tif", "also an input")
    assert digest(pn) == before


def test_output_never_replaces_the_position_errors(scan_file, tmp_path):
    pe = tmp_path / "pe.txt"
    np.savetxt(pe, np.zeros(104))
    before = digest(pe)
    refused(run("check", scan_file, "-o", pe, "--overwrite", "--set", f"align.position_errors={pe}"),
            "pe.txt", "also an input")
    assert digest(pe) == before


def test_tiff_folder_never_replaces_a_map_in_it(scan_file, tmp_path):
    tif = tmp_path / "tif"
    tif.mkdir()
    out = tmp_path / "r.h5"
    from dfxcorr.export import tiff_paths

    pn = tiff_paths(tif, out.stem)[0]  # a pixel noise map saved under the name of one of the TIFFs
    tifffile.imwrite(pn, np.ones((90, 102), np.float32))
    before = digest(pn)
    refused(run("reconstruct", scan_file, "-o", out, "--tiff", tif, "--overwrite", "--set",
                f"load.pixel_noise={pn}"), "also an input")
    assert digest(pn) == before and not out.exists()


def test_iterative_diagnosis_never_replaces_its_own_map(scan_file, tmp_path):
    out = tmp_path / "diag"
    out.mkdir()
    pn = out / "pixel_noise.tif"
    tifffile.imwrite(pn, np.ones((90, 102), np.float32))
    before = digest(pn)
    refused(run("diagnose", scan_file, "-o", out, "--overwrite", "--set", f"load.pixel_noise={pn}"),
            "pixel_noise.tif", "also an input")
    assert digest(pn) == before and sorted(p.name for p in out.iterdir()) == ["pixel_noise.tif"]


def test_import_never_replaces_its_reference_scan(scan_file, tmp_path):
    ref = tmp_path / "ref.h5"
    ref.write_bytes(scan_file.read_bytes())
    scan = io.read_scan(scan_file)
    np.save(tmp_path / "stack.npy", np.asarray(scan.data[:]))
    np.savetxt(tmp_path / "positions.txt", scan.position)
    before = digest(ref)
    refused(run("import", "scanning", "--frames", tmp_path / "stack.npy", "--positions", tmp_path / "positions.txt",
                "--reference", ref, "-o", ref, "--overwrite"), "ref.h5", "also an input")
    assert digest(ref) == before


# --------------------------------------------------------------------------------------------------
# No traceback, no hang
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("setting", ["fit.reweight=10000000000000000000000000000000",
                                     "retrieve.iterations=10000000000000000000000000000000",
                                     "retrieve.iterations=1000000", "fit.maxiter=10000000000",
                                     "retrieve.block_mb=1e300", "align.reference_offset=1e300",
                                     "fit.subsample=10000000000000000000", "mask.dilate=10000000000000000000000"])
def test_absurd_numbers_are_refused(scan_file, tmp_path, setting):
    refused(run("check", scan_file, "-o", tmp_path / "r.h5", "--set", setting), setting.split("=")[0], "must")


@pytest.fixture
def fifo(tmp_path):
    path = tmp_path / "fifo"
    os.mkfifo(path)
    return path


@pytest.mark.parametrize("role", ["scan", "config", "scan list", "log", "frames", "positions", "pixel noise"])
def test_a_fifo_never_blocks(fifo, scan_file, tmp_path, role):
    out = tmp_path / "r.h5"
    args = {"scan": ["check", fifo, "-o", out],
            "config": ["check", scan_file, "-o", out, "-c", fifo],
            "scan list": ["batch", fifo, "-o", tmp_path / "res"],
            "log": ["--log-file", fifo, "check", scan_file, "-o", out],
            "frames": ["import", "scanning", "--frames", fifo, "--positions", scan_file, "--reference", scan_file,
                       "-o", out],
            "positions": ["import", "scanning", "--frames", scan_file, "--positions", fifo, "--reference",
                          scan_file, "-o", out],
            "pixel noise": ["check", scan_file, "-o", out, "--set", f"load.pixel_noise={fifo}"]}[role]
    res = cli_capped(*args, timeout=60)  # a hang shows as a TimeoutError
    assert res.exit_code == 2 and one_error_line(res.stderr, "fifo", "FIFO"), res.stderr + res.traceback
    assert not out.exists()


def test_non_utf8_root_attribute_is_refused(tmp_path, rng):
    path = tmp_path / "s.h5"
    write_scan(path, tiny_scan(rng))
    with h5py.File(path, "r+") as f:
        f.attrs["operator"] = np.bytes_(b"M\xfcller")
    for command in ("check", "reconstruct"):
        refused(run(command, path, "-o", tmp_path / "r.h5"), "operator", "UTF-8")


@pytest.mark.parametrize("value", [1e39, 1e300])
def test_counts_beyond_any_detector_are_refused(tmp_path, rng, value):
    path = tmp_path / "s.h5"
    scan = tiny_scan(rng)
    data = scan.data.astype(np.float64)
    data[2, 1, 1] = value  # a lit sample
    write_scan(path, Scan(data=data, position=scan.position, reference=scan.reference))
    for command in ("check", "reconstruct"):
        refused(run(command, path, "-o", tmp_path / "r.h5"), "frame 2", "counts above")


def _unlit(path, J, H, W, dtype, chunks):
    """A scan declaring J frames of H x W in which no row is lit (all positions far below the detector)."""
    with h5py.File(path, "w") as f:
        f.attrs["format"], f.attrs["format_version"] = "dfxcorr-scan", 1
        f.create_dataset(f"{DET}/data", shape=(J, H, W), dtype=dtype, chunks=chunks, compression="gzip")
        f.create_dataset("entry/scan/position", data=np.full(J, H + 10.0))
        for m, value in (("transmission", 1e4), ("visibility", 0.3), ("phase", 0.0)):
            f.create_dataset(f"entry/reference/{m}", data=np.full((3, W), value))


def test_huge_unlit_declaration_refused_within_memory_cap(tmp_path):
    path = tmp_path / "huge.h5"
    _unlit(path, 100000, 100000, 8, np.uint16, (1, 64, 8))
    assert path.stat().st_size < 2e6
    for command in ("check", "reconstruct"):
        res = cli_capped(command, path, "-o", tmp_path / "r.h5")
        assert res.exit_code == 2 and one_error_line(res.stderr, "no detector row is lit"), res.stderr + res.traceback


def test_unlit_float_frames_are_not_read(tmp_path, monkeypatch):
    path = tmp_path / "wide.h5"
    _unlit(path, 2000, 20000, 500, np.float64, (1, 64, 500))
    read = []
    real = h5py.Dataset.__getitem__

    def spy(dset, key):
        out = real(dset, key)
        if dset.name == f"/{DET}/data":
            read.append(np.size(out))
        return out
    monkeypatch.setattr(h5py.Dataset, "__getitem__", spy)
    for command in ("check", "reconstruct"):
        refused(run(command, path, "-o", tmp_path / "r.h5"), "no detector row is lit")
    # the float frames' counts are checked on the lit rows only: here none (160 GB declared)
    assert sum(read) == 0


@pytest.mark.slow
def test_sigterm_inside_a_compiled_kernel_ends_cleanly(tmp_path):
    # a parallel numba kernel returning when the handler has raised: numba wraps the exit in a SystemError
    script = textwrap.dedent("""
        import os, signal, threading
        import numba, numpy as np
        from dfxcorr.cli import _terminate, friendly
        signal.signal(signal.SIGTERM, _terminate)

        @numba.njit(parallel=True)
        def spin(n):
            s = np.zeros(2)
            for k in numba.prange(2):
                for i in range(n):
                    s[k] += np.sin(i)
            return s, s

        spin(1)

        @friendly
        def run():
            threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGTERM)).start()
            spin(10 ** 8)  # seconds, well past the signal: the handler runs when the kernel returns

        run()
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120,
                         check=False, cwd=tmp_path)
    assert res.returncode == 128 + signal.SIGTERM, res.stderr
    assert "SIGTERM" in res.stderr and "Traceback" not in res.stderr


# --------------------------------------------------------------------------------------------------
# check refuses whatever reconstruct refuses before computing
# --------------------------------------------------------------------------------------------------


def _scan_variants():
    H = 8
    return {"one frame": dict(J=1, position=[2.0]),
            "two frames": dict(J=2, position=[2.0, 3.0]),
            "every position below the detector": dict(J=6, position=np.full(6, H + 3.0)),
            "every position above the detector": dict(J=6, position=np.full(6, -10.0)),
            "each row lit in two frames": dict(J=6, A=1, position=np.arange(6) / 2.5)}


@pytest.mark.parametrize("kind", list(_scan_variants()))
def test_check_refuses_what_reconstruct_refuses(tmp_path, rng, kind):
    path = tmp_path / "s.h5"
    write_scan(path, tiny_scan(rng, **_scan_variants()[kind]))
    for command in ("check", "reconstruct"):
        refused(run(command, path, "-o", tmp_path / "r.h5"), "no detector row is lit in at least 3 frames")
    assert not (tmp_path / "r.h5").exists()


@pytest.mark.parametrize("value", [0, 65535])
def test_check_refuses_a_scan_of_nothing_but_faults(tmp_path, rng, value):
    scan = tiny_scan(rng)
    path = tmp_path / "s.h5"
    write_scan(path, Scan(data=np.full(scan.data.shape, value, np.uint16), position=scan.position,
                          reference=scan.reference))
    for command in ("check", "reconstruct"):  # check said ok, reconstruct refused (phase_offset not identifiable)
        refused(run(command, path, "-o", tmp_path / "r.h5"), "every lit sample is a detector fault")


@pytest.mark.parametrize("setting,words", [("align.position_errors={tmp}/pe.txt", ["pe.txt", "expected 12"]),
                                           ("load.pixel_noise={tmp}/pn.tif", ["pn.tif", "shape"])])
def test_check_refuses_configured_files_that_do_not_fit(tmp_path, rng, setting, words):
    path = tmp_path / "s.h5"
    write_scan(path, tiny_scan(rng))
    np.savetxt(tmp_path / "pe.txt", np.zeros(5))
    tifffile.imwrite(tmp_path / "pn.tif", np.ones((3, 3), np.float32))
    refused(run("check", path, "-o", tmp_path / "r.h5", "--set", setting.format(tmp=tmp_path)), *words)


# --------------------------------------------------------------------------------------------------
# Import
# --------------------------------------------------------------------------------------------------


def test_semicolon_log_with_decimal_commas_is_read_right(tmp_path):
    from dfxcorr.importer import StackImportError, read_positions

    (tmp_path / "log.csv").write_text("frame;y\n0;-14,0\n1;-13,5\n2;2,25\n")
    np.testing.assert_array_equal(read_positions(tmp_path / "log.csv", 3, column="y"), [-14.0, -13.5, 2.25])
    (tmp_path / "bare.csv").write_text("0;-14,0\n1;-13,5\n2;2,25\n")  # no header: two columns, refused
    with pytest.raises(StackImportError, match="line 1.*not one number"):
        read_positions(tmp_path / "bare.csv", 3)


def test_repeated_column_names_are_refused(tmp_path):
    from dfxcorr.importer import StackImportError, read_positions

    (tmp_path / "log.csv").write_text("y,y\n1,5\n2,6\n3,7\n")
    with pytest.raises(StackImportError, match=r"\['y'\] more than once"):
        read_positions(tmp_path / "log.csv", 3, column="y")


def test_glob_with_non_ascii_digits_sorts_without_a_traceback(tmp_path, rng):
    from dfxcorr.importer import read_stack

    # superscript two (a digit to str.isdigit, not to int), Arabic-Indic three
    for k, name in enumerate(["f_²", "f_1", "f_٣", "f_10", "f_2", "f_1²2"]):
        np.save(tmp_path / f"{name}.npy", np.full((2, 3), k, np.uint16))
    assert read_stack(str(tmp_path / "f_*.npy"))[:, 0, 0].tolist() == [1, 5, 4, 3, 0, 2]


def test_a_reference_series_already_cropped_to_the_active_area_is_accepted(tmp_path, scan_file):
    from dfxcorr.importer import import_scanning

    scan = io.read_scan(scan_file)
    frames = np.asarray(scan.data[:])
    np.save(tmp_path / "stack.npy", frames)
    np.savetxt(tmp_path / "positions.txt", scan.position)
    rng = np.random.default_rng(5)
    phases = 2 * np.pi * np.arange(5) / 5
    ref = scan.reference
    for k, p in enumerate(phases):  # 15 rows: the active area's size, not the detector's 90
        flat = ref.transmission * (1 + ref.visibility * np.cos(ref.phase + p))
        np.save(tmp_path / f"flat_{k}.npy", rng.poisson(flat).astype(np.uint16))
    out = import_scanning(tmp_path / "s.h5", frames=tmp_path / "stack.npy", positions=tmp_path / "positions.txt",
                          reference_stepping=str(tmp_path / "flat_*.npy"), steps_per_period=5)
    assert out.active_rows == 15
    back = io.read_scan(tmp_path / "s.h5")
    assert back.reference.data.shape == (5, 15, 102)
    # the frames' dark cannot be cropped without knowing where the area sat
    np.save(tmp_path / "dark.npy", np.zeros((90, 102)))
    res = run("import", "scanning", "--frames", tmp_path / "stack.npy", "--positions", tmp_path / "positions.txt",
              "--reference-stepping", tmp_path / "flat_*.npy", "--steps-per-period", "5", "--dark",
              tmp_path / "dark.npy", "-o", tmp_path / "d.h5")
    refused(res, "already cropped", "active_first_row")


def test_negative_int32_reference_counts_are_refused_outside_the_area_too(tmp_path, scan_file):
    scan = io.read_scan(scan_file)
    np.save(tmp_path / "stack.npy", np.asarray(scan.data[:]))
    np.savetxt(tmp_path / "positions.txt", scan.position)
    rng = np.random.default_rng(6)
    for k in range(5):
        flat = rng.poisson(100, (90, 102)).astype(np.int32)
        flat[30:45] += 1000
        flat[80, 7] = -3  # outside the active area
        np.save(tmp_path / f"flat_{k}.npy", flat)
    res = run("import", "scanning", "--frames", tmp_path / "stack.npy", "--positions", tmp_path / "positions.txt",
              "--reference-stepping", tmp_path / "flat_*.npy", "--steps-per-period", "5", "-o", tmp_path / "s.h5")
    refused(res, "negative")
    assert not (tmp_path / "s.h5").exists()


def test_non_finite_stepping_dark_in_a_scan_file_is_refused(tmp_path, rng):
    path = tmp_path / "s.h5"
    H, W = 8, 5
    data = rng.poisson(80, (12, H, W)).astype(np.uint16)
    dark = np.zeros((H, W))
    dark[1, 1] = np.nan
    write_scan(path, Scan(data=data, position=np.zeros(12), reference=io.SteppingReference(
        data=rng.poisson(80, (5, H, W)).astype(np.uint16), phase_step=np.arange(5.0), dark=dark)))
    refused(run("check", path, "-o", tmp_path / "r.h5"), "/entry/reference/stepping/dark", "not finite")


def test_a_compressed_dark_map_that_expands_to_gigabytes_is_refused_within_the_cap(tmp_path):
    path = tmp_path / "bomb.h5"
    H, W = 20000, 20000  # 3.2 GB of float64 zeros, stored in a few MB
    with h5py.File(path, "w") as f:
        f.attrs["format"], f.attrs["format_version"] = "dfxcorr-scan", 1
        f.create_dataset(f"{DET}/data", shape=(6, H, W), dtype=np.uint16, chunks=(1, 64, 2000), compression="gzip")
        f.create_dataset("entry/scan/position", data=np.full(6, H + 10.0))
        dark = f.create_dataset(f"{DET}/dark", shape=(H, W), dtype=np.float64, chunks=(1000, 1000),
                                compression="gzip", compression_opts=9)
        chunk = zlib.compress(np.zeros((1000, 1000)).tobytes(), 9)  # compressed once, stored 400 times
        for r in range(0, H, 1000):
            for c in range(0, W, 1000):
                dark.id.write_direct_chunk((r, c), chunk)
        for m, value in (("transmission", 1e4), ("visibility", 0.3), ("phase", 0.0)):
            f.create_dataset(f"entry/reference/{m}", data=np.full((3, W), value))
    assert path.stat().st_size < 20e6
    res = cli_capped("check", path, "-o", tmp_path / "r.h5")
    assert res.exit_code == 2 and one_error_line(res.stderr, "/entry/instrument/detector/dark", "expands"), (
        res.stderr + res.traceback)


@pytest.mark.slow
def test_disk_full_ends_in_one_line_and_keeps_the_old_result(scan_file, tmp_path):
    out = tmp_path / "r.h5"
    # the write is what fails: no vibration fit is needed before it
    assert run("reconstruct", scan_file, "-o", out, "--method", "none").exit_code == 0
    before = digest(out)
    # a file size limit makes writes fail as a full disk does (EFBIG instead of ENOSPC)
    script = textwrap.dedent("""
        import resource, signal, sys
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (50000, 50000))
        from dfxcorr.cli import main
        main(sys.argv[1:])
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, "-c", script, "reconstruct", str(scan_file), "-o", str(out), "--overwrite",
                          "--method", "none"],
                         capture_output=True, text=True, env=env, timeout=120, check=False, cwd=tmp_path)
    assert res.returncode == 2, res.stderr  # not a segmentation fault after HDF5's tracebacks
    assert one_error_line(res.stderr, "r.h5", "cannot write", "File too large") and "h5py" not in res.stderr
    assert digest(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["r.h5"]


_IMAGES = {f"image_{k}": np.ones((90, 102)) for k in ("transmission", "dark_field", "differential_phase")}


@pytest.mark.parametrize("arrays,words", [
    ({"image_transmission": np.ones((90, 102))}, ["no image_dark_field"]),
    ({**_IMAGES, "image_transmission": np.full((90, 102), "a")}, ["image_transmission", "not finite real"]),
    ({**_IMAGES, "image_dark_field": np.full((90, 102), np.nan)}, ["image_dark_field", "not finite real"]),
    ({**_IMAGES, "vib_phase_offset": np.ones((104, 0))}, ["vib_phase_offset", "(104, 0)"]),
    ({**_IMAGES, "extra": np.zeros((4000, 4000), np.uint8)}, ["extra.npy", "expands beyond"]),
])
def test_degenerate_truth_files_are_refused(scan_file, tmp_path, arrays, words):
    np.savez_compressed(tmp_path / "t.npz", **arrays)
    res = run("compare", scan_file, "-o", tmp_path / "cmp", "--truth", tmp_path / "t.npz", "--methods", "none")
    refused(res, "t.npz", *words)
    assert not (tmp_path / "cmp").exists()


def test_nps_of_a_scan_without_phase_variation_is_refused(tmp_path, rng):
    J, H, W, A = 30, 20, 16, 6
    ref = Reference(np.full((A, W), 1000.0), np.full((A, W), 0.3), np.zeros((A, W)))  # no fringe along the scan
    write_scan(tmp_path / "flat.h5", Scan(data=rng.poisson(1000, (J, H, W)).astype(np.uint16),
                                          position=np.linspace(-A, H, J), reference=ref))
    # the fringe frequency is 0: the default rings divided by it
    refused(run("nps", tmp_path / "flat.h5", "-o", tmp_path / "nps", "--methods", "none"), "flat.h5", "no finite pixel")


@pytest.mark.parametrize("setting,words", [
    ("simulate.height_mm=1e300", ["more than", "samples"]), ("simulate.pixel_mm=1e-300", ["more than"]),
    ("simulate.step_mm=1e-9", ["5.25e+11 frames"]), ("simulate.width_mm=1e-9", ["450 x 0 pixels"]),
    ("simulate.active_mm=1e-9", ["active area of 0 rows"]), ("simulate.flux=1e300", ["simulate.flux"]),
    ("effects.dose=1e300", ["effects.dose"]), ("simulate.reference_steps=1000000000", ["reference_steps"]),
    ("simulate.steps=1000000000", ["simulate.steps"]),
])
def test_simulate_at_extreme_settings_is_refused_before_allocating(tmp_path, setting, words):
    res = cli_capped("simulate", "-o", tmp_path / "s.h5", "--set", setting, timeout=60)
    assert res.exit_code == 2 and one_error_line(res.stderr, *words), res.stderr + res.traceback
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------------
# Counts, gains and fits outside what a detector and its noise allow
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("stepping", [True, False], ids=["stepping recording", "scan with a stepping reference"])
def test_negative_counts_in_a_signed_integer_reference_are_refused(tmp_path, scan_file, stepping):
    rng = np.random.default_rng(7)
    scan = io.read_scan(scan_file)
    A, W = (scan.shape[1], scan.shape[2]) if stepping else (scan.active_rows, scan.shape[2])
    phases = 2 * np.pi * np.arange(5) / 5
    series = np.stack([rng.poisson(400 * (1 + 0.3 * np.cos(p)), (A, W)) for p in phases]).astype(np.int32)
    series[2, 3, 4] = -40
    ref = io.SteppingReference(data=series, phase_step=phases)
    if stepping:
        sample = Scan(data=rng.poisson(300, (5, A, W)).astype(np.uint16), position=np.zeros(5), reference=ref,
                      phase_step=phases)
    else:
        sample = Scan(data=np.asarray(scan.data[:]), position=scan.position, reference=ref)
    write_scan(tmp_path / "s.h5", sample)
    for command in ("check", "reconstruct"):
        refused(run(command, tmp_path / "s.h5", "-o", tmp_path / "r.h5"), "/entry/reference/stepping/data",
                "negative")
    assert not (tmp_path / "r.h5").exists()


@pytest.mark.parametrize("gain", [1e-100, 1e-300, 1e9])
@pytest.mark.parametrize("source", ["load.gain", "scan file"])
def test_a_gain_no_detector_has_is_refused_alike_by_check_and_reconstruct(tmp_path, scan_file, gain, source):
    path, sets = scan_file, ["--set", f"load.gain={gain}"]
    if source == "scan file":
        path, sets = tmp_path / "s.h5", []
        write_scan(path, io.read_scan(scan_file))
        with h5py.File(path, "r+") as f:
            if "gain" in f[DET]:
                del f[f"{DET}/gain"]
            f[f"{DET}/gain"] = gain
    lines = []
    for command in ("check", "reconstruct"):
        res = run(command, path, "-o", tmp_path / "r.h5", *sets)
        refused(res, "gain", "[1e-06, 1e+06]")
        lines.append(res.stderr)
    assert lines[0] == lines[1]
    assert not (tmp_path / "r.h5").exists()


def _misfit(path) -> bool:
    from dfxcorr.export import read_result_h5

    return read_result_h5(path)["misfit"]


@pytest.mark.parametrize("fault", [pytest.param("two positions swapped", marks=pytest.mark.slow),
                                   "gain stated 1e4 times too high"])
def test_reconstruct_warns_of_and_marks_a_fit_noise_cannot_explain(tmp_path, scan_file, fault):
    from dataclasses import replace

    path, sets = scan_file, []
    if fault == "two positions swapped":
        scan = io.read_scan(scan_file)
        position = scan.position.copy()
        position[[40, 45]] = position[[45, 40]]
        path = tmp_path / "s.h5"
        write_scan(path, replace(scan, data=np.asarray(scan.data[:]), position=position))
    else:
        sets = ["--set", "load.gain=1e4"]
    res = run("reconstruct", path, "-o", tmp_path / "r.h5", *sets)
    assert res.exit_code == 0, res.output
    warning = [ln for ln in res.stderr.splitlines() if "WARNING" in ln and "reduced chi-square" in ln]
    assert len(warning) == 1 and "dfxcorr diagnose" in warning[0], res.stderr
    assert "outside what noise allows" in res.stdout
    assert _misfit(tmp_path / "r.h5")


def test_a_clean_scan_is_not_marked_a_misfit(tmp_path, scan_file):
    res = run("reconstruct", scan_file, "-o", tmp_path / "r.h5")
    assert res.exit_code == 0, res.output
    assert "WARNING" not in res.stderr and not _misfit(tmp_path / "r.h5")


# --------------------------------------------------------------------------------------------------
# A diagnosis folder: every file checked first, replaced as a unit
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("role", ["scan", "config"])
def test_diagnose_never_replaces_an_input_named_like_an_effect_picture(tmp_path, scan_file, role):
    out = tmp_path / "diag"
    out.mkdir()
    picture = out / "effect-dose.png"
    if role == "scan":
        picture.write_bytes(scan_file.read_bytes())
        args = [picture]
    else:
        picture.write_text("fit:\n  subsample: 4\n")
        args = [scan_file, "-c", picture]
    before = digest(picture)
    refused(run("diagnose", *args, "-o", out, "--overwrite"), "effect-dose.png", "also an input")
    assert digest(picture) == before


def test_diagnose_refuses_the_working_directory_as_its_folder(tmp_path, scan_file, monkeypatch):
    monkeypatch.chdir(tmp_path)
    refused(run("diagnose", scan_file, "-o", "."), "working directory")
    refused(run("diagnose", scan_file, "-o", tmp_path.parent), "working directory")


@pytest.mark.slow
def test_an_overwrite_diagnosis_leaves_no_file_of_the_previous_run(tmp_path, scan_file):
    out = tmp_path / "diag"
    out.mkdir()
    tifffile.imwrite(out / "pixel_noise.tif", np.ones((7, 7), np.float32))  # another scan's map
    (out / "effect-harmonic.png").write_bytes(b"old")
    (out / "report.md").write_text("old")
    (out / "notes.txt").write_text("kept")
    res = run("diagnose", scan_file, "-o", out, "--overwrite", "--set", "diagnose.subsample=4")
    assert res.exit_code == 0, res.output
    import json
    doc = json.loads((out / "diagnosis.json").read_text())
    names = {p.name for p in out.iterdir()}
    pictures = {f"effect-{e['name']}.png" for e in doc["effects"] if e["detected"]}
    assert names == {"diagnosis.json", "report.md", "residuals.png", "signatures.png", "notes.txt", *pictures}
    assert (out / "report.md").read_text().startswith("# dfxcorr diagnose") and not list(tmp_path.glob(".diag*"))


@pytest.mark.parametrize("base", ["none", "configured"])
def test_diagnosis_of_a_recording_without_residual_dof_is_refused_before_computing(tmp_path, base):
    scan = S.simulate(sim_config(**{"simulate.geometry": "stepping", "simulate.steps": 3,
                                    "simulate.steps_per_period": 3}))[0]
    write_scan(tmp_path / "s.h5", scan)
    refused(run("diagnose", tmp_path / "s.h5", "-o", tmp_path / "diag", "--base", base), "at most 3 frames",
            "no residual")
    assert not (tmp_path / "diag").exists()


# --------------------------------------------------------------------------------------------------
# check and reconstruct judge a run alike
# --------------------------------------------------------------------------------------------------


def _identifiability_cases():
    def scan(**overrides):
        return S.simulate(sim_config(**overrides))[0]

    def frames(keep):
        from dataclasses import replace

        s = scan()
        return replace(s, data=s.data[keep], position=s.position[keep],
                       exposure_time=None if s.exposure_time is None else s.exposure_time[keep])

    def empty_but(keep):
        s = scan()
        data = np.zeros_like(s.data)
        data[keep] = s.data[keep]
        s.data = data
        return s

    stepping = {"simulate.geometry": "stepping", "simulate.steps": 3, "simulate.steps_per_period": 3}
    return {"3 frames": (lambda: frames([40, 45, 50]), []),
            "3-step stepping": (lambda: scan(**stepping), []),
            "background=true": (scan, ["vibration.background=true"]),
            "all but 3 frames empty": (lambda: empty_but([30, 50, 70]), []),
            "diagnose.subsample=1000": (scan, ["diagnose.subsample=1000"])}


@pytest.mark.parametrize("case", [pytest.param(c, marks=pytest.mark.slow) if "=" in c else c
                                  for c in _identifiability_cases()])
def test_check_and_reconstruct_judge_a_run_alike(tmp_path, case):
    make, sets = _identifiability_cases()[case]
    write_scan(tmp_path / "s.h5", make())
    args = [a for s in sets for a in ("--set", s)]
    checked = run("check", tmp_path / "s.h5", "-o", tmp_path / "r.h5", *args)
    done = run("reconstruct", tmp_path / "s.h5", "-o", tmp_path / "r.h5", *args)
    assert checked.exit_code == done.exit_code, (checked.output, done.output)
    if done.exit_code == 2:
        refused(checked, "not identifiable")
        assert ([ln for ln in checked.stderr.splitlines() if ln.startswith("error:")]
                == [ln for ln in done.stderr.splitlines() if ln.startswith("error:")])
    else:
        assert done.exit_code == 0 and "ok: reconstruct would run" in checked.stdout, done.output
