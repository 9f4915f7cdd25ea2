"""Findings replicate on disjoint halves of the detector, and the halves of a real recording tell one story."""
from dataclasses import replace

import numpy as np
import pytest

from dfxcorr import config as C
from dfxcorr.analysis.diagnose import diagnose
from dfxcorr.analysis.replication import difference, halves
from dfxcorr.analysis.report import reconstruct_settings
from dfxcorr.effects import REGISTRY
from dfxcorr.effects.base import Estimate
from dfxcorr.sim import simulate as S
from dfxcorr.stats import chi2_tail

from conftest import shared_path, sim_config


def test_the_difference_of_two_estimates_is_chi_square_in_their_errors(rng):
    se = np.full((50, 1), 0.1)
    a = Estimate(rng.normal(0, 1, (50, 1)), se)
    same = Estimate(a.value + rng.normal(0, 0.1 * np.sqrt(2), (50, 1)), se)
    stat, dof = difference(a, same, gauge="none")
    assert dof == 50 and chi2_tail(stat, dof)[0] > 1e-3
    # a per-frame effect defined up to a constant: a shift of one half's estimates is no difference
    stat_shift, dof_shift = difference(a, replace(same, value=same.value + 5.0), gauge="shift")
    assert dof_shift == 49 and stat_shift < stat and chi2_tail(stat_shift, dof_shift)[0] > 1e-3
    assert difference(a, replace(same, value=same.value + 5.0), gauge="none")[0] > 1e4
    # entries without an error (frames one half never sees) are left out
    unseen = replace(same, se=np.where(np.arange(50)[:, None] < 10, np.inf, 0.1))
    assert difference(a, unseen, gauge="none")[1] == 40
    # a scalar: one dof
    assert difference(Estimate(np.asarray(1.0), np.asarray(0.1)), Estimate(np.asarray(1.5), np.asarray(0.1)),
                      gauge="none") == pytest.approx((12.5, 1))


def test_halves_are_columns_and_in_phase_stepping_rows_too():
    assert [(a.label, b.label) for a, b in halves((10, 6, 9), rows=False)] == [("columns 0-3", "columns 4-8")]
    assert len(halves((10, 6, 9), rows=True)) == 2 and len(halves((10, 1, 9), rows=True)) == 1


def _named(diag) -> set[str]:
    """Whole-detector effects a diagnosis names (an alternative counts: the finding is 'one of these')."""
    return {n for e in diag.effects if e.detected and not REGISTRY[e.name].policy.pixelwise
            for n in (e.name, *e.alternatives)}


@pytest.mark.slow
def test_a_dose_that_only_half_the_detector_sees_does_not_replicate():
    """A per-frame dose is the whole detector's: one that only the left half's columns carry is named (its test
    sees it) but its halves disagree, so it stays out of the recommended reconstruction."""
    scan, _ = S.simulate(sim_config(**{"simulate.seed": 4}))
    J, H, W = scan.shape
    factor = np.ones((J, 1, W))
    factor[:, :, : W // 2] = 1 + 0.03 * np.random.default_rng(4).standard_normal((J, 1, 1))
    scan = replace(scan, data=np.round(np.asarray(scan.data) * factor).astype(np.asarray(scan.data).dtype))
    diag = diagnose(scan, C.defaults())
    dose = next(e for e in diag.effects if e.name == "dose")
    assert dose.detected and dose.replication is not None and dose.replication.replicated is False, dose
    assert dose.replication.p_value < 1e-6 and "does not replicate" in dose.verdict_text()
    assert "vibration.dose=true" not in reconstruct_settings(diag)


def _crop(tmp_path, name, files, columns, steps):
    """Import a shared stepping series with only some detector columns."""
    from dfxcorr.importer import import_stepping

    out = tmp_path / name
    out.mkdir()
    for kind, paths in files.items():
        for i, path in enumerate(paths):
            np.save(out / f"{kind}_{i:04d}.npy", np.load(path)[..., columns])
    import_stepping(out / "scan.h5", sample=str(out / "sample_*.npy"), reference=str(out / "flat_*.npy"),
                    steps_per_period=steps)
    return out / "scan.h5"


def _series(folder, sample, flat):
    return {"sample": sorted(folder.glob(sample)), "flat": sorted(folder.glob(flat))}


@pytest.mark.shared
@pytest.mark.slow
@pytest.mark.parametrize("recording", ["tum-ipp-stepping", "psi-microspheres"])
def test_no_half_of_a_real_recording_names_what_the_whole_does_not(tmp_path, recording):
    """Each half of the detector may lack the power to name an effect, but may not name a whole-detector one
    that the whole does not; and the whole's findings agree with themselves on its halves."""
    folder = shared_path("real", recording)
    if recording == "tum-ipp-stepping":
        files, steps, width = _series(folder, "data_stepping_*.npy", "flat_stepping_*.npy"), 11, 487
    else:
        # one pair of the series, its 19 steps as frames
        files, steps, width = {"sample": [folder / "sample_0.npy"], "flat": [folder / "flat_0.npy"]}, 19, 1280
    cfg = C.defaults()
    whole = diagnose(_crop(tmp_path, "whole", files, slice(None), steps), cfg)
    named = _named(whole)
    for side, columns in (("left", slice(0, width // 2)), ("right", slice(width // 2, None))):
        half = diagnose(_crop(tmp_path, side, files, columns, steps), cfg)
        assert _named(half) <= named, (side, _named(half), named)
    for e in whole.effects:
        if e.detected and e.replication is not None and e.replication.replicated is not None:
            assert e.replication.replicated, (e.name, e.replication.why)
