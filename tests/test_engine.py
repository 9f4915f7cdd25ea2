"""The model beyond the compiled kernels: samples that read the images between rows (the exact block-tridiagonal solve)
and channel terms that depend on the detector row, and the evaluation that dispatches to the kernels or to the model's
own arrays."""
from dataclasses import replace

import numpy as np
import pytest

from dfxcorr import engine as E
from dfxcorr import fisher_pixels as FP
from dfxcorr import kernels as K
from dfxcorr import model as M
from dfxcorr.catalogue import CATALOGUE, PAPER_MODEL, Effect
from dfxcorr.effects.channel import score_tests
from dfxcorr.fit import fit_vibrations
from dfxcorr.observations import displaced_reading

from conftest import modelled_counts, random_images, random_params, tiny_obs

NAMES = ("phase_offset", "tilt", "visibility_loss", "dose")


def displaced(rng, obs, spread=1.3):
    """``obs`` with each frame reading the images up to ``spread`` rows off its own, samples reading outside unused."""
    shift = rng.uniform(-spread, spread, obs.n_frames)[obs.frame]
    reading, inside = displaced_reading(obs.row, obs.rows, shift)
    return replace(obs, reading=reading, use=obs.use & inside[:, None])


def channel_values(ch):
    """The kernels' tuple of channel gradients, from the engine's Channels."""
    return ch.phase, ch.vis, ch.dose, ch.background, ch.harmonic


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


def numeric_information(obs, params, w, names):
    """J^T W J, J the central-difference derivative of the residuals at the images solved for each parameter value,
    in :func:`dfxcorr.model.fisher_index`'s order: the profiled information, exactly for noise-free data without the
    harmonic (the images are then linear in the data)."""

    def residuals(p):
        dsg = M.design(obs, p)
        return (obs.counts - M.expected(obs, dsg, M.solve_images(obs, dsg, w))).ravel()

    index = M.fisher_index(names, obs.n_frames)
    jac = np.empty((obs.counts.size, len(index)))
    for i, (name, j, m) in enumerate(index):
        up, down = ({k: v.copy() for k, v in params.items()} for _ in range(2))
        up[name][j, m] += 1e-6
        down[name][j, m] -= 1e-6
        jac[:, i] = (residuals(up) - residuals(down)) / 2e-6
    return jac.T @ (w.ravel()[:, None] * jac)


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
        assert cb == pytest.approx(ca, rel=1e-9) and gb.rows == {}
        for x, y in zip(ga, channel_values(gb), strict=True):
            np.testing.assert_allclose(y, x, rtol=1e-7, atol=1e-9 * max(np.abs(x).max(), 1e-300))
    table = M.component_table(NAMES)[:3]
    pa, qa = FP.fisher(obs, ch, w, a["coef"], a["inverse"], table)
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

    grad = M.channel_adjoint(NAMES, cost(params)[1], x=obs.x)
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

    numeric = numeric_information(obs, params, w, NAMES)
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


# --------------------------------------------------------------------------------------------------
# A channel term that depends on the detector row: a toy catalogue entry through the model, the engine and the fit
# --------------------------------------------------------------------------------------------------

#: Toy: a fringe-phase gradient along the scan direction, a_j y added to the phase of frame j (a constant gradient
#: is a phase image linear in y: the images take it up).
TOY = Effect("toy_row_phase", "phase", True, ("x^0 y^1",), 0.0, "shift", "toy: a_j y added to the phase",
             gauge_dims=1, unit="rad")


@pytest.fixture
def toy(monkeypatch):
    monkeypatch.setitem(CATALOGUE, TOY.name, TOY)
    return TOY.name


def test_a_row_term_is_a_phase_that_varies_along_the_rows(rng, toy):
    obs = tiny_obs(rng, J=14, H=8, W=5)
    params = random_params(rng, obs.n_frames, NAMES + (toy,))
    images = random_images(rng, obs)
    turn = np.exp(1j * params[toy][obs.frame, 0, None] * obs.y[:, None])
    fringe = (obs.fc + 1j * obs.fs) * turn
    shifted = replace(obs, fc=fringe.real, fs=fringe.imag)
    without = {k: v for k, v in params.items() if k != toy}
    np.testing.assert_allclose(M.expected(obs, M.design(obs, params), images),
                               M.expected(shifted, M.design(shifted, without), images), rtol=1e-12)


def test_the_model_path_with_a_zero_row_term_is_the_compiled_path(rng, toy):
    obs = tiny_obs(rng, J=14, H=8, W=5)
    params = random_params(rng, obs.n_frames, NAMES)
    obs = replace(obs, counts=modelled_counts(rng, obs, params))
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    zero = M.channels({**params, toy: np.zeros((obs.n_frames, 1))}, x=obs.x, n_frames=obs.n_frames)
    assert E.compiled(ch) and not E.compiled(zero)
    a, b = K.retrieve(obs, ch, iterations=2, keep_inverse=True), E.retrieve(obs, zero, iterations=2, keep_inverse=True)
    for key in ("coef", "inverse", "expected", "weights"):
        np.testing.assert_allclose(b[key], a[key], rtol=1e-8, atol=1e-10 * np.abs(a[key]).max())
    w = a["weights"]
    for square in (False, True):
        ca, ga = K.reduced_cost(obs, ch, w, square=square)
        cb, gb = E.reduced_cost(obs, zero, w, square=square)
        assert cb == pytest.approx(ca, rel=1e-9) and set(gb.rows) == {(K.PHASE, 1)}
        for x, y in zip(ga, channel_values(gb), strict=True):
            np.testing.assert_allclose(y, x, rtol=1e-7, atol=1e-9 * max(np.abs(x).max(), 1e-300))
    pa, qa = FP.fisher(obs, ch, w, a["coef"], a["inverse"], M.component_table(NAMES)[:3])
    pb, qb = E.fisher(obs, zero, w, a["coef"], a["inverse"], NAMES)
    np.testing.assert_allclose(pb, pa, rtol=1e-8, atol=1e-10 * np.abs(pa).max())
    np.testing.assert_allclose(qb, qa, rtol=1e-7, atol=1e-9 * np.abs(pa).max())


def test_row_term_gradient_sums_and_information_match_finite_differences(rng, toy):
    names = NAMES + (toy,)
    obs = tiny_obs(rng, J=10, H=6, W=3)
    params = random_params(rng, obs.n_frames, names)
    obs = replace(obs, counts=modelled_counts(rng, obs, params))
    w = 1.0 / np.maximum(obs.counts, 1.0)
    def cost(p, square=False):
        return E.reduced_cost(obs, M.channels(p, x=obs.x, n_frames=obs.n_frames), w, square=square)

    grad = M.channel_adjoint(names, cost(params)[1], x=obs.x)
    for name in names:
        for j in (2, 6):
            up, down = ({k: v.copy() for k, v in params.items()} for _ in range(2))
            up[name][j, 0] += 1e-6
            down[name][j, 0] -= 1e-6
            numeric = (cost(up)[0] - cost(down)[0]) / 2e-6
            assert grad[name][j, 0] == pytest.approx(numeric, rel=1e-5, abs=1e-6 * abs(cost(params)[0]))
    # noise-free data: the profiled information is J^T W J of the residuals at the images solved for each value
    obs = replace(obs, counts=M.expected(obs, M.design(obs, params), random_images(rng, obs)))

    numeric = numeric_information(obs, params, w, names)
    dsg = M.design(obs, params)
    images = M.solve_images(obs, dsg, w, keep_inverse=True)
    plain, corr = E.fisher(obs, dsg.channels, w, images.coef, images.inverse, names)
    np.testing.assert_allclose(plain - corr, numeric, rtol=1e-4, atol=1e-6 * np.abs(numeric).max())
    # the Gauss-Newton sums are the plain information's diagonal
    sums = M.channel_adjoint(names, cost(params, square=True)[1], x=obs.x, square=True)
    diag = np.diag(plain)
    for i, (name, j, m) in enumerate(M.fisher_index(names, obs.n_frames)):
        assert sums[name][j, m] == pytest.approx(diag[i], rel=1e-9)


def test_a_row_term_is_tested_fitted_and_recovered_within_its_errors(toy):
    rng = np.random.default_rng(12)
    obs = tiny_obs(rng, J=24, H=14, W=40, A=12)
    truth = {**random_params(rng, obs.n_frames, PAPER_MODEL), toy: rng.normal(0.0, 0.3, (obs.n_frames, 1))}
    truth[toy] -= np.median(truth[toy])
    without = {k: v for k, v in truth.items() if k != toy}
    w_of = dict.fromkeys(("with", "without"))
    for label, p in (("with", truth), ("without", without)):
        data = replace(obs, counts=modelled_counts(rng, obs, p))
        w_of[label] = (data, 1.0 / np.maximum(data.counts, 1.0))
    # the score test of the candidate at the model's true parameters: chi-square with its dof where the data lack it
    scores = {label: score_tests(data, without, w, PAPER_MODEL, [toy], dispersion=1.0).tests[toy]
              for label, (data, w) in w_of.items()}
    assert scores["without"].p_value > 1e-3 and scores["with"].p_value < 1e-12, scores
    data, _ = w_of["with"]
    fit = fit_vibrations(data, effects=PAPER_MODEL + (toy,))
    est, se = fit.params[toy][:, 0], fit.uncertainty[toy][:, 0]
    good = np.isfinite(se)
    # the gauge: a common gradient is the images' (compare after removing the mean difference)
    diff = est[good] - truth[toy][good, 0]
    pull = (diff - np.average(diff, weights=1 / se[good] ** 2)) / se[good]
    # 23 pulls: their RMS scatters about 1 by 0.15 (one standard deviation) where the errors are right
    # (0.5-1.5: more than 3 of them either way)
    assert good.all() and 0.5 < np.sqrt(np.mean(pull ** 2)) < 1.5, pull


def test_expected_counts_by_runs_of_columns_on_every_path(rng, toy):
    obs = tiny_obs(rng, J=14, H=8, W=5)
    images = random_images(rng, obs)
    plain = random_params(rng, obs.n_frames, NAMES)
    for o, params in ((obs, plain), (displaced(rng, obs), plain), (obs, random_params(rng, obs.n_frames, (toy,)))):
        runs = list(E.expected_by_columns(o, params, images, samples=2 * o.frame.size))
        assert [c.tolist() for c, *_ in runs] == [[0, 1], [2, 3], [4]]
        np.testing.assert_allclose(np.concatenate([ibar for *_, ibar in runs], axis=1),
                                   M.expected(o, M.design(o, params), images), rtol=1e-12)
