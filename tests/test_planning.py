"""Planning the vibration fit's columns: the spacing within a sample budget, the coarse first pass, the predicted
time, the alias limit, and ``fit.subsample: auto`` from a pilot's predicted uncertainty."""
import numpy as np
import pytest

from dfxcorr import config as C
from dfxcorr import planning
from dfxcorr.align import subsample_columns
from dfxcorr.fit import fit_vibrations
from dfxcorr.sim import simulate as S

from conftest import prepare, sim_config


@pytest.mark.parametrize("width, samples_per_column, budget, expected", [
    (204, 8 * 180, 10_000_000, 1),  # the 8-step stepping recording of 180 x 204: every column
    (1440, 195 * 220, 10_000_000, 7),  # the binned clinical scan
    (2880, 195 * 440, 10_000_000, 25),  # the full-resolution clinical scan
    (400, 10_000, 10, 100),  # a tiny budget stops at the alias limit W / 4
])
def test_column_step_is_the_smallest_within_the_samples(width, samples_per_column, budget, expected):
    n = planning.column_step(width, samples_per_column, most=budget)
    assert n == expected
    assert expected == width // 4 or samples_per_column * width / expected <= budget
    assert expected == 1 or samples_per_column * width / (expected - 1) > budget


def fit_cfg(**fit) -> dict:
    return C.load([], [f"fit.{k}={v}" for k, v in fit.items()])


def test_coarse_step_leaves_about_a_million_samples_to_the_first_pass():
    auto = fit_cfg()
    # 400 columns of 42 900 samples: 17.2 M samples, every 17th column leaves about 1 M
    assert planning.coarse_step(auto, 400, 42_900, step=1, width=1440) == 17
    # at least COARSE_MIN_COLUMNS columns in the first pass
    assert planning.coarse_step(auto, 64, 10 ** 6, step=1, width=1440) == 64 // planning.COARSE_MIN_COLUMNS
    # a fit small enough for one pass has none
    assert planning.coarse_step(auto, 100, 1000, step=1, width=400) == 1
    # an explicit spacing is taken, but never beyond the alias limit W / 4 of the detector's columns
    assert planning.coarse_step(fit_cfg(coarse=5), 400, 1000, step=2, width=1440) == 5
    assert planning.coarse_step(fit_cfg(coarse=500), 400, 1000, step=2, width=1440) == 1440 // 4 // 2
    assert planning.coarse_step(fit_cfg(coarse=1), 400, 10 ** 6, step=1, width=1440) == 1


def test_fit_seconds_counts_the_coarse_pass_and_the_polish():
    n, per_column = 300, 40_000
    one_pass = planning.fit_seconds(n, per_column, 1)
    assert one_pass == pytest.approx(planning.FIT_SECONDS_PER_SAMPLE * n * per_column)
    assert planning.fit_seconds(n, per_column, 0) == one_pass
    # every 7th of 300 columns is 43: their full fit, then the last stages on all 300
    coarse = planning.fit_seconds(n, per_column, 7)
    assert coarse == pytest.approx(planning.fit_seconds(43, per_column, 1)
                                   + planning.POLISH_SECONDS_PER_SAMPLE * n * per_column)
    assert coarse < one_pass
    # from the pilot estimate: no coarse pass, its own rate on all columns, slowed where samples read between rows
    for c in (1, 7):
        assert planning.fit_seconds(n, per_column, c, from_pilot=True, slowdown=2.5) == pytest.approx(
            2.5 * planning.PILOT_SECONDS_PER_SAMPLE * n * per_column)
    # predicted from the pilot only where the maximum-likelihood fit may start there
    assert planning.start_seconds(fit_cfg(), n, per_column) == planning.fit_seconds(n, per_column, 1, from_pilot=True)
    assert np.isnan(planning.start_seconds(fit_cfg(start="neutral"), n, per_column))
    assert np.isnan(planning.start_seconds(C.load([], ["fit.method=correlation"]), n, per_column))
    plan = planning.ColumnPlan(columns=np.arange(0, 300, 2), why="test", seconds=3.0, coarse=7)
    assert "predicted fit time 3.0 s, its stages first on every 7-th" in plan.summary()


@pytest.mark.parametrize("seconds", [0.5, 3.0, 20.0])
def test_within_seconds_is_the_smallest_spacing_predicted_to_fit(seconds):
    cfg, W, per_column = fit_cfg(), 1440, 42_900

    def predicted(n):
        cols = subsample_columns(W, n).size
        return planning.fit_seconds(cols, per_column, planning.coarse_step(cfg, cols, per_column, step=n, width=W))
    n = planning.within_seconds(cfg, W, per_column, seconds)
    assert predicted(n) <= seconds
    assert n == 1 or predicted(n - 1) > seconds
    # nothing fits: the alias limit; everything fits: every column
    assert planning.within_seconds(cfg, W, per_column, 0.0) == W // 4
    assert planning.within_seconds(cfg, W, per_column, 1e9) == 1


def test_fit_columns_refuses_a_spacing_beyond_the_alias_limit():
    cfg = fit_cfg()
    np.testing.assert_array_equal(planning.fit_columns(100, cfg, 7), np.arange(3, 100, 7))
    np.testing.assert_array_equal(planning.fit_columns(100, fit_cfg(column_offset=0), 25), [0, 25, 50, 75])
    # 4 columns are left at spacing 26, but tilts 12.08 rad apart (pi W / n < 4 pi) look the same on them
    with pytest.raises(C.ConfigError, match="fit.subsample=26: tilts that differ by 12.08 rad are indistinguishable"):
        planning.fit_columns(100, cfg, 26)
    with pytest.raises(C.ConfigError, match="fit.subsample=40 leaves 2 of 100 columns; use at most 25"):
        planning.fit_columns(100, cfg, 40)


@pytest.fixture(scope="module")
def planned():
    """A small scan prepared as reconstruct prepares it, its pilot vibration estimate, and its plan for a 0.007 rad
    target (no time floor)."""
    scan, _ = S.simulate(sim_config())
    prep = prepare(scan, C.defaults())
    pilot = planning.pilot_estimate(prep)
    plan = planning.plan_columns(prep, fit_cfg(target_uncertainty=0.007, time_floor="null"), pilot=pilot)
    return prep, pilot, plan


def test_subsample_auto_takes_more_columns_for_a_tighter_target(planned, caplog):
    prep, pilot, plan = planned
    W = prep.shape[2]
    with caplog.at_level("INFO", logger="dfxcorr"):
        looser = planning.plan_columns(prep, fit_cfg(target_uncertainty=0.012, time_floor="null"), pilot=pilot)
    assert looser.columns.size < plan.columns.size < W
    assert plan.uncertainty <= 0.007 and looser.uncertainty <= 0.012
    # the log names the columns, the predicted uncertainty and time
    assert f"vibration fit columns: {looser.columns.size} columns" in caplog.text
    assert "predicted phi0/phi1 uncertainty" in caplog.text and "predicted fit time" in caplog.text
    assert f"s from the pilot estimate ({looser.seconds:.1f} s from the neutral values" in caplog.text
    # the prediction with the default pilot is this one
    assert planning.plan_columns(prep, fit_cfg(target_uncertainty=0.007, time_floor="null"),
                                 report=False).uncertainty == pytest.approx(plan.uncertainty)


@pytest.mark.slow
def test_subsample_auto_reaches_the_target_uncertainty_it_predicts(planned):
    """The pilot's prediction is what the fit on the chosen columns then reports (within 25 %, and not optimistic
    by more than 10 %)."""
    prep, _, plan = planned
    fitted = fit_vibrations(prep.observations(columns=plan.columns, dtype=np.float32))
    good = fitted.well_determined
    reported = max(float(np.median(fitted.uncertainty[n][good])) for n in ("phase_offset", "tilt"))
    assert 0.75 * plan.uncertainty < reported < 1.1 * plan.uncertainty


def test_time_budget_bounds_the_predicted_seconds_and_the_uncertainty_scales_as_one_over_sqrt_columns(planned):
    prep, pilot, plan = planned
    W, per_column = prep.shape[2], prep.store.samples_per_column()
    for budget in (plan.seconds / 2, plan.seconds / 5):
        cfg = fit_cfg(time_budget=budget)
        short = planning.plan_columns(prep, cfg, pilot=pilot)
        assert "fit.time_budget" in short.why
        assert short.seconds <= budget and plan.columns.size * budget / plan.seconds - 1 <= short.columns.size
        # the most columns within the budget: the next finer spacing would not fit
        finer = subsample_columns(W, short.columns[1] - short.columns[0] - 1).size
        assert planning.fit_seconds(finer, per_column, planning.coarse_step(cfg, finer, per_column, step=1,
                                                                            width=W)) > budget
        # columns add information independently
        assert short.uncertainty == pytest.approx(plan.uncertainty * np.sqrt(plan.columns.size / short.columns.size))


def test_time_floor_is_the_whole_runs_and_takes_every_column_of_a_small_scan(planned):
    prep, pilot, plan = planned
    W = prep.shape[2]
    # the floor is the whole run's: the fit's predicted seconds and the other stages' for every sample of the scan
    rest = planning.REST_SECONDS_PER_SAMPLE * prep.store.samples_per_column() * W
    floor = planning.plan_columns(prep, fit_cfg(target_uncertainty=0.012, time_floor=plan.seconds + rest),
                                  pilot=pilot)
    assert floor.columns.size >= plan.columns.size and floor.seconds <= plan.seconds
    every = planning.plan_columns(prep, fit_cfg(target_uncertainty=0.012, time_floor=7.0), pilot=pilot)
    assert every.columns.size == W and every.seconds + rest <= 7.0
    # without a floor (the default) the fit ends at the target
    default = planning.plan_columns(prep, fit_cfg(target_uncertainty=0.007), pilot=pilot)
    assert np.array_equal(default.columns, plan.columns)


def test_max_samples_holds_the_columns_of_auto(planned):
    prep, pilot, plan = planned
    per_column = prep.store.samples_per_column()
    held = planning.plan_columns(prep, fit_cfg(target_uncertainty=0.001, time_floor="null",
                                               max_samples=per_column * plan.columns.size // 2), pilot=pilot)
    assert held.columns.size * per_column <= per_column * plan.columns.size // 2
    assert "held at fit.max_samples" in held.why


def test_without_a_target_auto_fits_the_most_columns_max_samples_holds(planned):
    prep, pilot, plan = planned
    W, per_column = prep.shape[2], prep.store.samples_per_column()
    # the default: no target, every column where they fit in fit.max_samples (the scan's Cramer-Rao level)
    every = planning.plan_columns(prep, fit_cfg(), pilot=pilot)
    assert W * per_column <= C.defaults()["fit"]["max_samples"]
    assert every.columns.size == W and "fit.target_uncertainty=null" in every.why
    assert every.uncertainty < plan.uncertainty
    # fewer samples allowed: the widest spacing whose columns fit, said so; a time floor changes nothing
    most = per_column * W // 3
    for extra in ({}, {"time_floor": 1e6}):
        held = planning.plan_columns(prep, fit_cfg(max_samples=most, **extra), pilot=pilot)
        assert held.columns.size * per_column <= most
        assert held.columns.size == subsample_columns(W, planning.column_step(W, per_column, most=most)).size
        assert "held at fit.max_samples" in held.why
