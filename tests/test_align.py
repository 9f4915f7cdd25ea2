"""Flat-field alignment against analytic references."""
import dataclasses

import numpy as np

from dfxcorr import config as C
from dfxcorr.align import build_observations, interpolate_rows, lit_blocks, realign
from dfxcorr.io import Reference, Scan, SteppingReference
from dfxcorr.reference import fit_reference
from dfxcorr.sim import simulate as S

from conftest import prepare, sim_config


def test_linear_maps_are_reproduced_exactly_including_outer_half_rows():
    A, W = 6, 3
    u = np.arange(A) + 0.5
    maps = 2.0 + 0.7 * u[:, None] + np.arange(W)[None, :]
    query = np.array([0.0, 0.2, 0.5, 2.75, 5.5, 5.99])
    np.testing.assert_allclose(interpolate_rows(maps, query), 2.0 + 0.7 * query[:, None] + np.arange(W), rtol=1e-12)


def test_the_fringe_is_interpolated_as_the_format_says_and_a_wrapped_phase_gives_the_same(rng):
    """tf, vf and the unwrapped phase linearly (spec/scan-format.md), the phase turned by the phase step: a wrapped
    reference phase gives the fringe of the unwrapped one, with a step of 1.3 rad between rows."""
    A, W, H = 10, 2, 30
    u = np.arange(A) + 0.5
    true_phase = 1.3 * u[:, None] * np.ones((1, W))  # crosses several multiples of 2 pi
    t, v = rng.uniform(1e3, 2e3, (A, W)), rng.uniform(0.1, 0.4, (A, W))
    position = np.array([-3.25, 0.4, 7.8, 21.6])
    step = np.array([0.0, 1.0, -2.0, 0.5])
    obs = {}
    for name, phase in (("unwrapped", true_phase), ("wrapped", np.angle(np.exp(1j * true_phase)))):
        ref = Reference(t, v, phase)
        obs[name] = build_observations(Scan(data=np.ones((4, H, W)), position=position, reference=ref,
                                            phase_step=step), ref, min_frames=1)
    o = obs["wrapped"]
    f = o.row + 0.5 - position[o.frame] - 0.5
    k0 = np.clip(np.floor(f).astype(int), 0, A - 2)
    a = (f - k0)[:, None]
    lerp = lambda m: (1 - a) * m[k0] + a * m[k0 + 1]  # noqa: E731
    linear = lerp(true_phase) + step[o.frame][:, None]
    np.testing.assert_allclose(o.tf, lerp(t), rtol=1e-12)
    np.testing.assert_allclose(o.vf, lerp(v), rtol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (o.phif - linear))), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (o.phif - obs["unwrapped"].phif))), 0.0, atol=1e-12)


def test_lit_blocks_follow_the_geometry():
    row, frame, u = lit_blocks(np.array([-1.5, 0.0, 2.25]), 3, 5)
    for r, j, uu in zip(row, frame, u, strict=True):
        assert 0 <= uu < 3
        assert uu == r + 0.5 - [-1.5, 0.0, 2.25][j]
    assert list(np.bincount(row, minlength=5)) == [2, 1, 2, 1, 1]  # row 1 at u = 3.0 is just outside [0, 3)
    assert np.all(np.diff(row) >= 0)


def test_reference_maps_from_a_noise_free_stepping_series(rng):
    A, W, S = 4, 5, 7
    t = rng.uniform(1e3, 2e3, (A, W))
    v = rng.uniform(0.1, 0.4, (A, W))
    phi = rng.uniform(-3, 3, (A, W))
    steps = 2 * np.pi * np.arange(S) / S + 0.1
    data = t * (1 + v * np.cos(phi + steps[:, None, None]))
    ref = fit_reference(SteppingReference(data=data, phase_step=steps), effects=()).reference
    np.testing.assert_allclose(ref.transmission, t, rtol=1e-7)
    np.testing.assert_allclose(ref.visibility, v, rtol=1e-6)
    np.testing.assert_allclose(np.angle(np.exp(1j * (ref.phase - phi))), 0, atol=1e-6)


def test_compiled_interpolation_is_the_formula():
    """The kernel gives (1 - a) m[k0] + a m[k0 + 1] exactly, in float64 and rounded once to float32."""
    rng = np.random.default_rng(7)
    maps = rng.normal(size=(9, 13))
    u = rng.uniform(0.0, 9.0, 500)
    f = u - 0.5
    k0 = np.clip(np.floor(f).astype(np.int64), 0, maps.shape[0] - 2)
    a = (f - k0)[:, None]
    oracle = (1.0 - a) * maps[k0] + a * maps[k0 + 1]
    np.testing.assert_array_equal(interpolate_rows(maps, u), oracle)
    np.testing.assert_array_equal(interpolate_rows(maps, u, dtype=np.float32), oracle.astype(np.float32))
    np.testing.assert_array_equal(interpolate_rows(maps[:1], u), np.repeat(maps[:1], u.size, axis=0))
    cols = np.array([11, 0, 4, 4])
    np.testing.assert_array_equal(interpolate_rows(maps, u, columns=cols), oracle[:, cols])
    np.testing.assert_array_equal(interpolate_rows(maps[:1], u, columns=cols),
                                  np.repeat(maps[:1, cols], u.size, axis=0))


def _same_observations(a, b) -> bool:
    """Every input field of two Observations equal (arrays by value, float32 bit for bit)."""
    for f in dataclasses.fields(a):
        if not f.init or not f.compare:
            continue
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if x is None or y is None or x.dtype != y.dtype or not np.array_equal(x, y):
                return False
        elif x != y:
            return False
    return True


def test_realigning_with_the_base_store_shares_only_what_the_correction_left_alone():
    """An offset-only correction (scatter's) keeps the counts and the flat field's rows: the shortcut gives the
    observations a full read gives; a shift of the flat field's rows is read in full, base or not."""
    scan, _ = S.simulate(sim_config())
    prep = prepare(scan, C.defaults())
    store, ref = prep.store, prep.reference
    like = store.observations(ref, columns=np.arange(10, 40, 3), rows=(20, 50), dtype=np.float32)
    rng = np.random.default_rng(4)
    offset = dataclasses.replace(store, offset=rng.uniform(0, 50, store.counts.shape).astype(np.float32))
    shared = realign(offset, ref, like, 0.0, base=store)
    assert shared.counts is like.counts and shared.offset is not None
    assert _same_observations(shared, realign(offset, ref, like, 0.0))
    moved = realign(store, ref, like, 0.3, base=store)
    assert _same_observations(moved, realign(store, ref, like, 0.3))
    assert not np.array_equal(moved.phif, like.phif)
