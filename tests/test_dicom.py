"""DICOM export: values, padding, geometry, study and series, stable UIDs, the sidecar, the command line."""
from __future__ import annotations

import dataclasses
import subprocess
import sys

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from dfxcorr import dicom as D
from dfxcorr.cli import main
from dfxcorr.export import read_result_h5, write_result_h5
from dfxcorr.result import Result, paper_params
from dfxcorr.sim.simulate import simulate_file

from conftest import one_error_line, sim_config

pydicom = pytest.importorskip("pydicom")

H, W, J = 12, 10, 5
PIXEL = (100e-6, 75e-6)  # (row, column) pitch in m, unequal so that their order shows
PROVENANCE = {"program": "dfxcorr", "version": "0.1.0", "date": "2024-01-01T00:00:00",
              "command_line": "dfxcorr reconstruct scan.h5 -o r.h5", "input_file": "scan.h5",
              "input_sha256": "ab" * 32, "external_files": ""}


def result(**changes) -> Result:
    """A synthetic result: smooth images with noise, NaN on the first row and the last column."""
    rng = np.random.default_rng(7)
    y, x = np.mgrid[:H, :W]
    images = {"transmission": 0.6 + 0.3 * np.exp(-((x - 5) ** 2 + (y - 6) ** 2) / 8),
              "dark_field": 0.9 - 0.4 * np.exp(-((x - 4) ** 2 + (y - 5) ** 2) / 6),
              "differential_phase": 0.5 * np.tanh((x - 5) / 2.0)}
    for a in images.values():
        a += 0.01 * rng.standard_normal(a.shape)
        a[0, :] = a[:, -1] = np.nan
    params = paper_params({}, J)
    r = Result(**images, params=params, estimated={n: True for n in params},
               uncertainty={n: np.zeros_like(p) for n, p in params.items()}, fit_mask=np.ones((H, W), np.uint8),
               motion_mask=np.zeros((H, W), np.uint8), cost=np.zeros(1), cost_stage=["fit"], reduced_chi2=1.0,
               method="ml", config={"fit": {"method": "ml"}}, provenance=PROVENANCE, pixel_size=PIXEL)
    return dataclasses.replace(r, **changes)


def read(paths):
    return [pydicom.dcmread(p) for p in paths]


def rwv(ds) -> np.ndarray:
    """Values through the Real World Value Mapping (NaN at the padding value)."""
    m = ds.RealWorldValueMappingSequence[0]
    stored = ds.pixel_array.astype(np.float64)
    return np.where(stored == ds.PixelPaddingValue, np.nan, m.RealWorldValueSlope * stored + m.RealWorldValueIntercept)


def rescaled(ds) -> np.ndarray:
    """Values through Rescale Slope and Intercept, in the Rescale Type's units."""
    return float(ds.RescaleSlope) * ds.pixel_array + float(ds.RescaleIntercept)


def test_values_come_back_within_half_a_stored_step(tmp_path):
    r = result()
    for name, ds in zip(Result.IMAGES, read(D.write_dicom(r, tmp_path)), strict=True):
        truth = np.asarray(r.image(name), np.float32).astype(np.float64)
        lit = np.isfinite(truth)
        half_step = np.ptp(truth[lit]) / (D.TOP - 1) / 2
        assert np.array_equal(np.isnan(rwv(ds)), ~lit)  # NaN pixels, and only they, hold the padding value
        assert ds.PixelPaddingValue == D.PADDING
        assert np.max(np.abs(rwv(ds)[lit] - truth[lit])) <= half_step * (1 + 1e-9)
        factor = D.QUANTITIES[name].rescale_factor
        assert np.max(np.abs(rescaled(ds)[lit] / factor - truth[lit])) <= half_step * (1 + 1e-6)
        # the padding value lies below every value: no lit pixel can be mistaken for it
        assert rescaled(ds)[~lit].max() < rescaled(ds)[lit].min()


def test_units_and_display(tmp_path):
    t, v, phi = read(D.write_dicom(result(), tmp_path))
    units = [ds.RealWorldValueMappingSequence[0].MeasurementUnitsCodeSequence[0] for ds in (t, v, phi)]
    assert [(u.CodeValue, u.CodingSchemeDesignator) for u in units] == [("{ratio}", "UCUM")] * 2 + [("rad", "UCUM")]
    assert [ds.RescaleType for ds in (t, v, phi)] == ["PCT", "PCT", "MRAD"]
    assert [ds.PhotometricInterpretation for ds in (t, v, phi)] == ["MONOCHROME1"] * 2 + ["MONOCHROME2"]
    for ds in (t, v, phi):
        lit = rescaled(ds)[ds.pixel_array != D.PADDING]
        assert float(ds.WindowWidth) >= 1
        assert lit.min() <= float(ds.WindowCenter) <= lit.max()


def test_geometry(tmp_path):
    r = result()
    for ds in read(D.write_dicom(r, tmp_path)):
        assert (ds.Rows, ds.Columns) == r.transmission.shape
        assert [float(s) for s in ds.PixelSpacing] == pytest.approx([0.1, 0.075], rel=1e-12)
        assert [float(s) for s in ds.ImagerPixelSpacing] == [float(s) for s in ds.PixelSpacing]
        assert ds.PatientOrientation == ""
    for ds in read(D.write_dicom(result(pixel_size=None), tmp_path / "unknown")):
        assert "PixelSpacing" not in ds and "ImagerPixelSpacing" not in ds


def test_one_study_three_series(tmp_path):
    paths = D.write_dicom(result(), tmp_path, stem="r")
    assert [p.name for p in paths] == ["r_transmission.dcm", "r_dark_field.dcm", "r_differential_phase.dcm"]
    datasets = read(paths)
    assert len({ds.StudyInstanceUID for ds in datasets}) == 1
    assert len({ds.SeriesInstanceUID for ds in datasets}) == 3
    assert len({ds.SOPInstanceUID for ds in datasets}) == 3
    assert [ds.SeriesNumber for ds in datasets] == [1, 2, 3]
    for ds in datasets:
        assert ds.SOPClassUID == D.SC_IMAGE_STORAGE == ds.file_meta.MediaStorageSOPClassUID
        assert ds.file_meta.MediaStorageSOPInstanceUID == ds.SOPInstanceUID
        assert "dfxcorr 0.1.0" in ds.SecondaryCaptureDeviceSoftwareVersions
        assert "sha256" in ds.ImageComments and "scan.h5" in ds.DerivationDescription


def uid_set(paths):
    return [(ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.SOPInstanceUID) for ds in read(paths)]


def test_uids_are_stable_for_a_result_and_differ_between_results(tmp_path):
    r = result()
    first = uid_set(D.write_dicom(r, tmp_path / "a"))
    assert uid_set(D.write_dicom(r, tmp_path / "b")) == first
    write_result_h5(tmp_path / "r.h5", r)  # the same result read back from its file
    assert uid_set(D.write_dicom(tmp_path / "r.h5", tmp_path / "c")) == first
    other_image = r.dark_field.copy()
    other_image[5, 5] += 1e-3
    other_run = {**r.provenance, "date": "2024-01-02T00:00:00"}
    for other in (result(dark_field=other_image), result(provenance=other_run)):
        uids = uid_set(D.write_dicom(other, tmp_path / "other", overwrite=True))
        assert not {u for row in uids for u in row} & {u for row in first for u in row}


SIDECAR = """\
PatientName: Müller^Jürgen
PatientID: 00123
PatientBirthDate: 1960-02-29
PatientSex: F
StudyDate: 20240105
StudyTime: 14:30:00
AccessionNumber: A17
BodyPartExamined: CHEST
PatientOrientation: [L, F]
"""


def test_sidecar_attributes_are_carried_and_absent_ones_left_empty(tmp_path):
    side = tmp_path / "patient.yaml"
    side.write_text(SIDECAR, encoding="utf-8")
    ds = read(D.write_dicom(result(), tmp_path / "out", sidecar=D.read_sidecar(side)))[0]
    patient = (ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex)
    assert patient == ("Müller^Jürgen", "00123", "19600229", "F")  # 00123 is not read as the octal 83
    assert (ds.StudyDate, ds.StudyTime, ds.AccessionNumber) == ("20240105", "143000", "A17")
    assert list(ds.PatientOrientation) == ["L", "F"] and ds.BodyPartExamined == "CHEST"
    for key in ("StudyID", "ReferringPhysicianName"):  # type 2, not in the sidecar: present and empty
        assert key in ds and ds[key].value in ("", None)
    assert "Laterality" not in ds  # the body part is known to be unpaired


def test_no_sidecar_invents_nothing(tmp_path):
    ds = read(D.write_dicom(result(), tmp_path))[0]
    for key in D.TYPE2:
        assert key in ds and ds[key].value in ("", None), key
    assert "PatientAge" not in ds and "InstitutionName" not in ds and "StudyDescription" not in ds


def test_sidecar_study_uid_joins_an_existing_study(tmp_path):
    datasets = read(D.write_dicom(result(), tmp_path, sidecar={"StudyInstanceUID": "1.2.3.4.5"}))
    assert {ds.StudyInstanceUID for ds in datasets} == {"1.2.3.4.5"}


@pytest.mark.parametrize("text, words", [
    ("PatientNme: Doe\n", ["PatientNme", "PatientName"]),
    ("PatientSex: X\n", ["PatientSex", "M, F or O"]),
    ("StudyDate: 2024-13-01\n", ["StudyDate"]),
    ("StudyTime: 25:30:00\n", ["StudyTime", "HHMMSS"]),
    ("PatientOrientation: [L]\n", ["PatientOrientation"]),
    ("- PatientName\n", ["mapping"]),
])
def test_bad_sidecars_are_refused_in_one_line(tmp_path, text, words):
    side = tmp_path / "patient.yaml"
    side.write_text(text)
    res = CliRunner().invoke(main, ["dicom", str(scan_result(tmp_path)), "-o", str(tmp_path / "out"),
                                    "--sidecar", str(side)])
    assert res.exit_code == 2
    assert one_error_line(res.stderr, "patient.yaml", *words), res.stderr
    assert not (tmp_path / "out").exists()


def scan_result(tmp_path):
    path = tmp_path / "r.h5"
    if not path.exists():
        write_result_h5(path, result())
    return path


def test_dicom_command_from_an_existing_result(tmp_path):
    path = scan_result(tmp_path)
    res = CliRunner().invoke(main, ["dicom", str(path), "-o", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    datasets = read(D.dicom_paths(tmp_path / "out", "r"))
    stored = read_result_h5(path)
    for name, ds in zip(Result.IMAGES, datasets, strict=True):
        lit = np.isfinite(stored[name])
        assert np.allclose(rwv(ds)[lit], stored[name][lit], rtol=0, atol=1e-3 * np.ptp(stored[name][lit]))
    again = CliRunner().invoke(main, ["dicom", str(path), "-o", str(tmp_path / "out")])
    assert again.exit_code == 2 and one_error_line(again.stderr, "exists", "--overwrite")
    assert CliRunner().invoke(main, ["dicom", str(path), "-o", str(tmp_path / "out"), "--overwrite"]).exit_code == 0


def test_a_file_that_is_not_a_result_is_refused(tmp_path):
    side = tmp_path / "not_a_result.h5"
    with h5py.File(side, "w") as f:
        f.attrs["format"] = "dfxcorr-scan"
    res = CliRunner().invoke(main, ["dicom", str(side), "-o", str(tmp_path / "out")])
    assert res.exit_code == 2 and one_error_line(res.stderr, "not_a_result.h5", "dfxcorr-result"), res.stderr


def test_without_pydicom_one_line_names_the_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pydicom", None)  # import pydicom now raises ImportError
    path = scan_result(tmp_path)
    for args in (["dicom", path, "-o", tmp_path / "out"],
                 ["reconstruct", tmp_path / "scan.h5", "-o", tmp_path / "new.h5", "--dicom", tmp_path / "out"]):
        res = CliRunner().invoke(main, [str(a) for a in args])
        assert res.exit_code == 2
        assert one_error_line(res.stderr, 'pip install "dfxcorr[dicom]"'), res.stderr
    assert not (tmp_path / "out").exists() and not (tmp_path / "new.h5").exists()
    with pytest.raises(D.DicomError, match="pip install"):
        D.write_dicom(result(), tmp_path / "out")


@pytest.fixture(scope="module")
def sim_scan(tmp_path_factory):
    path = tmp_path_factory.mktemp("scan") / "scan.h5"
    simulate_file(sim_config(), path)
    return path


def test_an_existing_output_is_refused_before_any_computation(sim_scan, tmp_path):
    (tmp_path / "dcm").mkdir()
    (tmp_path / "dcm" / "r_dark_field.dcm").write_bytes(b"earlier")
    res = CliRunner().invoke(main, ["reconstruct", str(sim_scan), "-o", str(tmp_path / "r.h5"),
                                    "--dicom", str(tmp_path / "dcm")])
    assert res.exit_code == 2 and one_error_line(res.stderr, "r_dark_field.dcm", "exists"), res.stderr
    assert not (tmp_path / "r.h5").exists()  # refused before the reconstruction, which writes it first
    assert (tmp_path / "dcm" / "r_dark_field.dcm").read_bytes() == b"earlier"
    res = CliRunner().invoke(main, ["reconstruct", str(sim_scan), "-o", str(tmp_path / "r.h5"),
                                    "--dicom-sidecar", str(sim_scan)])
    assert res.exit_code == 2 and one_error_line(res.stderr, "--dicom-sidecar", "--dicom")


@pytest.mark.slow
def test_reconstruct_round_trips_the_three_images(sim_scan, tmp_path):
    side = tmp_path / "patient.json"
    side.write_text('{"PatientName": "Doe^John", "PatientID": "P7"}')
    out = tmp_path / "r.h5"
    res = CliRunner().invoke(main, ["reconstruct", str(sim_scan), "-o", str(out), "--set", "fit.subsample=3",
                                    "--dicom", str(tmp_path / "dcm"), "--dicom-sidecar", str(side)])
    assert res.exit_code == 0, res.output
    stored = read_result_h5(out)
    datasets = read(D.dicom_paths(tmp_path / "dcm", "r"))
    for name, ds in zip(Result.IMAGES, datasets, strict=True):
        lit = np.isfinite(stored[name])
        assert lit.any() and np.array_equal(np.isnan(rwv(ds)), ~lit)
        assert np.max(np.abs(rwv(ds)[lit] - stored[name][lit])) <= 1e-3 * np.ptp(stored[name][lit])
        assert [float(s) for s in ds.PixelSpacing] == pytest.approx([5.0, 5.0])  # the simulation's 5 mm pixels
        assert ds.PatientName == "Doe^John" and ds.PatientID == "P7"
    # the same result exported again from its file: the same UIDs
    res = CliRunner().invoke(main, ["dicom", str(out), "-o", str(tmp_path / "again"), "--sidecar", str(side)])
    assert res.exit_code == 0, res.output
    assert uid_set(D.dicom_paths(tmp_path / "again", "r")) == uid_set(D.dicom_paths(tmp_path / "dcm", "r"))


@pytest.mark.slow
def test_the_package_imports_without_pydicom():
    code = "import sys; sys.modules['pydicom'] = None; import dfxcorr.cli, dfxcorr.dicom"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True).returncode == 0
