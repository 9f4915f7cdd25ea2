"""Configuration: schema, validation, --set, nearest-name suggestions, commented defaults."""

import pytest
import yaml

from dfxcorr import config as C
from dfxcorr.analysis import compare
from dfxcorr.estimators import ESTIMATORS
from dfxcorr.sim import simulate as S

from conftest import ROOT


def test_defaults_validate_and_round_trip():
    cfg = C.defaults()
    assert C.merge(C.defaults(), cfg) == cfg
    assert C.load([], []) == cfg
    assert yaml.safe_load(C.dump(cfg)) == cfg


def test_shipped_default_yaml_is_the_schema():
    """configs/default.yaml is generated from the schema; this catches drift."""
    assert (ROOT / "configs" / "default.yaml").read_text() == C.commented_defaults() + "\n"
    assert yaml.safe_load((ROOT / "configs" / "default.yaml").read_text()) == C.defaults()


def test_commented_defaults_parse_back_for_both_schemas():
    assert yaml.safe_load(C.commented_defaults()) == C.defaults()
    assert yaml.safe_load(C.commented_defaults(S.SCHEMA)) == C.defaults(S.SCHEMA)


def test_set_overrides_and_files_layer(tmp_path):
    f = tmp_path / "a.yaml"
    f.write_text("fit:\n  subsample: 10\nvibration:\n  visibility: false\n")
    cfg = C.load([f], ["fit.subsample=5", "mask.threshold=3.5"])
    assert cfg["fit"]["subsample"] == 5 and cfg["mask"]["threshold"] == 3.5
    assert not cfg["vibration"]["visibility"]
    assert C.effects_of(cfg) == ("phase_offset", "tilt")


@pytest.mark.parametrize("item,message", [
    ("fit.subsampel=3", "did you mean 'subsample'"),
    ("vibraton.tilt=false", "did you mean 'vibration'"),
    ("fit.subsample=0", "fit.subsample must be auto or an integer in"),
    ("fit.subsample=2.5", "fit.subsample must be int"),
    ("vibration.tilt=3", "vibration.tilt must be bool"),
    ("fit.method=mll", "fit.method must be one of"),
    ("fit.subsample", "expected section.key=value"),
    ("mask.enabled=null", "must not be null"),
])
def test_bad_values_are_named(item, message):
    with pytest.raises(C.ConfigError, match=message):
        C.load([], [item])


def test_bad_file_is_named(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("fit:\n  gtoll: 1\n")
    with pytest.raises(C.ConfigError, match=r"bad.yaml: unknown key fit.gtoll; did you mean 'gtol'"):
        C.load([f])
    f.write_text("fit: [1, 2\n")
    with pytest.raises(C.ConfigError, match="not valid YAML"):
        C.load([f])


def test_one_list_of_estimators():

    assert C.SCHEMA["fit"]["method"].choices == C.METHODS
    assert set(ESTIMATORS) | {"none"} == set(C.METHODS) == set(compare.METHODS)


@pytest.mark.parametrize("text, value", [("1e-5", 1e-5), ("2E3", 2000.0), ("1.5e-3", 1.5e-3), ("1_000", 1000)])
def test_numbers_with_an_exponent_are_numbers(text, value):
    """YAML 1.1 would read 1e-5 as a string and --set fit.gtol=1e-5 would be refused."""
    assert C.load([], [f"fit.gtol={text}"])["fit"]["gtol"] == value
