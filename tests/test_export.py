"""Export: the results-file contract of spec/results-format.md, TIFFs and pictures."""
from __future__ import annotations

import h5py
import numpy as np
import pytest
import tifffile
import yaml

from dfxcorr import export
from dfxcorr.errors import OutputExistsError
from dfxcorr.export import check_output, read_result_h5, write_result_h5, write_tiffs
from dfxcorr.plots import write_fit_plot, write_preview
from dfxcorr.result import Result

H, W, J = 12, 10, 7
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PROVENANCE = {"program": "dfxcorr", "version": "0.1.0", "date": "2024-01-01T00:00:00",
              "command_line": "dfxcorr reconstruct scan.h5 -o out.h5", "input_file": "scan.h5",
              "input_sha256": "ab" * 32, "external_files": ""}
CONFIG = {"fit": {"method": "ml", "effects": ["phase_offset", "tilt", "visibility_loss", "dose"],
                  "tolerance": 1e-6},
          "vibration": {"visibility": True}, "output": {"tiff": False, "stem": None}}

# spec/results-format.md: (path, shape or None for a scalar/string, dtype kind or exact dtype)
SPEC_DATASETS = [
    ("entry/dfxcorr/program", "str"),
    ("entry/dfxcorr/version", "str"),
    ("entry/dfxcorr/date", "str"),
    ("entry/dfxcorr/command_line", "str"),
    ("entry/dfxcorr/input_file", "str"),
    ("entry/dfxcorr/input_sha256", "str"),
    ("entry/dfxcorr/configuration", "str"),
    ("entry/dfxcorr/results/transmission", ((H, W), np.float32)),
    ("entry/dfxcorr/results/dark_field", ((H, W), np.float32)),
    ("entry/dfxcorr/results/differential_phase", ((H, W), np.float32)),
    ("entry/dfxcorr/vibration/phase_offset", ((J,), np.float64)),
    ("entry/dfxcorr/vibration/tilt", ((J,), np.float64)),
    ("entry/dfxcorr/vibration/visibility", ((J,), np.float64)),
    ("entry/dfxcorr/fit/mask", ((H, W), np.uint8)),
    ("entry/dfxcorr/fit/cost", ((5,), np.float64)),
    ("entry/dfxcorr/fit/reduced_chi2", ((), np.float64)),
]


def make_result(*, estimate_visibility=True, uncorrected=True) -> Result:
    rng = np.random.default_rng(1234)
    y, x = np.mgrid[:H, :W]
    t = (0.6 + 0.3 * np.exp(-((x - 5) ** 2 + (y - 6) ** 2) / 8)).astype(np.float64)
    v = 0.9 - 0.4 * np.exp(-((x - 4) ** 2 + (y - 5) ** 2) / 6)
    phi = 0.5 * np.tanh((x - 5) / 2.0) * np.exp(-((y - 6) ** 2) / 10)
    dark = np.zeros((H, W), bool)
    dark[0, :] = True
    dark[:, -1] = True
    images = []
    for a in (t, v, phi):
        a = a + 0.01 * rng.standard_normal(a.shape)
        a[dark] = np.nan
        images.append(a)
    stripes = 0.05 * np.sin(np.arange(H) * 1.3)[:, None]
    params = {
        "phase_offset": rng.normal(0, 0.2, (J, 1)),
        "tilt": rng.normal(0, 0.05, (J, 1)),
        "visibility_loss": 1 + rng.normal(0, 0.03, (J, 1)),
        "dose": 1 + rng.normal(0, 0.02, (J, 1)),
        "curvature": rng.normal(0, 0.01, (J, 1)),
    }
    uncertainty = {k: np.full(v_.shape, 0.01) for k, v_ in params.items()}
    uncertainty["phase_offset"][3, 0] = np.inf
    estimated = {k: True for k in params}
    estimated["visibility_loss"] = estimate_visibility
    mask = (~dark).astype(np.uint8)
    mask[5:7, 3:5] = 0
    motion = np.zeros((H, W), np.uint8)
    motion[5:7, 3:5] = 1
    return Result(
        transmission=images[0], dark_field=images[1], differential_phase=images[2],
        params=params, estimated=estimated, uncertainty=uncertainty, fit_mask=mask, motion_mask=motion,
        cost=np.array([100.0, 20.0, 5.0, 4.0, 3.9]), cost_stage=["phase", "phase", "all", "all", "all"],
        reduced_chi2=1.03, method="ml", config=CONFIG, provenance=PROVENANCE,
        uncorrected={"transmission": images[0] * (1 + stripes), "dark_field": images[1] * (1 - abs(stripes)),
                     "differential_phase": images[2] + stripes} if uncorrected else None,
        timings={"load": 0.5, "fit": 2.25},
        extra={"well_determined": np.ones(J, bool), "notes": {"gauge": np.array([0.0, 1.0])}},
    )


@pytest.fixture
def result():
    return make_result()


def _string(ds) -> str:
    return ds.asstr()[()]


# --------------------------------------------------------------------------------------------------
# check_output
# --------------------------------------------------------------------------------------------------


def test_check_output(tmp_path):
    path = tmp_path / "out.h5"
    check_output(path, overwrite=False)
    path.write_bytes(b"old")
    check_output(path, overwrite=True)
    with pytest.raises(OutputExistsError, match="--overwrite") as info:
        check_output(path, overwrite=False)
    assert str(path) in str(info.value)
    assert isinstance(info.value, FileExistsError)
    with pytest.raises(IsADirectoryError):
        check_output(tmp_path, overwrite=True)


# --------------------------------------------------------------------------------------------------
# results file
# --------------------------------------------------------------------------------------------------


def test_results_file_matches_spec(tmp_path, result):
    path = tmp_path / "out.h5"
    write_result_h5(path, result)
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "dfxcorr-result"
        assert int(f.attrs["format_version"]) == 1
        assert np.issubdtype(np.asarray(f.attrs["format_version"]).dtype, np.integer)
        assert f["entry"].attrs["default"] == "dfxcorr/results"
        assert f["entry"].attrs["NX_class"] == "NXentry"
        assert f["entry/dfxcorr"].attrs["NX_class"] == "NXprocess"
        assert f["entry/dfxcorr/results"].attrs["NX_class"] == "NXdata"
        assert f["entry/dfxcorr/results"].attrs["signal"] == "transmission"
        for path_, spec in SPEC_DATASETS:
            assert path_ in f, path_
            ds = f[path_]
            if spec == "str":
                assert h5py.check_string_dtype(ds.dtype) is not None, path_
                assert ds.shape == (), path_
            else:
                shape, dtype = spec
                assert ds.shape == shape, path_
                assert ds.dtype == dtype, path_
        proc = f["entry/dfxcorr"]
        for key, value in PROVENANCE.items():
            assert _string(proc[key]) == value
        for name in ("phase_offset", "tilt", "visibility"):
            assert proc["vibration"][name].attrs["estimated"] == 1
        assert proc["vibration/phase_offset"].attrs["units"] == "rad"
        assert proc["results/differential_phase"].attrs["units"] == "rad"
        # further per-frame effects, squeezed to [J]
        for name in ("dose", "curvature"):
            ds = proc["vibration"][name]
            assert ds.shape == (J,) and ds.dtype == np.float64
            assert ds.attrs["estimated"] == 1
            np.testing.assert_array_equal(ds[()], result.params[name][:, 0])
        np.testing.assert_array_equal(proc["vibration/visibility"][()], result.params["visibility_loss"][:, 0])
        assert proc["vibration/uncertainty/phase_offset"].shape == (J,)
        assert np.isinf(proc["vibration/uncertainty/phase_offset"][3])
        # fit group, extras
        assert proc["fit/motion_mask"].dtype == np.uint8
        assert list(proc["fit/stage"].asstr()[()]) == result.cost_stage
        assert _string(proc["fit/method"]) == "ml"
        assert proc["timings/fit"][()] == 2.25
        assert proc["uncorrected/dark_field"].dtype == np.float32
        assert proc["uncorrected/dark_field"].shape == (H, W)
        np.testing.assert_array_equal(proc["extra/well_determined"][()], np.ones(J, bool))
        np.testing.assert_array_equal(proc["extra/notes/gauge"][()], [0.0, 1.0])
    assert [p.name for p in tmp_path.iterdir()] == ["out.h5"]


def test_round_trip(tmp_path, result):
    path = tmp_path / "out.h5"
    write_result_h5(path, result)
    back = read_result_h5(path)
    for name in Result.IMAGES:
        original = result.image(name)
        assert back[name].dtype == np.float32
        np.testing.assert_array_equal(np.isnan(back[name]), np.isnan(original))
        assert np.isnan(original).any()
        np.testing.assert_allclose(back[name], original.astype(np.float32), rtol=0, atol=0, equal_nan=True)
    for name, effect in export.SPEC_EFFECTS.items():
        np.testing.assert_array_equal(back["vibration"][name], result.params[effect][:, 0])
        assert back["estimated"][name] is True
    np.testing.assert_array_equal(back["vibration"]["dose"], result.params["dose"][:, 0])
    np.testing.assert_array_equal(back["mask"], result.fit_mask)
    np.testing.assert_array_equal(back["cost"], result.cost)
    assert back["reduced_chi2"] == pytest.approx(1.03)
    assert back["configuration"] == CONFIG
    assert back["provenance"] == PROVENANCE
    assert back["stage"] == result.cost_stage
    assert back["method"] == "ml"
    assert back["timings"] == result.timings
    assert back["format_version"] == 1


def test_configuration_is_yaml_of_resolved_config(tmp_path, result):
    path = tmp_path / "out.h5"
    write_result_h5(path, result)
    with h5py.File(path, "r") as f:
        text = _string(f["entry/dfxcorr/configuration"])
    assert yaml.safe_load(text) == CONFIG
    assert list(yaml.safe_load(text)) == list(CONFIG)  # order kept (sort_keys=False)


def test_missing_provenance_written_empty(tmp_path, result):
    result.provenance = {"program": "dfxcorr"}
    write_result_h5(tmp_path / "out.h5", result)
    back = read_result_h5(tmp_path / "out.h5")
    assert back["provenance"]["program"] == "dfxcorr"
    assert back["provenance"]["input_sha256"] == ""


def test_not_estimated_effect_written_neutral(tmp_path):
    result = make_result(estimate_visibility=False, uncorrected=False)
    del result.params["tilt"]
    path = tmp_path / "out.h5"
    write_result_h5(path, result)
    with h5py.File(path, "r") as f:
        vib = f["entry/dfxcorr/vibration"]
        np.testing.assert_array_equal(vib["visibility"][()], np.ones(J))
        assert vib["visibility"].attrs["estimated"] == 0
        assert vib["visibility"].dtype == np.float64
        np.testing.assert_array_equal(vib["tilt"][()], np.zeros(J))
        assert vib["tilt"].attrs["estimated"] == 0
        assert vib["phase_offset"].attrs["estimated"] == 1
        assert "visibility" not in vib["uncertainty"]
        assert "uncorrected" not in f["entry/dfxcorr"]
    back = read_result_h5(path)
    assert back["estimated"]["visibility"] is False
    assert back["uncorrected"] is None


def test_global_and_multi_component_effects(tmp_path, result):
    result.params["visibility_tilt"] = np.zeros((J, 2))
    result.params["background"] = np.array([1.0, 2.0, 3.0])
    result.params["harmonic"] = np.array([0.01, 0.02])
    write_result_h5(tmp_path / "out.h5", result)
    with h5py.File(tmp_path / "out.h5", "r") as f:
        vib = f["entry/dfxcorr/vibration"]
        assert vib["visibility_tilt"].shape == (J, 2)
        assert list(vib["visibility_tilt"].attrs["components"]) == ["x^1", "x^2"]
        np.testing.assert_array_equal(vib["background"][()], [1.0, 2.0, 3.0])
        assert vib["harmonic"].shape == (2,)
        assert vib["harmonic"].attrs["estimated"] == 1


def test_refuses_existing_output(tmp_path, result):
    path = tmp_path / "out.h5"
    path.write_bytes(b"precious")
    with pytest.raises(OutputExistsError):
        write_result_h5(path, result)
    assert path.read_bytes() == b"precious"
    write_result_h5(path, result, overwrite=True)
    assert read_result_h5(path)["method"] == "ml"


def test_failure_leaves_nothing_behind(tmp_path, result):
    result.dark_field = np.array([object()] * (H * W), dtype=object).reshape(H, W)
    with pytest.raises(TypeError):  # h5py cannot store Python objects
        write_result_h5(tmp_path / "out.h5", result)
    assert list(tmp_path.iterdir()) == []


def test_failure_keeps_existing_output(tmp_path, result, monkeypatch):
    path = tmp_path / "out.h5"
    path.write_bytes(b"precious")

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(export, "_write_tree", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        write_result_h5(path, result, overwrite=True)
    assert path.read_bytes() == b"precious"
    assert [p.name for p in tmp_path.iterdir()] == ["out.h5"]


def test_uncompressed(tmp_path, result):
    write_result_h5(tmp_path / "out.h5", result, compression=None)
    with h5py.File(tmp_path / "out.h5", "r") as f:
        assert f["entry/dfxcorr/results/transmission"].compression is None


# --------------------------------------------------------------------------------------------------
# TIFF
# --------------------------------------------------------------------------------------------------


def test_tiffs(tmp_path, result):
    out = tmp_path / "tiff" / "sub"
    files = write_tiffs(out, result, stem="scan")
    names = sorted(p.name for p in files)
    assert names == ["scan.yaml", "scan_dark_field.tif", "scan_differential_phase.tif", "scan_transmission.tif"]
    assert sorted(p.name for p in out.iterdir()) == names
    for name in Result.IMAGES:
        image = tifffile.imread(out / f"scan_{name}.tif")
        assert image.dtype == np.float32 and image.shape == (H, W)
        np.testing.assert_array_equal(image, result.image(name).astype(np.float32))
    assert yaml.safe_load((out / "scan.yaml").read_text()) == CONFIG


def test_tiffs_refuse_before_writing_any(tmp_path, result):
    (tmp_path / "scan_differential_phase.tif").write_bytes(b"old")
    with pytest.raises(OutputExistsError, match="scan_differential_phase.tif"):
        write_tiffs(tmp_path, result, stem="scan")
    assert [p.name for p in tmp_path.iterdir()] == ["scan_differential_phase.tif"]
    write_tiffs(tmp_path, result, stem="scan", overwrite=True)
    assert tifffile.imread(tmp_path / "scan_differential_phase.tif").shape == (H, W)


# --------------------------------------------------------------------------------------------------
# pictures
# --------------------------------------------------------------------------------------------------


def _assert_png(path):
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE
    assert len(data) > 1000


@pytest.mark.parametrize("uncorrected", [pytest.param(True, marks=pytest.mark.slow), False])
def test_preview(tmp_path, uncorrected):
    result = make_result(uncorrected=uncorrected)
    if not uncorrected:
        result.differential_phase = np.full((H, W), np.nan)  # nothing to window on
    path = write_preview(tmp_path / "preview.png", result, title="test")
    assert path == tmp_path / "preview.png"
    _assert_png(path)
    assert [p.name for p in tmp_path.iterdir()] == ["preview.png"]
    with pytest.raises(OutputExistsError):
        write_preview(path, result)


@pytest.mark.slow
def test_fit_plot(tmp_path):
    result = make_result(estimate_visibility=False)
    result.params["visibility_tilt"] = np.zeros((J, 2))
    result.params["background"] = np.array([1.0, 2.0, 3.0])
    path = write_fit_plot(tmp_path / "fit.png", result)
    _assert_png(path)
    assert [p.name for p in tmp_path.iterdir()] == ["fit.png"]
    with pytest.raises(OutputExistsError):
        write_fit_plot(path, result)


@pytest.mark.slow
def test_import_is_cheap():
    import subprocess
    import sys

    code = "import sys, dfxcorr.export; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_chi2_limits_hold_the_reduced_chi_square_of_noise():
    from dfxcorr.result import chi2_limits

    rng = np.random.default_rng(3)
    for dof in (5, 50, 5000, 500000):
        lo, hi = chi2_limits(dof)
        assert 0 <= lo <= 0.5 and hi >= 2
        draws = rng.chisquare(dof, 20000) / dof  # what a right model gives: none outside (tail 3e-7 a side)
        assert np.all((draws >= lo) & (draws <= hi))
    assert chi2_limits(10 ** 7) == (0.5, 2.0)  # the practical floor: noise alone leaves +-0.002
    assert chi2_limits(20)[1] == pytest.approx(3.44, abs=0.01)  # the skewed quantile, not 1 + 5 sqrt(2 / 20) = 3.24


def test_pixel_size_round_trips(tmp_path):
    r = make_result()
    write_result_h5(tmp_path / "unknown.h5", r)
    assert read_result_h5(tmp_path / "unknown.h5")["pixel_size"] is None
    r.pixel_size = (1e-4, 7.5e-5)
    write_result_h5(tmp_path / "known.h5", r)
    assert read_result_h5(tmp_path / "known.h5")["pixel_size"] == (1e-4, 7.5e-5)
    with h5py.File(tmp_path / "known.h5") as f:
        assert f["entry/dfxcorr/results/x_pixel_size"].attrs["units"] == "m"
