"""detector_lag and pixel_noise: simulated, estimated, named alone when concealed alone, and applied by reconstruct."""
from dataclasses import replace

import numpy as np
import pytest
import tifffile

from dfxcorr import config as C
from dfxcorr import pipeline
from dfxcorr.align import collect_lit_rows
from dfxcorr.analysis.diagnose import diagnose
from dfxcorr.analysis.evaluate import image_rmse
from dfxcorr.analysis.report import reconstruct_settings, write_report
from dfxcorr.effects.detector_lag import lag_free, measured_lag, without_lag
from dfxcorr.effects.pixel_noise import PixelNoiseError, class_chi2
from dfxcorr.retrieve import retrieve
from dfxcorr.sim import simulate as S

from conftest import chi2_tolerance, prepare, real_ipp_scan, sim_config

#: Mean effects that lag can pose as: none may be detected once lag is named.
PROXIES = {"visibility_tilt", "dose", "curvature", "harmonic", "detector_gain"}


def quantisation_bound(store) -> float:
    """Largest error of the lag estimate that the uint16 storage's rounding (0.5 count per sample) can cause."""
    prev = store.counts[store.left_prev].astype(float) - store.dark[store.row[store.left_prev]]
    # the pixels just left and their previous frame are both rounded (the latter's recursion grows it by < 2)
    return 0.5 * prev.size / prev.sum() * 3


def test_lag_free_is_the_recursion_over_each_pixels_frames_with_gaps():
    # S_j = I_j - dark - a S_(j-1), S_(j-1) = 0 where frame j - 1 did not light the row; float32 as the store holds it
    rng = np.random.default_rng(5)
    lit = rng.random((7, 12)) < 0.7  # (row, frame)
    row, frame = np.nonzero(lit)
    counts = rng.integers(100, 1000, (row.size, 3)).astype(np.uint16)
    dark = rng.uniform(0, 50, (7, 3))
    a = 0.07
    want = np.zeros(counts.shape, np.float32)
    for k in range(row.size):
        s = counts[k].astype(np.float32) - dark[row[k]].astype(np.float32)
        if k and row[k - 1] == row[k] and frame[k - 1] == frame[k] - 1:
            s = s - np.float32(a) * want[k - 1]
        want[k] = s
    want += dark[row]
    np.testing.assert_array_equal(lag_free(counts, dark, row, frame, a), want)
    # some blocks only, in any order and repeated: the same values
    some = np.array([20, 3, 0, len(row) - 1, 3])
    np.testing.assert_array_equal(lag_free(counts, dark, row, frame, a, blocks=some), want[some])
    with pytest.raises(ValueError, match="blocks outside"):
        lag_free(counts, dark, row, frame, a, blocks=np.array([-1]))


def test_lag_free_counts_are_the_lag_free_frames():
    # without photon noise and in float64 the recursion must give back the scan without lag
    base = {"simulate.noise": False, "simulate.dtype": "float64"}
    lagged, _ = S.simulate(sim_config(**base, **{"effects.detector_lag": 0.05}))
    clean, _ = S.simulate(sim_config(**base))
    a, b = collect_lit_rows(lagged), collect_lit_rows(clean)
    assert np.array_equal(a.row, b.row) and np.array_equal(a.frame, b.frame)
    assert not np.allclose(a.counts, b.counts, rtol=1e-3)
    np.testing.assert_allclose(without_lag(a, 0.05).counts, b.counts, rtol=1e-5, atol=1e-2)
    fraction, se = measured_lag(a)
    assert fraction == pytest.approx(0.05, rel=1e-5)
    # the rows just left carry the lag and nothing else: zero without it
    assert measured_lag(b)[0] == 0.0 and np.all(b.left_counts == 0)


@pytest.mark.slow
@pytest.mark.parametrize("amplitude", [0.03, 0.001])
def test_lag_is_named_alone_and_the_fit_recovers(amplitude):
    scan, truth = S.simulate(sim_config(**{"effects.detector_lag": amplitude, "simulate.seed": 11}))
    cfg = C.defaults()
    diag = diagnose(scan, cfg)
    found = [e.name for e in diag.effects if e.detected]
    assert found == ["detector_lag"], [(e.name, e.statistic) for e in diag.effects]
    lag = diag.effects[0].to_json()
    store = collect_lit_rows(scan)
    assert lag["value"] == pytest.approx(float(truth["detector_lag"]), abs=5 * lag["se"] + quantisation_bound(store))
    assert diag.final_chi2 == pytest.approx(1.0, abs=chi2_tolerance(diag, cfg))
    assert diag.unexplained == [], diag.unexplained
    if amplitude > 0.01:
        # a small lag hardly moves the chi-square: it adds a^2 of the previous frame's variance but a of its mean
        assert diag.initial_chi2 > diag.final_chi2
    assert f"load.detector_lag={lag['value']:.6g}" in reconstruct_settings(diag)


@pytest.mark.slow
def test_reconstruct_with_the_lag_lowers_the_image_error():
    scan, truth = S.simulate(sim_config(**{"effects.detector_lag": 0.03, "simulate.seed": 12}))
    plain = pipeline.reconstruct(scan, C.defaults())
    corrected = pipeline.reconstruct(scan, C.load([], ["load.detector_lag=0.03"]))
    before = image_rmse({k: plain.image(k) for k in plain.IMAGES}, truth)
    after = image_rmse({k: corrected.image(k) for k in corrected.IMAGES}, truth)
    assert after["differential_phase"] < 0.9 * before["differential_phase"], (before, after)
    assert after["dark_field"] < before["dark_field"] and corrected.reduced_chi2 < plain.reduced_chi2


def test_lag_option_is_validated():
    with pytest.raises(C.ConfigError, match="load.detector_lag"):
        C.load([], ["load.detector_lag=1.5"])


def pixel_noise_scan(factor=1 / 3, seed=11):
    return S.simulate(sim_config(**{"effects.pixel_noise": factor, "simulate.seed": seed}))


@pytest.mark.slow
def test_pixel_noise_is_named_alone_with_the_classes_of_the_truth(tmp_path):
    scan, truth = pixel_noise_scan()
    cfg = C.defaults()
    diag = diagnose(scan, cfg)
    assert [e.name for e in diag.effects if e.detected] == ["pixel_noise"], [(e.name, e.statistic)
                                                                              for e in diag.effects]
    boundary = truth["pixel_noise"] != 1
    lit = np.isfinite(diag.before.pixel)
    assert np.all((diag.pixel_noise != 1)[lit] == boundary[lit])
    # each class's factor: noise of its reduced chi-square (kurtosis of scaled Poisson noise negligible at these
    # counts) plus what the fitted parameters' noise adds to every pixel alike (chi2_tolerance's first term)
    allowance = (cfg["diagnose"]["subsample"] * sum(np.size(p) for p in diag.params.values())
                 / (diag.rounds[-1]["chi2_before"] / diag.rounds[-1]["reduced_chi2_before"]))
    for c in diag.effects[0].values["classes"]:
        assert c["factor"] == pytest.approx(1 / 3, abs=5 * np.sqrt(2 / c["dof"]) / 3 + allowance), c
    assert diag.final_chi2 == pytest.approx(1.0, abs=chi2_tolerance(diag, cfg))
    assert diag.unexplained == [], diag.unexplained
    written = write_report(diag, tmp_path)
    assert tmp_path / "pixel_noise.tif" in written
    np.testing.assert_allclose(tifffile.imread(tmp_path / "pixel_noise.tif"), diag.pixel_noise, rtol=1e-6)
    assert f"load.pixel_noise={tmp_path / 'pixel_noise.tif'}" in (tmp_path / "report.md").read_text()


@pytest.mark.slow
def test_reconstruct_with_the_pixel_noise_map_brings_each_class_to_one(tmp_path):
    scan, truth = pixel_noise_scan(seed=13)
    tifffile.imwrite(tmp_path / "f.tif", truth["pixel_noise"].astype(np.float32))
    classes = (truth["pixel_noise"] != 1).astype(int)
    chi2 = {}
    for name, sets in (("plain", []), ("map", [f"load.pixel_noise={tmp_path / 'f.tif'}"])):
        prep = prepare(scan, C.load([], sets))
        result = pipeline.reconstruct(prep, C.load([], sets))
        obs = prep.observations()
        obs = replace(obs, use=obs.roi)
        rec = retrieve(obs, result.params)
        chi2[name] = class_chi2(obs, rec.expected, rec.images.valid, classes)
    dof = 12 * classes.sum()
    assert chi2["plain"][1] == pytest.approx(1 / 3, abs=0.05)
    assert chi2["map"][1] == pytest.approx(1.0, abs=5 * np.sqrt(2 / dof) + 0.03)
    assert chi2["map"][0] == pytest.approx(1.0, abs=0.03)


def test_pixel_noise_map_of_the_wrong_shape_is_refused(tmp_path):
    scan, _ = S.simulate(sim_config())
    tifffile.imwrite(tmp_path / "f.tif", np.ones((3, 4), np.float32))
    with pytest.raises(PixelNoiseError, match="load.pixel_noise"):
        prepare(scan, C.load([], [f"load.pixel_noise={tmp_path / 'f.tif'}"]))


@pytest.mark.shared
@pytest.mark.slow
def test_real_recording_pixel_classes_come_to_one(tmp_path):
    path = real_ipp_scan(tmp_path)
    diag = diagnose(path, C.defaults())
    assert "pixel_noise" in [e.name for e in diag.effects if e.detected]
    report = next(e for e in diag.effects if e.name == "pixel_noise")
    # the module-boundary pixels carry well below the Poisson variance (about a third in the boundaries' centres)
    assert min(c["factor"] for c in report.values["classes"]) < 0.5
    _, labels = np.unique(np.round(diag.pixel_noise, 6), return_inverse=True)
    labels = labels.reshape(diag.pixel_noise.shape)
    prep = prepare(path, C.defaults())
    for noise, expect_one in ((None, False), (diag.pixel_noise, True)):
        obs = replace(prep, noise=replace(prep.noise, factors=noise)).observations()
        obs = replace(obs, use=obs.roi)
        rec = retrieve(obs, diag.params)
        per_class = class_chi2(obs, rec.expected, rec.images.valid, labels)
        dof = {k: 8 * int((labels == k).sum()) for k in per_class}  # 11 steps, 3 unknowns per pixel
        near_one = all(abs(v - 1) < 5 * np.sqrt(2 / dof[k]) + 0.01 for k, v in per_class.items())
        assert near_one == expect_one, per_class


@pytest.mark.parametrize("read_noise", [25.0, pytest.param(1.0, marks=pytest.mark.slow)])
def test_the_readout_of_unlit_rows_measures_the_read_noise(read_noise):
    """A flat panel's unlit rows hold dark + read noise: their variance (row means out) is sigma_e^2 plus the
    integer counts' rounding (1/12), as on every sample, within the sampling error of a variance (sd sqrt(2 / N)
    relative, 5 of them allowed); a scan whose unlit rows were not read out (zeros) and a phase-stepping
    recording give nothing."""
    from dfxcorr.effects.detector_gain import unlit_readout

    scan, _ = S.simulate(sim_config(**{**S.FLAT_PANEL, "effects.read_noise": read_noise, "simulate.seed": 4}))
    r = unlit_readout(scan)
    assert r.size > 10000
    assert np.issubdtype(scan.data.dtype, np.integer)
    assert np.mean(r ** 2) / (read_noise ** 2 + 1 / 12) == pytest.approx(1.0, abs=5 * np.sqrt(2 / r.size))
    assert unlit_readout(S.simulate(sim_config(**{"simulate.seed": 4}))[0]).size == 0
    stepping, _ = S.simulate(sim_config(**{**S.FLAT_PANEL_STEPPING, "simulate.seed": 4}))
    assert unlit_readout(stepping).size == 0


def _class_chi2(rng, factor_seen):
    """Per-pixel chi-square (dof 27) of a 60 x 40 detector whose columns 10-11 are a pixel class, each pixel's
    variance ``factor_seen(row)`` times what the model states (1: the class's factor in the model is right)."""
    dof = np.full((60, 40), 27.0)
    scale = np.ones((60, 40))
    scale[:, 10:12] = [[factor_seen(r)] for r in range(60)]
    return scale * rng.chisquare(27, (60, 40)), dof


def test_a_pixel_class_has_one_factor_along_its_lines_and_a_patch_does_not():
    from dfxcorr.effects.residuals import line_consistency

    rng = np.random.default_rng(5)
    factors = np.ones((60, 40))
    factors[:, 10:12] = 1.5
    # a real class: its factor in the model, its pixels at noise along the whole column
    X, dof = _class_chi2(rng, lambda r: 1.0)
    odd = line_consistency(factors, X, dof)
    assert odd.log_p > np.log(0.01) and odd.spread < 1.0, odd
    # a patch (rows 20-29 at 3x, the rest at 1) fitted as a class of factor 1.5: the strata's factors differ
    X, dof = _class_chi2(rng, lambda r: 3.0 / 1.5 if 20 <= r < 30 else 1.0 / 1.5)
    odd = line_consistency(factors, X, dof)
    assert odd.log_p < np.log(1e-6) and odd.spread > 2.0 and odd.along == "rows", odd
    assert line_consistency(np.ones((60, 40)), X, dof) is None  # no class, nothing to test
