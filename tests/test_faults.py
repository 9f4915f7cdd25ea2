"""Detector faults as data: saturated samples, empty and repeated frames are left out of the fit and the
images with a warning, the result stays within noise of the fault-free twin, ``check`` reports them and
``diagnose`` names no catalogue effect for them."""
from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner

from dfxcorr import config as C
from dfxcorr import io, pipeline
from dfxcorr.analysis.evaluate import frames_lighting, gauge_median
from dfxcorr.cli import main
from dfxcorr.faults import find_faults, saturation_level
from dfxcorr.sim import simulate as S

from conftest import sim_config

#: Lit samples above this quantile are clipped: 8 %, as where a clinical scan's direct beam saturates the panel.
SATURATED_SHARE = 0.08
DROPPED = 50


def errors(result, truth, scan, skip=()) -> dict:
    """RMS errors of the per-frame estimates over the well-lit frames (but ``skip``), median gauge."""
    good = frames_lighting(scan.position, scan.active_rows, scan.shape[1])
    good[list(skip)] = False
    out = {}
    for name, key, scale in (("phase_offset", "vib_phase_offset", False), ("tilt", "vib_tilt", False),
                             ("visibility_loss", "vib_visibility", True)):
        est = gauge_median(result.params[name][:, 0], good, scale=scale)
        tru = gauge_median(truth[key], good, scale=scale)
        out[name] = float(np.sqrt(np.mean((est - tru)[good] ** 2)))
    return out


@pytest.fixture(scope="module")
def twin():
    """A small simulated scan, its truth and the errors of its fault-free reconstruction."""
    scan, truth = S.simulate(sim_config())
    cfg = C.load([], ["fit.subsample=3"])
    return scan, truth, cfg, errors(pipeline.reconstruct(scan, cfg), truth, scan)


def clipped(scan):
    data = np.asarray(scan.data)
    level = int(np.quantile(data[data > 0], 1 - SATURATED_SHARE))
    return replace(scan, data=np.minimum(data, level).astype(data.dtype)), level


@pytest.mark.slow
def test_saturation_is_left_out_within_noise_of_the_twin(twin, caplog):
    scan, truth, cfg, base = twin
    sat, level = clipped(scan)
    with caplog.at_level(logging.WARNING, logger="dfxcorr"):
        result = pipeline.reconstruct(sat, C.merge(cfg, {"load": {"saturation": level}}))
    assert any("saturated samples" in r.getMessage() and f">= {level}" in r.getMessage() for r in caplog.records)
    ratios = {k: v / base[k] for k, v in errors(result, truth, scan).items()}
    assert all(r < 1.5 for r in ratios.values()), ratios  # measured 1.28, 1.23, 1.46
    assert result.reduced_chi2 == pytest.approx(1.0, abs=0.03)
    # fitted as if they were counts, the clipped samples take every estimate 2 to 3 times further off
    blind = pipeline.reconstruct(sat, cfg)
    assert blind.reduced_chi2 > 3


@pytest.mark.parametrize("kind", ["zeros", *(pytest.param(k, marks=pytest.mark.slow) for k in ("dark", "read twice"))])
def test_a_bad_frame_is_left_out_within_noise_of_the_twin(twin, caplog, kind):
    scan, truth, cfg, base = twin
    data = np.array(scan.data)
    data[DROPPED] = {"zeros": 0, "dark": 3, "read twice": data[DROPPED - 1]}[kind]
    with caplog.at_level(logging.WARNING, logger="dfxcorr"):
        result = pipeline.reconstruct(replace(scan, data=data), cfg)
    why = "a repeat of frame 49" if kind == "read twice" else "empty"
    assert any(f"{DROPPED} ({why})" in r.getMessage() for r in caplog.records), caplog.text
    ratios = {k: v / base[k] for k, v in errors(result, truth, scan, skip=[DROPPED]).items()}
    assert all(r < 1.5 for r in ratios.values()), ratios  # measured 1.11, 1.10, 0.97
    assert result.reduced_chi2 == pytest.approx(1.0, abs=0.03)


@pytest.mark.slow
def test_half_the_detector_saturated_leaves_the_other_half_fitted(twin):
    scan, truth, cfg, base = twin
    data = np.array(scan.data)
    data[:, :, :51] = 65535  # the direct beam beside the body, at the panel's maximum
    result = pipeline.reconstruct(replace(scan, data=data), cfg)
    # before: the motion mask's threshold fell to 3e-10 and masked every informative pixel, the fit ran 0 iterations
    # and left the estimates at their start; fitted on the unsaturated half they are off by 0.052 / 0.064 rad, against
    # the vibrations' spread of 0.34 / 0.40 rad
    assert result.motion_mask.sum() < 20 and result.fit_mask[:, 51:].sum() > 1000 and len(result.cost) > 0
    err = errors(result, truth, scan)
    assert err["phase_offset"] < 0.1 and err["tilt"] < 0.1, err
    assert np.all(np.isnan(result.transmission[:, :51])) and np.all(np.isfinite(result.transmission[:, 52:]))
    assert result.reduced_chi2 == pytest.approx(1.0, abs=0.03)


def test_the_dtype_maximum_is_saturation_by_default(rng):
    counts = rng.poisson(1000, (6, 4, 5)).astype(np.uint16)
    counts[2, 1, 3] = 65535
    faults = find_faults(((j, np.arange(4), counts[j]) for j in range(6)), shape=(6, 4, 5), dark=np.zeros((4, 5)),
                         level=saturation_level(counts.dtype, None))
    assert faults.level == 65535 and faults.saturated.tolist() == [0, 0, 1, 0, 0, 0] and not faults.bad_frames
    assert saturation_level(np.dtype(np.float32), None) is None


@pytest.mark.slow
def test_check_reports_the_faults(twin, tmp_path):
    scan, *_ = twin
    data = np.array(scan.data)
    data[DROPPED] = 0
    data[30:32, 20:22] = 65535  # lit rows
    io.write_scan(tmp_path / "s.h5", replace(scan, data=data))
    res = CliRunner().invoke(main, ["check", str(tmp_path / "s.h5"), "-o", str(tmp_path / "r.h5")])
    assert res.exit_code == 0, res.output
    line = next(ln for ln in res.stdout.splitlines() if ln.startswith("detector faults"))
    assert "saturated samples (counts >= 65535) in frames 30-31" in line and f"{DROPPED} (empty)" in line
    clean = CliRunner().invoke(main, ["check", str(tmp_path / "s.h5"), "-o", str(tmp_path / "r.h5"), "--set",
                                      "load.saturation=1e9"])
    assert "saturated" not in clean.stdout.split("detector faults")[1].split("\n")[0].replace("no saturated", "")


@pytest.mark.slow
def test_diagnose_names_no_effect_for_saturation(twin):
    from dfxcorr.analysis.diagnose import diagnose

    scan, _, cfg, _ = twin
    sat, level = clipped(scan)
    diag = diagnose(sat, C.merge(C.defaults(), {"load": {"saturation": level}}))
    assert [e.name for e in diag.effects if e.detected] == []
    assert diag.final_chi2 == pytest.approx(1.0, abs=0.05)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["zeros", "read twice"])
def test_diagnose_names_no_effect_for_a_bad_frame(twin, kind):
    from dfxcorr.analysis.diagnose import diagnose

    scan, *_ = twin
    data = np.array(scan.data)
    data[DROPPED] = 0 if kind == "zeros" else data[DROPPED - 1]
    diag = diagnose(replace(scan, data=data), C.defaults())
    assert [e.name for e in diag.effects if e.detected] == []
