"""The simulator's beam-path parallax: each frame sees the phantom evaluated where the displaced sample is."""
import hashlib
import re

import numpy as np
import pytest

from dfxcorr import config as C
from dfxcorr.sim import phantom as P
from dfxcorr.sim import simulate as S

from conftest import ROOT, cli_capped, one_error_line, sim_config

EXACT = {"simulate.noise": False, "simulate.dtype": "float64"}
# an odd height puts the detector's centre on a row, so that d_j = kappa (c_j - c_0) takes whole values
ODD = {"simulate.height_mm": 455.0}
KEYS = ("transmission", "dark_field", "differential_phase")

# Pinned before the option existed: kappa = 0 must not change the scan (sha256 of scan.data: integer counts, the same
# on every machine) nor the truth images (their sums and sums of squares, to 1e-12: the phantom's floating-point
# functions differ in the last bit between CPUs, which a digest of the images would read as a change).
THORAX = ((1972.9869021870993, 1683.3825080310562), (8244.418110807826, 7745.923562661953),
          (0.0, 0.05964683841144981))
PINNED = {
    "thorax": ({}, "2884401680639ec4cf64e13e15eb883ff9348e3b567a89463fbd30f80c8be15f", THORAX),
    "slab": ({"simulate.phantom": "slab"}, "5492b0e58536c8adbecff83db8b7561d63bf5464a338674982fbbab6f39cb12a",
             ((191.4798313234711, 3.9939570592227605), (9180.0, 9180.0), (0.0, 0.0))),
    "moving heart with scatter": ({"effects.sample_motion": 0.3, "effects.heart_step_mm": 10.0,
                                   "effects.scatter": 0.1},
                                  "903ee8f0db8ebe2880d6e6ef3b528ffa39ebfa292c9b902a6cd0801acb3da761", THORAX),
}


def displacement(scan, kappa: float) -> np.ndarray:
    """d_j = kappa (c_j - c_0) from the file's positions: c_j = position_j + (A - 1) / 2, c_0 = (H - 1) / 2."""
    A, H = scan.reference.transmission.shape[0], scan.shape[1]
    return kappa * (scan.position + (A - 1) / 2 - (H - 1) / 2)


@pytest.mark.parametrize("case", list(PINNED))
def test_without_parallax_the_scan_and_truth_are_unchanged(case):
    settings, counts_digest, image_sums = PINNED[case]
    scan, truth = S.simulate(sim_config(**settings, **{"effects.parallax": 0.0}))
    assert hashlib.sha256(scan.data.tobytes()).hexdigest() == counts_digest
    sums = [(truth[f"image_{k}"].sum(), (truth[f"image_{k}"] ** 2).sum()) for k in KEYS]
    np.testing.assert_allclose(sums, image_sums, rtol=1e-12, atol=1e-12)
    assert truth["beam_path"] == 0.0


@pytest.mark.parametrize("kappa", [0.05, -0.3])
def test_a_frame_is_the_static_simulation_of_the_phantom_at_the_displaced_rows(kappa):
    cfg = sim_config(**EXACT, **{"effects.parallax": kappa})
    moving, static = S.Simulation(cfg), S.Simulation(sim_config(**EXACT))
    scan = moving.scan()
    J, H, W = scan.shape
    d = displacement(scan, kappa)
    assert np.abs(d).max() > 0.9 * abs(kappa) * H / 2  # the first and last frames see the sample well displaced
    for j in (0, 3, J // 3, J // 2 + 7, J - 1):
        # the static simulator with the whole phantom re-evaluated d_j rows further on (beyond the detector too)
        static.images = P.thorax(shape=(H, W), shift=float(d[j]), pixel_mm=5.0, magnification=1.2)
        r0, expected = static.frame_counts(j)
        r1, counts = moving.frame_counts(j)
        assert r0 == r1 and counts.shape == expected.shape and counts.size
        np.testing.assert_allclose(counts, expected, rtol=1e-12, atol=0)


@pytest.mark.parametrize("kappa,frame,step", [(0.25, 56, 1), (0.25, 48, -1), (0.0625, 68, 1)])
def test_a_displacement_of_one_row_shows_the_next_row_of_the_static_images(kappa, frame, step):
    moving = S.Simulation(sim_config(**EXACT, **ODD, **{"effects.parallax": kappa}))
    static = S.Simulation(sim_config(**EXACT, **ODD))
    assert moving.displacement[frame] == step == displacement(moving.scan(), kappa)[frame]
    r0, counts = moving.frame_counts(frame)
    rows = np.arange(r0, r0 + counts.shape[0])
    assert rows.min() + step >= 0 and rows.max() + step < moving.shape[1]
    # the sample's images move by one row; the flat field stays where the frame's active area is
    static.images = {k: np.roll(v, -step, axis=0) for k, v in static.images.items()}
    _, expected = static.frame_counts(frame)
    np.testing.assert_allclose(counts, expected, rtol=1e-12, atol=0)
    assert not np.allclose(counts, S.Simulation(sim_config(**EXACT, **ODD)).frame_counts(frame)[1], rtol=1e-3)


def test_rows_beyond_the_detector_see_the_phantom_where_it_continues():
    H, W = 90, 102
    tall = P.thorax(shape=(H + 20, W), pixel_mm=5.0)  # ten more rows on each side, same centre
    seen = P.thorax_rows(rows=np.arange(80, 90), shape=(H, W), shift=7.0, pixel_mm=5.0)
    for k in KEYS:
        np.testing.assert_allclose(seen[k], tall[k][97:107], rtol=1e-12, atol=1e-15)
    assert (seen["transmission"] < 1).any()  # the body reaches below the detector


@pytest.mark.parametrize("supersample", [1, 2, 8])
def test_any_rows_of_the_displaced_thorax_are_those_of_the_whole_detector(supersample):
    H, W = 90, 102
    whole = P.thorax(shape=(H, W), shift=-2.3, pixel_mm=5.0, supersample=supersample)
    rows = np.array([0, 1, 2, 17, 18, 40, 41, 42, 43, 60, 89])  # strips of 16 rows at 8 x 8, of all at 2 x 2
    some = P.thorax(shape=(H, W), rows=rows, shift=-2.3, pixel_mm=5.0, supersample=supersample)
    for k in KEYS:
        np.testing.assert_array_equal(some[k], whole[k][rows])


@pytest.mark.slow
def test_the_truth_carries_kappa_and_the_undisplaced_images():
    scan, truth = S.simulate(sim_config(**{"effects.parallax": -0.04}))
    _, plain = S.simulate(sim_config())
    assert truth["beam_path"] == -0.04 and truth["beam_path"].dtype == np.float64
    for k in KEYS:
        np.testing.assert_array_equal(truth[f"image_{k}"], plain[f"image_{k}"])
    assert not np.array_equal(scan.data, S.simulate(sim_config())[0].data)


@pytest.mark.parametrize("phantom", ["blank", "slab"])
def test_a_blank_or_a_slab_looks_the_same_from_everywhere(phantom):
    seen = S.simulate(sim_config(**{"simulate.phantom": phantom, "effects.parallax": 0.5}))[0]
    np.testing.assert_array_equal(seen.data, S.simulate(sim_config(**{"simulate.phantom": phantom}))[0].data)


def test_phase_stepping_has_no_travel_and_so_no_parallax():
    stepping = {"simulate.geometry": "stepping", "simulate.steps": 5, "simulate.steps_per_period": 5}
    sim = S.Simulation(sim_config(**stepping, **{"effects.parallax": 0.5}))
    assert not sim.displacement.any()
    np.testing.assert_array_equal(S.simulate(sim.cfg)[0].data, S.simulate(sim_config(**stepping))[0].data)


def test_the_moved_heart_keeps_its_shifted_images_and_the_rest_moves_with_the_parallax():
    heart = {**EXACT, "effects.heart_step_mm": 10.0}
    moving = S.Simulation(sim_config(**heart, **{"effects.parallax": 0.05}))
    still = S.Simulation(sim_config(**heart))
    J = moving.shape[0]
    for j in (J // 2 - 5, J // 2 + 5):
        r0, counts = moving.frame_counts(j)
        _, plain = still.frame_counts(j)
        inside = moving.after["region"][r0:r0 + counts.shape[0]]
        assert moving.displacement[j] and inside.any() and (~inside).any()
        if j >= J // 2:
            np.testing.assert_array_equal(counts[inside], plain[inside])
        else:
            assert not np.allclose(counts[inside], plain[inside], rtol=1e-6)
        assert not np.allclose(counts[~inside], plain[~inside], rtol=1e-6)


@pytest.mark.parametrize("value,words", [(1.0, "must lie in (-1, 1)"), (-1.5, "must lie in (-1, 1)"),
                                         (float("nan"), "must lie in (-1, 1)"), (float("inf"), "must lie in (-1, 1)"),
                                         ("0.1x", "must be int or float"), (True, "must be int or float")])
def test_the_parallax_setting_is_validated(value, words):
    with pytest.raises(C.ConfigError, match=re.escape(f"effects.parallax {words}")):
        sim_config(**{"effects.parallax": value})


@pytest.mark.parametrize("value,words", [(0, "must lie in [1, 16]"), (17, "must lie in [1, 16]"),
                                         (2.5, "must be int")])
def test_the_supersample_setting_is_validated(value, words):
    with pytest.raises(C.ConfigError, match=re.escape(f"simulate.supersample {words}")):
        sim_config(**{"simulate.supersample": value})


def test_simulate_refuses_a_parallax_of_a_whole_row_per_row_in_one_line(tmp_path):
    res = cli_capped("simulate", "-o", tmp_path / "s.h5", "--set", "effects.parallax=1", timeout=60)
    assert res.exit_code == 2 and one_error_line(res.stderr, "effects.parallax", "(-1, 1)"), res.stderr + res.traceback
    assert list(tmp_path.iterdir()) == []


def test_the_parallax_configuration_is_the_shared_scans_geometry_with_kappa():
    cfg = C.load([ROOT / "configs" / "parallax-simulation.yaml"], [], schema=S.SCHEMA)
    g = S.geometry(cfg)
    assert (g["H"], g["W"], g["A"], g["position"].size) == (180, 204, 30, 209)
    assert cfg["effects"]["parallax"] == 0.02 and cfg["simulate"]["flux"] == 2e4
    d = S.parallax_shift(cfg, g["position"], g["A"], g["H"])
    assert d[-1] - d[-30] == pytest.approx(0.02 * 29)  # the 30 frames lighting the last row: 0.58 rows apart
