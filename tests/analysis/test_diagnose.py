"""The diagnosis, proven on concealed effects: each is named first and the fit returns to the noise."""
import json
from dataclasses import replace

import numpy as np
import pytest

from dfxcorr import config as C
from dfxcorr.align import subsample_columns
from dfxcorr.analysis.diagnose import diagnose, held_band
from dfxcorr.analysis.report import write_report
from dfxcorr.sim import simulate as S

from conftest import chi2_tolerance, concealed, prepare, real_ipp_scan, sim_config


# one concealed effect stays in the fast tier; the rest take 2-8 s each. beam_path has its own test
# (tests/effects/test_beam_path.py): images on the pixel grid cannot bring it back to the noise
@pytest.mark.parametrize("effect", [e if e == "phase_offset" else pytest.param(e, marks=pytest.mark.slow)
                                    for e in S.CONCEALED if e != "beam_path"])
def test_concealed_effect_is_named_first_and_the_fit_recovers(effect):
    scan, truth, cfg = concealed(effect)
    diag = diagnose(scan, cfg)
    found = [e.name for e in diag.effects if e.detected]
    assert found and found[0] == effect, [(e.name, e.statistic, e.dof) for e in diag.effects]
    if effect == "visibility_tilt":
        # Its x^2 term is hardly determined at the realistic amplitude (fitted v2 off by about its own
        # std, 0.05): on the columns the fit did not see, that parameter noise leaves about 4 % of excess
        # chi-square, beyond the tolerance's estimate. Either the fit is back at the noise, or what is
        # left (at most that parameter noise) is reported as unexplained.
        assert diag.final_chi2 == pytest.approx(1.0, abs=chi2_tolerance(diag, cfg)) or diag.unexplained
        assert diag.final_chi2 < 1.0 + chi2_tolerance(diag, cfg) + 0.06
    else:
        assert diag.final_chi2 == pytest.approx(1.0, abs=chi2_tolerance(diag, cfg))
    # towards 1: from above for most effects, from below where the noise is below the stated model (pixel_noise)
    assert abs(diag.initial_chi2 - 1) > abs(diag.final_chi2 - 1)
    if effect == "detector_gain":
        assert diag.effects[0].values["gain"] == pytest.approx(2.0, rel=0.03)
    if effect == "harmonic":
        # version 2: the term follows the sample, so nothing else soaks up what it would miss
        assert found == ["harmonic"] and diag.unexplained == [], (found, diag.unexplained)
        hc, hs = diag.params["harmonic"]
        assert np.hypot(hc, hs) == pytest.approx(np.hypot(*truth["harmonic"]), rel=0.05)
        assert np.arctan2(hs, hc) == pytest.approx(np.arctan2(truth["harmonic"][1], truth["harmonic"][0]), abs=0.05)
    if effect == "sample_motion":
        region = truth["motion_mask"] & (truth["image_transmission"] > 0.01)
        assert diag.motion_mask[region].mean() > 0.7 and diag.motion_mask[~truth["motion_mask"]].mean() < 0.01


@pytest.mark.slow
def test_reconstruct_with_the_harmonic_lowers_the_image_error():
    from dfxcorr.analysis.evaluate import image_rmse
    from dfxcorr.pipeline import reconstruct

    scan, truth, cfg = concealed("harmonic")
    without = reconstruct(scan, cfg)
    with_ = reconstruct(scan, C.merge(cfg, {"vibration": {"harmonic": True}}))
    err0, err1 = (image_rmse({k: r.image(k) for k in r.IMAGES}, truth) for r in (without, with_))
    assert err1["transmission"] < 0.8 * err0["transmission"] and err1["dark_field"] < err0["dark_field"], (err0, err1)
    assert with_.reduced_chi2 < without.reduced_chi2


# seeds of the frame-by-frame simulator (each frame draws its noise from its own stream)
@pytest.mark.parametrize("seed", [22, pytest.param(23, marks=pytest.mark.slow)])
def test_clean_scans_raise_no_alarm(seed):
    scan, _ = S.simulate(sim_config(**{"simulate.seed": seed}))
    diag = diagnose(scan, C.defaults())
    assert not any(e.detected for e in diag.effects), [(e.name, e.p_value) for e in diag.effects]
    assert diag.unexplained == [], diag.unexplained
    assert diag.final_chi2 == pytest.approx(1.0, abs=0.03)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [21, 22])
def test_clean_scan_with_a_stated_gain_raises_no_alarm(seed):
    # a third of the photons behind the same counts: the dim spine has a few photons per sample, where the
    # per-pixel Pearson chi-square is biased up and heavy-tailed
    scan, _ = S.simulate(sim_config(**{"simulate.seed": seed, "effects.detector_gain": 3.0}))
    assert scan.gain == 3.0
    diag = diagnose(scan, C.defaults())
    assert not any(e.detected for e in diag.effects), [(e.name, e.p_value, e.verdict) for e in diag.effects]
    assert diag.unexplained == [], diag.unexplained


@pytest.mark.slow
def test_unstated_gain_is_named_first_and_alone():
    scan, _ = S.simulate(sim_config(**{"simulate.seed": 21, "effects.detector_gain": 3.0,
                                        "effects.declare_gain": False}))
    diag = diagnose(scan, C.defaults())
    assert [e.name for e in diag.effects if e.detected] == ["detector_gain"]
    assert diag.effects[0].values["gain"] == pytest.approx(3.0, rel=0.03)
    assert diag.unexplained == [], diag.unexplained


@pytest.mark.slow
def test_motion_below_its_detection_limit_is_not_named_a_gain():
    # a patch whose transmission swings by 5 % (half the per-pixel detection limit): its variance excess raised a
    # gain by 3.1 %, which a gain cannot do (one factor for every pixel: its strata by row asked for 6.85 times the
    # change where the patch is, -0.7 ... 1.3 elsewhere); what the motion mask does not take is located
    scan, _, cfg = concealed("sample_motion", amplitude=0.05)
    diag = diagnose(scan, cfg)
    found = [e.name for e in diag.effects if e.detected]
    assert set(found) <= {"sample_motion"}, found  # before: detector_gain (1.03), then sample_motion
    assert diag.unexplained, "the motion's misfit left over is located"


# Physics in no catalogue, made here (not in the simulator): the diagnosis must locate it, not explain it away.

def nonlinear_scan(*, seed=31, saturation=1e5):
    """Counts compressed by the detector as I / (1 + I / I_sat): 17 % at the flat field's 2e4 counts."""
    scan, truth = S.simulate(sim_config(**{"simulate.seed": seed, "simulate.dtype": "float64"}))
    scan.data = scan.data / (1 + scan.data / saturation)
    return scan, truth


def row_gain_scan(*, seed=32, amplitude=0.3):
    """Detector rows in bands of 4 with gains 1.3 and 0.7 (noise g * mean in those rows), the file says 1."""
    scan, truth = S.simulate(sim_config(**{"simulate.seed": seed, "simulate.noise": False,
                                            "simulate.dtype": "float64"}))
    rng = np.random.default_rng(seed)
    gain = 1 + amplitude * np.where(np.arange(scan.shape[1]) // 4 % 2 == 0, 1.0, -1.0)[None, :, None]
    scan.data = gain * rng.poisson(scan.data / gain)
    return scan, truth


@pytest.mark.slow
def test_detector_nonlinearity_is_located_not_explained_away(tmp_path):
    scan, _ = nonlinear_scan()
    diag = diagnose(scan, C.defaults())
    # the variance is below photon noise overall, which a gain below 1 explains (and nothing else does); no
    # structured catalogue effect may be added for what remains
    assert [e.name for e in diag.effects if e.detected] in ([], ["detector_gain"])
    write_report(diag, tmp_path)
    doc = json.loads((tmp_path / "diagnosis.json").read_text())
    assert doc["unexplained"] and set(doc["unexplained"][0]) == {"axis", "statistic", "dof", "p_value", "where",
                                                                  "description"}
    assert "| count |" in (tmp_path / "report.md").read_text()
    # compressed counts: the variance falls below photon noise at the highest counts
    assert any(u.axis == "count" and "below noise" in u.description for u in diag.unexplained), diag.unexplained
    assert all(u.p_value < 0.01 for u in diag.unexplained)
    tried = {e.name: e for e in diag.effects}
    assert tried["harmonic"].verdict in ("rejected", "raised chi-square")  # significant, tried, refused


@pytest.mark.slow
def test_row_gain_pattern_is_named_pixel_noise():
    # per-row noise variance is what pixel_noise models: named alone, the two row classes found with their factors
    scan, _ = row_gain_scan()
    diag = diagnose(scan, C.defaults())
    assert [e.name for e in diag.effects if e.detected] == ["pixel_noise"], [(e.name, e.verdict) for e in diag.effects]
    rows = np.arange(scan.shape[1])
    high = rows // 4 % 2 == 0
    lit = np.isfinite(diag.before.pixel)
    f = diag.pixel_noise
    # factors relative to the regular class, whichever of the two bands it is
    ratio = np.median(f[high[:, None] & lit]) / np.median(f[~high[:, None] & lit])
    assert ratio == pytest.approx(1.3 / 0.7, rel=0.05)
    assert diag.unexplained == [], diag.unexplained


@pytest.mark.slow
def test_base_none_rediscovers_the_papers_model():
    scan, _ = S.simulate(sim_config(**{"simulate.seed": 3}))
    diag = diagnose(scan, C.defaults(), base="none")
    assert diag.base_model == []
    assert sorted(e.name for e in diag.effects if e.detected) == sorted(["phase_offset", "tilt", "visibility_loss"])


def test_unidentifiable_effects_are_never_detected():
    # stepping with step errors only: per-frame visibility is not identifiable (paper Sec. II-F), and with a
    # uniform flat field an additive background is taken up by the transmission. Per-step dose, beside the step
    # errors in the model, shares two directions with them (a dose and a phase pattern following the first
    # harmonic of the step phase): it is tested in the rest of its directions, and not named
    scan, _ = S.simulate(sim_config(**{"simulate.geometry": "stepping", "effects.visibility_loss": 0.0,
                                        "effects.tilt": 0.0, "effects.phase_offset": 0.1}))
    diag = diagnose(scan, C.load([], ["vibration.tilt=false"]))
    verdict = {e.name: e for e in diag.effects}
    for name in ("visibility_loss", "background"):
        assert not verdict[name].identifiable and not verdict[name].detected, name
    steps = scan.shape[0]
    assert verdict["dose"].shared == 2 and verdict["dose"].dof == steps - 1 - 2 and not verdict["dose"].detected
    assert verdict["dose"].identifiable and verdict["dose"].excess == 0
    assert not any(e.detected for e in diag.effects)


@pytest.mark.slow
def test_report_files_follow_the_contract(tmp_path):
    scan, _, cfg = concealed("dose")
    diag = diagnose(scan, cfg)
    written = write_report(diag, tmp_path)
    doc = json.loads((tmp_path / "diagnosis.json").read_text())
    assert doc["format"] == "dfxcorr-diagnosis" and doc["format_version"] == 4
    assert doc["unexplained"] == []
    assert doc["base_model"] == ["phase_offset", "tilt", "visibility_loss"]
    assert set(doc["reduced_chi2"]) == {"initial", "final"}
    first = doc["effects"][0]
    assert first["name"] == "dose" and first["detected"] and first["identifiable"] and first["verdict"] == "added"
    # a per-frame dose is the whole detector's: the halves of its columns agree within their errors
    assert first["replication"]["replicated"] and len(first["replication"]["halves"]) == 2
    for key in ("statistic", "dof", "p_value", "delta_chi2", "reduced_chi2_after", "where", "estimate"):
        assert key in first
    stats_ = [e["statistic"] for e in doc["effects"][1:]]
    assert stats_ == sorted(stats_, reverse=True)
    assert doc["final_model"][-1] == "dose"
    for png in ("residuals.png", "signatures.png", "effect-dose.png"):
        assert (tmp_path / png).read_bytes()[:4] == b"\x89PNG"
    assert len(written) == 5
    # the dose picture shows the per-frame estimate of the final model, and the residual map after it is flat
    change, = diag.changes
    np.testing.assert_array_equal(change["per_frame"], diag.params["dose"])
    assert np.nanmean(change["after"]["residual"]) < np.nanmean(change["before"]["residual"])
    report = (tmp_path / "report.md").read_text()
    assert "Criterion" in report and "--set vibration.dose=true" in report and "## Unexplained" in report
    assert "| replicated |" in report and "| yes (p " in report
    assert "![adding dose](effect-dose.png)" in report
    # a second report into the same folder: refused, or replaced with --overwrite (every picture included)
    from dfxcorr.errors import OutputExistsError
    with pytest.raises(OutputExistsError):
        write_report(diag, tmp_path)
    assert write_report(diag, tmp_path, overwrite=True) == written


@pytest.mark.shared
@pytest.mark.slow
@pytest.mark.parametrize("order", ["mean-first", "noise-first"])
def test_real_recording_is_diagnosed(tmp_path, order):
    """The shared 11-step recording, whichever kind of candidate a round tries first: pixel_noise alone."""
    diag = diagnose(real_ipp_scan(tmp_path), C.load([], [f"diagnose.order={order}"]))
    assert [e.name for e in diag.effects if e.detected] == ["pixel_noise"]
    verdict = {e.name: e for e in diag.effects}
    assert not verdict["visibility_loss"].identifiable and not verdict["visibility_loss"].detected
    # the recording's noise is below Poisson mostly in the detector's module-boundary pixels (whole columns
    # and rows): a global gain explains little of that structure, so either the final model describes the
    # data to within the noise or the structure is located, by column and row, as unexplained
    axes = {u.axis for u in diag.unexplained}
    assert abs(diag.final_chi2 - 1) < 0.01 or {"column", "row"} <= axes, (diag.final_chi2, diag.unexplained)
    assert not any(e.detected for e in diag.effects if e.name not in ("detector_gain", "pixel_noise"))


@pytest.mark.slow
def test_unidentifiable_effect_that_explains_the_misfit_stops_the_naming():
    # phase stepping with a per-step visibility loss: the configured model drops visibility_loss (not
    # identifiable, paper Sec. II-F); proxies (sample_motion, curvature, pixel_noise) must not be named for it
    sets = ["simulate.geometry=stepping", "simulate.steps=5", "simulate.steps_per_period=5", "simulate.pixel_mm=2.4",
            "simulate.height_mm=153.6", "simulate.width_mm=460.8", "simulate.seed=5", "effects.visibility_loss=0.2"]
    scan, _ = S.simulate(C.load([], sets, schema=S.SCHEMA))
    diag = diagnose(scan, C.defaults())
    assert not any(e.detected for e in diag.effects), [(e.name, e.p_value) for e in diag.effects if e.detected]
    vis = next(e for e in diag.effects if e.name == "visibility_loss")
    assert not vis.identifiable and vis.blind.explains_misfit
    assert vis.blind.reduced_chi2_with == pytest.approx(1.0, abs=0.05)
    assert diag.final_chi2 > 1.2
    # the misfit it leaves is still located
    assert diag.unexplained


@pytest.mark.slow
@pytest.mark.parametrize("order", ["mean-first", "noise-first"])
def test_a_flat_panel_in_detector_units_with_step_errors_names_the_steps_and_the_noise_model_only(order):
    """5 phase steps, gain 0.5 and read noise 25 unstated, per-step phase errors, --base none: the step errors and
    the noise model, nothing else; a wrong noise model (reduced chi-square ~200 before) must not make the step
    errors look like they make things worse, nor let a proxy in; and the same whichever kind of candidate a round
    tries first (a noise model decided first is settled again in the mean effects' trials)."""
    scan, truth = S.simulate(sim_config(**{**S.FLAT_PANEL_STEPPING, "simulate.seed": 11}))
    diag = diagnose(scan, C.load([], [f"diagnose.order={order}"]), base="none")
    found = {e.name: e for e in diag.effects if e.detected}
    assert set(found) == {"phase_offset", "electronic_noise", "detector_gain"}, list(found)
    assert diag.initial_chi2 > 50 and diag.final_chi2 == pytest.approx(1.0, abs=0.06)
    assert found["detector_gain"].values["gain"] == pytest.approx(0.5, rel=0.1)
    assert found["electronic_noise"].values["value"] == pytest.approx(25.0, rel=0.1)
    assert diag.unexplained == []


@pytest.mark.slow
def test_a_detector_artefact_in_no_catalogue_is_located_not_named():
    """Line noise of a flat panel (one offset per frame and row, its read noise stated): no catalogue effect
    explains it; the report locates it along the (frame, row) blocks."""
    key, amplitude, _, extra, sets = S.UNCATALOGUED["line_noise"]
    scan, _ = S.simulate(sim_config(**{**extra, key: amplitude, "simulate.seed": 11}))
    diag = diagnose(scan, C.load([], sets))
    assert not [e.name for e in diag.effects if e.detected]
    assert "frame_row" in {u.axis for u in diag.unexplained}


@pytest.mark.slow
@pytest.mark.parametrize(("effect", "mimics", "axis"), [("detector_nonlinearity", "harmonic", "count"),
                                                       ("ghost", "dose", "row")])
def test_a_detector_effect_that_mimics_a_catalogue_effect_is_located_not_named(effect, mimics, axis):
    """A 2 % non-linearity makes a real second harmonic, and a 1 % ghost of the previous frame a change of dose;
    neither has one size across the recording (along the count, along the rows): the catalogue effect is refused as
    a proxy and its signature reported unexplained there, at most the noise model is named on the way."""
    key, amplitude, _, extra, sets = S.UNCATALOGUED[effect]
    scan, _ = S.simulate(sim_config(**{**extra, key: amplitude, "simulate.seed": 11}))
    diag = diagnose(scan, C.load([], sets))
    assert {e.name for e in diag.effects if e.detected} <= {"detector_gain", "electronic_noise", "pixel_noise"}
    proxy = [u for u in diag.unexplained if mimics in u.description]
    assert proxy and proxy[0].axis == axis and proxy[0].p_value < 0.01, diag.unexplained


@pytest.mark.slow
def test_a_true_harmonic_has_one_size_across_the_count_and_the_rows():
    """The consistency test does not refuse a real catalogue effect (harmonic 0.02: its sizes on strata of row
    spanned 0.37, significant at p 0.01 but within diagnose.proxy_spread): named, nothing left."""
    scan, truth = S.simulate(sim_config(**{"effects.harmonic": 0.02, "simulate.seed": 11}))
    diag = diagnose(scan, C.defaults())
    assert [e.name for e in diag.effects if e.detected] == ["harmonic"]
    assert diag.unexplained == []


def test_held_band_is_every_column_or_a_centred_band():
    np.testing.assert_array_equal(held_band(100, 1000, most=1e6), np.arange(100))
    band = held_band(100, 1000, most=30_000)
    np.testing.assert_array_equal(band, np.arange(35, 65))
    assert held_band(100, 10 ** 9, most=1e4).size == 4  # never fewer columns than a test needs


@pytest.mark.slow
def test_a_scan_larger_than_the_held_samples_is_tested_on_a_band_and_fitted_over_the_detector():
    # the concealed step errors are still named first with the per-pixel tests on a band of a third of the columns;
    # the pixels outside it are tested by nothing (NaN in the residual map), the fit still sees every part
    scan, truth, cfg = concealed("phase_offset")
    prep = prepare(scan, cfg)
    W, per_column = scan.shape[2], prep.store.samples_per_column()
    most = per_column * W / 3
    diag = diagnose(prep, {**cfg, "diagnose": {**cfg["diagnose"], "max_held_samples": most}})
    assert [e.name for e in diag.effects if e.detected][0] == "phase_offset"
    tested = np.isfinite(diag.after.pixel).any(axis=0)
    band = held_band(W, per_column, most=most)
    assert band.size == W // 3 and diag.tested_columns == (band[0], band[-1] + 1)
    assert diag.to_json()["tested_columns"] == [band[0], band[-1] + 1] and f"{band[0]}-{band[-1]}" in diag.band
    assert not tested[:band[0]].any() and not tested[band[-1] + 1:].any() and tested[band].mean() > 0.5


@pytest.mark.slow
def test_a_band_between_the_fits_columns_is_still_tested():
    # a band narrower than the fit's column step (a full-resolution clinical scan's 93 columns against the fit's
    # every 434th) holds none of the fit's columns: its count bins come from every column of the fit
    scan, _ = S.simulate(sim_config(**{"simulate.seed": 3}))
    cfg = C.defaults()
    prep = prepare(scan, cfg)
    W, per_column = scan.shape[2], prep.store.samples_per_column()
    band = held_band(W, per_column, most=4 * per_column)
    assert not np.isin(band, subsample_columns(W, 30)).any()
    diag = diagnose(prep, {**cfg, "diagnose": {**cfg["diagnose"], "max_held_samples": 4 * per_column,
                                               "subsample": 30}})
    assert diag.tested_columns == (band[0], band[-1] + 1)
    assert np.isfinite(diag.after.pixel[:, band]).all(axis=1).mean() > 0.5


@pytest.mark.slow
def test_a_gross_misfit_of_the_mean_is_not_absorbed_by_the_noise_model():
    """Frames in reversed order: the mean model is off everywhere (reduced chi-square ~1e5, the standardized
    residuals' kurtosis 37). Any misfit is matched by a variance large enough, so no noise-model effect may be
    named for it; the misfit is located and called gross, and nothing is recommended."""
    from dfxcorr.analysis.report import GROSS, _markdown, reconstruct_settings

    scan, _ = S.simulate(sim_config(**{"simulate.seed": 7}))
    scan = replace(scan, data=np.asarray(scan.data)[::-1].copy())
    diag = diagnose(scan, C.defaults())
    assert not [e.name for e in diag.effects if e.detected], [(e.name, e.verdict) for e in diag.effects]
    assert diag.final_chi2 > GROSS and diag.unexplained
    assert reconstruct_settings(diag) == [] and "**The misfit is gross**" in _markdown(diag)
