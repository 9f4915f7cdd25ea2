"""The observations' fringe: the flat field's quadratures, what is derived from them, and the columns cut; the
positions taken as slices; ranges of rows taken as views."""
from dataclasses import replace

import numba
import numpy as np
import pytest

import dfxcorr.align as align
from dfxcorr.align import FRINGE_CHUNK, build_observations, collect_lit_rows
from dfxcorr.chunks import row_bounds, row_chunks
from dfxcorr.io import Reference, Scan
from dfxcorr.observations import Reading, index_slice

from conftest import tiny_obs


def test_the_fringe_is_the_flat_fields_quadratures_in_the_samples_dtype():
    """In float32 within a few ulps of float64 (tests/test_align.py checks v^f and phi^f made from them against the
    reference interpolated directly)."""
    rng = np.random.default_rng(1)
    A, W = 4, 7
    ref = Reference(rng.uniform(500, 1500, (A, W)), rng.uniform(0.2, 0.5, (A, W)),
                    np.cumsum(rng.uniform(0.5, 1.5, (A, W)), axis=0))
    scan = Scan(data=rng.poisson(800, (12, 6, W)).astype(np.float64), position=-A + 1.0 + np.arange(12) * 8 / 11,
                reference=ref)
    obs = build_observations(scan, ref)
    amp = np.hypot(obs.fc, obs.fs)
    single = build_observations(scan, ref, dtype=np.float32)
    for a, b in zip(single.fringe, obs.fringe, strict=True):
        assert a.dtype == np.float32
        # single-precision products and trigonometry: a few ulps of the amplitude
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6 * amp.max())


def test_the_fringe_and_region_made_a_run_of_blocks_at_a_time_equal_them_made_at_once(monkeypatch):
    """Each frame's phase step and the visibility threshold taken with the blocks of their own run."""
    rng = np.random.default_rng(2)
    A, W, J = 4, 7, 12
    ref = Reference(rng.uniform(500, 1500, (A, W)), rng.uniform(0.2, 0.5, (A, W)),
                    np.cumsum(rng.uniform(0.5, 1.5, (A, W)), axis=0))
    scan = Scan(data=rng.poisson(800, (J, 6, W)).astype(np.float64), position=-A + 1.0 + np.arange(J) * 8 / 11,
                reference=ref, phase_step=rng.uniform(-np.pi, np.pi, J))
    store = collect_lit_rows(scan)

    def made():
        return store.observations(ref, dtype=np.float32, min_visibility=0.35)

    whole = made()
    monkeypatch.setattr(align, "FRINGE_CHUNK", 3 * W)
    assert align.FRINGE_CHUNK < FRINGE_CHUNK and whole.row.size > 9
    chunked = made()
    for a, b in zip((chunked.fc, chunked.fs, chunked.roi), (whole.fc, whole.fs, whole.roi), strict=True):
        np.testing.assert_array_equal(a, b)
    assert 0 < whole.roi.mean() < 1 and np.all(whole.vf[~whole.roi] == 0)
    # the region is where the visibility interpolated directly reaches the threshold
    np.testing.assert_array_equal(whole.roi, store.observations(ref).vf >= 0.35)


def test_keeping_the_fringe_where_asked_zeroes_visibility_elsewhere_and_leaves_the_rest():
    obs = tiny_obs(np.random.default_rng(3))
    where = obs.counts > 800
    kept = obs.keep_fringe(where)
    np.testing.assert_array_equal(kept.vf[~where], 0.0)
    np.testing.assert_array_equal(kept.fc[where], obs.fc[where])
    np.testing.assert_array_equal(kept.fs[where], obs.fs[where])
    assert kept.counts is obs.counts and kept.tf is obs.tf


def test_a_subset_cuts_the_fringe_as_a_copy_or_a_view():
    obs = tiny_obs(np.random.default_rng(4))
    cols = np.array([1, 4, 5])
    for copy in (True, False):
        cut = obs.subset(cols, copy=copy)
        for a, b in zip(cut.fringe, obs.fringe, strict=True):
            np.testing.assert_array_equal(a, b[:, cols])
    run = obs.subset(np.arange(2, 5), copy=False)
    assert np.shares_memory(run.fringe[0], obs.fringe[0])


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


def test_the_observations_of_a_range_of_rows_are_views_of_the_whole_ones():
    rng = np.random.default_rng(7)
    obs = tiny_obs(rng, J=9, H=8, W=5)
    K, C = obs.counts.shape
    R = obs.rows.size
    obs = replace(obs, noise=rng.uniform(0.5, 2.0, (R, C)), roi=rng.random((K, C)) > 0.2,
                  offset=rng.uniform(0.0, 5.0, (K, C)), gain=2.5, electronic=7.0)
    lo, hi = 2, 5
    part = obs.of_rows(lo, hi)
    assert (part.gain, part.electronic, part.shape) == (2.5, 7.0, obs.shape)
    blocks = np.flatnonzero(np.isin(obs.pixel, np.arange(lo, hi)))
    np.testing.assert_array_equal(part.rows, obs.rows[lo:hi])
    np.testing.assert_array_equal(part.row, obs.row[blocks])
    np.testing.assert_array_equal(part.frame, obs.frame[blocks])
    np.testing.assert_array_equal(part.y, obs.y[blocks])
    np.testing.assert_array_equal(part.columns, obs.columns)
    for name in ("counts", "tf", "fc", "fs", "dark", "use", "roi", "offset"):
        a, b = getattr(part, name), getattr(obs, name)
        np.testing.assert_array_equal(a, b[blocks], err_msg=name)
        assert np.shares_memory(a, b) and a.flags["C_CONTIGUOUS"], name
    np.testing.assert_array_equal(part.noise, obs.noise[lo:hi])
    np.testing.assert_array_equal(part.pixel_gain(), obs.pixel_gain()[lo:hi])
    assert obs.block_range(lo, hi) == slice(blocks[0], blocks[-1] + 1)
    assert obs.block_range(lo, R).stop == K
    for bad in ((3, 3), (-1, 2), (0, R + 1)):
        with pytest.raises(ValueError, match="range"):
            obs.block_range(*bad)


def test_ranges_of_rows_cover_the_rows_once_in_order_near_their_budget():
    obs = tiny_obs(np.random.default_rng(8), J=20, H=12, W=6)
    K, C = obs.counts.shape
    per_row = np.diff(np.append(obs.starts, K)) * C
    for samples in (1, 3 * C, 40 * C):
        ranges = obs.row_ranges(samples)
        lo, hi = np.array(ranges).T
        assert lo[0] == 0 and hi[-1] == obs.rows.size and np.all(lo < hi) and np.array_equal(lo[1:], hi[:-1])
        held = np.array([per_row[a:b].sum() for a, b in ranges])
        # each range from the first row at or after a multiple of the budget: at most a row beyond it
        assert held.max() < max(samples, C) + per_row.max()
        assert len(ranges) <= -(-K // max(samples // C, 1))
    assert len(obs.row_ranges(3 * C)) > 2
    assert obs.row_ranges(K * C) == [(0, obs.rows.size)]


def test_samples_that_read_between_rows_are_not_taken_a_run_of_rows_at_a_time():
    obs = tiny_obs(np.random.default_rng(9))
    between = replace(obs, reading=Reading(obs.pixel.copy(), np.zeros(obs.pixel.size)))
    with pytest.raises(ValueError, match="between rows"):
        between.of_rows(0, 1)


def test_rows_are_cut_at_the_first_row_starting_at_or_after_each_position():
    """Where the cuts fall decides the compiled kernels' chunks, and so the order of their sums."""
    starts = np.array([0, 2, 4, 9])
    np.testing.assert_array_equal(row_bounds(starts, np.array([2.0])), [0, 1, 4])
    np.testing.assert_array_equal(row_bounds(starts, np.array([2.5, 3.0, 9.0, 12.0])), [0, 2, 3, 4])
    np.testing.assert_array_equal(row_bounds(starts, np.array([])), [0, 4])
    np.testing.assert_array_equal(row_bounds(np.array([], int), np.array([1.0])), [0])
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        # 4 chunks of about 3 of 12 blocks: rows starting at or after 3, 6 and 9
        np.testing.assert_array_equal(row_chunks(starts, 12, per_thread=4), [0, 2, 3, 4])
    finally:
        numba.set_num_threads(threads)
