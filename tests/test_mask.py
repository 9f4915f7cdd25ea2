"""Motion-pixel masking (paper Sec. II-E) on a region that moves during the scan."""
import logging
from dataclasses import replace

import numpy as np
import pytest

from dfxcorr import config as C
from dfxcorr import model as M
from dfxcorr import pipeline, planning
from dfxcorr.align import build_observations
from dfxcorr.analysis.evaluate import frames_lighting, gauge_median, vibration_pulls
from dfxcorr.chunks import row_counts
from dfxcorr.mask import START_CHI2, between_rows_miss, motion_mask, pilot_vibrations, start_misfit
from dfxcorr.reference import resolve_reference

from conftest import prepare, random_params, tiny_obs
from test_engine import displaced


def test_moving_region_is_flagged_and_little_else(small_scan):
    scan, truth = small_scan(**{"effects.sample_motion": 0.3})
    obs = build_observations(scan, resolve_reference(scan))
    moving, _, _, _ = motion_mask([obs], pilot=pilot_vibrations(obs), dilate=0)
    region = truth["motion_mask"]
    lit_region = region & (truth["image_transmission"] > 0.01)
    assert moving[lit_region].mean() > 0.8
    assert moving[~region].mean() < 0.01


def test_clean_scan_masks_almost_nothing(small_scan):
    scan, _ = small_scan()
    obs = build_observations(scan, resolve_reference(scan))
    pilot = pilot_vibrations(obs)
    moving, _, _, _ = motion_mask([obs], pilot=pilot, dilate=0)
    assert moving.mean() < 0.01
    moving, _, _, _ = motion_mask([obs], pilot=pilot, dilate=1)
    assert moving.mean() < 0.05  # the dilation grows each isolated false alarm to up to 5 pixels


@pytest.mark.slow
def test_mask_keeps_moving_pixels_out_of_the_fit_only(small_scan):
    scan, truth = small_scan(**{"effects.sample_motion": 0.3})
    result = pipeline.reconstruct(scan, C.load([], ["fit.subsample=3"]))
    region = truth["motion_mask"]
    assert result.fit_mask[region].sum() == 0
    assert np.isfinite(result.transmission[region]).mean() > 0.9  # retrieved all the same
    assert result.motion_mask[region].mean() > 0.8


@pytest.mark.slow
def test_a_heart_that_moves_half_way_is_masked_where_its_data_disagree(small_scan):
    # the heart shifts 8 mm from the middle frame on: only pixels lit both before and after saw two samples
    scan, truth = small_scan(**{"effects.heart_step_mm": 8.0, "simulate.seed": 5})
    obs = build_observations(scan, resolve_reference(scan))
    moving, score, _, _ = motion_mask([obs], pilot=pilot_vibrations(obs), dilate=0)
    J, H, _ = scan.shape
    rows_before = np.isin(np.arange(H), obs.row[obs.frame < J // 2])
    rows_after = np.isin(np.arange(H), obs.row[obs.frame >= J // 2])
    both = (rows_before & rows_after)[:, None] & np.isfinite(score)
    change = np.abs(truth["image_transmission_after"] / truth["image_transmission"] - 1)
    inconsistent = both & (change > 0.1)
    still = ~(both & (change > 0.02))
    assert inconsistent.sum() > 100
    assert moving[inconsistent].mean() > 0.5
    assert moving[still].sum() <= 0.1 * moving.sum()


def test_mask_grows_as_a_dilation_of_the_whole_image():
    from scipy import ndimage

    from dfxcorr.mask import mask_from_score

    rng = np.random.default_rng(3)
    score = rng.normal(1.0, 0.1, (60, 80))
    score[[0, 7, 30, 59], [79, 40, 0, 3]] = 50.0  # a few pixels far above, two on the edges
    for dilate in (1, 2):
        moving, thr = mask_from_score(score, threshold=10.0, dilate=dilate)
        assert thr == 10.0
        assert np.array_equal(moving, ndimage.binary_dilation(score > 10.0, iterations=dilate))
    # a pixel lit in few frames must also be as improbable as the threshold is at the typical dof: one that is not
    # (a score of 50 on 1 degree of freedom against 10 on 20) is not flagged, the others are
    dof = np.full(score.shape, 20.0)
    dof[0, 79] = 1.0
    moving, _ = mask_from_score(score, dof=dof, threshold=10.0, dilate=0)
    expected = score > 10.0
    expected[0, 79] = False
    assert np.array_equal(moving, expected)


@pytest.mark.slow
def test_row_blocks_give_the_mask_of_one_pass(small_scan):
    scan, _ = small_scan(**{"effects.sample_motion": 0.3})
    prep = prepare(scan, C.defaults())
    columns = np.arange(1, scan.shape[2], 3)
    pilot = pilot_vibrations(prep.observations(columns=columns))
    whole = motion_mask([prep.observations(columns=columns)], pilot=pilot)
    blocks = motion_mask((prep.observations(columns=columns, rows=r) for r in planning.row_blocks(prep.store, 0.05)),
                         pilot=pilot)
    assert len(planning.row_blocks(prep.store, 0.05)) > 3
    np.testing.assert_array_equal(whole[0], blocks[0])
    np.testing.assert_allclose(whole[1], blocks[1], rtol=1e-12, equal_nan=True)
    assert whole[2] == blocks[2]


def test_runs_of_columns_give_the_mask_of_one_pass_where_samples_read_between_rows(small_scan):
    scan, _ = small_scan(**{"effects.sample_motion": 0.3})
    cfg = C.load([], ["geometry.parallax=0.02"])
    prep = prepare(scan, cfg)
    assert prep.store.parallax
    columns = np.arange(1, scan.shape[2], 3)
    plan = planning.ColumnPlan(columns=columns, why="test", pilot=pilot_vibrations(prep.observations(columns=columns)))
    many = planning.row_blocks(prep.store, 0.05)
    assert len(many) > 3
    # one run of the fit's whole columns per retrieval block, or all of them at once: the same pixels
    np.testing.assert_array_equal(pipeline.fit_motion_mask(prep, cfg, plan, many),
                                  pipeline.fit_motion_mask(prep, cfg, plan, many[:1]))


def truth_params(truth) -> dict:
    return {"phase_offset": truth["vib_phase_offset"][:, None], "tilt": truth["vib_tilt"][:, None],
            "visibility_loss": truth["vib_visibility"][:, None]}


def test_a_start_in_the_basin_fits_every_frame_within_noise_and_one_frame_off_does_not(small_scan):
    scan, truth = small_scan()
    obs = build_observations(scan, resolve_reference(scan))
    at_truth = start_misfit(obs, truth_params(truth))
    # the largest of ~100 frames' reduced chi-squares, each over >= ~700 samples (sd 0.05): within 5 sd of 1
    assert at_truth == pytest.approx(1.0, abs=0.25)
    off = truth_params(truth)
    j = int(np.flatnonzero(frames_lighting(scan.position, scan.active_rows, scan.shape[1]))[10])
    off["phase_offset"] = off["phase_offset"].copy()
    off["phase_offset"][j] += np.pi / 2  # a quarter fringe: another basin for that frame
    assert start_misfit(obs, off) > 3 * START_CHI2
    assert start_misfit(obs, off, gauge_fraction=1.01) == np.inf  # no frame well determined: never a start
    # a pixel left with two used samples is not solved: its samples' residuals, however wild, do not count
    r = obs.rows.size // 2
    blocks = np.arange(obs.starts[r], obs.starts[r + 1])
    use = obs.use.copy()
    use[blocks[2:], 0] = False
    unsolved = replace(obs, use=use)
    wild = obs.counts.copy()
    wild[blocks[:2], 0] *= 10.0
    assert start_misfit(replace(unsolved, counts=wild), truth_params(truth)) == start_misfit(unsolved,
                                                                                             truth_params(truth))


def test_the_fit_from_the_pilot_reaches_the_minimum_of_the_staged_fit(small_scan, caplog):
    scan, truth = small_scan()
    with caplog.at_level(logging.INFO, logger="dfxcorr"):
        fast = pipeline.reconstruct(scan, C.load([], ["fit.subsample=3"]))
    assert any("starts at the pilot estimate" in r.getMessage() for r in caplog.records)
    staged = pipeline.reconstruct(scan, C.load([], ["fit.subsample=3", "fit.start=neutral"]))
    assert len(fast.cost) < len(staged.cost)
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    for name in ("phase_offset", "tilt"):
        a = gauge_median(fast.params[name][:, 0], good, scale=False)
        b = gauge_median(staged.params[name][:, 0], good, scale=False)
        # the same minimum: apart by a small fraction of the reported standard error
        assert np.all(np.abs(a - b)[good] < 0.05 * staged.uncertainty[name][good, 0]), name
    # and of the whole model: its chi-squares within one unit (a likelihood ratio of e^0.5)
    assert abs(fast.reduced_chi2 - staged.reduced_chi2) * staged.dof < 1.0


def test_the_pilot_where_samples_read_between_rows_lands_near_the_truth(small_scan):
    """Where the samples read the images between rows (a parallax, kappa 0.1 on 5 mm pixels) the pilot's steps use
    each pixel's own images: with the images coupled between rows they went astray from the neutral start (6.7 rad
    rms from the truth). Its phase offsets are as close to the truth as its twin's without parallax (measured 0.0072
    and 0.0073 rad rms): within twice."""
    errors = []
    for kappa in (0.0, 0.1):
        scan, truth = small_scan(**{"effects.parallax": kappa})
        prep = prepare(scan, C.load([], [f"geometry.parallax={kappa}"]))
        assert prep.observations(columns=np.arange(2)).reading is not None or not kappa
        pilot = pilot_vibrations(prep.observations(columns=np.arange(scan.shape[2])))
        good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
        err = pilot["phase_offset"][good, 0] - truth["vib_phase_offset"][good]
        errors.append(float(np.sqrt(np.mean((err - np.median(err)) ** 2))))
    assert errors[1] < 2 * errors[0], errors


def test_the_miss_of_reading_between_rows_is_exact_for_images_quadratic_along_the_rows(rng):
    """Linear interpolation between rows misses -f (1 - f) c of an image a + b u + c u^2 read at u = lo + f: the
    estimate from the images' second differences is exactly that, in the expected counts over the noise, at every
    pixel (the end rows take their neighbours' second difference); 0 where the samples read their own rows. A row
    not solved (held at 0) spans no second difference and no sample reading it counts: still exact."""
    obs = tiny_obs(rng, J=16, H=9, W=11)
    params = random_params(rng, obs.n_frames, ("phase_offset", "tilt", "visibility_loss"))
    ch = M.channels(params, x=obs.x, n_frames=obs.n_frames)
    a, b, c = (rng.uniform(0.5, 1.0, (11, 3)), rng.normal(0.0, 0.1, (11, 3)), rng.normal(0.0, 0.05, (11, 3)))
    coef = a + b * obs.rows[:, None, None] + c * obs.rows[:, None, None] ** 2
    valid = np.ones(coef.shape[:2], bool)
    w = np.where(obs.use, rng.uniform(0.5, 2.0, obs.counts.shape), 0.0)
    assert np.all(between_rows_miss(obs, ch, coef, valid, w)[row_counts(obs, w > 0) > 0] == 0.0)
    obs = displaced(rng, obs, spread=0.9)
    lo, hi, f = obs.read_rows()
    x = (obs.rows[lo] + f)[:, None, None]
    missed = (a + b * x + c * x ** 2) - ((1 - f)[:, None, None] * coef[lo] + f[:, None, None] * coef[hi])
    dsg = M.design_channels(obs, ch)
    counts = missed[..., 0] * dsg.A + missed[..., 1] * dsg.Bc + missed[..., 2] * dsg.Bs
    for held in ((), ((4, 5),)):
        valid, solved = np.ones(coef.shape[:2], bool), coef.copy()
        for r, col in held:
            valid[r, col], solved[r, col] = False, 0.0
        counted = np.where(obs.gather_valid(valid), w, 0.0)
        n = row_counts(obs, counted > 0)
        want = np.sqrt(obs.segment_sum(counted * counts ** 2) / np.maximum(n, 1))
        got = between_rows_miss(obs, ch, solved, valid, w)
        assert np.all(n[~valid] == 0) and np.all(np.isnan(got[n == 0])) and want[n > 0].min() > 0
        np.testing.assert_allclose(got[n > 0], want[n > 0], rtol=1e-10)


@pytest.mark.slow
def test_pixels_the_reading_between_rows_misses_stay_out_of_the_vibration_fit(small_scan):
    """2.5 mm pixels, a parallax of 0.1 set as simulated: read between rows, the edges of ribs and lungs moving by
    fractions of a row leave a misfit that pulls the per-frame phase (measured pull 5.9). With the pixels where that
    reading misses more than a quarter of the noise left out of the vibration fit (mask.between_rows), the phase
    offsets are back at their standard errors (measured 1.02): the pull of some 200 frames scatters by about 0.05."""
    scan, truth = small_scan(**{"simulate.pixel_mm": 2.5, "simulate.step_mm": 2.5, "effects.parallax": 0.1})
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    pulls = []
    for sets in ([], ["mask.between_rows=null"]):
        r = pipeline.reconstruct(scan, C.load([], ["geometry.parallax=0.1", *sets]), progress=False)
        pulls.append(vibration_pulls(r.params, r.uncertainty, truth, good))
    assert pulls[0]["phase_offset"] < 1.3 < 3.0 < pulls[1]["phase_offset"], pulls
