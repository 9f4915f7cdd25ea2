"""The model where samples read the images between rows: the exact block-tridiagonal solve, and the evaluation that
dispatches to the compiled kernels or to the model's own arrays."""
from dataclasses import replace

import numpy as np
import pytest

from dfxcorr import engine as E
from dfxcorr import kernels as K
from dfxcorr import model as M
from dfxcorr.observations import displaced_reading

from conftest import modelled_counts, random_images, random_params, tiny_obs

NAMES = ("phase_offset", "tilt", "visibility_loss", "dose")


def displaced(rng, obs, spread=1.3):
    """``obs`` with each frame reading the images up to ``spread`` rows off its own, samples reading outside unused."""
    shift = rng.uniform(-spread, spread, obs.n_frames)[obs.frame]
    reading, inside = displaced_reading(obs.row, obs.rows, shift)
    return replace(obs, reading=reading, use=obs.use & inside[:, None])


def dense_design(obs, columns):
    """The full design of each column: (C, K, p R), sample k's columns on the two rows it reads."""
    R, K_, p = obs.rows.size, obs.row.size, len(columns)
    lo, f = obs.reading.lo, obs.reading.frac
    hi = np.minimum(lo + 1, R - 1)
    X = np.zeros((obs.columns.size, K_, p * R))
    for a, col in enumerate(columns):
        np.add.at(X, (slice(None), np.arange(K_), p * lo + a), ((1 - f)[:, None] * col).T)
        np.add.at(X, (slice(None), np.arange(K_), p * hi + a), (f[:, None] * col).T)
    return X


def test_displaced_reading_of_whole_rows():
    row = np.array([0, 0, 1, 1, 2, 2, 3])
    frame = np.array([0, 1, 0, 1, 0, 1, 0])
    reading, inside = displaced_reading(row, np.arange(4), np.array([1.0, -0.25])[frame])
    # frame 0 reads one row further (the last row reads beyond the images); frame 1 a quarter row back
    np.testing.assert_array_equal(inside, [True, False, True, True, True, True, False])
    np.testing.assert_array_equal(reading.lo[inside], [1, 2, 0, 3, 1])
    np.testing.assert_allclose(reading.frac[inside], [0, 0, 0.75, 0, 0.75])


def test_images_read_between_rows_are_the_least_squares_solution(rng):
    obs = displaced(rng, tiny_obs(rng, J=14, H=8, W=4))
    params = random_params(rng, obs.n_frames, NAMES)
    dsg = M.design(obs, params)
    w = np.where(obs.use, rng.uniform(0.5, 2, obs.counts.shape), 0.0)
    cols = [dsg.A, dsg.Bc, dsg.Bs]
    coef, valid, inverse, coupling = M.solve_read_between(obs, cols, obs.counts - dsg.offset, w, keep_inverse=True)
    assert valid.all()
    for c, X in enumerate(dense_design(obs, cols)):
        N = X.T @ (w[:, c, None] * X)
        exact = np.linalg.solve(N, X.T @ (w[:, c] * (obs.counts - dsg.offset)[:, c])).reshape(-1, 3)
        np.testing.assert_allclose(coef[:, c], exact, rtol=1e-8, atol=1e-10 * np.abs(exact).max())
        Ni = np.linalg.inv(N)
        for q in range(obs.rows.size):
            np.testing.assert_allclose(inverse[q, c], Ni[3 * q:3 * q + 3, 3 * q:3 * q + 3], rtol=1e-7,
                                       atol=1e-9 * np.abs(Ni).max())
            if q + 1 < obs.rows.size:
                np.testing.assert_allclose(coupling[q, c], Ni[3 * q:3 * q + 3, 3 * q + 3:3 * q + 6], rtol=1e-7,
                                           atol=1e-9 * np.abs(Ni).max())


def test_reading_at_the_own_row_is_the_compiled_path(rng):
    """A reading of zero displacement is the paper's geometry: the model's arrays give the kernels' values."""
    obs = tiny_obs(rng, J=14, H=8, W=5)
    params = random_params(rng, obs.n_frames, NAMES)
    obs = replace(obs, counts=modelled_counts(rng, obs, params))
    reading, inside = displaced_reading(obs.row, obs.rows, np.zeros(obs.row.size))
    assert inside.all()
    same = replace(obs, reading=reading)
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    a, b = K.retrieve(obs, ch, iterations=2, keep_inverse=True), E.retrieve(same, ch, iterations=2, keep_inverse=True)
    for key in ("coef", "inverse", "expected", "weights"):
        np.testing.assert_allclose(b[key], a[key], rtol=1e-8, atol=1e-10 * np.abs(a[key]).max())
    assert b["chi2"] == pytest.approx(a["chi2"], rel=1e-9) and b["samples"] == a["samples"]
    w = a["weights"]
    for square in (False, True):
        ca, ga = K.reduced_cost(obs, ch, w, square=square)
        cb, gb = E.reduced_cost(same, ch, w, square=square)
        assert cb == pytest.approx(ca, rel=1e-9)
        for x, y in zip(ga, gb, strict=True):
            np.testing.assert_allclose(y, x, rtol=1e-7, atol=1e-9 * max(np.abs(x).max(), 1e-300))
    table = M.component_table(NAMES)[:3]
    pa, qa = K.fisher(obs, ch, w, a["coef"], a["inverse"], table)
    pb, qb = E.fisher(same, ch, w, a["coef"], a["inverse"], NAMES)
    np.testing.assert_allclose(pb, pa, rtol=1e-8, atol=1e-10 * np.abs(pa).max())
    np.testing.assert_allclose(qb, qa, rtol=1e-7, atol=1e-9 * np.abs(pa).max())


def test_reduced_cost_gradient_where_samples_read_between_rows(rng):
    obs = tiny_obs(rng, J=14, H=8, W=5)
    params = random_params(rng, obs.n_frames, NAMES)
    obs = displaced(rng, replace(obs, counts=modelled_counts(rng, obs, params)))
    w = np.where(obs.use, 1.0 / np.maximum(obs.counts, 1.0), 0.0)

    def cost(p):
        return E.reduced_cost(obs, M.channels(p, x=obs.x, n_frames=obs.n_frames), w)

    grad = M.channel_adjoint(NAMES, M.Channels(*cost(params)[1]), x=obs.x)
    for name in NAMES:
        for j in (3, 7):
            h = 1e-6
            up, down = ({k: v.copy() for k, v in params.items()} for _ in range(2))
            up[name][j, 0] += h
            down[name][j, 0] -= h
            numeric = (cost(up)[0] - cost(down)[0]) / (2 * h)
            assert grad[name][j, 0] == pytest.approx(numeric, rel=1e-5, abs=1e-6 * abs(cost(params)[0]))


def test_profiled_information_where_samples_read_between_rows(rng):
    """plain - correction = J^T W J, J the derivative of the residuals at the images solved for each parameter value
    (exact for data the model fits without residual, the images being linear in the data without the harmonic)."""
    obs = displaced(rng, tiny_obs(rng, J=10, H=6, W=3))
    params = random_params(rng, obs.n_frames, NAMES)
    obs = replace(obs, counts=M.expected(obs, M.design(obs, params), random_images(rng, obs)))
    w = np.where(obs.use, 1.0 / np.maximum(obs.counts, 1.0), 0.0)

    def residuals(p):
        dsg = M.design(obs, p)
        return (obs.counts - M.expected(obs, dsg, M.solve_images(obs, dsg, w))).ravel()

    index = M.fisher_index(NAMES, obs.n_frames)
    jac = np.empty((obs.counts.size, len(index)))
    for i, (name, j, m) in enumerate(index):
        up, down = ({k: v.copy() for k, v in params.items()} for _ in range(2))
        up[name][j, m] += 1e-6
        down[name][j, m] -= 1e-6
        jac[:, i] = (residuals(up) - residuals(down)) / 2e-6
    numeric = jac.T @ (w.ravel()[:, None] * jac)
    dsg = M.design(obs, params)
    images = M.solve_images(obs, dsg, w, keep_inverse=True)
    info, _ = M.fisher_matrix(obs, dsg, images, w, NAMES)
    np.testing.assert_allclose(info, numeric, rtol=1e-4, atol=1e-6 * np.abs(numeric).max())
    plain, corr = E.fisher(obs, dsg.channels, w, images.coef, images.inverse, NAMES)
    np.testing.assert_allclose(plain - corr, numeric, rtol=1e-4, atol=1e-6 * np.abs(numeric).max())


def test_images_read_between_rows_reproduce_noise_free_data(rng):
    obs = displaced(rng, tiny_obs(rng, J=14, H=8, W=5), spread=0.8)
    params = random_params(rng, obs.n_frames, NAMES + ("harmonic",))
    dsg = M.design(obs, params)
    truth = random_images(rng, obs)
    obs = replace(obs, counts=M.expected(obs, dsg, truth))
    est = E.retrieve(obs, dsg.channels, weights=np.ones_like(obs.counts))
    assert np.all(est["valid"])
    np.testing.assert_allclose(est["coef"], truth.coef, rtol=1e-6, atol=1e-8)
