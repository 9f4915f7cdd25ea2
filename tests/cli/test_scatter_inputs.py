"""Scatter settings at their extremes on the command line: a kernel far wider than the detector in bounded memory,
a scatter above the primary applied, never a traceback."""
import numpy as np
import pytest

from dfxcorr.io import write_scan
from dfxcorr.sim import simulate as S

from conftest import cli_capped, one_error_line, sim_config


def scatter_scan(folder, s: float):
    path = folder / f"scan-{s:g}.h5"
    scan, _ = S.simulate(sim_config(**{"effects.scatter": s, "simulate.seed": 11}))
    write_scan(path, scan)
    return path


@pytest.fixture(scope="module")
def scan_file(tmp_path_factory):
    return scatter_scan(tmp_path_factory.mktemp("scatter"), 0.1)


@pytest.mark.parametrize("command", ["check"] + [pytest.param(c, marks=pytest.mark.slow)
                                                 for c in ("reconstruct", "diagnose")])
def test_a_kernel_wider_than_the_detector_runs_in_bounded_memory(scan_file, tmp_path, command):
    # 1e9 mm: 2e8 pixels of std. A band padded to whole blocks of sigma / 32 pixels would be 284 TiB; the block
    # sums hold only the band's blocks (one), the field is the constant it is
    out = tmp_path / ("d" if command == "diagnose" else "r.h5")
    res = cli_capped(command, scan_file, "-o", out, "--set", "load.scatter=0.1", "--set",
                     "load.scatter_width_mm=1e9", timeout=300)
    assert res.traceback == "" and res.exit_code == 0, (res.exit_code, res.stderr[-2000:], res.traceback)


@pytest.mark.slow
def test_a_scatter_above_the_primary_changes_the_reconstruction(tmp_path):
    # s >= 1 (thick samples) is applied: the images differ from those without
    import h5py

    scan_file = scatter_scan(tmp_path, 1.5)
    images = {}
    for s in ("0", "1.5"):
        out = tmp_path / f"r{s}.h5"
        # the correction is applied before any fit: the retrieval alone shows it
        res = cli_capped("reconstruct", scan_file, "-o", out, "--set", f"load.scatter={s}", "--method", "none",
                         timeout=300)
        assert res.traceback == "" and res.exit_code == 0, (res.stderr[-2000:], res.traceback)
        with h5py.File(out) as f:
            images[s] = f["entry/dfxcorr/results/transmission"][()]
    ok = np.isfinite(images["0"]) & np.isfinite(images["1.5"])
    # the scatter taken for transmission without the correction: t lower with it
    assert np.nanmedian(images["1.5"][ok] / images["0"][ok]) < 0.9


@pytest.mark.parametrize("command", ["reconstruct", "simulate"])
def test_a_scatter_beyond_any_sample_is_refused_in_one_line(scan_file, tmp_path, command):
    # a field scaled by 1e300 underflows to zero: the correction would vanish while the log says it is applied
    args = (("simulate", "-o", tmp_path / "s.h5", "--set", "effects.scatter=1e300") if command == "simulate"
            else ("reconstruct", scan_file, "-o", tmp_path / "r.h5", "--set", "load.scatter=1e300"))
    res = cli_capped(*args, timeout=60)
    assert res.exit_code == 2 and one_error_line(res.stderr, "scatter", "[0, 100]"), (res.exit_code, res.stderr)
    assert not (tmp_path / "r.h5").exists() and not (tmp_path / "s.h5").exists()
