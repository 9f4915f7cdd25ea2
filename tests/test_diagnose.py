"""The diagnosis, proven on concealed effects: each is named first and the fit returns to the noise."""
import json

import numpy as np
import pytest

from dfxcorr import config as C
from dfxcorr.sim import simulate as S
from dfxcorr.analysis.diagnose import diagnose, write_report

from conftest import shared_path, sim_config


def concealed(effect, *, seed=11, amplitude=None):
    key, realistic, _, extra, conceal = S.CONCEALED[effect]
    scan, truth = S.simulate(sim_config(**{**extra, key: realistic if amplitude is None else amplitude,
                                           "simulate.seed": seed}))
    return scan, truth, C.load([], conceal)


@pytest.mark.parametrize("effect", list(S.CONCEALED))
def test_concealed_effect_is_named_first_and_the_fit_recovers(effect):
    scan, truth, cfg = concealed(effect)
    diag = diagnose(scan, cfg)
    found = [e.name for e in diag.effects if e.detected]
    assert found and found[0] == effect, [(e.name, e.statistic, e.dof) for e in diag.effects]
    # a few percent above 1 remain: the parameter noise of a fit on every 4th column
    assert diag.final_chi2 == pytest.approx(1.0, abs=0.05)
    assert diag.initial_chi2 > diag.final_chi2
    if effect == "detector_gain":
        assert diag.effects[0].extra["gain"] == pytest.approx(2.0, rel=0.03)
    if effect == "sample_motion":
        region = truth["motion_mask"] & (truth["image_transmission"] > 0.01)
        assert diag.motion_mask[region].mean() > 0.7 and diag.motion_mask[~truth["motion_mask"]].mean() < 0.01


def test_clean_scans_raise_no_alarm():
    # seeds of the frame-by-frame simulator (each frame draws its noise from its own stream)
    for seed in (22, 23):
        scan, _ = S.simulate(sim_config(**{"simulate.seed": seed}))
        diag = diagnose(scan, C.defaults())
        assert not any(e.detected for e in diag.effects), [(e.name, e.p_value) for e in diag.effects]
        assert diag.final_chi2 == pytest.approx(1.0, abs=0.03)


def test_base_none_rediscovers_the_papers_model():
    scan, _ = S.simulate(sim_config(**{"simulate.seed": 3}))
    diag = diagnose(scan, C.defaults(), base="none")
    assert diag.base_model == []
    assert sorted(e.name for e in diag.effects if e.detected) == sorted(["phase_offset", "tilt", "visibility_loss"])


def test_unidentifiable_effects_are_never_detected():
    # stepping with step errors only: per-frame visibility is not identifiable (paper Sec. II-F), nor per-step
    # dose where every pixel is modulated, and with a uniform flat field an additive background is taken
    # up by the transmission
    scan, _ = S.simulate(sim_config(**{"simulate.geometry": "stepping", "effects.visibility_loss": 0.0,
                                        "effects.tilt": 0.0, "effects.phase_offset": 0.1}))
    diag = diagnose(scan, C.load([], ["vibration.tilt=false"]))
    verdict = {e.name: e for e in diag.effects}
    for name in ("visibility_loss", "dose", "background"):
        assert not verdict[name].identifiable and not verdict[name].detected, name
    assert not any(e.detected for e in diag.effects)


def test_report_files_follow_the_contract(tmp_path):
    scan, _, cfg = concealed("dose")
    diag = diagnose(scan, cfg)
    written = write_report(diag, tmp_path)
    doc = json.loads((tmp_path / "diagnosis.json").read_text())
    assert doc["format"] == "dfxcorr-diagnosis" and doc["format_version"] == 1
    assert doc["base_model"] == ["phase_offset", "tilt", "visibility_loss"]
    assert set(doc["reduced_chi2"]) == {"initial", "final"}
    first = doc["effects"][0]
    assert first["name"] == "dose" and first["detected"] and first["identifiable"]
    for key in ("statistic", "dof", "p_value", "delta_chi2", "reduced_chi2_after", "where", "estimate"):
        assert key in first
    stats_ = [e["statistic"] for e in doc["effects"][1:]]
    assert stats_ == sorted(stats_, reverse=True)
    assert doc["final_model"][-1] == "dose"
    assert (tmp_path / "residuals.png").read_bytes()[:4] == b"\x89PNG" and len(written) == 3
    report = (tmp_path / "report.md").read_text()
    assert "Criterion" in report and "--set vibration.dose=true" in report


@pytest.mark.shared
def test_real_recording_is_diagnosed(tmp_path):
    from dfxcorr.importer import import_stepping

    folder = shared_path("real", "tum-ipp-stepping")
    import_stepping(tmp_path / "ipp.h5", sample=str(folder / "data_stepping_*.npy"),
                    reference=str(folder / "flat_stepping_*.npy"), steps_per_period=11)
    diag = diagnose(tmp_path / "ipp.h5", C.defaults())
    verdict = {e.name: e for e in diag.effects}
    assert not verdict["visibility_loss"].identifiable and not verdict["visibility_loss"].detected
    # whatever is found, the final model describes the data to within the noise (the real recording's noise
    # is below Poisson, so modelling it moves the reduced chi-square up to 1)
    assert abs(diag.final_chi2 - 1) <= abs(diag.initial_chi2 - 1) and abs(diag.final_chi2 - 1) < 0.01
