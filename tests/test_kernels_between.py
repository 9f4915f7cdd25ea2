"""The compiled loops where samples read the images between rows equal the model's numpy expressions (the engine's
model path)."""
from dataclasses import replace

import numpy as np
import pytest

from dfxcorr import engine as E
from dfxcorr import fisher_between as FB
from dfxcorr import kernels_between as KB
from dfxcorr import model as M

from conftest import modelled_counts, random_params, tiny_obs
from test_engine import displaced

NAMES = ("phase_offset", "tilt", "visibility_loss", "dose")
WITH_ALL = NAMES + ("background", "harmonic")


def close(got, want, rtol=1e-9):
    np.testing.assert_allclose(got, want, rtol=rtol, atol=rtol * max(np.abs(want).max(), 1e-300))


@pytest.fixture(params=[NAMES, WITH_ALL], ids=["plain", "harmonic"])
def case(request, rng):
    obs = tiny_obs(rng, J=16, H=9, W=11)
    params = random_params(rng, obs.n_frames, request.param)
    obs = displaced(rng, replace(obs, counts=modelled_counts(rng, obs, params)))
    # no sample reads row 3 of column 4: that image cannot be solved, its neighbours can
    lo, hi, f = obs.read_rows()
    use = obs.use.copy()
    use[(lo == 3) | ((hi == 3) & (f > 0)), 4] = False
    return replace(obs, use=use), M.channels(params, x=obs.x, n_frames=obs.n_frames)


@pytest.mark.parametrize("iterations,next_weights,given", [(1, False, False), (2, True, False), (2, False, True)])
def test_retrieval_equals_the_model(case, rng, iterations, next_weights, given):
    obs, ch = case
    weights = rng.uniform(0.5, 2.0, obs.counts.shape) / 800 if given else None
    want = E.model_retrieve(obs, ch, weights=weights, iterations=iterations, keep_inverse=True,
                           next_weights=next_weights, gain=1.3)
    got = KB.retrieve(obs, ch, weights=weights, iterations=iterations, keep_inverse=True, next_weights=next_weights,
                      gain=1.3)
    np.testing.assert_array_equal(got["valid"], want["valid"])
    assert not want["valid"][3, 4] and want["valid"].sum() == want["valid"].size - 1
    for key in ("coef", "inverse", "coupling", "expected", "weights"):
        close(got[key], want[key])
    assert got["chi2"] == pytest.approx(want["chi2"], rel=1e-9) and got["samples"] == want["samples"]


def test_retrieval_with_pixel_noise_and_known_photons(case, rng):
    obs, ch = case
    obs = replace(obs, noise=rng.uniform(0.8, 1.5, (obs.rows.size, obs.columns.size)),
                  offset=rng.uniform(0, 20, obs.counts.shape), electronic=4.0)
    want, got = E.model_retrieve(obs, ch, iterations=2), KB.retrieve(obs, ch, iterations=2, keep_expected=False)
    close(got["coef"], want["coef"])
    assert got["chi2"] == pytest.approx(want["chi2"], rel=1e-9)
    assert got["expected"].shape == (0, obs.columns.size) and got["inverse"] is None


@pytest.mark.parametrize("square", [False, True])
@pytest.mark.parametrize("phase", [None, 0.4])
def test_reduced_cost_equals_the_model(case, square, phase):
    obs, ch = case
    w = np.where(obs.use, 1.0 / np.maximum(obs.counts, 1.0), 0.0)
    cost, sums = KB.reduced_cost(obs, ch, w, phase=phase, square=square)
    want_cost, want = E.model_reduced_cost(obs, ch, w, phase=phase, square=square)
    assert cost == pytest.approx(want_cost, rel=1e-9)
    for a, b in zip(sums, (want.phase, want.vis, want.dose, want.background, want.harmonic), strict=True):
        close(a, b)


def test_reduced_cost_skips_channels_not_asked_for(case):
    obs, ch = case
    w = np.where(obs.use, 1.0 / np.maximum(obs.counts, 1.0), 0.0)
    _, sums = KB.reduced_cost(obs, ch, w, channels=("phase",))
    _, full = KB.reduced_cost(obs, ch, w)
    close(sums[0], full[0])
    assert all(not np.any(s_) for s_ in sums[1:])


def read_only_between(obs):
    """``obs`` with rows 5 and 6 of column 6 read only by the samples between them, all at one fraction: they tell one
    combination of their images, and row 6's complement in the elimination is singular (held apart)."""
    lo, hi, f = obs.read_rows()
    use = obs.use.copy()
    use[((hi == 5) & (lo == 4)) | (lo == 6) | ((lo == 5) & (f == 0)), 6] = False
    return replace(obs, reading=replace(obs.reading, frac=np.where(lo == 5, 0.4, obs.reading.frac)), use=use)


@pytest.mark.parametrize("held", [False, True], ids=["", "a row held apart"])
@pytest.mark.parametrize("profiled", [True, False])
def test_fisher_information_equals_the_model(case, rng, profiled, held):
    obs, ch = case
    obs = read_only_between(obs) if held else obs
    names = WITH_ALL if np.any(ch.harmonic) else NAMES
    w = np.where(obs.use, 1.0 / np.maximum(obs.counts, 1.0), 0.0)
    dsg = M.design_channels(obs, ch)
    images = M.solve_images(obs, dsg, w)
    want_plain, want_corr, _ = M.fisher_parts(obs, dsg, images, w, names, profiled=profiled)
    plain, corr = FB.fisher(obs, ch, w, images.coef, M.component_table(names)[:3], profiled=profiled)
    close(plain, want_plain)
    close(corr, want_corr)
    assert np.any(corr) == profiled


@pytest.mark.parametrize("names", [NAMES, WITH_ALL], ids=["plain", "harmonic"])
@pytest.mark.parametrize("J", [96, 90], ids=["six groups", "a short last group"])
def test_fisher_information_of_a_tall_scan_equals_the_model(rng, names, J):
    # 200 rows, frames in blocks (fisher_between.FRAME_GROUP) beside the global components' block: N^-1 Y of each
    # block is cut off where it is negligible, and each pair of blocks multiplied over the rows both reach
    obs = tiny_obs(rng, J=J, H=200, W=3, A=16)
    params = random_params(rng, obs.n_frames, names)
    obs = displaced(rng, replace(obs, counts=modelled_counts(rng, obs, params)))
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    w = np.where(obs.use, 1.0 / np.maximum(obs.counts, 1.0), 0.0)
    dsg = M.design_channels(obs, ch)
    images = M.solve_images(obs, dsg, w)
    want_plain, want_corr, _ = M.fisher_parts(obs, dsg, images, w, names, profiled=True)
    plain, corr = FB.fisher(obs, ch, w, images.coef, M.component_table(names)[:3])
    close(plain, want_plain)
    close(corr, want_corr)


def test_block_solve_stops_where_the_inverse_has_decayed():
    # a scaled block-tridiagonal N (random blocks, couplings not symmetric) whose row 150 cannot be solved: N^-1
    # decays away from the right-hand sides' rows 90-95, the backward sweep stops where it has, the forward one at
    # the unsolvable row (exactly 0 beyond it)
    R, G, r0, r1, bad = 200, 5, 90, 95, 150
    rng = np.random.default_rng(3)
    Ds = np.empty((R, 3, 3))
    for r in range(R):
        a = rng.normal(size=(3, 3))
        Ds[r] = 4.0 * np.eye(3) + 0.3 * (a @ a.T)
    Us = 0.8 * rng.normal(size=(R, 3, 3)) / 3.0
    Ds[bad], Us[bad - 1], Us[bad], Us[-1] = np.eye(3), 0.0, 0.0, 0.0
    valid = np.ones(R, bool)
    valid[bad] = False
    scale = rng.uniform(0.5, 2.0, (R, 3))
    Finv = np.empty((R, 3, 3))
    Finv[0] = np.linalg.inv(Ds[0])
    for r in range(1, R):
        Finv[r] = np.linalg.inv(Ds[r] - Us[r - 1].T @ Finv[r - 1] @ Us[r - 1])
    Mr = np.einsum("rpa,rpb->rab", np.roll(Us, 1, axis=0), np.roll(Finv, 1, axis=0))
    Y = np.zeros((R, 3, G))
    Y[r0:r1 + 1] = rng.normal(size=(r1 + 1 - r0, 3, G))
    Ns = np.zeros((3 * R, 3 * R))
    for r in range(R):
        Ns[3 * r:3 * r + 3, 3 * r:3 * r + 3] = Ds[r]
        if r + 1 < R:
            Ns[3 * r:3 * r + 3, 3 * r + 3:3 * r + 6] = Us[r]
            Ns[3 * r + 3:3 * r + 6, 3 * r:3 * r + 3] = Us[r].T
    s = scale.ravel()
    exact = (np.linalg.solve(Ns, Y.reshape(3 * R, G) / s[:, None]) / s[:, None]).reshape(R, 3, G)
    exact[bad] = 0.0
    W = np.full((R, 3, G), np.nan)
    first, last = FB._solve_block(Y, 0, G, r0, r1, scale, valid, Finv, Us, Mr, W)
    assert 0 < first < r0 and r1 < last <= bad
    peak = np.abs(exact).max()
    assert np.abs(exact[:first]).max() < 1e-13 * peak and np.abs(exact[last + 1:]).max() < 1e-13 * peak
    np.testing.assert_allclose(W[first:last + 1], exact[first:last + 1], rtol=0, atol=1e-13 * peak)


#: Agreement of float32 samples with the same samples in float64: the fringe's quadratures are made in the samples'
#: dtype (single-precision cos and sin, within 1e-7 of their amplitude) and the weights are read in it.
FRINGE32 = 1e-6


def test_float32_samples_read_between_rows_give_the_float64_result(case):
    obs, ch = case
    samples = ("counts", "tf", "fc", "fs", "dark")
    single = replace(obs, **{n: getattr(obs, n).astype(np.float32) for n in samples})
    # the same samples in float64
    obs = replace(single, **{n: getattr(single, n).astype(np.float64) for n in samples})
    w = np.where(obs.use, 1.0 / np.maximum(obs.counts, 1.0), 0.0)
    cost, sums = KB.reduced_cost(single, ch, w)
    cost64, sums64 = KB.reduced_cost(obs, ch, w)
    assert cost == pytest.approx(cost64, rel=FRINGE32)
    for a, b in zip(sums, sums64, strict=True):
        close(a, b, rtol=FRINGE32)
    got, want = KB.retrieve(single, ch, iterations=2), KB.retrieve(obs, ch, iterations=2)
    assert got["expected"].dtype == np.float32
    for key in ("coef", "expected", "weights"):
        close(got[key], want[key], rtol=FRINGE32)
    assert got["chi2"] == pytest.approx(want["chi2"], rel=FRINGE32)
    # the Fisher information reads the weights in the samples' dtype
    table = M.component_table(NAMES)[:3]
    for a, b in zip(FB.fisher(single, ch, w.astype(np.float32), want["coef"], table),
                    FB.fisher(obs, ch, w.astype(np.float32).astype(np.float64), want["coef"], table), strict=True):
        close(a, b, rtol=FRINGE32)


def test_observations_without_a_reading_are_refused(rng):
    obs = tiny_obs(rng)
    ch = M.channels({}, x=obs.x, n_frames=obs.n_frames)
    with pytest.raises(ValueError, match="own row"):
        KB.retrieve(obs, ch)


def test_the_weights_asked_into_an_array_land_there(case):
    """The between-rows retrieval copies its weights where ``out`` says, the given weights included."""
    obs, ch = case
    w = np.where(obs.use, 1.0 / np.maximum(obs.counts, 1.0), 0.0)
    plain = E.retrieve(obs, ch, weights=w, next_weights=True, keep_expected=False)
    into = w.copy()
    done = E.retrieve(obs, ch, weights=into, next_weights=True, keep_expected=False, out=into)
    assert done["weights"] is into
    np.testing.assert_array_equal(into, plain["weights"])


def test_a_row_held_apart_is_held_alike_in_the_kernels_and_the_model(case):
    """Row 6 of column 6 (:func:`read_only_between`) is held apart, the same in the compiled loops and the numpy
    model; every other row is solved."""
    obs, ch = case
    obs = read_only_between(obs)
    want, got = E.model_retrieve(obs, ch, iterations=1), KB.retrieve(obs, ch, iterations=1)
    np.testing.assert_array_equal(got["valid"], want["valid"])
    assert not want["valid"][6, 6] and want["valid"][5, 6]
    others = np.delete(want["valid"], 6, axis=1)
    assert others.sum() == others.size - 1  # row 3 of column 4 (the case's)
    close(got["coef"], want["coef"])


def test_a_row_held_apart_solves_as_the_least_squares_with_it_fixed_at_zero(rng):
    """Rows 0 and 1 read only between them at one fraction, without a sine (absent on row 0), and row 1 coupled to
    row 2 through transmission-only samples between them: what row 1's c and s add is all in row 0, its complement
    is singular. Held apart, the numpy factors and the kernels' solve the least squares with row 1 fixed at 0, and
    their inverse blocks are that problem's (a dense solve)."""
    from dfxcorr import banded as B

    R, p = 4, 3
    phases = 2 * np.pi * np.arange(9) / 9
    rows = [(0, 0.4, (1.0, np.cos(a), 0.0)) for a in phases]
    rows += [(1, 0.3 + 0.05 * k, (1.0, 0.0, 0.0)) for k in range(6)]
    rows += [(r, 0.5 if r == 2 else 0.0, (1.0, np.cos(a), np.sin(a))) for r in (2, 3) for a in phases]
    A = np.zeros((len(rows), R * p))
    for i, (lo, f, X) in enumerate(rows):
        A[i, lo * p:lo * p + p] += (1 - f) * np.array(X)
        if f:
            A[i, lo * p + p:lo * p + 2 * p] += f * np.array(X)
    b = A @ rng.normal(size=R * p) + 0.01 * rng.normal(size=len(rows))
    N = A.T @ A
    D = np.stack([N[r * p:r * p + p, r * p:r * p + p] for r in range(R)])
    U = np.stack([N[r * p:r * p + p, r * p + p:r * p + 2 * p] if r + 1 < R else np.zeros((p, p)) for r in range(R)])
    assert np.abs(U[1]).max() > 0
    present = np.einsum("rii->ri", D) > 0
    keep = [i for i in range(R * p) if i // p != 1 and present[i // p, i % p]]
    x_want = np.zeros(R * p)
    x_want[keep] = np.linalg.lstsq(A[:, keep], b, rcond=None)[0]
    inv_want = np.zeros((R * p, R * p))
    inv_want[np.ix_(keep, keep)] = np.linalg.inv(A[:, keep].T @ A[:, keep])
    # numpy: the blocks scaled to a unit diagonal (an absent unknown's to the identity), factored
    scale = np.sqrt(np.where(present, np.einsum("rii->ri", D), 1.0))
    Ds = np.where(present[:, :, None] | present[:, None, :], D / (scale[:, :, None] * scale[:, None, :]), 0.0)
    Ds += np.eye(p) * ~present[:, None, :]
    Us = np.zeros_like(U)
    Us[:-1] = U[:-1] / (scale[:-1, :, None] * scale[1:, None, :])
    Finv, Uh, held = B.forward(Ds[:, None], Us[:, None])
    np.testing.assert_array_equal(held[:, 0], [False, True, False, False])
    fac = B.ReadBetween(scale[:, None], ~held, Finv, Uh)
    rhs = (A.T @ b).reshape(R, 1, p, 1)
    np.testing.assert_allclose(fac.solve(rhs).ravel(), x_want, atol=1e-10)
    diag, upper = fac.inverse()
    # the inverse's entries of unknowns present on both rows (an absent one is a placeholder)
    both = present[:, :, None] & np.concatenate([present[1:], np.zeros((1, p), bool)])[:, None, :]
    own = present[:, :, None] & present[:, None, :]
    for r in range(R):
        np.testing.assert_allclose(np.where(own[r], diag[r, 0], 0.0), inv_want[r * p:r * p + p, r * p:r * p + p],
                                   atol=1e-10)
        if r + 1 < R:
            np.testing.assert_allclose(np.where(both[r], upper[r, 0], 0.0),
                                       inv_want[r * p:r * p + p, r * p + p:r * p + 2 * p], atol=1e-10)
    # the kernels: the six stored entries of each symmetric block
    sym = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    D6 = np.stack([D[:, i, j] for i, j in sym], axis=1)[..., None]
    U6 = np.stack([U[:, i, j] for i, j in sym], axis=1)[..., None]
    sc, ok, Fi, Un = np.empty((R, 3)), np.empty(R, bool), np.empty((R, 3, 3)), np.empty((R, 3, 3))
    KB._factor(D6, U6, np.full((R, 1), 100.0), 0, sc, ok, Fi, Un)
    np.testing.assert_array_equal(ok, ~held[:, 0])
    x_got = np.empty((R, 3, 1))
    KB._solve(rhs[:, 0], 0, sc, ok, Fi, Un, x_got)
    np.testing.assert_allclose(x_got.ravel(), x_want, atol=1e-10)
    dg, up = np.empty((R, 3, 3)), np.empty((R, 3, 3))
    KB._inverse(sc, ok, Fi, Un, dg, up)
    np.testing.assert_allclose(dg, diag[:, 0], atol=1e-10)
    np.testing.assert_allclose(up, upper[:, 0], atol=1e-10)
