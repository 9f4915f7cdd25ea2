"""The simulator's detector and scatter options: each changes the counts as documented, the defaults not at all."""
import hashlib

import numpy as np
import pytest
from scipy import ndimage

from dfxcorr import config as C
from dfxcorr.align import lit_blocks
from dfxcorr.io import read_scan
from dfxcorr.sim import simulate as S

from conftest import sim_config

EXACT = {"simulate.noise": False, "simulate.dtype": "float64"}

# sha256 of scan.data.tobytes() of sim_config(**settings) with S.simulate, pinned: options added to the simulator
# must leave scans made without them bit-identical.
PINNED = {
    "default": ({}, "2884401680639ec4cf64e13e15eb883ff9348e3b567a89463fbd30f80c8be15f"),
    "detector options": ({"effects.read_noise": 25.0, "effects.detector_lag": 0.03, "effects.detector_gain": 2.0,
                          "effects.pixel_noise": 0.5, "effects.position_error": 0.3, "effects.dose": 0.02,
                          "effects.background": 0.05, "simulate.reference_steps": 5, "simulate.tiles": 4},
                         "60b6cdc591adf30faa506a8899c6b86d743e352cf658bab225464e8c984c7513"),
    "stepping": ({"simulate.geometry": "stepping", "simulate.steps": 5, "simulate.steps_per_period": 5,
                  "effects.read_noise": 25.0, "simulate.flux": 2000.0},
                 "5ea67bd999f193e0612031f029ef503bf827fc1a68bab8eb0c510fe3ebafcd51"),
}


def counts(**settings) -> np.ndarray:
    return S.simulate(sim_config(**settings))[0].data


def lit_rows(scan, j: int) -> np.ndarray:
    return lit_blocks(scan.position[j:j + 1], scan.reference.transmission.shape[0], scan.shape[1])[0]


@pytest.mark.parametrize("case", list(PINNED))
def test_pinned_scans_are_bit_identical(case):
    settings, digest = PINNED[case]
    assert hashlib.sha256(counts(**settings).tobytes()).hexdigest() == digest


@pytest.mark.slow
def test_dark_is_added_to_every_read_sample_and_stated_in_the_file(tmp_path):
    base = counts(**EXACT)
    with_dark = counts(**EXACT, **{"effects.dark": 100.0})
    lit = base > 0
    np.testing.assert_array_equal(with_dark[lit], base[lit] + 100.0)
    assert (with_dark[~lit] == 0).all()  # only the lit rows are read without full_readout
    full = counts(**EXACT, **{"effects.dark": 100.0, "effects.full_readout": True})
    np.testing.assert_array_equal(full, base + 100.0)
    cfg = sim_config(**{"effects.dark": 100.0, "simulate.reference_steps": 5})
    scan, truth = S.simulate_file(cfg, tmp_path / "scan.h5")
    back = read_scan(tmp_path / "scan.h5")
    assert (back.dark == 100.0).all() and back.dark.shape == scan.shape[1:] and truth["dark"] == 100.0
    assert (back.reference.dark == 100.0).all() and back.reference.data.min() > 50
    S.simulate_file(sim_config(), tmp_path / "plain.h5")
    assert not read_scan(tmp_path / "plain.h5").dark.any()


def test_read_noise_adds_its_variance_on_a_flat_panel_in_detector_units():
    sets = {**S.FLAT_PANEL_STEPPING, "simulate.dtype": "float64"}
    scan, truth = S.simulate(sim_config(**sets))
    mean = counts(**{**sets, "simulate.noise": False, "effects.read_noise": 0.0})
    assert scan.gain == 1.0 and truth["gain"] == 0.5 and truth["electronic_noise"] == 25.0
    assert (scan.dark == 100.0).all() and np.std(truth["vib_phase_offset"]) > 0.03 and not truth["vib_tilt"].any()
    # variance g (Ibar - dark) + sigma_e^2 in every sample, from photons and readout
    ratio = (scan.data - mean) ** 2 / (0.5 * (mean - 100.0) + 25.0 ** 2)
    assert ratio.mean() == pytest.approx(1.0, abs=0.03)


def test_full_readout_reads_zero_signal_rows_at_the_dark_with_the_read_noise():
    sets = {**S.FLAT_PANEL, "simulate.dtype": "float64"}
    scan, _ = S.simulate(sim_config(**sets))
    partial = counts(**{**sets, "effects.full_readout": False})
    unlit = np.ones(scan.shape, bool)
    for j in range(scan.shape[0]):
        unlit[j, lit_rows(scan, j)] = False
    zero = scan.data[unlit]
    assert zero.size > 1e5 and zero.mean() == pytest.approx(100.0, abs=0.3)
    assert zero.var() == pytest.approx(625.0, rel=0.02)
    # the lit rows are the same samples as without full readout: their noise is drawn as before
    np.testing.assert_array_equal(scan.data[~unlit], partial[~unlit])


@pytest.mark.slow
def test_scatter_is_the_superposition_of_each_frames_primary():
    sets = {**EXACT, "effects.scatter": 0.1}
    scan, truth = S.simulate(sim_config(**sets))
    scatter = scan.data - counts(**EXACT)
    # with no visibility the counts are the primary, dose x t^f x t
    primary = counts(**EXACT, **{"simulate.visibility": 1e-12})
    width = 50.0 / 5.0  # scatter_width_mm / pixel_mm
    assert truth["scatter"] == 0.1
    for j in range(0, scan.shape[0], 7):
        rows = lit_rows(scan, j)
        # an independent superposition: a Gaussian filter of the whole frame's primary, zeros off the lit rows and
        # beyond the detector's edges (its kernel cut at 12 sigma: e^-72)
        frame = np.zeros(scan.shape[1:])
        frame[rows] = primary[j, rows]
        expected = 0.1 * ndimage.gaussian_filter(frame, width, mode="constant", truncate=12.0)
        np.testing.assert_allclose(scatter[j, rows], expected[rows], rtol=1e-9, atol=1e-9 * expected.max())
        assert (scatter[j, np.setdiff1d(np.arange(scan.shape[1]), rows)] == 0).all()
    lit = primary > 0
    # the 15-row band under a 10-row kernel keeps about a third of s
    assert 0.02 < scatter[lit].sum() / primary[lit].sum() < 0.05
    # the per-sample ratio: well above the mean behind the densest parts (the spine), below it in air
    ratio = scatter[lit] / primary[lit]
    t = np.broadcast_to(truth["image_transmission"], scan.shape)[lit]
    assert np.median(ratio[t < 0.01]) > 0.1 and np.median(ratio[t == 1.0]) < 0.05


@pytest.mark.slow
def test_scatter_in_a_noisy_scan_adds_the_noise_free_field():
    noisy = counts(**{"effects.scatter": 0.1}).astype(float)
    clean = counts().astype(float)
    exact = counts(**EXACT, **{"effects.scatter": 0.1}) - counts(**EXACT)
    lit = exact > 0
    assert (noisy[lit].sum() - clean[lit].sum()) / exact[lit].sum() == pytest.approx(1.0, rel=0.03)


@pytest.mark.parametrize("dark", [0.0, 100.0])
def test_nonlinearity_compresses_the_dark_free_signal(dark):
    linear = counts(**EXACT)
    bent = counts(**EXACT, **{"effects.detector_nonlinearity": 0.02, "effects.dark": dark})
    lit = linear > 0
    np.testing.assert_allclose(bent[lit] - dark, linear[lit] * (1 - 0.02 * linear[lit] / 2e4), rtol=1e-12)
    # 2 % lost at the flat field's level
    level = np.abs(linear / 2e4 - 1) < 0.01
    assert level.any() and np.all(np.abs((bent[level] - dark) / linear[level] - 0.98) < 3e-4)


@pytest.mark.parametrize("shift_mm", [20.0, pytest.param(-20.0, marks=pytest.mark.slow)])
def test_ghost_of_an_earlier_frame_lands_shifted_by_its_rows(shift_mm):
    sets = {"effects.ghost": 0.01, "effects.ghost_frames": 2, "effects.ghost_shift_mm": shift_mm}
    base = counts(**EXACT)
    ghosted = counts(**EXACT, **sets)
    d = int(shift_mm / 5.0)
    expected = np.zeros_like(base)
    if d > 0:
        expected[2:, d:] = 0.01 * base[:-2, :-d]
    else:
        expected[2:, :d] = 0.01 * base[:-2, -d:]
    np.testing.assert_allclose(ghosted - base, expected, rtol=1e-12, atol=1e-9)
    # not at the same pixel: the ghost is no lag
    j = 50
    assert np.abs(ghosted[j] - base[j] - 0.01 * base[j - 2]).max() > 10


def test_line_noise_is_one_offset_per_frame_and_row():
    sets = {**S.FLAT_PANEL, "simulate.dtype": "float64"}
    scan, truth = S.simulate(sim_config(**sets, **{"effects.line_noise": 5.0}))
    plain = counts(**sets)
    offset = truth["line_offset"]
    assert offset.shape == scan.shape[:2] and offset.std() == pytest.approx(5.0, rel=0.05)
    # every row of every frame (full readout), all columns alike, the noise of the rest unchanged (but where
    # the read noise took a sample below 0, which the file stores as 0)
    stored = (scan.data > 0) & (plain > 0)
    assert stored.mean() > 0.999
    np.testing.assert_allclose((scan.data - plain)[stored], np.broadcast_to(offset[:, :, None], scan.shape)[stored],
                               atol=1e-9)


@pytest.mark.parametrize("name", ["electronic_noise", "scatter", *S.UNCATALOGUED])
def test_concealment_tables_are_valid_and_change_the_counts(name):
    key, realistic, smaller, extra, conceal = {**S.CONCEALED, **S.UNCATALOGUED}[name]
    assert all(0 < a < realistic for a in smaller) and smaller == sorted(smaller, reverse=True)
    C.load([], conceal)  # valid reconstruct settings
    section, option = key.split(".")
    off = S.SCHEMA[section][option].default
    assert not np.array_equal(counts(**{**extra, key: realistic}), counts(**{**extra, key: off}))


@pytest.mark.slow
def test_a_flat_panel_fits_to_the_noise_once_its_read_noise_is_stated():
    from dfxcorr.pipeline import reconstruct

    scan, _ = S.simulate(sim_config(**S.FLAT_PANEL))
    stated = reconstruct(scan, C.load([], S.FLAT_PANEL_STATED), progress=False)
    # the file's dark is the one added and the variance g (Ibar - dark) + sigma_e^2 holds
    assert stated.reduced_chi2 == pytest.approx(1.0, abs=0.03)


@pytest.mark.slow
def test_scatter_fakes_a_dark_field_signal():
    from dfxcorr.pipeline import reconstruct

    def lung_dark_field(scatter):
        scan, truth = S.simulate(sim_config(**{"effects.scatter": scatter}))
        v, vt = reconstruct(scan, C.defaults(), progress=False).image("dark_field"), truth["image_dark_field"]
        return np.nanmedian((v / vt)[vt < 0.9])

    assert lung_dark_field(0.0) == pytest.approx(1.0, abs=0.02)
    # measured 0.917: the 15-row band keeps about a third of s = 0.1 under the 10-row kernel
    assert lung_dark_field(0.1) < 0.95
