"""Unattended safety (output side): no output is ever an input, concurrent and interrupted runs
leave nothing behind, every refusal comes before any work as one line on stderr with exit code 2, and
configurations cannot expand. ``dfxcorr check`` tells in seconds whether ``reconstruct`` would run."""
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from dfxcorr import check, io
from dfxcorr import config as C
from dfxcorr.cli import main
from dfxcorr.errors import OutputExistsError
from dfxcorr.sim import simulate as S

from conftest import ROOT, sim_config

SMALL = ["--set", "simulate.pixel_mm=5", "--set", "simulate.step_mm=5", "--set", "simulate.seed=3"]


@pytest.fixture(scope="module")
def scan_file(tmp_path_factory):
    """A small scan (104 frames of 90 x 102) in a folder of its own."""
    path = tmp_path_factory.mktemp("scan") / "scan.h5"
    io.write_scan(path, S.simulate(sim_config())[0])
    return path


@pytest.fixture(scope="module")
def stepping_files(tmp_path_factory):
    """Sample and reference series of a phase-stepping recording as .npy files (5 steps of 8 x 9)."""
    d = tmp_path_factory.mktemp("steps")
    rng = np.random.default_rng(11)
    phase = 2 * np.pi * np.arange(5) / 5
    for prefix in ("s", "f"):
        for k, p in enumerate(phase):
            np.save(d / f"{prefix}_{k}.npy", rng.poisson(400 * (1 + 0.3 * np.cos(p + np.arange(9) / 3)),
                                                          (8, 9)).astype(np.uint16))
    return d


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def refused(res, *words):
    """Exit code 2, exactly one line on stderr naming ``words``, no traceback."""
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    assert "Traceback" not in res.output
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def digest(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def leftovers(folder) -> list[str]:
    return sorted(p.name for p in Path(folder).rglob("*") if p.name.endswith(".part") or "probe" in p.name)


# --------------------------------------------------------------------------------------------------
# 1. No output is ever an input, whatever the spelling
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("spelling", ["relative", "absolute", "symlink", "hardlink"])
def test_reconstruct_never_replaces_its_scan(scan_file, tmp_path, monkeypatch, spelling):
    work = tmp_path / "w"
    work.mkdir()
    scan = work / "in.h5"
    scan.write_bytes(scan_file.read_bytes())
    before = digest(scan)
    monkeypatch.chdir(work)
    out = {"relative": "./in.h5", "absolute": str(scan), "symlink": "link.h5", "hardlink": "hard.h5"}[spelling]
    if spelling == "symlink":
        os.symlink("in.h5", "link.h5")
    if spelling == "hardlink":
        os.link("in.h5", "hard.h5")
    refused(run("reconstruct", "in.h5", "-o", out, "--overwrite"), "is also an input")
    assert digest(scan) == before


def test_outputs_are_not_the_configuration(scan_file, tmp_path):
    cfg = tmp_path / "my.yaml"
    cfg.write_text("fit:\n  subsample: 4\n")
    refused(run("reconstruct", scan_file, "-o", cfg, "-c", cfg, "--overwrite"), "my.yaml", "is also an input")
    refused(run("reconstruct", scan_file, "-o", tmp_path / "my.h5", "-c", cfg, "--tiff", tmp_path, "--overwrite"),
            "my.yaml", "is also an input")  # the TIFFs' configuration is <output stem>.yaml
    refused(run("simulate", cfg, "-o", cfg, "--overwrite"), "is also an input")
    assert cfg.read_text() == "fit:\n  subsample: 4\n"


def test_import_never_replaces_a_source_file(stepping_files, tmp_path):
    source = stepping_files / "s_0.npy"
    before = digest(source)
    args = ["import", "stepping", "--sample", stepping_files / "s_*.npy", "--reference", stepping_files / "f_*.npy",
            "--steps-per-period", "5", "--overwrite", "-o"]
    refused(run(*args, source), "s_0.npy", "is also an input")
    refused(run(*args, stepping_files / "f_3.npy"), "is also an input")
    assert digest(source) == before
    res = run(*args, tmp_path / "ok.h5")
    assert res.exit_code == 0, res.output


def test_log_file_is_opened_only_after_the_check(scan_file, tmp_path):
    before = digest(scan_file)
    refused(run("--log-file", scan_file, "reconstruct", scan_file, "-o", tmp_path / "r.h5"),
            "scan.h5", "is also an input")
    assert digest(scan_file) == before and not (tmp_path / "r.h5").exists()
    refused(run("--log-file", tmp_path / "missing" / "x.log", "check", scan_file), "missing", "does not exist")
    refused(run("--log-file", tmp_path / "r.h5", "check", scan_file, "-o", tmp_path / "r.h5"), "written twice")
    res = run("--log-file", tmp_path / "ok.log", "check", scan_file, "-o", tmp_path / "r.h5")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "ok.log").exists()


# --------------------------------------------------------------------------------------------------
# 2., 3. Concurrent and interrupted runs
# --------------------------------------------------------------------------------------------------


def test_concurrent_runs_to_one_output_never_share_a_temporary_file(tmp_path):
    out = tmp_path / "out.h5"
    with pytest.raises(OutputExistsError), io.atomic_path(out) as tmp_a:  # run A holds its temporary file ...
        tmp_a.write_bytes(b"run A")
        res = run("simulate", "-o", out, *SMALL)  # ... while run B writes the same output
        assert res.exit_code == 0, res.output
        assert tmp_a.exists()  # B neither took nor removed A's temporary file
    # A, finishing second without --overwrite, refused to replace B's result and removed only its own file
    with h5py.File(out) as f:
        assert f.attrs["format"] == "dfxcorr-scan"
    assert leftovers(tmp_path) == []


def test_with_overwrite_the_last_complete_run_wins(tmp_path):
    out = tmp_path / "out.txt"
    with io.atomic_path(out, overwrite=True) as a, io.atomic_path(out, overwrite=True) as b:
        assert a != b
        a.write_text("A")
        b.write_text("B")
    assert out.read_text() == "A" and leftovers(tmp_path) == []


@pytest.mark.slow
def test_sigterm_while_writing_leaves_nothing(tmp_path):
    # the CLI's own handler, a real SIGTERM while the scan's temporary file is open
    script = textwrap.dedent("""
        import os, signal, sys
        import h5py
        from dfxcorr.cli import main
        opened = h5py.File.__init__
        def init(self, name, *args, **kwargs):
            opened(self, name, *args, **kwargs)
            if str(name).endswith(".part"):
                os.kill(os.getpid(), signal.SIGTERM)
        h5py.File.__init__ = init
        main(sys.argv[1:])
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, "-c", script, "simulate", "-o", str(tmp_path / "out.h5"), *SMALL],
                         capture_output=True, text=True, env=env, timeout=120, check=False)
    assert res.returncode == 128 + signal.SIGTERM, res.stderr
    assert "SIGTERM" in res.stderr and "Traceback" not in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------------
# 4. Every output checked before any work
# --------------------------------------------------------------------------------------------------


def test_an_existing_tiff_or_picture_is_refused_before_the_run(scan_file, tmp_path):
    (tmp_path / "tif").mkdir()
    (tmp_path / "tif" / "r_dark_field.tif").write_bytes(b"old")
    refused(run("reconstruct", scan_file, "-o", tmp_path / "r.h5", "--tiff", tmp_path / "tif"), "r_dark_field.tif",
            "exists")
    (tmp_path / "r_fit.png").write_bytes(b"old")
    refused(run("reconstruct", scan_file, "-o", tmp_path / "r.h5", "--preview"), "r_fit.png", "exists")
    assert not (tmp_path / "r.h5").exists() and not (tmp_path / "r_preview.png").exists()


def test_an_unwritable_folder_is_refused_before_the_run(scan_file, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    chattr = shutil.which("chattr")
    immutable = bool(chattr) and subprocess.run([chattr, "+i", str(ro)], capture_output=True,
                                                 check=False).returncode == 0
    if not immutable:
        if os.geteuid() == 0:
            pytest.skip("root without chattr: every folder is writable")
        ro.chmod(0o555)
    try:
        refused(run("reconstruct", scan_file, "-o", ro / "r.h5"), "ro")
        refused(run("diagnose", scan_file, "-o", ro / "sub"), "ro")
    finally:
        if immutable:
            subprocess.run([chattr, "-i", str(ro)], capture_output=True, check=False)
        ro.chmod(0o755)
    assert list(ro.iterdir()) == []


def test_names_that_cannot_be_written_are_refused_before_the_run(scan_file, tmp_path):
    long = "a" * (255 - io.TEMP_NAME_OVERHEAD - 2) + ".h5"  # fits alone, not with its temporary name
    refused(run("reconstruct", scan_file, "-o", tmp_path / long), "too long")
    refused(run("reconstruct", scan_file, "-o", tmp_path / "\udcff.h5"), "not valid UTF-8")  # byte 0xff
    (tmp_path / "file").write_text("x")
    refused(run("reconstruct", scan_file, "-o", tmp_path / "file" / "r.h5"), "is not a folder")
    (tmp_path / "r_preview.png").mkdir()
    refused(run("reconstruct", scan_file, "-o", tmp_path / "r.h5", "--preview", "--overwrite"), "is a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "r_preview.png"]


def test_demo_checks_all_its_outputs_first(tmp_path):
    (tmp_path / "tiff").mkdir()
    (tmp_path / "tiff" / "result.yaml").write_text("old")
    refused(run("demo", tmp_path), "result.yaml", "exists")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiff"]


# --------------------------------------------------------------------------------------------------
# 6. Configurations cannot expand, repeat keys or hide bad bytes
# --------------------------------------------------------------------------------------------------

LAUGHS = """\
a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]
b: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]
c: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]
d: &d [*c,*c,*c,*c,*c,*c,*c,*c,*c]
e: &e [*d,*d,*d,*d,*d,*d,*d,*d,*d]
f: &f [*e,*e,*e,*e,*e,*e,*e,*e,*e]
fit:
  subsample: [*f,*f,*f,*f,*f,*f,*f,*f,*f]
"""


@pytest.mark.parametrize("text,words", [
    (LAUGHS, ["line 2", "aliases"]),
    ("fit:\n  subsample: 3\nalign:\n  min_frames: 3\nfit:\n  maxiter: 5\n", ["line 5", "duplicate key 'fit'"]),
    ("fit: {subsample: 3, subsample: 4}\n", ["duplicate key 'subsample'"]),
], ids=["billion-laughs", "repeated-section", "repeated-key"])
def test_configurations_that_expand_or_repeat_are_refused(tmp_path, text, words):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    line = refused(run("config", "--check", cfg), "c.yaml", *words)
    assert len(line) < 200


def test_bad_bytes_and_huge_values_are_named_briefly(tmp_path):
    cfg = tmp_path / "latin1.yaml"
    cfg.write_bytes(b"fit:\n  method: r\xe9gression\n")
    refused(run("config", "--check", cfg), "latin1.yaml", "not UTF-8", "0xe9")
    line = refused(run("config", "--set", "fit.subsample=" + "x" * 10000), "fit.subsample")
    assert len(line) < 200
    refused(run("config", "--set", "fit.subsample=[&a 1, *a]"), "aliases")
    with pytest.raises(C.ConfigError, match="fit.method must be one of"):
        C.validate_value("fit", "method", "y" * 10 ** 6)


# --------------------------------------------------------------------------------------------------
# 8. Refusals instead of tracebacks
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("command,setting,words", [
    ("reconstruct", "fit.subsample=204", ["fit.subsample=204", "no column"]),
    ("reconstruct", "fit.column_offset=102", ["fit.column_offset=102", "outside"]),
    ("reconstruct", "mask.dilate=100000", ["mask.dilate", "exceeds the detector"]),
    ("reconstruct", "load.gain=.inf", ["load.gain", "finite"]),
    ("diagnose", "diagnose.subsample=1000", ["diagnose.subsample=1000"]),
])
def test_configuration_beyond_the_scan_is_refused_before_the_run(scan_file, tmp_path, command, setting, words):
    refused(run(command, scan_file, "-o", tmp_path / "out", "--set", setting), *words)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kind", ["empty", "pickled", "single-array", "missing"])
def test_a_bad_truth_file_is_refused_without_unpickling(scan_file, tmp_path, kind):
    truth = tmp_path / "t.npz"
    if kind == "empty":
        truth.write_bytes(b"")
    elif kind == "pickled":
        np.savez(truth, image_transmission=np.array([{"x": 1}], dtype=object))
    elif kind == "single-array":
        np.save(tmp_path / "t.npy", np.zeros(3))
        truth = tmp_path / "t.npy"
    refused(run("compare", scan_file, "-o", tmp_path / "cmp", "--truth", truth, "--methods", "none"), truth.name)
    assert not (tmp_path / "cmp").exists()


# --------------------------------------------------------------------------------------------------
# dfxcorr check
# --------------------------------------------------------------------------------------------------


def test_check_says_what_reconstruct_would_do(scan_file, tmp_path):
    res = run("check", scan_file, "-o", tmp_path / "r.h5", "--tiff", tmp_path / "tif", "--preview",
              "--set", "fit.subsample=10")
    assert res.exit_code == 0, res.output
    out = res.stdout
    assert "104 frames of 90 x 102" in out and "active area 15 rows" in out
    assert "ml on 10 of 102 columns" in out  # columns 5, 15, ..., 95
    assert "r_fit.png" in out and "r.yaml" in out
    assert list(tmp_path.iterdir()) == []
    refused(run("check", scan_file, "--set", "fit.subsample=60"), "fit.subsample=60")  # alias limit


def test_check_memory_estimate_counts_lit_samples(scan_file):
    scan = io.read_scan(scan_file, header_only=True)
    p = check.plan(scan, C.defaults())
    J, H, W = scan.shape
    # every row of this scan is lit in A = 15 frames
    assert p.lit_samples == H * 15 * W
    # the store, the images, the row blocks, the fit's columns: more than the lit rows, and the row blocks
    # trade memory one for one
    assert p.memory_bytes > p.lit_samples * 2 + check.BASE_BYTES
    more = check.plan(scan, C.load([], ["retrieve.block_mb=1256"]))
    assert more.memory_bytes - p.memory_bytes == 1000 * 10 ** 6
    full = io.read_scan(scan_file)
    assert check.plan(full, C.defaults()).lit_samples == p.lit_samples


def test_check_refuses_visibility_loss_in_phase_stepping(stepping_files, tmp_path):
    scan = tmp_path / "steps.h5"
    res = run("import", "stepping", "--sample", stepping_files / "s_*.npy", "--reference",
              stepping_files / "f_*.npy", "--steps-per-period", "5", "-o", scan)
    assert res.exit_code == 0, res.output
    fit = ["--set", "fit.subsample=2"]  # 9 columns
    res = run("check", scan, "-o", tmp_path / "r.h5", *fit)
    assert res.exit_code == 0 and "visibility_loss will not be fitted" in res.stdout, res.output
    refused(run("check", scan, *fit, "--set", "vibration.visibility=true"), "visibility_loss",
            "vibration.visibility=false")
    refused(run("reconstruct", scan, "-o", tmp_path / "r.h5", *fit, "--set", "vibration.visibility=true"),
            "visibility_loss")
    assert not (tmp_path / "r.h5").exists()


def test_check_refuses_a_scan_that_is_not_one(tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    refused(run("check", bad), "bad.h5", "not an HDF5 file")
    refused(run("reconstruct", bad, "-o", tmp_path / "r.h5"), "not an HDF5 file")
