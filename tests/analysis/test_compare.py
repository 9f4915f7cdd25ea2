"""dfxcorr compare and dfxcorr nps end to end, and the noise-power-spectrum functions they rest on."""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from dfxcorr.analysis.compare import fringe_frequency, radial_nps
from dfxcorr.cli import main
from dfxcorr.export import read_result_h5

SMALL = ["--set", "simulate.pixel_mm=5", "--set", "simulate.step_mm=5"]
# few iterations: these tests check the plumbing, tests/test_baselines.py the estimators
FAST = ["--set", "fit.subsample=6", "--set", "fit.maxiter=40", "--set", "fit.reweight=0"]


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def thorax(tmp_path_factory):
    """A folder holding thorax.h5."""
    d = tmp_path_factory.mktemp("scans")
    res = run("simulate", "-o", d / "thorax.h5", *SMALL)
    assert res.exit_code == 0, res.output
    return d


@pytest.fixture(scope="module")
def scans(thorax):
    """The folder of ``thorax`` with two blank scans beside it, blank1.h5 and blank2.h5."""
    for name, seed in (("blank1", 11), ("blank2", 12)):
        res = run("simulate", "-o", thorax / f"{name}.h5", *SMALL, "--set", "simulate.phantom=blank",
                  "--set", f"simulate.seed={seed}")
        assert res.exit_code == 0, res.output
    return thorax


@pytest.mark.slow
def test_compare_writes_results_pictures_and_table(scans, tmp_path):
    out = tmp_path / "cmp"
    res = run("compare", scans / "thorax.h5", "-o", out, "--truth", scans / "thorax.truth.npz", *FAST)
    assert res.exit_code == 0, res.output
    table = json.loads((out / "table.json").read_text())
    rows = {r["method"]: r for r in table["methods"]}
    assert list(rows) == ["none", "correlation", "alternating", "ml"]
    for key in ("reduced_chi2", "runtime_s", "rmse_phase_offset", "rmse_tilt", "rmse_visibility_loss",
                "rmse_dark_field"):
        assert all(np.isfinite(r[key]) for r in rows.values()), key
    assert rows["ml"]["rmse_phase_offset"] < 0.2 * rows["none"]["rmse_phase_offset"]
    assert rows["ml"]["reduced_chi2"] < rows["none"]["reduced_chi2"]
    # the correlation method has no visibility term: written as not estimated, its error is v^s itself
    corr = read_result_h5(out / "correlation.h5")
    assert not corr["estimated"]["visibility"] and np.all(corr["vibration"]["visibility"] == 1)
    assert rows["correlation"]["rmse_visibility_loss"] == pytest.approx(rows["none"]["rmse_visibility_loss"])
    assert read_result_h5(out / "alternating.h5")["cost"].size == rows["alternating"]["iterations"] > 0
    for png in ("images.png", "convergence.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| ml |" in (out / "table.md").read_text()
    # outputs are not replaced unless asked
    again = run("compare", scans / "thorax.h5", "-o", out, "--methods", "none")
    assert again.exit_code == 2 and "exists" in again.output


def test_compare_refuses_a_truth_that_does_not_fit_and_unknown_methods(thorax, tmp_path):
    np.savez(tmp_path / "bad.npz", image_transmission=np.ones((3, 3)))
    res = run("compare", thorax / "thorax.h5", "-o", tmp_path / "b", "--truth", tmp_path / "bad.npz", "--methods",
              "none")
    assert res.exit_code == 2 and "image_transmission has shape (3, 3)" in res.output
    res = run("compare", thorax / "thorax.h5", "-o", tmp_path / "c", "--methods", "none,magic")
    assert res.exit_code == 2 and "magic" in res.output


@pytest.mark.slow
def test_nps_of_blank_scans(scans, tmp_path):
    out = tmp_path / "nps"
    res = run("nps", scans / "blank1.h5", scans / "blank2.h5", "-o", out, *FAST)
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "nps.json").read_text())
    # the simulated fringes: 2 + 0.5 x^2 periods over the 15-row active area, median over x at x^2 = 1/4
    assert doc["fringe_frequency"] == pytest.approx(2.125 / 15, rel=1e-6)
    assert doc["first_harmonic"] == pytest.approx(2 * doc["fringe_frequency"])
    assert set(doc["mean"]) == {"none", "correlation", "ml"}
    assert len(doc["frequency"]) == round(2 / doc["fringe_frequency"])  # rings f / 4 wide by default
    assert all(s > 0 for s in doc["std"]["ml"])  # two scans: a spread
    # vibrations put power at the fringe frequency; the ML correction removes most of it
    assert doc["power_near_fringe"]["ml"]["fringe"] < 0.5 * doc["power_near_fringe"]["none"]["fringe"]
    assert (out / "nps.csv").read_text().startswith("frequency_cycles_per_pixel,none_mean,none_std")
    assert (out / "nps.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_nps_of_white_noise_is_flat_at_its_variance():
    rng = np.random.default_rng(2)
    sigma = 0.3
    spectra = []
    for _ in range(8):
        image = rng.normal(1.0, sigma, (256, 256))
        image[:5] = np.nan  # unlit rows are left out
        f, p = radial_nps(image, bins=16)
        spectra.append(p)
    assert f[0] == pytest.approx(0.5 / 32) and f[-1] == pytest.approx(0.5 - 0.5 / 32)
    # one periodogram ring scatters by ~8 %; the mean of eight by ~3 %. The lowest ring holds only a
    # few frequencies next to the removed mean.
    np.testing.assert_allclose(np.mean(spectra, axis=0)[1:], sigma ** 2, rtol=0.08)


def test_nps_finds_a_sinusoid_at_its_frequency():
    rows = np.arange(200)[:, None]
    image = 1 + 0.05 * np.cos(2 * np.pi * 0.14 * rows) * np.ones((1, 180))
    f, p = radial_nps(image, bins=25)
    assert f[np.argmax(p)] == pytest.approx(0.14, abs=0.5 / 25)


def test_fringe_frequency_from_a_wrapped_reference_phase():
    u = np.arange(30)[:, None] + 0.5
    x = np.linspace(-1, 1, 51)[None, :]
    cycles = 2.0 + 0.5 * x ** 2                                   # fringes over the active area
    phase = np.angle(np.exp(1j * (2 * np.pi * cycles * u / 30 + 1.3 * x)))
    assert fringe_frequency(phase) == pytest.approx(np.median(cycles) / 30, rel=1e-9)
