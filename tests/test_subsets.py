"""Columns that stand for all: spread by their information, each standing for its stratum's."""
import numpy as np
import pytest

from dfxcorr import fit as F
from dfxcorr.catalogue import PAPER_MODEL
from dfxcorr.noise import noise_weights
from dfxcorr.subsets import column_information, information_columns, spread_columns, standing_columns

from conftest import random_params, tiny_obs


def clinical_like(C=93):
    """Information per column falling from the outer columns (in air, 20x the mean) towards the middle."""
    x = (2 * np.arange(C) + 1) / C - 1
    return 0.04 + 0.6 / (1.03 - np.abs(x)) ** 1.5


def test_equal_columns_are_spread_evenly_each_standing_for_its_share():
    keep, stands = information_columns(np.ones(96), most=8)
    np.testing.assert_array_equal(keep, np.arange(6, 96, 12))
    np.testing.assert_allclose(stands, 12.0)


def test_the_information_is_estimated_exactly_and_a_dominant_column_stands_for_itself():
    info = clinical_like()
    keep, stands = information_columns(info, most=16)
    assert keep.size <= 16 and np.all(np.diff(keep) > 0)
    np.testing.assert_allclose(np.sum(stands * info[keep]), info.sum(), rtol=1e-12)
    # the outermost columns hold more than a stratum each: taken, and standing for about themselves
    assert keep[0] == 0 and keep[-1] == info.size - 1
    assert 0.5 < stands[0] < 2.0 and 0.5 < stands[-1] < 2.0


@pytest.mark.parametrize("weight", [lambda x: 1.0, lambda x: x ** 2, lambda x: (1 + x) ** 2 / 4])
def test_a_smoothly_weighted_sum_is_estimated_where_even_spreading_is_biased(weight):
    """The tilt's information is the phase's times x^2: sums of info times smooth functions of x over the columns,
    estimated from 16 of 93."""
    info = clinical_like()
    x = (2 * np.arange(info.size) + 1) / info.size - 1
    f = info * weight(x)
    keep, stands = information_columns(info, most=16)
    estimate = np.sum(stands * f[keep])
    even = np.unique(np.linspace(0, info.size - 1, 16).astype(int))
    naive = f[even].sum() * info.size / even.size
    truth = f.sum()
    assert abs(estimate / truth - 1) < 0.1
    # what the evenly spread columns with the outermost two made of it (the Hessian 2.7x too large)
    assert abs(naive / truth - 1) > 0.5


def test_no_information_falls_back_to_evenly_spread_columns():
    keep, stands = information_columns(np.zeros(40), most=5)
    np.testing.assert_array_equal(keep, [4, 12, 20, 28, 36])
    np.testing.assert_allclose(stands, 8.0)


def test_evenly_spread_columns_keep_the_outermost_and_all_when_fewer():
    obs = tiny_obs(np.random.default_rng(0), W=9)
    sub = spread_columns(obs, most=3)
    np.testing.assert_array_equal(sub.columns, obs.columns[[0, 4, 8]])
    assert spread_columns(obs, most=9) is obs


def test_columns_without_finite_information_are_never_taken_and_nothing_asked_is_refused():
    info = np.array([1.0, np.nan, 2.0, np.inf, 0.0, 3.0, 1.0, 1.0])
    keep, stands = information_columns(info, most=3)
    assert not set(keep.tolist()) & {1, 3, 4}
    finite = np.where(np.isfinite(info), info, 0.0)
    np.testing.assert_allclose(np.sum(stands * finite[keep]), finite.sum())
    assert information_columns(np.zeros(0), most=4)[0].size == 0
    with pytest.raises(ValueError, match="at least 1"):
        information_columns(info, most=0)


def test_standing_columns_keep_the_information_of_all_and_all_when_fewer(rng):
    """Their weights times what each stands for: the columns' information summed over them is that of all."""
    obs = tiny_obs(rng, W=40)
    params = random_params(rng, obs.n_frames, PAPER_MODEL)
    w = np.asarray(noise_weights(obs, obs.counts), np.float64)
    info = column_information(obs, params, w)
    sub, sw = standing_columns(obs, w, info, most=6)
    assert sub.columns.size <= 6 and sw.shape == sub.counts.shape and sw.dtype == w.dtype
    np.testing.assert_allclose(column_information(sub, params, sw).sum(), info.sum(), rtol=1e-12)
    assert standing_columns(obs, w, None, most=40) == (obs, w)
    for info_of in (None, info[:-1]):
        with pytest.raises(ValueError, match="information"):
            standing_columns(obs, w, info_of, most=39)


def test_the_uncertainty_between_rows_is_that_of_standing_columns_and_per_pixel_of_all(rng, monkeypatch):
    """Where samples read between rows, the uncertainty is computed on UNCERTAINTY_COLUMNS columns standing for all
    (how close that comes to all of them on realistic scans: scripts/uncertainty_columns.py); per pixel, on all."""
    from test_engine import displaced

    obs = tiny_obs(rng, J=14, H=8, W=48)
    between = displaced(rng, obs, spread=0.6)
    params = random_params(rng, obs.n_frames, ("phase_offset", "tilt"))
    w = np.asarray(noise_weights(between, between.counts), np.float64)
    every = F.uncertainty(between, params, w)
    per_pixel = F.uncertainty(obs, params, w)
    monkeypatch.setattr(F, "UNCERTAINTY_COLUMNS", 16)
    sub, sw = standing_columns(between, w, column_information(between, params, w), most=16)
    expected = F.uncertainty(sub, params, sw)
    standing = F.uncertainty(between, params, w)
    for name in params:
        np.testing.assert_array_equal(standing[name], expected[name])
        assert not np.allclose(standing[name], every[name], rtol=1e-6, atol=0)
        np.testing.assert_array_equal(F.uncertainty(obs, params, w)[name], per_pixel[name])
