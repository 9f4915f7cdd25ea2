"""The observations' fringe quadratures: their definition, and one set shared by the copies that keep the flat field;
the positions taken as slices."""
from dataclasses import replace

import numpy as np
import pytest

from dfxcorr.observations import Quadratures, index_slice

from conftest import tiny_obs


def quadratures(obs):
    amp = obs.tf * obs.vf
    return amp * np.cos(obs.phif), amp * np.sin(obs.phif)


def test_the_fringe_is_the_flat_fields_quadratures_in_the_samples_dtype():
    obs = tiny_obs(np.random.default_rng(1))
    for a, b in zip(obs.fringe, quadratures(obs), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=0)
    single = replace(obs, tf=obs.tf.astype(np.float32), vf=obs.vf.astype(np.float32),
                     phif=obs.phif.astype(np.float32))
    for a, b in zip(single.fringe, quadratures(obs), strict=True):
        assert a.dtype == np.float32
        # single-precision products and trigonometry: a few ulps of the amplitude
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6 * np.abs(obs.tf * obs.vf).max())


def test_copies_keeping_the_flat_field_share_its_quadratures_and_others_make_their_own():
    obs = tiny_obs(np.random.default_rng(2))
    fc, fs = obs.fringe
    masked = replace(obs, use=obs.use & (obs.counts > 800), dark=obs.dark + 3.0)
    assert masked.fringe[0] is fc and masked.fringe[1] is fs
    moved = replace(obs, phif=obs.phif + 0.3)
    for a, b in zip(moved.fringe, quadratures(moved), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=0)
    # the original and the copy sharing its slot keep the quadratures of their own flat field
    assert obs.fringe[0] is fc and masked.fringe[1] is fs
    assert not np.allclose(moved.fringe[0], fc)


def test_a_subset_cuts_the_quadratures_already_made_and_equals_making_them_afresh():
    obs = tiny_obs(np.random.default_rng(3))
    cols = np.array([1, 4, 5])
    fresh = obs.subset(cols)
    expected = quadratures(fresh)
    made = obs.fringe
    for copy in (True, False):
        cut = obs.subset(cols, copy=copy)
        for a, b, c in zip(cut.fringe, expected, made, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-14, atol=0)
            np.testing.assert_array_equal(a, c[:, cols])
    run = obs.subset(np.arange(2, 5), copy=False)
    assert np.shares_memory(run.fringe[0], obs.fringe[0])


def test_a_slot_that_does_not_keep_makes_the_same_quadratures_at_every_call():
    obs = tiny_obs(np.random.default_rng(4))
    passing = replace(obs, quadratures=Quadratures(keep=False))
    first, again = passing.fringe, replace(passing, use=~passing.use).fringe
    for a, b, c in zip(first, again, quadratures(obs), strict=True):
        np.testing.assert_allclose(a, c, rtol=1e-14, atol=0)
        np.testing.assert_array_equal(a, b)
    assert first[0] is not again[0] and passing.quadratures.value is None


def test_held_pixels_are_placed_and_read_where_they_are_runs_or_not():
    obs = tiny_obs(np.random.default_rng(6))
    H, W = obs.shape[1:]
    image = np.arange(float(H * W)).reshape(H, W)
    for cols in (np.arange(1, 4), np.array([0, 2, 5])):
        sub = obs.subset(cols)
        np.testing.assert_array_equal(sub.held(image), image[np.ix_(sub.rows, sub.columns)])
        out = np.zeros((H, W))
        sub.place(out, sub.held(image))
        np.testing.assert_array_equal(out[np.ix_(sub.rows, sub.columns)], image[np.ix_(sub.rows, sub.columns)])
        assert out.sum() == image[np.ix_(sub.rows, sub.columns)].sum()


@pytest.mark.parametrize("columns", [None, np.arange(40), np.arange(3, 40, 7), np.array([5]), np.array([1, 2, 4]),
                                     np.array([9, 4, 0]), np.array([3, 3]), np.array([-1]), np.array([-3, -2, -1]),
                                     np.array([-1, 0, 1]), np.zeros(0, int)])
def test_index_slice_takes_the_positions_of_the_index_array(columns):
    a = np.arange(6 * 40).reshape(6, 40)
    at = index_slice(columns, 40)
    expected = a if columns is None else a[:, columns]
    assert np.array_equal(a[:, at], expected)
    # evenly spaced, ascending columns within the detector are a slice (a view); others stay an index array
    even = columns is not None and columns.size > 0 and columns[0] >= 0 and (
        columns.size == 1 or bool(np.all(np.diff(columns) == columns[1] - columns[0])) and columns[1] > columns[0])
    assert isinstance(at, slice) == (columns is None or even)


def test_index_slice_leaves_positions_beyond_the_axis_to_refuse():
    with pytest.raises(IndexError):
        np.zeros((2, 12))[:, index_slice(np.array([10, 11, 12]), 12)]
