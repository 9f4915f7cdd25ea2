"""The report renders every kind of verdict, and recommends what the diagnosis found and ran with."""
import json

import numpy as np
import pytest

from dfxcorr import config as C
from dfxcorr.analysis.loop import Blind, Rejection
from dfxcorr.analysis.replication import Replication
from dfxcorr.analysis.report import Diagnosis, EffectReport, _markdown, reconstruct_settings
from dfxcorr.effects import REGISTRY
from dfxcorr.effects.base import Consistency, Finding, Hypothesis, Option, Unexplained
from dfxcorr.observations import Noise

SHAPE = (6, 4, 8)


def _diagnosis(effects, *, cfg=None, final_model=("phase_offset", "tilt", "visibility_loss", "dose")):
    J, H, W = SHAPE
    hyp = Hypothesis(tuple(final_model), Noise(1.0, 0.0), np.zeros((H, W), bool), np.zeros(J))
    return Diagnosis(scan="scan.h5", base_model=["phase_offset", "tilt", "visibility_loss"], initial_chi2=3.0,
                     final_chi2=1.01, effects=effects, final_model=list(final_model), before=None, after=None,
                     params={}, criterion="the rule", rounds=[], signatures=[], shape=SHAPE, final=hyp, start=hyp,
                     unexplained=[Unexplained("count", 40.0, 6, 1e-6, "dimmest pixels", "a misfit")],
                     cfg=C.defaults() if cfg is None else cfg, registry=REGISTRY)


def _every_verdict() -> list[EffectReport]:
    dose = Finding("all frames", "std 2 %", {"value": 0.02}, options=(Option("vibration.dose", "true"),))
    agree = Replication(({"part": "columns 0-3", "estimate": 1.0, "se": 0.1},), 0.5, 1, 0.48, True, "agree")
    differ = Replication((), 30.0, 1, 1e-8, False, "the halves differ")
    odd = Consistency(50.0, 5, 1e-9, float(np.log(1e-9)), "row", (0.1, 0.2, 3.0, 0.1, 0.1, 0.1))
    return [
        EffectReport("dose", True, True, 900.0, 5, 0.0, "added", delta_chi2=880.0, reduced_chi2_after=1.01,
                     finding=dose, replication=agree, alternatives=("phase_offset",),
                     alternative_estimates={"phase_offset": "std 0.01 rad"}),
        EffectReport("phase_offset", False, True, 880.0, 5, 0.0, "alternative", alternatives=("dose",)),
        EffectReport("curvature", True, True, 90.0, 5, 1e-12, "added", delta_chi2=60.0, reduced_chi2_after=1.0,
                     finding=Finding("few frames", "std 0.1 rad", options=(Option("vibration.curvature", "true"),)),
                     replication=differ),
        EffectReport("harmonic", False, True, 50.0, 2, 1e-10, "rejected", rejection=Rejection(None, False, 1.2)),
        EffectReport("reference_offset", False, True, 40.0, 1, 1e-9, "raised chi-square",
                     rejection=Rejection(None, True, 1.004)),
        EffectReport("background", False, True, 30.0, 3, 1e-6, "proxy", refused=odd),
        EffectReport("visibility_tilt", False, False, 20.0, 8, 0.01, "not identifiable", excess=4),
        EffectReport("visibility_loss", False, False, 300.0, 4, 0.0, "explains, not identifiable",
                     blind=Blind(True, None, 1.02, stopped=True)),
        EffectReport("detector_gain", False, True, 12.0, 1, 1e-3, "not material"),
        EffectReport("scatter", False, True, 0.5, 1, 0.5, "not significant"),
        EffectReport("tilt", False, True, 70.0, 4, 1e-14, "explained by another", explained_by="dose"),
        EffectReport("electronic_noise", False, True, 900.0, 1, 0.0, "held: gross misfit"),
    ]


def test_every_verdict_kind_renders_in_the_report_and_the_json():
    diag = _diagnosis(_every_verdict())
    text = _markdown(diag)
    doc = json.loads(json.dumps(diag.to_json(), default=float))
    rows = {line.split("|")[1].strip(): line for line in text.splitlines() if line.startswith("| ")}
    assert "none of the signatures' excess" in rows["harmonic"]
    assert "raises the reduced chi-square to 1.0040" in rows["reference_offset"]
    assert "a proxy" in rows["background"] and "pixels of other rows" in rows["background"]
    assert "nothing else is named in its place" in rows["visibility_loss"]
    assert "does not replicate" in rows["curvature"] and "| no (p 1e-08) |" in rows["curvature"]
    assert "or phase_offset" in rows["dose"] and "| yes (p 0.48) |" in rows["dose"]
    assert "cannot tell them apart" in rows["phase_offset"]
    by_name = {e["name"]: e for e in doc["effects"]}
    assert [e["verdict"] for e in doc["effects"]] == [e.verdict for e in diag.effects]
    assert by_name["harmonic"]["explained_share"] is None and by_name["reference_offset"]["reduced_chi2_with"] > 1
    assert by_name["background"]["refused_as_proxy"] == "row"
    assert by_name["dose"]["alternatives"] == ["phase_offset"] and by_name["dose"]["replication"]["replicated"]
    assert by_name["visibility_loss"]["stopped"] and by_name["visibility_tilt"]["excess_null_directions"] == 4
    assert doc["format_version"] == 4 and doc["unexplained"][0]["axis"] == "count"
    # a candidate the data tell from its partner names it, not as an alternative
    assert "nothing beyond dose" in rows["tilt"] and by_name["tilt"]["explained_by"] == "dose"
    assert "alternatives" not in by_name["tilt"] and "grossly off" in rows["electronic_noise"]


def test_a_finding_that_does_not_replicate_is_not_recommended():
    sets = reconstruct_settings(_diagnosis(_every_verdict()))
    assert "vibration.dose=true" in sets and "vibration.curvature=true" not in sets


def test_the_recommended_command_keeps_the_settings_the_diagnosis_ran_with(tmp_path):
    cfg = C.load([], ["vibration.curvature=true", "load.electronic=625", f"load.pixel_noise={tmp_path / 'f.tif'}",
                      "diagnose.alpha=0.001"])
    gain = Finding("all pixels", "g = 2", {"gain": 2.0}, options=(Option("load.gain", "2"),))
    diag = _diagnosis([EffectReport("detector_gain", True, True, 100.0, 1, 0.0, "added", finding=gain)], cfg=cfg,
                      final_model=("phase_offset", "tilt", "visibility_loss", "curvature"))
    sets = reconstruct_settings(diag)
    assert {"vibration.curvature=true", "load.electronic=625", f"load.pixel_noise={tmp_path / 'f.tif'}",
            "load.gain=2"} <= set(sets)
    assert not any(s.startswith("diagnose.") for s in sets)
    # what it recommends reproduces the configuration it ran with, the finding on top
    assert C.load([], sets)["load"] == {**cfg["load"], "gain": 2.0}


@pytest.mark.parametrize("model", [("phase_offset", "tilt"), ("phase_offset", "tilt", "visibility_loss")])
def test_the_papers_effects_the_final_model_lacks_are_switched_off(model):
    sets = reconstruct_settings(_diagnosis([], final_model=model))
    assert ("vibration.visibility=false" in sets) is ("visibility_loss" not in model)
