"""Confounded candidates are decided together: per-step dose and phase errors in phase stepping.

Each alone is identifiable (4 dof in 5 steps); a dose pattern following the first harmonic of the step phase and a
phase pattern following it are two directions they share, which the images absorb when both are free. The
decision rests on what the data identify of each beyond the other, never on which explains a little more.
"""
from dataclasses import replace

import numpy as np
import pytest

from dfxcorr import config as C
from dfxcorr.analysis.diagnose import diagnose
from dfxcorr.sim import simulate as S

from conftest import sim_config

STEPPING = {"simulate.geometry": "stepping", "simulate.steps": 5, "simulate.steps_per_period": 5,
            "effects.tilt": 0.0, "effects.visibility_loss": 0.0, "simulate.seed": 21}


def _found(diag) -> dict[str, tuple[str, ...]]:
    return {e.name: e.alternatives for e in diag.effects if e.detected}


@pytest.mark.parametrize(("effects", "named"), [
    pytest.param({"effects.dose": 0.02, "effects.phase_offset": 0.0}, {"dose": ()}, marks=pytest.mark.slow),
    pytest.param({"effects.dose": 0.0, "effects.phase_offset": 0.05}, {"phase_offset": ()}, marks=pytest.mark.slow),
    pytest.param({"effects.dose": 0.02, "effects.phase_offset": 0.05}, {"dose": (), "phase_offset": ()},
                 marks=pytest.mark.slow),
])
def test_dose_and_phase_errors_are_told_apart_where_the_data_do(effects, named):
    scan, _ = S.simulate(sim_config(**{**STEPPING, **effects}))
    diag = diagnose(scan, C.defaults(), base="none")
    assert _found(diag) == named, [(e.name, e.verdict) for e in diag.effects]
    assert diag.final_chi2 == pytest.approx(1.0, abs=0.03)
    # each finding holds on the halves of the detector (or, fitted with a partner, is not compared)
    assert all(e.replication is not None and e.replication.replicated is not False
               for e in diag.effects if e.detected), [(e.name, e.replication) for e in diag.effects if e.detected]
    assert not [u for u in diag.unexplained if u.axis in ("frame", "phase")], diag.unexplained


@pytest.mark.slow
def test_a_dose_the_phase_errors_explain_as_well_is_named_with_them():
    """A dose that follows the first harmonic of the step phase is what phase errors would do: one finding,
    'phase errors or dose', each with its estimate; neither named alone."""
    scan, _ = S.simulate(sim_config(**{**STEPPING, "effects.dose": 0.0, "effects.phase_offset": 0.0}))
    theta = 2 * np.pi * np.arange(5) / 5
    data = np.asarray(scan.data)
    scan = replace(scan, data=np.round(data * (1 + 0.02 * np.cos(theta))[:, None, None]).astype(data.dtype))
    diag = diagnose(scan, C.defaults(), base="none")
    (finding,) = [e for e in diag.effects if e.detected]
    assert {finding.name, *finding.alternatives} == {"dose", "phase_offset"}
    assert set(finding.alternative_estimates) == set(finding.alternatives)
    other = next(e for e in diag.effects if e.name in finding.alternatives)
    assert other.verdict == "alternative" and not other.detected
    assert diag.final_chi2 == pytest.approx(1.0, abs=0.03)
