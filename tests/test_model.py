"""Identities and derivatives of the forward model."""
from dataclasses import replace

import numpy as np
import pytest

from dfxcorr import kernels as K
from dfxcorr import model as M
from dfxcorr.catalogue import PAPER_MODEL, effect, neutral_params
from dfxcorr.noise import noise_weights

from conftest import ALL, modelled_counts, random_images, random_params, tiny_obs


def test_neutral_parameters_leave_the_model_unchanged(rng):
    obs = tiny_obs(rng)
    plain = M.design(obs, {})
    neutral = M.design(obs, neutral_params(ALL, obs.n_frames))
    for a in ("A", "Bc", "Bs", "offset"):
        np.testing.assert_allclose(getattr(neutral, a), getattr(plain, a), rtol=1e-14, atol=1e-12)


@pytest.mark.parametrize("names", [PAPER_MODEL, ALL], ids=["paper", "all"])
def test_closed_form_images_reproduce_noise_free_data(rng, names):
    obs = tiny_obs(rng)
    params = random_params(rng, obs.n_frames, names)
    dsg = M.design(obs, params)
    truth = random_images(rng, obs)
    obs = replace(obs, counts=M.expected(obs, dsg, truth))
    est = M.solve_images(obs, dsg, np.ones_like(obs.counts))
    np.testing.assert_allclose(est.t, truth.t, rtol=1e-9)
    np.testing.assert_allclose(est.v, truth.v, rtol=1e-9)
    np.testing.assert_allclose(est.phi, truth.phi, atol=1e-9)


def test_harmonic_follows_the_sample(rng):
    """spec/diagnosis.md version 2: v cos psi becomes v (cos psi + a2 cos(2 psi + beta)), with the sample's phi in
    psi and its v in the product of the visibilities."""
    obs = tiny_obs(rng)
    params = random_params(rng, obs.n_frames, ALL)
    dsg = M.design(obs, params)
    truth = random_images(rng, obs)
    t, v, phi = (a[obs.pixel] for a in (truth.t, truth.v, truth.phi))
    a2, beta = np.hypot(*params["harmonic"]), np.arctan2(params["harmonic"][1], params["harmonic"][0])
    psi = M.fringe_phase(obs, dsg.channels) + phi
    direct = dsg.dose * obs.tf * t * (1 + obs.vf * dsg.vis * v * (np.cos(psi) + a2 * np.cos(2 * psi + beta)))
    np.testing.assert_allclose(M.expected(obs, dsg, truth), direct + dsg.offset, rtol=1e-12)


def test_image_columns_are_the_derivatives_of_the_model(rng):
    """dIbar/dc and dIbar/ds with the harmonic, against finite differences, and Euler's identity that makes a
    Gauss-Newton step a closed-form solve."""
    obs = tiny_obs(rng)
    params = random_params(rng, obs.n_frames, ALL)
    dsg = M.design(obs, params)
    truth = random_images(rng, obs)
    c = truth.coef[obs.pixel]
    columns = M.image_columns(dsg, c[..., 1], c[..., 2])
    for a, col in zip((1, 2), columns, strict=True):
        h = 1e-6
        up, down = truth.coef.copy(), truth.coef.copy()
        up[..., a] += h
        down[..., a] -= h
        fd = ((M.expected(obs, dsg, M.Images(up, truth.valid)) - M.expected(obs, dsg, M.Images(down, truth.valid)))
              / (2 * h))
        np.testing.assert_allclose(col, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
    modulated = M.expected(obs, dsg, truth) - dsg.offset - c[..., 0] * dsg.A
    np.testing.assert_allclose(c[..., 1] * columns[0] + c[..., 2] * columns[1], modulated, rtol=1e-9,
                               atol=1e-12 * np.abs(modulated).max())


def test_harmonic_steps_reach_the_converged_images(rng, monkeypatch):
    """kernels.HARMONIC_STEPS Gauss-Newton steps against a converged solve, at twice the simulator's realistic
    amplitude: every pixel within 1 % of its standard error, most at rounding (the slowest are pixels whose
    modulation is hardly above noise, where the direction of (c, s) is poorly determined)."""
    obs = tiny_obs(rng, J=40, H=20, W=30, A=8)
    params = random_params(rng, obs.n_frames, PAPER_MODEL)
    params["harmonic"] = 0.06 * np.array([np.cos(0.5), np.sin(0.5)])
    obs = replace(obs, counts=modelled_counts(rng, obs, params))
    w = noise_weights(obs, obs.counts)
    dsg = M.design(obs, params)
    images = M.solve_images(obs, dsg, w, keep_inverse=True)
    first = np.abs(M.solve_pixels(obs, [dsg.A, dsg.Bc, dsg.Bs], obs.counts - dsg.offset, w)[0] - images.coef)
    monkeypatch.setattr(K, "HARMONIC_STEPS", 40)
    converged = M.solve_images(obs, dsg, w)
    se = np.sqrt(np.einsum("...ii->...i", images.inverse))[images.valid]
    d = np.abs(images.coef - converged.coef)[images.valid] / se
    assert np.median(first[images.valid] / se) > 0.01  # without the steps the harmonic would matter
    assert d.max() < 0.01 and np.median(d) < 1e-6, (d.max(), np.median(d))


def test_zero_harmonic_is_the_model_without_it(rng):
    obs = tiny_obs(rng)
    params = random_params(rng, obs.n_frames, PAPER_MODEL)
    w = noise_weights(obs, obs.counts)
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    zero = M.channels({**params, "harmonic": np.zeros(2)}, x=obs.x, n_frames=obs.n_frames)
    for key in ("coef", "expected", "weights"):
        np.testing.assert_array_equal(K.retrieve(obs, zero, iterations=2)[key], K.retrieve(obs, ch, iterations=2)[key])
    cost, grads = K.reduced_cost(obs, ch, w)
    cost0, grads0 = K.reduced_cost(obs, zero, w)
    assert cost0 == cost
    for a, b in zip(grads0[:4], grads[:4], strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", ALL)
def test_sample_derivatives_match_finite_differences(rng, name):
    obs = tiny_obs(rng)
    params = random_params(rng, obs.n_frames, ALL)
    images = M.solve_images(obs, M.design(obs, params), np.ones_like(obs.counts))
    fields = M.sample_derivatives(obs, M.design(obs, params), images, name)
    e = effect(name)
    for m, F in enumerate(fields):
        h = 1e-6 * max(1.0, abs(e.neutral))
        up, down = {k: v.copy() for k, v in params.items()}, {k: v.copy() for k, v in params.items()}
        if e.per_frame:
            up[name][:, m] += h
            down[name][:, m] -= h
        else:
            up[name][m] += h
            down[name][m] -= h
        fd = (M.expected(obs, M.design(obs, up), images) - M.expected(obs, M.design(obs, down), images)) / (2 * h)
        np.testing.assert_allclose(F, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


@pytest.mark.parametrize("names", [PAPER_MODEL, ALL])
def test_reduced_cost_gradient_matches_finite_differences(rng, names, monkeypatch):
    """Envelope theorem (paper eq. 25): the gradient at fixed images is the gradient of the reduced cost.

    With the harmonic the images are Gauss-Newton iterates: the theorem holds at their convergence (four
    samples per pixel here, hardly more than the three unknowns, converge slowest).
    """
    monkeypatch.setattr(K, "HARMONIC_STEPS", 40)
    obs = tiny_obs(rng)
    params = random_params(rng, obs.n_frames, names)
    w = 1.0 / np.maximum(obs.counts, 1.0)

    def reduced(p):
        dsg = M.design(obs, p)
        return float(np.sum(w * (obs.counts - M.expected(obs, dsg, M.solve_images(obs, dsg, w))) ** 2))

    dsg = M.design(obs, params)
    images = M.solve_images(obs, dsg, w)
    grad = M.gradient(obs, dsg, images, w, obs.counts - M.expected(obs, dsg, images), names)
    for name in names:
        e = effect(name)
        idx = [(3, 0), (7, e.size - 1)] if e.per_frame else [(i,) for i in range(e.size)]
        for ix in idx:
            h = 1e-6 * (100.0 if name == "background" else 1.0)
            up, down = {k: v.copy() for k, v in params.items()}, {k: v.copy() for k, v in params.items()}
            up[name][ix] += h
            down[name][ix] -= h
            fd = (reduced(up) - reduced(down)) / (2 * h)
            assert grad[name][ix] == pytest.approx(fd, rel=2e-5, abs=1e-6 * abs(fd) + 1e-8)


def test_gauge_transformations_leave_the_prediction_unchanged(rng):
    """Paper eq. 22: phase offset/tilt shifts and a visibility scale are taken up by the images."""
    obs = tiny_obs(rng)
    params = random_params(rng, obs.n_frames, PAPER_MODEL)
    w = np.ones_like(obs.counts)

    def prediction(p):
        dsg = M.design(obs, p)
        return M.expected(obs, dsg, M.solve_images(obs, dsg, w))

    base = prediction(params)
    moved = {k: v.copy() for k, v in params.items()}
    moved["phase_offset"] += 0.3
    moved["tilt"] -= 0.2
    moved["visibility_loss"] *= 0.8
    np.testing.assert_allclose(prediction(moved), base, rtol=1e-10)


def test_profiled_fisher_is_smaller_than_plain_and_positive(rng):
    obs = tiny_obs(rng)
    params = random_params(rng, obs.n_frames, PAPER_MODEL)
    w = 1.0 / np.maximum(obs.counts, 1.0)
    dsg = M.design(obs, params)
    images = M.solve_images(obs, dsg, w, keep_inverse=True)
    prof, index = M.fisher_matrix(obs, dsg, images, w, PAPER_MODEL)
    plain, _ = M.fisher_matrix(obs, dsg, images, w, PAPER_MODEL, profiled=False)
    lit = np.bincount(obs.frame, minlength=obs.n_frames) > 0
    assert np.all(np.diag(prof)[lit[[j for _, j, _ in index]]] > 0)
    # profiling removes information, never adds it: plain - profiled is positive semi-definite
    assert np.linalg.eigvalsh(plain - prof).min() > -1e-9 * np.abs(plain).max()
    # the gauge directions of eq. 22 carry no information once the images are free
    shift = np.array([1.0 if n == "phase_offset" else 0.0 for n, _, _ in index])
    assert shift @ prof @ shift < 1e-8 * (shift @ plain @ shift)
    lev = M.leverage(obs, dsg, images, w)
    assert np.all(prof.diagonal() <= plain.diagonal() + 1e-9)
    # three unknowns per pixel: the leverages of a pixel sum to 3
    np.testing.assert_allclose(obs.segment_sum(lev)[images.valid], 3.0, rtol=1e-8)


def test_unknown_effect_is_refused():
    with pytest.raises(ValueError, match="unknown effect 'tilted'"):
        effect("tilted")


def test_wrap_angle_is_the_angle_of_the_phasor():
    a = np.random.default_rng(11).uniform(-40.0, 40.0, 10000)
    w = M.wrap_angle(a)
    assert np.all((w >= -np.pi) & (w < np.pi))
    # the same angle: whole turns apart, and the phasor's own angle away from the cut at pi
    np.testing.assert_allclose((a - w) / (2 * np.pi), np.round((a - w) / (2 * np.pi)), atol=1e-12)
    inside = np.abs(np.abs(w) - np.pi) > 1e-9
    np.testing.assert_allclose(w[inside], np.angle(np.exp(1j * a))[inside], atol=1e-12)
