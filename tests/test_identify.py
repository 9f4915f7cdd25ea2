"""Identifiability: the information-free directions that :mod:`dfxcorr.identify` counts, on small synthetic
acquisitions whose null directions are known in closed form (paper Sec. II-F)."""
import numpy as np
import pytest

from dfxcorr import identify as I
from dfxcorr import kernels as K
from dfxcorr import model as M
from dfxcorr.align import build_observations
from dfxcorr.catalogue import PAPER_MODEL, effect, neutral_params
from dfxcorr.fit import initial_weights
from dfxcorr.io import Reference, Scan

from conftest import tiny_obs


def stepping_obs(rng, *, steps=5, H=4, W=6):
    """A phase-stepping recording: every frame lights every row, equally spaced steps over one period."""
    ref = Reference(rng.uniform(500, 1500, (H, W)), rng.uniform(0.2, 0.5, (H, W)), rng.uniform(-3, 3, (H, W)))
    data = rng.poisson(800, (steps, H, W)).astype(np.float64)
    scan = Scan(data=data, position=np.zeros(steps), reference=ref,
                phase_step=2 * np.pi * np.arange(steps) / steps)
    assert scan.is_stepping
    return build_observations(scan, ref, min_frames=1)


def uniform_scan_obs(rng, *, J=12, H=6, W=7, A=4):
    """A scan over a flat field of uniform transmission and visibility (its phase varies along the scan, so
    every pixel's images are determined)."""
    ref = Reference(np.full((A, W), 1000.0), np.full((A, W), 0.3), np.cumsum(rng.uniform(0.5, 1.5, (A, W)), axis=0))
    position = -A + 1.0 + np.arange(J) * (H + A - 2) / (J - 1)
    data = rng.poisson(800, (J, H, W)).astype(np.float64)
    return build_observations(Scan(data=data, position=position, reference=ref), ref)


def information(obs, names):
    """:func:`dfxcorr.identify.information` at the neutral model and images retrieved with the initial weights."""
    weights = initial_weights(obs, {})
    ch = M.channels(neutral_params(names, obs.n_frames), x=obs.x, n_frames=obs.n_frames)
    solved = K.retrieve(obs, ch, weights=weights, keep_inverse=True)
    return I.information(obs, ch, M.Images(solved["coef"], solved["valid"], solved["inverse"]), weights, names)


@pytest.mark.parametrize("steps", [5, 8, 11])
def test_visibility_loss_in_phase_stepping_has_four_excess_null_directions(rng, steps):
    """Paper eqs. 39-44: with per-step phase and visibility, I = t + c^s_j c_i - s^s_j s_i is bilinear, so any
    invertible 2 x 2 map of the per-step (c^s, s^s) undone on the pixels' (c, s) (4 directions) and a shift of
    either taken up by t (eqs. 42-43: 2 more) fit as well: 6 null directions, of which a common phase shift and a
    common visibility scale are the gauge, 4 in excess, whatever the number of steps."""
    inf = information(stepping_obs(rng, steps=steps), ["phase_offset", "visibility_loss"])
    given_phase = I.conditional(inf, "visibility_loss", ("phase_offset",))
    assert given_phase.verdict == I.Identifiability("visibility_loss", False, 4)
    # the per-step visibilities keep steps - 1 (gauge) - 4 (excess) directions of information
    assert given_phase.dof == steps - 5
    joint = I.conditional(inf, ("phase_offset", "visibility_loss"), ())
    assert joint.verdict == I.Identifiability("phase_offset+visibility_loss", False, 4)
    assert joint.dof == 2 * steps - 6
    # the per-step phases alone are determined up to their gauge
    assert I.conditional(inf, "phase_offset", ()).verdict == I.Identifiability("phase_offset", True, 0)


def test_dose_and_phase_offset_share_two_directions_in_five_step_stepping(rng):
    """Each alone is identifiable with 4 dof (5 steps, 1 gauge direction); together they keep 6, not 8: the
    per-step vector d_j (1, cos psi_j, sin psi_j) has two directions that the images take up (two extra)."""
    inf = information(stepping_obs(rng, steps=5), ["dose", "phase_offset"])
    for name in ("dose", "phase_offset"):
        alone = I.conditional(inf, name, ())
        assert alone.verdict == I.Identifiability(name, True, 0) and alone.dof == 4
    joint = I.conditional(inf, ("dose", "phase_offset"), ())
    assert joint.dof == 4 + 4 - 2
    assert joint.verdict == I.Identifiability("dose+phase_offset", False, 2)
    assert I.conditional(inf, "dose", ("phase_offset",)).verdict == I.Identifiability("dose", False, 2)


def test_background_over_a_uniform_flat_field_is_taken_up_by_the_transmission(rng):
    """With t^f the same in every frame a pixel sees, b0 + b1 x + b2 y is a per-pixel constant that t absorbs:
    all 3 components are null (no gauge): in a scan of a uniform flat field and in phase stepping."""
    for obs in (uniform_scan_obs(rng), stepping_obs(rng)):
        inf = information(obs, ["phase_offset", "background"])
        for base in ((), ("phase_offset",)):
            cond = I.conditional(inf, "background", base)
            assert cond.verdict == I.Identifiability("background", False, 3) and cond.dof == 0
    # over a flat field whose transmission varies along the scan, the frames tell the background apart
    inf = information(tiny_obs(rng), ["background"])
    assert I.conditional(inf, "background", ()).verdict == I.Identifiability("background", True, 0)


def test_the_papers_model_in_a_scan_is_identifiable(rng):
    obs = tiny_obs(rng)
    verdicts = I.select(obs, PAPER_MODEL)
    assert verdicts == [I.Identifiability(n, True, 0) for n in PAPER_MODEL]
    # and each of its effects given the other two keeps every direction beyond its gauge
    inf = information(obs, list(PAPER_MODEL))
    live = int(inf.live.sum()) // len(PAPER_MODEL)
    for name in PAPER_MODEL:
        cond = I.conditional(inf, name, [n for n in PAPER_MODEL if n != name])
        assert cond.dof == live - effect(name).gauge_dims


def test_select_drops_what_the_chosen_effects_leave_undetermined(rng):
    """Each effect is judged given the identifiable ones before it: in stepping the visibility loss after the
    per-step phase is dropped, and the dose after it is judged without it."""
    obs = stepping_obs(rng, steps=8)
    verdicts = I.select(obs, ["phase_offset", "visibility_loss", "dose"])
    assert verdicts == [I.Identifiability("phase_offset", True, 0), I.Identifiability("visibility_loss", False, 4),
                        I.Identifiability("dose", False, 2)]
    assert I.select(obs, []) == []


def test_pinv_rank_of_known_matrices(rng):
    inverse, rank = I.pinv_rank(np.diag([4.0, 0.5, 0.0]))
    np.testing.assert_allclose(inverse, np.diag([0.25, 2.0, 0.0]))
    assert rank == 2
    # B B^T of a 6 x 2 B: rank 2, the Moore-Penrose inverse whatever the scale of each component
    B = rng.normal(size=(6, 2))
    scale = np.diag(10.0 ** np.arange(-3, 3))
    a = scale @ B @ B.T @ scale
    inverse, rank = I.pinv_rank(a)
    assert rank == 2
    np.testing.assert_allclose(a @ inverse @ a, a, rtol=1e-8, atol=1e-12 * np.abs(a).max())
    np.testing.assert_allclose(inverse @ a @ inverse, inverse, rtol=1e-8, atol=1e-12 * np.abs(inverse).max())
    # a full-rank matrix: the inverse
    full = B.T @ B + np.eye(2)
    inverse, rank = I.pinv_rank(full)
    assert rank == 2
    np.testing.assert_allclose(inverse, np.linalg.inv(full), rtol=1e-12)
    # a component left with a rounding's worth of its information before profiling counts as empty
    inverse, rank = I.pinv_rank(np.diag([1.0, 1e-12]), reference=np.array([1.0, 1.0]))
    assert rank == 1 and inverse[1, 1] == 0.0
    assert I.pinv_rank(np.diag([1.0, 1e-12]), reference=np.array([1.0, 1e-11]))[1] == 2
    assert I.pinv_rank(np.zeros((3, 3)))[1] == 0
    assert I.pinv_rank(np.zeros((0, 0)))[1] == 0
