"""The command line end to end: CliRunner for the commands, a subprocess for the installed entry point."""
import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from dfxcorr.cli import main
from dfxcorr.export import read_result_h5

from conftest import ROOT

SMALL = ["--set", "simulate.pixel_mm=5", "--set", "simulate.step_mm=5", "--set", "simulate.seed=3"]


@pytest.fixture(scope="module")
def scan_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("scan")
    res = CliRunner().invoke(main, ["simulate", "-o", str(d / "scan.h5"), *SMALL])
    assert res.exit_code == 0, res.output
    return d / "scan.h5"


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_simulate_writes_scan_and_truth(scan_file):
    truth = np.load(scan_file.with_name("scan.truth.npz"))
    with h5py.File(scan_file) as f:
        assert f.attrs["format"] == "dfxcorr-scan"
        assert f["entry/instrument/detector/data"].shape == (104, 90, 102)
    assert truth["vib_phase_offset"].shape == (104,)


@pytest.fixture(scope="module")
def reconstructed(scan_file, tmp_path_factory):
    """A reconstruction of ``scan_file`` with TIFF images and a preview: the folder and the command's outcome."""
    d = tmp_path_factory.mktemp("reconstructed")
    res = run("reconstruct", scan_file, "-o", d / "r.h5", "--set", "fit.subsample=3", "--tiff", d / "tif", "--preview")
    return d, res


def test_reconstruct_writes_the_contract(reconstructed):
    tmp_path, res = reconstructed
    assert res.exit_code == 0, res.output
    r = read_result_h5(tmp_path / "r.h5")
    assert r["transmission"].shape == (90, 102) and r["transmission"].dtype == np.float32
    assert r["configuration"]["fit"]["subsample"] == 3
    assert 0.9 < r["reduced_chi2"] < 1.1
    for name in ("transmission", "dark_field", "differential_phase"):
        assert (tmp_path / "tif" / f"r_{name}.tif").exists()
    assert yaml.safe_load((tmp_path / "tif" / "r.yaml").read_text())["fit"]["subsample"] == 3
    assert (tmp_path / "r_preview.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_resolved_configuration_reproduces_the_run(scan_file, reconstructed, tmp_path):
    first = reconstructed[0] / "r.h5"
    assert reconstructed[1].exit_code == 0, reconstructed[1].output
    cfg = tmp_path / "resolved.yaml"
    with h5py.File(first) as f:
        cfg.write_text(f["entry/dfxcorr/configuration"][()].decode())
    second = tmp_path / "b.h5"
    assert run("reconstruct", scan_file, "-o", second, "-c", cfg).exit_code == 0
    a, b = read_result_h5(first), read_result_h5(second)
    np.testing.assert_array_equal(a["dark_field"], b["dark_field"])
    np.testing.assert_array_equal(a["vibration"]["tilt"], b["vibration"]["tilt"])


def refused(res, *words):
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.strip().splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, res.output
    assert "Traceback" not in res.output
    for w in words:
        assert w in lines[0], lines[0]


def test_config_typo_is_refused_with_a_suggestion(scan_file, tmp_path):
    out = tmp_path / "r.h5"
    refused(run("reconstruct", scan_file, "-o", out, "--set", "fit.subsampel=3"), "fit.subsampel", "subsample")
    assert not out.exists()


def test_non_hdf5_input_is_refused(tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    out = tmp_path / "r.h5"
    refused(run("reconstruct", bad, "-o", out), "not an HDF5 file")
    assert not out.exists() and not list(tmp_path.glob(".*part"))


def test_scan_spec_refusal_names_the_dataset(scan_file, tmp_path):
    broken = tmp_path / "broken.h5"
    shutil.copy(scan_file, broken)
    with h5py.File(broken, "r+") as f:
        del f["entry/reference/visibility"]
        f["entry/reference/visibility"] = np.full((15, 102), 1.5)
    out = tmp_path / "r.h5"
    refused(run("reconstruct", broken, "-o", out), "/entry/reference/visibility")
    assert not out.exists()


def test_existing_output_is_refused_without_overwrite(scan_file, tmp_path):
    out = tmp_path / "r.h5"
    out.write_bytes(b"keep me")
    refused(run("reconstruct", scan_file, "-o", out), "--overwrite")
    assert out.read_bytes() == b"keep me"


def test_stepping_scan_with_visibility_is_refused(tmp_path):
    scan = tmp_path / "step.h5"
    assert run("simulate", "-o", scan, *SMALL, "--set", "simulate.geometry=stepping",
               "--set", "effects.visibility_loss=0").exit_code == 0
    refused(run("reconstruct", scan, "-o", tmp_path / "r.h5", "--set", "vibration.visibility=true"),
            "visibility_loss", "not identifiable")
    res = run("reconstruct", scan, "-o", tmp_path / "r.h5")  # auto: fitted where identifiable, else not
    assert res.exit_code == 0, res.output
    assert not read_result_h5(tmp_path / "r.h5")["estimated"]["visibility"]


def test_config_defaults_and_check(tmp_path):
    res = run("config", "--defaults")
    assert res.exit_code == 0 and "subsample: auto" in res.output
    f = tmp_path / "my.yaml"
    f.write_text("fit:\n  subsample: 7\n")
    res = run("config", "--check", f)
    assert res.exit_code == 0 and yaml.safe_load(res.output)["fit"]["subsample"] == 7


@pytest.mark.slow
def test_installed_entry_point_runs_in_a_subprocess(scan_file, tmp_path):
    exe = shutil.which("dfxcorr")
    cmd = [exe] if exe else [sys.executable, "-m", "dfxcorr.cli"]
    out = tmp_path / "r.h5"
    proc = subprocess.run([*cmd, "reconstruct", str(scan_file), "-o", str(out), "--set", "fit.subsample=4"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert out.exists()
    # not a terminal: progress arrives as plain log lines, no carriage-return bars
    assert "\r" not in proc.stderr and "vibration fit: done" in proc.stderr
    proc = subprocess.run([*cmd, "reconstruct", str(scan_file), "-o", str(out)], capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.strip().startswith("error:") and "Traceback" not in proc.stderr


def test_module_entry_point_knows_every_command():
    # python -m runs the module's guard: a command registered below it would be unknown there
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    listing = subprocess.run([sys.executable, "-m", "dfxcorr.cli", "--help"], capture_output=True, text=True,
                             env=env, timeout=120)
    assert listing.returncode == 0, listing.stderr
    commands = [ln.split()[0] for ln in listing.stdout.split("Commands:")[1].splitlines() if ln.strip()]
    assert set(main.commands) <= set(commands), (sorted(main.commands), listing.stdout)
    proc = subprocess.run([sys.executable, "-m", "dfxcorr.cli", "batch", "--help"], capture_output=True, text=True,
                          env=env, timeout=120)
    assert proc.returncode == 0 and "--array-index" in proc.stdout, proc.stderr
