"""Issue 21, reliability round two: inputs named by the configuration never replaced, no traceback and no hang on
hostile inputs (FIFOs, huge declarations, absurd numbers, a signal inside a compiled kernel), and ``check`` refusing
whatever ``reconstruct`` refuses before computing."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile
from capped import cli_capped, one_error_line
from click.testing import CliRunner

from dfxcorr import io
from dfxcorr.cli import main
from dfxcorr.io import Reference, Scan, write_scan
from dfxcorr.sim import simulate as S

from conftest import sim_config

DET = "entry/instrument/detector"
ROOT = Path(__file__).resolve().parents[1]


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


def test_unlit_float_frames_are_not_read(tmp_path):
    path = tmp_path / "wide.h5"
    _unlit(path, 2000, 20000, 500, np.float64, (1, 64, 500))
    t0 = time.perf_counter()
    for command in ("check", "reconstruct"):
        refused(run(command, path, "-o", tmp_path / "r.h5"), "no detector row is lit")
    assert time.perf_counter() - t0 < 5  # 33 s each before: every declared frame was read


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
            spin(10 ** 9)

        run()
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120,
                         check=False)
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


@pytest.mark.parametrize("setting,words", [("align.position_errors={tmp}/pe.txt", ["pe.txt", "expected 12"]),
                                           ("load.pixel_noise={tmp}/pn.tif", ["pn.tif", "shape"])])
def test_check_refuses_configured_files_that_do_not_fit(tmp_path, rng, setting, words):
    path = tmp_path / "s.h5"
    write_scan(path, tiny_scan(rng))
    np.savetxt(tmp_path / "pe.txt", np.zeros(5))
    tifffile.imwrite(tmp_path / "pn.tif", np.ones((3, 3), np.float32))
    refused(run("check", path, "-o", tmp_path / "r.h5", "--set", setting.format(tmp=tmp_path)), *words)
