"""Phase-stepping recordings: import in every format, reference step errors, reconstruction, region of interest."""
import numpy as np
import pytest
import tifffile

from dfxcorr import config as C
from dfxcorr import pipeline
from dfxcorr.importer import import_stepping
from dfxcorr.io import read_scan
from dfxcorr.planning import IdentifiabilityError
from dfxcorr.reference import fit_reference
from dfxcorr.sim import simulate as S

from conftest import shared_path, sim_config

STEPPING = {"simulate.geometry": "stepping", "simulate.steps": 11, "simulate.steps_per_period": 11,
            "simulate.dtype": "uint32", "effects.phase_offset": 0.15, "effects.tilt": 0.0,
            "effects.visibility_loss": 0.0, "effects.dose": 0.02, "simulate.reference_steps": 11,
            "simulate.reference_frames": 10, "simulate.reference_step_errors": 0.1, "simulate.seed": 5}


@pytest.fixture(scope="module")
def stepping():
    return S.simulate(sim_config(**STEPPING))


def write_series(kind, folder, prefix, stack):
    """Write a series [S, H, W] in one of the importer's input layouts; returns the source argument."""
    folder.mkdir(exist_ok=True)
    if kind == "npy-per-step":
        for k, frame in enumerate(stack):
            np.save(folder / f"{prefix}_{k}.npy", frame)
        return str(folder / f"{prefix}_*.npy")
    if kind == "npy-stack":
        np.save(folder / f"{prefix}.npy", stack)
        return str(folder / f"{prefix}.npy")
    if kind == "tiff-per-step":
        for k, frame in enumerate(stack):
            tifffile.imwrite(folder / f"{prefix}_{k}.tif", frame)
        return str(folder / f"{prefix}_*.tif")
    if kind == "tiff-stack":
        tifffile.imwrite(folder / f"{prefix}.tif", stack)
        return str(folder / f"{prefix}.tif")
    stack.astype("<u4").tofile(folder / f"{prefix}.raw")
    return str(folder / f"{prefix}.raw")


@pytest.mark.parametrize("kind", ["npy-per-step", "npy-stack", "tiff-per-step", "tiff-stack", "raw"])
def test_import_round_trip_is_lossless(tmp_path, stepping, kind):
    scan, _ = stepping
    ref = np.rint(scan.reference.data).astype(np.uint32)
    raw = kind == "raw"
    out = import_stepping(tmp_path / "s.h5", sample=write_series(kind, tmp_path / "in", "data", scan.data),
                          reference=write_series(kind, tmp_path / "in", "flat", ref), steps_per_period=11,
                          shape=scan.shape[1:] if raw else None, dtype="<u4" if raw else None)
    back = read_scan(tmp_path / "s.h5")
    assert back.data.dtype == scan.data.dtype and np.array_equal(back.data, scan.data)
    assert np.array_equal(back.reference.data, ref) and out.is_stepping
    np.testing.assert_allclose(back.phase_step, 2 * np.pi * np.arange(11) / 11)


def without_fringes(scan, dose, columns=10):
    """The same recording with no grating in front of the first ``columns`` columns (like a real detector).

    There the counts are the step average, scaled by each step's dose.
    """
    data = scan.data.astype(np.float64)
    flat = scan.reference.data.copy()
    data[:, :, :columns] = np.rint(data[:, :, :columns].mean(axis=0) * (dose / dose.mean())[:, None, None])
    flat[:, :, :columns] = flat[:, :, :columns].mean(axis=0)
    return S.Scan(data=data, position=scan.position, reference=S.SteppingReference(flat, scan.reference.phase_step),
                  phase_step=scan.phase_step)


def test_dose_needs_pixels_without_fringes(stepping):
    scan, _ = stepping
    with pytest.raises(IdentifiabilityError, match="dose is not identifiable"):
        pipeline.reconstruct(scan, C.load([], ["fit.subsample=2", "vibration.dose=true"]))


def test_stepping_reconstruction_recovers_step_errors_dose_and_images(tmp_path, stepping, caplog):
    scan, truth = stepping
    scan = without_fringes(scan, truth["vib_dose"])
    truth = dict(truth)
    truth["image_transmission"] = truth["image_transmission"].copy()
    truth["image_transmission"][:, :10] = np.nan
    with caplog.at_level("INFO", logger="dfxcorr"):
        result = pipeline.reconstruct(scan, C.load([], ["fit.subsample=2", "vibration.dose=true"]))
    # the pilot's steps diverge on a stepping recording: the fit is refused that start and runs its stages
    assert "vibration fit starts at the neutral values" in caplog.text
    assert not result.estimated["visibility_loss"]
    # step errors relative to the median step; the reference's own step errors shift the gauge only
    est = result.params["phase_offset"][:, 0]
    tru = truth["vib_phase_offset"]
    d = (est - np.median(est)) - (tru - np.median(tru))
    d -= np.mean(d)  # a common offset is taken up by the phase image
    assert np.all(np.abs(d) < 5 * result.uncertainty["phase_offset"][:, 0] + 2e-3)
    dose = result.params["dose"][:, 0] / np.median(result.params["dose"][:, 0])
    np.testing.assert_allclose(dose, truth["vib_dose"] / np.median(truth["vib_dose"]), atol=2e-3)
    assert result.reduced_chi2 == pytest.approx(1.0, abs=0.03)
    lit = truth["image_transmission"] > 0.05
    assert np.sqrt(np.nanmean((result.transmission / truth["image_transmission"] - 1)[lit] ** 2)) < 0.01
    assert np.all(np.isnan(result.dark_field[:, :10]))


def test_reference_step_errors_are_estimated(stepping):
    scan, truth = stepping
    nominal = fit_reference(scan.reference, effects=())
    fitted = fit_reference(scan.reference, effects=("phase_offset",))
    est = fitted.params["phase_offset"][:, 0]
    err = (est - np.mean(est)) - (truth["reference_steps"] - 2 * np.pi * np.arange(11) / 11)
    err -= np.mean(err)
    assert np.abs(err).max() < 5e-3
    assert fitted.reduced_chi2["fitted"] < nominal.reduced_chi2["nominal"]
    # the simulated reference averages reference_frames = 10 frames: variance mean / 10, chi2_red 0.1
    assert fitted.reduced_chi2["fitted"] == pytest.approx(0.1, abs=0.005)


def test_visibility_cannot_be_fitted_on_a_stepping_reference(stepping):
    scan, _ = stepping
    with pytest.raises(ValueError, match="visibility_loss.*not identifiable"):
        fit_reference(scan.reference, effects=("phase_offset", "visibility_loss"))
    with pytest.raises(ValueError, match="dose is not identifiable"):
        fit_reference(scan.reference, effects=("phase_offset", "dose"), optional=())


def test_region_without_fringes_is_left_out_and_nan(stepping):
    result = pipeline.reconstruct(without_fringes(*stepping[:1], stepping[1]["vib_dose"]),
                                  C.load([], ["fit.subsample=2"]))
    assert np.all(np.isnan(result.dark_field[:, :10]))
    assert np.isfinite(result.dark_field[:, 12:]).mean() > 0.99


@pytest.mark.shared
@pytest.mark.slow
def test_real_recording_imports_and_reconstructs(tmp_path):
    folder = shared_path("real", "tum-ipp-stepping")
    scan = import_stepping(tmp_path / "ipp.h5", sample=str(folder / "data_stepping_*.npy"),
                           reference=str(folder / "flat_stepping_*.npy"), steps_per_period=11)
    assert scan.shape == (11, 195, 487)
    result = pipeline.reconstruct(tmp_path / "ipp.h5", C.defaults())
    grating = np.isfinite(result.dark_field)
    assert 0.5 < grating.mean() < 0.95  # the area outside the gratings is detected and left out
    assert result.reduced_chi2 < 1.05
    assert np.abs(result.params["phase_offset"][:, 0]).max() < 0.3
