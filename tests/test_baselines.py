"""The baseline estimators: alternating optimisation reaches the ML optimum; the correlation method is exact
without a sample structure and fails on the thorax (paper Fig. 8)."""
import numpy as np
import pytest

from dfxcorr import config as C
from dfxcorr import model as M
from dfxcorr import pipeline
from dfxcorr.align import build_observations, subsample_columns
from dfxcorr.analysis.evaluate import frames_lighting, gauge_median, vibration_rmse
from dfxcorr.baselines import fit_alternating, fit_correlation, robust_polyfit
from dfxcorr.catalogue import PAPER_MODEL, neutral_params
from dfxcorr.fit import fit_vibrations, initial_weights
from dfxcorr.reference import resolve_reference


def fit_data(scan, every):
    obs = build_observations(scan, resolve_reference(scan))
    return obs.subset(subsample_columns(scan.shape[2], every))


def reduced_cost(obs, params, weights):
    """sum w (I - Ibar)^2 at the closed-form images: the likelihood part of every fit's cost."""
    dsg = M.design(obs, params)
    return float(np.sum(weights * (obs.counts - M.expected(obs, dsg, M.solve_images(obs, dsg, weights))) ** 2))


@pytest.mark.slow
def test_alternating_converges_to_the_ml_optimum(small_scan):
    scan, _ = small_scan()
    obs = fit_data(scan, 3)
    w = initial_weights(obs, neutral_params(PAPER_MODEL, obs.n_frames))
    ml = fit_vibrations(obs, weights=w, reweight=0, gtol=1e-4)
    alt = fit_alternating(obs, weights=w, reweight=0, maxiter=600)
    assert alt.converged
    # each alternation minimises over one block of unknowns: the cost never increases
    assert np.all(np.diff(alt.cost) <= 1e-9 * alt.cost[1:])
    # the gauge (eq. 22) does not change the cost: the last entry is the cost of the returned parameters
    assert alt.cost[-1] == pytest.approx(reduced_cost(obs, alt.params, w), rel=1e-7)
    # ML's cost carries its weak prior; its likelihood part matches (to the prior's pull)
    assert reduced_cost(obs, ml.params, w) == pytest.approx(alt.cost[-1], rel=1e-3)
    good = ml.well_determined
    for name in PAPER_MODEL:
        z = (alt.params[name] - ml.params[name])[good] / ml.uncertainty[name][good]
        assert np.sqrt(np.mean(z ** 2)) < 0.2, name
        assert np.abs(z).max() < 0.5, name
    np.testing.assert_allclose(alt.uncertainty["tilt"][good], ml.uncertainty["tilt"][good], rtol=0.02)


@pytest.mark.slow
def test_alternating_updates_global_effects_as_one_block(small_scan):
    scan, truth = small_scan(**{"effects.harmonic": 0.05})
    obs = fit_data(scan, 4)
    effects = (*PAPER_MODEL, "harmonic")
    w = initial_weights(obs, neutral_params(effects, obs.n_frames))
    # both fits start at the true per-frame parameters, so that neither meets a local minimum of an
    # edge frame, and must then find the same harmonic
    start = {"phase_offset": truth["vib_phase_offset"][:, None], "tilt": truth["vib_tilt"][:, None],
             "visibility_loss": truth["vib_visibility"][:, None]}
    alt = fit_alternating(obs, effects=effects, start=start, weights=w, reweight=0, maxiter=300)
    ml = fit_vibrations(obs, effects=effects, start=start, weights=w, reweight=0, prior=False, staged=False,
                        circmean_iterations=0, gtol=1e-5)
    assert alt.converged
    assert np.all(np.diff(alt.cost) <= 1e-9 * alt.cost[1:])
    np.testing.assert_allclose(alt.params["harmonic"], ml.params["harmonic"],
                               atol=0.1 * ml.uncertainty["harmonic"].min())
    np.testing.assert_allclose(alt.params["harmonic"], truth["harmonic"], atol=4 * ml.uncertainty["harmonic"].max())


@pytest.mark.parametrize("curvature", [0.0, pytest.param(0.2, marks=pytest.mark.slow)])
def test_correlation_is_exact_for_constant_attenuation_without_noise(small_scan, curvature):
    scan, truth = small_scan(**{"simulate.phantom": "slab", "simulate.noise": False, "simulate.dtype": "float64",
                                "effects.curvature": curvature})
    effects = ("phase_offset", "tilt", "visibility_loss") + (("curvature",) if curvature else ())
    res = fit_correlation(build_observations(scan, resolve_reference(scan)), effects=effects)
    # the method has no visibility term: v^s is not estimated, whatever the data hold
    assert "visibility_loss" not in res.params
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    for name in (n for n in effects if n != "visibility_loss"):
        err = gauge_median(res.params[name][:, 0], good, scale=False) - gauge_median(truth[f"vib_{name}"], good,
                                                                                     scale=False)
        # grid of 1 degree refined by a parabola: far below a thousandth of a radian
        assert np.abs(err[good]).max() < 1e-4, name
        assert np.all(res.uncertainty[name][good] < 1e-4)


@pytest.mark.slow
def test_correlation_fails_on_the_thorax_where_ml_does_not(small_scan):
    # paper Sec. III-D.2: no visibility loss simulated, no quadratic term fitted
    scan, truth = small_scan(**{"effects.visibility_loss": 0.0})
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    sets = ["fit.subsample=3", "vibration.visibility=false", "retrieve.uncorrected=false"]
    err = {m: vibration_rmse(pipeline.reconstruct(scan, C.load([], sets + [f"fit.method={m}"])).params, truth, good)
           for m in ("correlation", "ml")}
    # the transmission's correlation with the fringes biases the column-wise positions
    assert err["correlation"]["phase_offset"] > 10 * err["ml"]["phase_offset"]
    assert err["correlation"]["phase_offset"] > 0.1


def test_robust_polyfit_ignores_gross_outliers_and_phase_wraps():
    rng = np.random.default_rng(5)
    x = np.linspace(-1, 1, 41)
    true = np.array([[3.0, 0.8, -0.3], [-0.2, -1.1, 0.4]])
    y = true @ np.stack([x ** 0, x, x ** 2])
    y = np.angle(np.exp(1j * y))              # the data are phases: wrapped
    outlier = rng.random(y.shape) < 0.2
    y = np.where(outlier, rng.uniform(-np.pi, np.pi, y.shape), y)
    valid = np.ones(y.shape, bool)
    valid[1, :38] = False                     # the second row has too few values for three terms
    coef, sigma, converged = robust_polyfit(x, y, valid, powers=[0, 1, 2])
    assert converged
    fit_row0 = coef[0] @ np.stack([x ** 0, x, x ** 2])
    np.testing.assert_allclose(np.angle(np.exp(1j * (fit_row0 - true[0] @ np.stack([x ** 0, x, x ** 2])))), 0,
                               atol=1e-6)
    assert np.all(np.isinf(sigma[1])) and np.all(coef[1] == 0)


def test_correlation_needs_a_phase_effect(small_scan):
    scan, _ = small_scan()
    with pytest.raises(C.ConfigError, match="grating positions only"):
        fit_correlation(fit_data(scan, 6), effects=("visibility_loss",))
