"""dfxcorr batch: one process per scan, failures isolated, resumable, and one task of a SLURM array."""
from dataclasses import replace

import h5py
import pytest
from click.testing import CliRunner

from dfxcorr import io
from dfxcorr.cli import main
from dfxcorr.sim import simulate as S

from conftest import sim_config

TINY = ["--set", "simulate.pixel_mm=10", "--set", "simulate.step_mm=10"]
FIT = ["--set", "fit.subsample=4"]  # 51 columns


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    d = tmp_path_factory.mktemp("scans")
    for k, name in enumerate(("a", "b")):
        res = CliRunner().invoke(main, ["simulate", "-o", str(d / f"{name}.h5"), *TINY,
                                        "--set", f"simulate.seed={k + 1}"])
        assert res.exit_code == 0, res.output
    (d / "broken.h5").write_bytes(b"not an HDF5 file")
    listing = d / "scans.txt"
    listing.write_text(f"# scans of the day\n{d / 'a.h5'}\n\n{d / 'broken.h5'}\n{d / 'b.h5'}\n")
    return d, listing


def run(*args, env=None):
    return CliRunner().invoke(main, [str(a) for a in args], env=env)


def is_result(path):
    with h5py.File(path, "r") as f:
        return f.attrs["format"] == "dfxcorr-result"


@pytest.mark.slow
def test_a_failed_scan_does_not_stop_the_others_and_a_rerun_resumes(scans, tmp_path):
    d, listing = scans
    out = tmp_path / "out"
    res = run("batch", listing, "-o", out, "--jobs", "2", *FIT, env={"SLURM_ARRAY_TASK_ID": None})
    assert res.exit_code == 1, res.output
    assert is_result(out / "a.h5") and is_result(out / "b.h5")
    assert not (out / "broken.h5").exists()
    table = res.stdout.splitlines()
    row = {line.split()[0]: line.split()[1] for line in table[1:-1]}
    assert row == {str(d / "a.h5"): "done", str(d / "broken.h5"): "failed", str(d / "b.h5"): "done"}
    assert "not an HDF5 file" in res.output and "not an HDF5 file" in (out / "broken.log").read_text()
    assert table[-1] == "3 scans: 2 done, 0 skipped, 1 failed"
    again = run("batch", listing, "-o", out, *FIT, env={"SLURM_ARRAY_TASK_ID": None})
    assert again.exit_code == 1
    assert again.stdout.splitlines()[-1] == "3 scans: 0 done, 2 skipped, 1 failed"


@pytest.mark.slow
def test_one_task_of_a_job_array_processes_its_line_only(scans, tmp_path):
    d, listing = scans
    out = tmp_path / "array"
    # which line a task takes is the point, not its fit
    none = ["--set", "fit.method=none"]
    res = run("batch", listing, "-o", out, *FIT, *none, env={"SLURM_ARRAY_TASK_ID": "5"})  # line 5: b.h5
    assert res.exit_code == 0, res.output
    assert is_result(out / "b.h5") and not (out / "a.h5").exists()
    failed = run("batch", listing, "-o", out, *FIT, *none, "--array-index", "4")  # line 4: broken.h5
    assert failed.exit_code == 1
    blank = run("batch", listing, "-o", out, "--array-index", "3")  # line 3 is blank
    assert blank.exit_code == 2 and "line 3" in blank.output


def test_scans_whose_results_would_collide_are_refused_before_any_run(scans, tmp_path):
    d, _ = scans
    (tmp_path / "other").mkdir()
    listing = tmp_path / "dup.txt"
    listing.write_text(f"{d / 'a.h5'}\n{tmp_path / 'other' / 'a.h5'}\n")
    res = run("batch", listing, "-o", tmp_path / "out", env={"SLURM_ARRAY_TASK_ID": None})
    assert res.exit_code == 2 and "lines 1 and 2" in res.output
    assert not (tmp_path / "out" / "a.h5").exists()


def _tiny_scan(path, *, seed=1, swap=None):
    """A scan of TINY's geometry; ``swap`` = (j, k) exchanges two frames' positions (a wrong motor log)."""
    scan = S.simulate(sim_config(**{"simulate.pixel_mm": 10.0, "simulate.step_mm": 10.0, "simulate.seed": seed}))[0]
    if swap is not None:
        position = scan.position.copy()
        position[list(swap)] = position[list(swap[::-1])]
        scan = replace(scan, position=position)
    io.write_scan(path, scan, overwrite=True)


def rows(res):
    return {line.split()[0]: line for line in res.stdout.splitlines()[1:-1]}


@pytest.mark.slow
def test_a_resumed_batch_reruns_results_whose_scan_or_configuration_changed(tmp_path):
    _tiny_scan(tmp_path / "a.h5")
    listing = tmp_path / "scans.txt"
    listing.write_text(f"{tmp_path / 'a.h5'}\n")
    out = tmp_path / "out"
    env = {"SLURM_ARRAY_TASK_ID": None}
    assert run("batch", listing, "-o", out, *FIT, env=env).exit_code == 0
    first = (out / "a.h5").read_bytes()
    same = run("batch", listing, "-o", out, *FIT, env=env)
    assert same.stdout.splitlines()[-1] == "1 scans: 0 done, 1 skipped, 0 failed"
    assert (out / "a.h5").read_bytes() == first
    other = run("batch", listing, "-o", out, "--set", "fit.subsample=5", env=env)
    assert other.exit_code == 0, other.output
    assert "re-run: the configuration changed" in rows(other)[str(tmp_path / "a.h5")]
    assert other.stdout.splitlines()[-1] == "1 scans: 1 done, 0 skipped, 0 failed"
    with h5py.File(out / "a.h5", "r") as f:
        assert "fit:\n  method: ml\n  subsample: 5" in f["entry/dfxcorr/configuration"].asstr()[()]
    _tiny_scan(tmp_path / "a.h5", seed=2)
    changed = run("batch", listing, "-o", out, "--set", "fit.subsample=5", env=env)
    assert "re-run: the scan changed" in rows(changed)[str(tmp_path / "a.h5")]


@pytest.mark.slow
def test_batch_marks_a_result_whose_fit_noise_cannot_explain(tmp_path):
    _tiny_scan(tmp_path / "good.h5")
    _tiny_scan(tmp_path / "swapped.h5", swap=(20, 23))
    listing = tmp_path / "scans.txt"
    listing.write_text(f"{tmp_path / 'good.h5'}\n{tmp_path / 'swapped.h5'}\n")
    res = run("batch", listing, "-o", tmp_path / "out", *FIT, env={"SLURM_ARRAY_TASK_ID": None})
    assert res.exit_code == 0, res.output
    table = rows(res)
    scan, status, _, chi2, mark = table[str(tmp_path / "swapped.h5")].split()[:5]
    assert status == "done" and float(chi2) > 2 and mark == "misfit"
    assert "misfit" not in table[str(tmp_path / "good.h5")]
    assert res.stdout.splitlines()[-1].startswith("2 scans: 2 done, 0 skipped, 0 failed; 1 marked misfit")
