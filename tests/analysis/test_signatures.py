"""Residual signatures: an injected misfit is found where it is, data drawn from the model raise nothing beyond the
family-wise rate, and the text that says where."""
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from dfxcorr import model as M
from dfxcorr.align import build_observations
from dfxcorr.analysis.signatures import locate, signatures
from dfxcorr.effects.residuals import pixel_chi2, reduced_map
from dfxcorr.io import Reference, Scan
from dfxcorr.retrieve import retrieve
from dfxcorr.stats import ranges


@pytest.fixture(scope="module")
def model_scan():
    """Observations of a small scan (40 frames, 14 x 16 pixels, 6 active rows) and their expected counts under the
    model without effects (about 700 counts), for random images."""
    rng = np.random.default_rng(1)
    J, H, W, A = 40, 14, 16, 6
    ref = Reference(rng.uniform(800, 1200, (A, W)), rng.uniform(0.2, 0.4, (A, W)),
                    np.cumsum(rng.uniform(0.5, 1.5, (A, W)), axis=0))
    position = -A + 1.0 + np.arange(J) * (H + A - 2) / (J - 1)
    shell = build_observations(Scan(data=np.zeros((J, H, W)), position=position, reference=ref), ref)
    R, C = shell.rows.size, shell.columns.size
    t, v, phi = rng.uniform(0.5, 1, (R, C)), rng.uniform(0.6, 1, (R, C)), rng.uniform(-np.pi, np.pi, (R, C))
    images = M.Images(np.stack([t, t * v * np.cos(phi), t * v * np.sin(phi)], axis=-1), np.ones((R, C), bool))
    return shell, M.expected(shell, M.design(shell, {}), images)


def drawn(model_scan, seed):
    shell, ibar = model_scan
    return replace(shell, counts=np.random.default_rng(seed).poisson(ibar).astype(np.float64))


def significant(sigs) -> set:
    return {(s["axis"], s["kind"]) for s in sigs if s["significant"]}


def one(sigs, axis, kind):
    (sig,) = [s for s in sigs if s["axis"] == axis and s["kind"] == kind]
    return sig


def test_data_drawn_from_the_model_raise_no_signature(model_scan):
    sigs = signatures(drawn(model_scan, 2), {}, alpha=0.01)
    assert {(s["axis"], s["kind"]) for s in sigs} == {
        ("frame", "variance"), ("row", "variance"), ("column", "variance"), ("phase", "variance"),
        ("count", "variance"), ("frame", "mean"), ("frame_row", "mean"), ("count", "level")}
    assert not significant(sigs)
    for s in sigs:
        assert 0 < s["p_value"] <= 1 and s["log_p"] == pytest.approx(np.log(s["p_value"]))


def test_holm_holds_the_family_wise_rate_on_data_drawn_from_the_model(model_scan):
    """Of 40 draws, those with any signature significant at alpha = 0.2 are within the binomial's 99.9 % bound;
    counting every test's own p < alpha instead (no correction for the 8 tests) would exceed it."""
    alpha, n = 0.2, 40
    alarms = uncorrected = 0
    for seed in range(100, 100 + n):
        sigs = signatures(drawn(model_scan, seed), {}, alpha=alpha)
        alarms += bool(significant(sigs))
        uncorrected += any(s["p_value"] < alpha for s in sigs)
    bound = stats.binom.ppf(0.999, n, alpha)
    assert alarms <= bound < uncorrected


def test_a_mean_offset_in_two_frames_is_the_frame_signature_there(model_scan):
    obs = drawn(model_scan, 3)
    # 25 counts (about one standard deviation per sample) added to every sample of frames 20 and 21
    counts = obs.counts + 25.0 * np.isin(obs.frame, [20, 21])[:, None]
    sigs = signatures(replace(obs, counts=counts), {}, alpha=0.01)
    assert significant(sigs) == {("frame", "mean"), ("frame_row", "mean")}
    sig = one(sigs, "frame", "mean")
    np.testing.assert_array_equal(np.flatnonzero(sig["bins"] > 3), [20, 21])
    # the images, fitted over each pixel's frames, take up part of it: a neighbour may read low, and is named too
    assert sig["where"] == f"frames {ranges(np.flatnonzero(np.abs(sig['bins']) > 3), limit=4)}"
    assert sig["description"].startswith("mean standardized residual per sample +")


def test_a_variance_excess_in_one_row_is_the_row_signature_there(model_scan):
    obs = drawn(model_scan, 4)
    rng = np.random.default_rng(5)
    _, ibar = model_scan
    # detector row 7 gets 1.44 times the Poisson variance on top
    extra = np.where((obs.row == 7)[:, None], 1.2 * np.sqrt(ibar) * rng.normal(size=ibar.shape), 0.0)
    sigs = signatures(replace(obs, counts=obs.counts + extra), {}, alpha=0.01)
    # the level may read it too: the whole recording's variance is above the stated noise model
    assert ("row", "variance") in significant(sigs) <= {("row", "variance"), ("count", "level")}
    sig = one(sigs, "row", "variance")
    assert sig["where"] == "detector rows 7"
    assert np.nanargmax(sig["bins"]) == 7 and "above noise in 1 of" in sig["description"]


def test_ranges_reads_runs_of_sorted_integers():
    assert ranges([3, 4, 5, 6, 7, 12, 40, 41]) == "3-7, 12, 40-41"
    assert ranges(np.array([5])) == "5"
    assert ranges([]) == ""
    assert ranges([1, 3, 5, 6], limit=2) == "1, 3, ..."
    assert ranges([1, 3, 5, 6], limit=3) == "1, 3, 5-6"


def test_located_pixels_are_the_reduced_chi_square_of_their_solved_samples(model_scan):
    obs = drawn(model_scan, 7)
    # a pixel without enough samples and a few samples not used: left out of every bin, NaN in the map
    use = obs.use.copy()
    use[obs.pixel == 3, 5] = False
    use[::17] = False
    obs = replace(obs, use=use)
    rec = retrieve(obs, {})
    located = locate(obs, {}, rec.images, counts=obs.counts[use], chunk=3 * obs.frame.size)
    X, dof, _ = pixel_chi2(obs, {}, rec.images)
    np.testing.assert_allclose(located.pixel, reduced_map(X, dof), rtol=1e-12)
    assert np.isnan(located.pixel[obs.rows[3], obs.columns[5]])
    # data drawn from the model: about 1 along every axis
    assert np.nanmean(located.pixel) == pytest.approx(1.0, abs=0.1)
    assert np.nanmean(located.frame) == pytest.approx(1.0, abs=0.1)


def test_samples_without_fringe_have_no_fringe_phase(model_scan):
    """Samples outside the region of interest (no fringe: they monitor dose and background) are left out of the phase
    signature. A variance excess in them alone is the column signature there, not a phase signature: labelled by
    their phase, which is that of zero quadratures, they would all fall into one bin."""
    shell, _ = model_scan
    dark = np.zeros(shell.columns.size, bool)
    dark[[2, 3, 11]] = True
    flat = replace(shell, fc=np.where(dark, 0.0, shell.fc), fs=np.where(dark, 0.0, shell.fs),
                   roi=np.broadcast_to(~dark, shell.counts.shape).copy())
    rng = np.random.default_rng(6)
    R, C = flat.rows.size, flat.columns.size
    t, v, phi = rng.uniform(0.5, 1, (R, C)), rng.uniform(0.6, 1, (R, C)), rng.uniform(-np.pi, np.pi, (R, C))
    images = M.Images(np.stack([t, t * v * np.cos(phi), t * v * np.sin(phi)], axis=-1), np.ones((R, C), bool))
    ibar = M.expected(flat, M.design(flat, {}), images)
    counts = rng.poisson(ibar) + np.where(dark, 1.0 * np.sqrt(ibar) * rng.normal(size=ibar.shape), 0.0)
    sigs = signatures(replace(flat, counts=counts), {}, alpha=0.01)
    assert ("column", "variance") in significant(sigs)
    assert ("phase", "variance") not in significant(sigs)
