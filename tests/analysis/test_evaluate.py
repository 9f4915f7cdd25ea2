"""Comparison with ground truth: errors and pulls in the gauge the images leave free."""
import numpy as np
import pytest

from dfxcorr.analysis.evaluate import vibration_pulls, vibration_rmse


def test_pulls_are_errors_in_units_of_their_standard_errors_in_the_estimates_gauge():
    rng = np.random.default_rng(5)
    J = 40
    good = np.ones(J, bool)
    good[:3] = False
    # the truth ordered by frame, errors far below its spacing: the median stays at the middle good frame
    truth = {"vib_phase_offset": np.linspace(-0.1, 0.1, J), "vib_visibility": np.linspace(0.8, 1.0, J)}
    se = {"phase_offset": rng.uniform(1e-4, 2e-4, (J, 1)), "visibility_loss": rng.uniform(1e-4, 2e-4, (J, 1))}
    # a common shift of the phase and a common factor of the visibility are the images': no error
    exact = {"phase_offset": truth["vib_phase_offset"][:, None] + 0.7,
             "visibility_loss": 1.3 * truth["vib_visibility"][:, None]}
    zero = vibration_pulls(exact, se, truth, good)
    assert set(zero) == {"phase_offset", "visibility_loss"}
    assert all(value == pytest.approx(0.0, abs=1e-9) for value in zero.values()), zero
    # an error of one standard error at every good frame but the median one
    sign = np.where(np.arange(J) % 2, 1.0, -1.0)
    sign[(3 + J) // 2] = 0.0
    off = {"phase_offset": exact["phase_offset"] + sign[:, None] * se["phase_offset"]}
    pulls = vibration_pulls(off, se, truth, good)
    assert list(pulls) == ["phase_offset"]
    assert pulls["phase_offset"] == pytest.approx(np.sqrt((good.sum() - 1) / good.sum()), rel=1e-9)
    assert vibration_rmse(off, truth, good)["phase_offset"] == pytest.approx(
        np.sqrt(np.mean((sign * se["phase_offset"][:, 0])[good] ** 2)), rel=1e-9)


def test_pulls_of_errors_drawn_with_the_stated_standard_errors_are_one():
    # errors far below the spread of the values: both medians of a per-value gauge would fall on one frame, whose
    # error every other would then carry (a pull RMS of about sqrt 2); the truth is carried into the estimate's gauge
    rng = np.random.default_rng(11)
    J = 800
    good = np.ones(J, bool)
    truth = {"vib_phase_offset": rng.normal(0.0, 0.4, J), "vib_visibility": rng.uniform(0.8, 1.0, J)}
    se = {"phase_offset": rng.uniform(1e-3, 2e-3, (J, 1)), "visibility_loss": rng.uniform(1e-3, 2e-3, (J, 1))}
    est = {"phase_offset": (truth["vib_phase_offset"] + 0.3)[:, None] + rng.normal(0.0, se["phase_offset"]),
           "visibility_loss": (1.1 * truth["vib_visibility"])[:, None] + rng.normal(0.0, se["visibility_loss"])}
    pulls = vibration_pulls(est, se, truth, good)
    # the RMS of J unit normals has a standard deviation of about 1 / sqrt(2 J) = 0.025: 4 of them
    assert pulls == pytest.approx({"phase_offset": 1.0, "visibility_loss": 1.0}, abs=4 / np.sqrt(2 * J))
