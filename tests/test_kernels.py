"""The compiled kernels against the numpy definition of the model (dfxcorr.model)."""
from dataclasses import replace

import numpy as np
import pytest

from dfxcorr import fisher_pixels as FP
from dfxcorr import kernels as K
from dfxcorr import model as M
from dfxcorr.catalogue import PAPER_MODEL, effect
from dfxcorr.noise import noise_weights, pearson
from dfxcorr.observations import Observations

from conftest import ALL, random_params, tiny_obs

#: Effect sets: each mean effect with the paper's model, and all together.
SETS = [tuple(dict.fromkeys((*PAPER_MODEL, n))) for n in ALL] + [tuple(ALL)]


def prepared(rng, *, masked=False, dtype=np.float64):
    """Observations with optional masked samples, a pixel without fringe and a pixel without used samples."""
    obs = tiny_obs(rng)
    if masked:
        use, fringe = rng.uniform(size=obs.use.shape) > 0.2, np.ones(obs.use.shape, bool)
        fringe[obs.starts[1]:obs.starts[2], 2] = False  # no fringe: only t is an unknown there
        use[obs.starts[2]:obs.starts[3], 3] = False  # nothing to solve for
        obs = replace(obs.keep_fringe(fringe), use=use)
    return replace(obs, **{name: getattr(obs, name).astype(dtype) for name in ("counts", "tf", "fc", "fs", "dark")})


def as_float64(obs):
    """The same samples in float64 (the oracle computes in float64)."""
    return Observations(*(np.asarray(a, dtype=np.float64) for a in (obs.counts, obs.tf, obs.fc, obs.fs,
                                                                     obs.dark)), obs.use, obs.row, obs.frame,
                        obs.columns, obs.shape, obs.gain, obs.electronic)


#: Agreement of float32 samples with the same samples in float64: the fringe's quadratures are held in the samples'
#: dtype (Observations.fc, fs; single precision, within 1e-7 of their amplitude), which moves the cost
#: and the images by about 1e-8 of their range.
FRINGE32 = 1e-6


def close(actual, desired, rtol=1e-9):
    """Agreement up to rounding: relative to the largest entry (sums with cancellation)."""
    desired = np.asarray(desired, dtype=np.float64)
    np.testing.assert_allclose(actual, desired, rtol=rtol, atol=rtol * max(np.abs(desired).max(), 1e-300))


def kernel_cost(obs, params, w, names, *, phase=None, square=False):
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    cost, g = K.reduced_cost(obs, ch, w, phase=phase, square=square)
    return cost, M.channel_adjoint(names, M.Channels(*g), x=obs.x, square=square)


@pytest.mark.parametrize("names", SETS, ids="+".join)
@pytest.mark.parametrize("masked", [False, True], ids=["all", "masked"])
def test_reduced_cost_and_gradient_match_the_model(rng, names, masked):
    obs = prepared(rng, masked=masked)
    params = random_params(rng, obs.n_frames, names)
    w = noise_weights(obs, obs.counts)
    for phase in (None, 0.7):
        dsg = M.design(obs, params)
        images = M.solve_images(obs, dsg, w, phase=phase)
        resid = obs.counts - M.expected(obs, dsg, images)
        cost, grad = kernel_cost(obs, params, w, names, phase=phase)
        assert cost == pytest.approx(float(np.sum(w * resid ** 2)), rel=1e-10)
        oracle = M.gradient(obs, dsg, images, w, resid, names)
        for n in names:
            close(grad[n], oracle[n])
        _, diag = kernel_cost(obs, params, w, names, phase=phase, square=True)
        for n in names:
            fields = M.sample_derivatives(obs, dsg, images, n)
            close(diag[n], np.stack([M.reduce_component(obs, n, w * F ** 2) for F in fields], axis=-1))


def test_float32_samples_give_the_float64_result(rng):
    obs = prepared(rng, masked=True, dtype=np.float32)
    obs = replace(obs, counts=np.rint(obs.counts).astype(np.uint16))
    ref = as_float64(obs)
    params = random_params(rng, obs.n_frames, ALL)
    w = noise_weights(ref, ref.counts).astype(np.float32)
    cost, grad = kernel_cost(obs, params, w, ALL)
    cost64, grad64 = kernel_cost(ref, params, w.astype(np.float64), ALL)
    assert cost == pytest.approx(cost64, rel=FRINGE32)
    for n in ALL:
        close(grad[n], grad64[n], rtol=FRINGE32)
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    close(K.retrieve(obs, ch, iterations=2)["coef"], K.retrieve(ref, ch, iterations=2)["coef"], rtol=FRINGE32)
    # the Fisher information reads the weights in the samples' dtype too
    images = K.retrieve(ref, ch, weights=w.astype(np.float64), keep_inverse=True)
    table = M.component_table(list(ALL))[:3]
    for got, want in zip(FP.fisher(obs, ch, w, images["coef"], images["inverse"], table),
                         FP.fisher(ref, ch, w.astype(np.float64), images["coef"], images["inverse"], table),
                         strict=True):
        close(got, want, rtol=FRINGE32)


@pytest.mark.parametrize("masked", [False, True], ids=["all", "masked"])
@pytest.mark.parametrize("iterations", [1, 2])
def test_retrieval_matches_the_model(rng, masked, iterations):
    obs = prepared(rng, masked=masked)
    obs = replace(obs, electronic=3.0, gain=1.5)
    params = random_params(rng, obs.n_frames, ALL)
    dsg = M.design(obs, params)
    w = noise_weights(obs, obs.counts)
    for it in range(iterations):
        images = M.solve_images(obs, dsg, w, keep_inverse=True)
        ibar = M.expected(obs, dsg, images)
        if it + 1 < iterations:
            w = noise_weights(obs, ibar)
    out = K.retrieve(obs, dsg.channels, iterations=iterations, keep_inverse=True)
    assert np.array_equal(out["valid"], images.valid)
    assert masked == (not images.valid.all())
    close(out["coef"], images.coef)
    close(out["inverse"], images.inverse)
    close(out["expected"], ibar)
    close(out["weights"], w, rtol=1e-12 if iterations == 1 else 1e-9)
    sel = images.valid[obs.pixel] & obs.use
    assert out["samples"] == sel.sum()
    assert out["chi2"] == pytest.approx(float(pearson(obs, ibar)[sel].sum()), rel=1e-9)
    start = K.retrieve(obs, dsg.channels, weights=w)
    close(start["coef"], M.solve_images(obs, dsg, w).coef)
    # the weights of a solve's model without the next solve: those that iterations + 1 would solve with
    ahead = K.retrieve(obs, dsg.channels, iterations=iterations, next_weights=True)["weights"]
    assert np.array_equal(ahead, K.retrieve(obs, dsg.channels, iterations=iterations + 1)["weights"])


@pytest.mark.parametrize("masked", [False, True], ids=["all", "masked"])
def test_expected_counts_at_given_images_match_the_model(rng, masked):
    obs = prepared(rng, masked=masked)
    params = random_params(rng, obs.n_frames, ALL)
    dsg = M.design(obs, params)
    images = M.solve_images(obs, dsg, noise_weights(obs, obs.counts))
    ibar = M.expected(obs, dsg, images)
    close(K.expected(obs, dsg.channels, images.coef), ibar)
    # the retrieval's own expected counts, to the last bit: one expression in both kernels
    out = K.retrieve(obs, dsg.channels)
    assert np.array_equal(K.expected(obs, dsg.channels, out["coef"]), out["expected"])


def correction_oracle(obs, dsg, images, w, names):
    """sum over pixels of Y^T N^-1 Y, Y = X^T W D (the profiled part of model.fisher_matrix), row by row."""
    J = obs.n_frames
    per_frame = [F for n in names if effect(n).per_frame for F in M.sample_derivatives(obs, dsg, images, n)]
    glob = [F for n in names if not effect(n).per_frame for F in M.sample_derivatives(obs, dsg, images, n)]
    Pf, Pg = len(per_frame), len(glob)
    D = np.stack(per_frame + glob, axis=-1)
    c = images.coef[obs.pixel]
    X = np.stack([dsg.A, *M.image_columns(dsg, c[..., 1], c[..., 2])], axis=-1)
    out = np.zeros((J * Pf + Pg, J * Pf + Pg))
    bounds = np.append(obs.starts, obs.frame.size)
    for r in range(obs.rows.size):
        for c in range(obs.columns.size):
            blocks = np.arange(bounds[r], bounds[r + 1])
            idx = np.concatenate([(obs.frame[blocks, None] * Pf + np.arange(Pf)).ravel(), J * Pf + np.arange(Pg)])
            Dp = np.zeros((blocks.size, idx.size))  # the pixel's samples x its parameters
            for b in range(blocks.size):
                Dp[b, b * Pf:(b + 1) * Pf] = D[blocks[b], c, :Pf]
            Dp[:, blocks.size * Pf:] = D[blocks, c, Pf:]
            Y = X[blocks, c].T @ (w[blocks, c, None] * Dp)
            out[np.ix_(idx, idx)] += Y.T @ images.inverse[r, c] @ Y
    return out


@pytest.mark.parametrize("names", [PAPER_MODEL, tuple(ALL)], ids="+".join)
def test_fisher_information_matches_the_model(rng, names):
    obs = prepared(rng, masked=True)
    params = random_params(rng, obs.n_frames, names)
    w = noise_weights(obs, obs.counts)
    dsg = M.design(obs, params)
    images = M.solve_images(obs, dsg, w, keep_inverse=True)
    plain, corr = FP.fisher(obs, dsg.channels, w, images.coef, images.inverse, M.component_table(names)[:3])
    close(plain, M.fisher_matrix(obs, dsg, images, w, names, profiled=False)[0])
    close(corr, correction_oracle(obs, dsg, images, w, names))


def test_channel_adjoint_is_the_transpose_of_the_channel_map(rng):
    obs = tiny_obs(rng)
    x, J = obs.x, obs.n_frames
    params = random_params(rng, J, ALL)
    step = random_params(rng, J, ALL)
    grad = M.Channels(rng.normal(size=(J, x.size)), rng.normal(size=(J, x.size)), rng.normal(size=J),
                      rng.normal(size=3), rng.normal(size=2))
    base = M.channels(params, x=x, n_frames=J)
    moved = M.channels({n: params[n] + step[n] for n in ALL}, x=x, n_frames=J)
    lhs = sum(np.sum(getattr(grad, f) * (getattr(moved, f) - getattr(base, f)))
              for f in ("phase", "vis", "dose", "background", "harmonic"))
    adj = M.channel_adjoint(ALL, grad, x=x)
    assert lhs == pytest.approx(sum(np.sum(adj[n] * step[n]) for n in ALL), rel=1e-12)


def test_threads_follow_the_environment(monkeypatch):
    import numba
    monkeypatch.delenv("SLURM_CPUS_PER_TASK", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert K.set_threads() == 1 == numba.get_num_threads()
    monkeypatch.setenv("SLURM_CPUS_PER_TASK", "64")
    assert K.set_threads() == numba.config.NUMBA_NUM_THREADS
    monkeypatch.delenv("SLURM_CPUS_PER_TASK")
    monkeypatch.delenv("OMP_NUM_THREADS")
    K.set_threads()


def test_blas_runs_on_one_thread_beside_the_kernels():
    """Idle OpenBLAS threads spin on the cores numba's threads need: set_threads holds BLAS to one."""
    from threadpoolctl import threadpool_info

    np.linalg.cholesky(np.eye(300))  # BLAS loaded and used
    K.set_threads()
    blas = [p for p in threadpool_info() if p["user_api"] == "blas"]
    assert blas and all(p["num_threads"] == 1 for p in blas)


def test_only_the_requested_channels_are_summed(rng):
    obs = prepared(rng)
    params = random_params(rng, obs.n_frames, ALL)
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    w = noise_weights(obs, obs.counts)
    cost, full = K.reduced_cost(obs, ch, w)
    part_cost, part = K.reduced_cost(obs, ch, w, channels=("phase", "background"))
    assert part_cost == cost
    for name, a, b in zip(K.CHANNEL_IDS, full, part, strict=True):
        np.testing.assert_array_equal(b, a if name in ("phase", "background") else 0.0)


def test_frame_grid_cost_is_the_direct_cost(rng):
    """The trigonometric-polynomial grid of fit.rescue_frames against the model evaluated at each grid point."""
    from dfxcorr.frames import frame_grid_cost
    obs = prepared(rng, masked=True)
    params = random_params(rng, obs.n_frames, ALL)
    w = noise_weights(obs, obs.counts)
    dsg = M.design(obs, params)
    images = M.solve_images(obs, dsg, w)
    j = obs.frame[obs.starts[2]]
    blocks = np.flatnonzero(obs.frame == j)
    offsets, tilts = np.linspace(-np.pi, np.pi, 5, endpoint=False), np.array([-0.3, 0.1])
    held = params["phase_offset"][j, 0] + params["tilt"][j, 0] * obs.x
    grid = frame_grid_cost(obs, dsg.channels, images.coef, w, blocks, offsets, tilts, held=held)
    for a, g0 in enumerate(offsets):
        for b, g1 in enumerate(tilts):
            trial = {k: v.copy() for k, v in params.items()}
            trial["phase_offset"][j, 0], trial["tilt"][j, 0] = g0, g1
            r = (obs.counts - M.expected(obs, M.design(obs, trial), images))[blocks]
            assert grid[a, b] == pytest.approx(float(np.sum(w[blocks] * r ** 2)), rel=1e-10)


@pytest.mark.parametrize("given", [False, True])
def test_the_weights_written_over_the_given_ones_are_those_of_a_fresh_array(rng, given):
    """A reweighting writes the next weights where the solve read its own (``out=weights``): the same values and
    images as into a new array; a wrong output array is refused."""
    obs = prepared(rng, masked=True, dtype=np.float32)
    ch = M.channels(random_params(rng, obs.n_frames, PAPER_MODEL), x=obs.x, n_frames=obs.n_frames)
    w = K.retrieve(obs, ch, next_weights=True, keep_expected=False)["weights"] if given else None
    fresh = K.retrieve(obs, ch, weights=w, iterations=2, next_weights=True, keep_expected=False)
    into = np.empty_like(fresh["weights"]) if w is None else w.copy()
    done = K.retrieve(obs, ch, weights=None if w is None else into, iterations=2, next_weights=True,
                      keep_expected=False, out=into)
    assert done["weights"] is into
    np.testing.assert_array_equal(into, fresh["weights"])
    np.testing.assert_array_equal(done["coef"], fresh["coef"])
    with pytest.raises(ValueError, match="C-ordered"):
        K.retrieve(obs, ch, next_weights=True, out=np.empty_like(into, dtype=np.float64))
