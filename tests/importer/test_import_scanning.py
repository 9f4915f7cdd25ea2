"""dfxcorr import scanning: frames and a motor log become a scan file, losslessly, one frame at a time."""
import logging

import h5py
import numpy as np
import pytest
import tifffile
from click.testing import CliRunner

from dfxcorr import pipeline
from dfxcorr.cli import main
from dfxcorr.export import read_result_h5
from dfxcorr.importer import StackImportError, active_area, import_scanning, read_positions, read_stack
from dfxcorr.io import SteppingReference, read_scan, write_scan

from conftest import one_error_line, run_capped


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A small simulated scan, its frames as one TIFF per frame and a .npy stack, and position logs."""
    from dfxcorr.sim import simulate as S

    from conftest import sim_config

    d = tmp_path_factory.mktemp("scanning")
    scan, _ = S.simulate(sim_config())
    write_scan(d / "sim.h5", scan)
    for j, frame in enumerate(scan.data):
        tifffile.imwrite(d / f"frame_{j}.tif", frame)
    np.save(d / "stack.npy", scan.data)
    np.savetxt(d / "positions.txt", scan.position)
    mm = scan.position * scan.pixel_size[0] * 1e3
    (d / "motor.csv").write_text("time,y_mm\n" + "".join(f"{j * 0.1},{float(v)!r}\n" for j, v in enumerate(mm)))
    return d, scan


def test_tiff_frames_and_text_log_round_trip(simulated, tmp_path):
    d, scan = simulated
    out = tmp_path / "scan.h5"
    res = run("import", "scanning", "--frames", d / "frame_*.tif", "--positions", d / "positions.txt",
              "--reference", d / "sim.h5", "-o", out)
    assert res.exit_code == 0, res.output
    back = read_scan(out)
    assert back.data.dtype == np.uint16 and np.array_equal(back.data, scan.data)
    np.testing.assert_array_equal(back.position, scan.position)
    np.testing.assert_array_equal(back.reference.phase, scan.reference.phase)
    with h5py.File(out) as f:
        chunks = f["entry/instrument/detector/data"].chunks  # within one frame, whole rows
        assert chunks[0] == 1 and chunks[2] == scan.shape[2]
        assert f["entry/instrument/detector/data"].compression == "gzip"


def test_npy_stack_and_csv_log_in_mm(simulated, tmp_path):
    d, scan = simulated
    out = tmp_path / "scan.h5"
    args = ["import", "scanning", "--frames", d / "stack.npy", "--positions", d / "motor.csv",
            "--position-column", "y_mm", "--position-units", "mm", "--reference", d / "sim.h5", "-o", out]
    res = run(*args)
    assert res.exit_code == 2 and one_error_line(res.stderr, "pixel size") and not out.exists()
    res = run(*args, "--pixel-size", scan.pixel_size[0])
    assert res.exit_code == 0, res.output
    back = read_scan(out)
    assert np.array_equal(back.data, scan.data)
    np.testing.assert_allclose(back.position, scan.position, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_imported_scan_reconstructs_as_the_original(simulated, tmp_path):
    d, scan = simulated
    out = tmp_path / "scan.h5"
    res = run("import", "scanning", "--frames", d / "stack.npy", "--positions", d / "positions.txt",
              "--reference", d / "sim.h5", "-o", out)
    assert res.exit_code == 0, res.output
    res = run("reconstruct", out, "-o", tmp_path / "r.h5")
    assert res.exit_code == 0, res.output
    direct = pipeline.reconstruct(scan)
    np.testing.assert_array_equal(read_result_h5(tmp_path / "r.h5")["transmission"],
                                  direct.transmission.astype(np.float32))


def detector_stepping(scan, first, steps=5, seed=0):
    """A reference stepping series on the detector: the active area at rows first .. first + A - 1, dark elsewhere."""
    rng = np.random.default_rng(seed)
    ref, (_, H, W), A = scan.reference, scan.shape, scan.active_rows
    phases = 2 * np.pi * np.arange(steps) / steps
    frames = rng.poisson(2.0, (steps, H, W)).astype(np.uint16)
    mean = ref.transmission * (1 + ref.visibility * np.cos(ref.phase[None] + phases[:, None, None]))
    frames[:, first:first + A] = rng.poisson(mean)
    return frames, phases


def test_reference_stepping_cropped_to_the_active_area_found_from_the_flux(simulated, tmp_path, caplog):
    d, scan = simulated
    frames, phases = detector_stepping(scan, first=31)
    frames[:, 70, 4] = 60000  # a hot pixel outside the active area must not move it
    for k, frame in enumerate(frames):
        np.save(tmp_path / f"flat_{k}.npy", frame)
    out = tmp_path / "scan.h5"
    with caplog.at_level(logging.INFO, logger="dfxcorr"):
        scan_out = import_scanning(out, frames=d / "stack.npy", positions=d / "positions.txt",
                                   reference_stepping=str(tmp_path / "flat_*.npy"), steps_per_period=5)
    assert scan_out.active_rows == scan.active_rows
    assert "active area rows 31 to 45" in caplog.text
    back = read_scan(out)
    assert isinstance(back.reference, SteppingReference)
    np.testing.assert_array_equal(back.reference.data, frames[:, 31:46])
    np.testing.assert_allclose(back.reference.phase_step, phases)
    given = import_scanning(tmp_path / "given.h5", frames=d / "stack.npy", positions=d / "positions.txt",
                            reference_stepping=str(tmp_path / "flat_*.npy"), steps_per_period=5,
                            active_first_row=30, active_rows=15)
    assert given.active_rows == 15
    np.testing.assert_array_equal(read_scan(tmp_path / "given.h5").reference.data, frames[:, 30:45])


def test_active_area_ignores_a_dead_row_and_background():
    profile = np.full(60, 40.0)
    profile[12:30] = 1000.0
    profile[20] = 0.0  # a dead row inside
    profile[50] = 5000.0  # a hot row outside
    assert active_area(profile) == (12, 18)


@pytest.mark.parametrize("text,column,match", [
    ("1\n2\nx\n", None, "line 3"),
    ("1\n2\ninf\n", None, "not finite"),
    ("1\n2\n", None, "2 positions for 3 frames"),
    ("a,b\n1,2\n3,4\n5,6\n", None, "name one"),
    ("a,b\n1,2\n3,4\n5,6\n", "c", "no column 'c'"),
    ("a,b\n1,2\n3\n5,6\n", "b", "line 3"),
])
def test_bad_position_logs_name_the_line_or_column(tmp_path, text, column, match):
    (tmp_path / "log.csv").write_text(text)
    with pytest.raises(StackImportError, match=match):
        read_positions(tmp_path / "log.csv", 3, column=column)


def test_position_log_forms(tmp_path):
    (tmp_path / "plain.txt").write_text("# motor y\n1.5\n\n-2\n3e-1\n")
    np.testing.assert_array_equal(read_positions(tmp_path / "plain.txt", 3), [1.5, -2, 0.3])
    (tmp_path / "t.tsv").write_text("t\ty\n0\t1\n1\t2\n2\t3\n")
    np.testing.assert_array_equal(read_positions(tmp_path / "t.tsv", 3, column="y"), [1, 2, 3])


def test_refusals_before_anything_is_written(simulated, tmp_path):
    d, scan = simulated
    out = tmp_path / "scan.h5"
    bad = tmp_path / "neg.npy"
    np.save(bad, -np.ones((scan.shape[0], *scan.shape[1:]), np.int16))
    cases = [
        (["--frames", d / "stack.npy", "--positions", d / "positions.txt"], "reference"),
        (["--frames", bad, "--positions", d / "positions.txt", "--reference", d / "sim.h5"], "negative"),
        (["--frames", d / "frame_1.tif", "--positions", d / "positions.txt", "--reference", d / "sim.h5"],
         "positions for 1 frames"),
        (["--frames", d / "stack.npy", "--positions", d / "positions.txt", "--reference-stepping", d / "stack.npy",
          "--steps-per-period", "1e-310"], "infinite"),
    ]
    for args, words in cases:
        res = run("import", "scanning", *args, "-o", out)
        assert res.exit_code == 2 and one_error_line(res.stderr, words), res.stderr
        assert not out.exists() and not list(tmp_path.glob(".*part"))


def _read_with_few_file_handles(pattern):
    import resource

    resource.setrlimit(resource.RLIMIT_NOFILE, (64, 64))
    return read_stack(pattern)[:, 0, 0].tolist()


@pytest.mark.parametrize("suffix", ["tif", "npy"])
def test_a_series_of_many_files_keeps_none_open(tmp_path, suffix):
    for k in range(200):
        frame = np.full((4, 5), k, np.uint16)
        if suffix == "tif":
            tifffile.imwrite(tmp_path / f"f_{k}.tif", frame)
        else:
            np.save(tmp_path / f"f_{k}.npy", frame)
    values = run_capped(lambda: _read_with_few_file_handles(str(tmp_path / f"f_*.{suffix}")))
    assert values == list(range(200))
