"""Tests of dfxcorr.importer: lossless import of phase-stepping series into the scan format."""
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile

from dfxcorr.errors import DfxcorrError, OutputExistsError
from dfxcorr.importer import StackImportError, frame_dtype, import_stepping, nominal_steps, read_stack
from dfxcorr.io import SteppingReference, read_scan

from conftest import SHARED

REAL = SHARED / "real" / "tum-ipp-stepping"
S, H, W = 5, 6, 8
EXPECTED_DTYPE = {"uint16": np.uint16, "int32": np.uint32, "float32": np.float32}
RAW_HEADER = 16


def counts(dtype: str, seed: int, n: int = S, shape=(H, W)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if dtype == "float32":
        # Fractional values: a lossy path through an integer or a narrower float would show.
        return (rng.poisson(3000, (n,) + shape) * 0.37 + 0.01).astype(np.float32)
    top = 65535 if dtype == "uint16" else 2 ** 31 - 1
    return rng.integers(0, top, (n,) + shape, endpoint=True).astype(dtype)


def write_series(tmp_path: Path, name: str, stack: np.ndarray, fmt: str) -> tuple[object, dict]:
    """Write ``stack`` in format ``fmt``; return the source for read_stack and the raw options."""
    raw = {"shape": stack.shape[1:], "dtype": stack.dtype.str}
    if fmt == "npy-per-step":
        for k, frame in enumerate(stack):
            np.save(tmp_path / f"{name}_{k:04d}.npy", frame)
        return str(tmp_path / f"{name}_*.npy"), {}
    if fmt == "npy-stack":
        np.save(tmp_path / f"{name}.npy", stack)
        return tmp_path / f"{name}.npy", {}
    if fmt == "tif-per-step":
        for k, frame in enumerate(stack):
            tifffile.imwrite(tmp_path / f"{name}_{k}.tif", frame)
        return str(tmp_path / f"{name}_*.tif"), {}
    if fmt == "tif-stack":
        tifffile.imwrite(tmp_path / f"{name}.tiff", stack)
        return str(tmp_path / f"{name}.tiff"), {}
    if fmt == "raw-stack":
        stack.tofile(tmp_path / f"{name}.raw")
        return str(tmp_path / f"{name}.raw"), raw
    if fmt == "raw-per-step-offset":
        paths = []
        for k, frame in enumerate(stack):
            path = tmp_path / f"{name}_{k}.bin"
            path.write_bytes(b"H" * RAW_HEADER + frame.tobytes())
            paths.append(path)
        return paths, {**raw, "offset": RAW_HEADER}
    raise AssertionError(fmt)


FORMATS = ["npy-per-step", "npy-stack", "tif-per-step", "tif-stack", "raw-stack", "raw-per-step-offset"]


@pytest.mark.parametrize("dtype", sorted(EXPECTED_DTYPE))
@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip(tmp_path, fmt, dtype):
    sample = counts(dtype, seed=1)
    flat = counts(dtype, seed=2)
    sample_src, raw = write_series(tmp_path, "data", sample, fmt)
    flat_src, _ = write_series(tmp_path, "flat", flat, fmt)
    out = tmp_path / "scan.h5"

    returned = import_stepping(out, sample=sample_src, reference=flat_src, steps_per_period=S, **raw)
    scan = read_scan(out)

    for got in (scan, returned):
        assert got.data.dtype == EXPECTED_DTYPE[dtype]
        assert np.array_equal(got.data, sample)
        assert got.shape == (S, H, W)
        assert np.all(got.position == 0)
        np.testing.assert_allclose(got.phase_step, 2 * np.pi * np.arange(S) / S, rtol=0, atol=1e-12)
        assert isinstance(got.reference, SteppingReference)
        assert got.reference.data.dtype == EXPECTED_DTYPE[dtype]
        assert np.array_equal(got.reference.data, flat)
        np.testing.assert_allclose(got.reference.phase_step, 2 * np.pi * np.arange(S) / S, rtol=0, atol=1e-12)
        assert got.reference.dark is None
    assert scan.is_stepping
    assert np.all(scan.dark == 0)


def test_read_stack_big_endian_raw_is_native(tmp_path):
    stack = counts("uint16", seed=3)
    path = tmp_path / "be.dat"
    stack.astype(">u2").tofile(path)
    got = read_stack(path, shape=(H, W), dtype=">u2")
    assert got.dtype == np.dtype("=u2")
    assert np.array_equal(got, stack)


def test_natural_sort(tmp_path):
    for k in range(1, 13):
        np.save(tmp_path / f"step_{k}.npy", np.full((2, 3), k, dtype=np.uint16))
    stack = read_stack(str(tmp_path / "step_*.npy"))
    assert stack.shape == (12, 2, 3)
    assert list(stack[:, 0, 0]) == list(range(1, 13))


def test_list_keeps_given_order(tmp_path):
    paths = []
    for k in range(3):
        paths.append(tmp_path / f"f{k}.npy")
        np.save(paths[-1], np.full((2, 2), k, dtype=np.uint16))
    assert list(read_stack(paths[::-1])[:, 0, 0]) == [2, 1, 0]


@pytest.mark.parametrize("source, expected", [
    (np.arange(6, dtype=np.uint8), np.uint16),
    (np.arange(6, dtype=np.int16), np.uint16),
    (np.arange(6, dtype=np.int32), np.uint32),
    (np.array([0, 2 ** 32 - 1], dtype=np.int64), np.uint32),
    (np.array([0, 2 ** 40], dtype=np.uint64), np.float64),
    (np.array([0.5, 1.25], dtype=np.float16), np.float32),
    (np.array([0.5, 1.25], dtype=np.float64), np.float64),
])
def test_frame_dtype_lossless(source, expected):
    out = frame_dtype(source, "x")
    assert out.dtype == expected
    assert np.array_equal(out, source)


@pytest.mark.parametrize("source, words", [
    (np.array([3, -1], dtype=np.int32), "negative"),
    (np.array([0, 2 ** 53 + 1], dtype=np.int64), "exact"),
    (np.array([1.0, np.nan], dtype=np.float32), "NaN"),
    (np.array([1.0, -2.0], dtype=np.float64), "negative"),
    (np.array([1 + 1j]), "complex"),
])
def test_frame_dtype_refuses(source, words):
    with pytest.raises(StackImportError, match="the-name") as info:
        frame_dtype(source, "the-name")
    assert words in str(info.value)


def test_nominal_steps():
    np.testing.assert_allclose(nominal_steps(4, steps_per_period=8), np.pi / 4 * np.arange(4))
    np.testing.assert_array_equal(nominal_steps(3, phases=[0, 1, 2.5]), [0, 1, 2.5])
    with pytest.raises(StackImportError, match="steps_per_period"):
        nominal_steps(3)
    with pytest.raises(StackImportError, match="steps_per_period"):
        nominal_steps(3, steps_per_period=3, phases=[0, 1, 2])
    with pytest.raises(StackImportError, match="phases"):
        nominal_steps(3, phases=[0, 1])
    with pytest.raises(StackImportError, match="phases"):
        nominal_steps(3, phases=[0, 1, np.inf])
    with pytest.raises(StackImportError, match="steps_per_period"):
        nominal_steps(3, steps_per_period=0)


def test_dark_provenance_gain_pixel_size(tmp_path):
    sample, flat = counts("uint16", seed=4), counts("uint16", seed=5)
    darks = counts("uint16", seed=6, n=3)
    np.save(tmp_path / "data.npy", sample)
    np.save(tmp_path / "flat.npy", flat)
    for k, frame in enumerate(darks):
        np.save(tmp_path / f"dark_{k}.npy", frame)
    out = tmp_path / "scan.h5"
    import_stepping(out, sample=tmp_path / "data.npy", reference=str(tmp_path / "flat.npy"),
                    dark=str(tmp_path / "dark_*.npy"), steps_per_period=4.5, gain=2.5, pixel_size=75e-6)
    scan = read_scan(out)
    np.testing.assert_allclose(scan.dark, darks.astype(np.float64).mean(axis=0))
    np.testing.assert_allclose(scan.reference.dark, scan.dark)  # reference_dark defaults to dark
    np.testing.assert_allclose(scan.phase_step, 2 * np.pi * np.arange(S) / 4.5)
    assert scan.gain == 2.5
    assert scan.pixel_size == (75e-6, 75e-6)
    with h5py.File(out) as f:
        group = f["entry/dfxcorr_import"]
        assert list(group["source_files"].asstr()[()]) == [str((tmp_path / "data.npy").resolve())]
        assert list(group["reference_files"].asstr()[()]) == [str((tmp_path / "flat.npy").resolve())]
        assert len(group["dark_files"]) == 3
        assert group["steps_per_period"][()] == 4.5
        assert group["source_dtype"].asstr()[()] == "uint16"


def test_separate_reference_dark_and_phases(tmp_path):
    sample, flat = counts("uint16", seed=7), counts("uint16", seed=8, n=4)
    np.save(tmp_path / "data.npy", sample)
    np.save(tmp_path / "flat.npy", flat)
    np.save(tmp_path / "dark.npy", np.full((H, W), 3, dtype=np.uint16))
    np.save(tmp_path / "rdark.npy", np.full((H, W), 5, dtype=np.uint16))
    phases = [0.0, 1.0, 2.0, 3.0, 4.5]
    with pytest.raises(StackImportError, match="reference_phases"):
        import_stepping(tmp_path / "a.h5", sample=tmp_path / "data.npy", reference=tmp_path / "flat.npy",
                        phases=phases)
    scan = import_stepping(tmp_path / "b.h5", sample=tmp_path / "data.npy", reference=tmp_path / "flat.npy",
                           dark=tmp_path / "dark.npy", reference_dark=tmp_path / "rdark.npy", phases=phases,
                           reference_phases=[0.0, 1.5, 3.0, 4.5])
    back = read_scan(tmp_path / "b.h5")
    np.testing.assert_array_equal(back.phase_step, phases)
    np.testing.assert_array_equal(back.reference.phase_step, [0.0, 1.5, 3.0, 4.5])
    assert np.all(back.dark == 3) and np.all(back.reference.dark == 5)
    assert np.array_equal(back.reference.data, scan.reference.data)


# ---- errors -----------------------------------------------------------------------------------------

def test_glob_matching_nothing(tmp_path):
    with pytest.raises(StackImportError, match="nothing_here_"):
        read_stack(str(tmp_path / "nothing_here_*.npy"))


def test_mismatched_frame_shapes(tmp_path):
    np.save(tmp_path / "s_1.npy", np.zeros((4, 5), np.uint16))
    np.save(tmp_path / "s_2.npy", np.zeros((4, 6), np.uint16))
    with pytest.raises(StackImportError) as info:
        read_stack(str(tmp_path / "s_*.npy"))
    msg = str(info.value)
    assert "s_1.npy" in msg and "s_2.npy" in msg and "(4, 5)" in msg and "(4, 6)" in msg


def test_stack_in_a_series_and_mixed_formats(tmp_path):
    np.save(tmp_path / "s_1.npy", np.zeros((4, 5), np.uint16))
    np.save(tmp_path / "s_2.npy", np.zeros((2, 4, 5), np.uint16))
    with pytest.raises(StackImportError, match="s_2.npy"):
        read_stack(str(tmp_path / "s_*.npy"))
    tifffile.imwrite(tmp_path / "m_1.tif", np.zeros((4, 5), np.uint16))
    np.save(tmp_path / "m_2.npy", np.zeros((4, 5), np.uint16))
    with pytest.raises(StackImportError, match="mixes formats"):
        read_stack(str(tmp_path / "m_*"))


def test_colour_tiff_refused(tmp_path):
    tifffile.imwrite(tmp_path / "rgb.tif", np.zeros((4, 5, 3), np.uint8), photometric="rgb")
    with pytest.raises(StackImportError, match="rgb.tif"):
        read_stack(tmp_path / "rgb.tif")


def test_unreadable_file(tmp_path):
    (tmp_path / "broken.npy").write_bytes(b"not a numpy file")
    with pytest.raises(StackImportError, match="broken.npy"):
        read_stack(tmp_path / "broken.npy")


def test_unequal_sample_reference_shapes(tmp_path):
    np.save(tmp_path / "data.npy", counts("uint16", seed=9))
    np.save(tmp_path / "flat.npy", counts("uint16", seed=10, shape=(H, W + 1)))
    with pytest.raises(StackImportError) as info:
        import_stepping(tmp_path / "o.h5", sample=tmp_path / "data.npy", reference=tmp_path / "flat.npy",
                        steps_per_period=S)
    assert "data.npy" in str(info.value) and "flat.npy" in str(info.value)
    assert not (tmp_path / "o.h5").exists()


def test_raw_without_dtype(tmp_path):
    counts("uint16", seed=11).tofile(tmp_path / "frames.raw")
    with pytest.raises(StackImportError, match=r"frames\.raw.*dtype"):
        read_stack(tmp_path / "frames.raw", shape=(H, W))
    with pytest.raises(StackImportError, match=r"frames\.raw.*shape"):
        read_stack(tmp_path / "frames.raw", dtype="<u2")


def test_raw_size_not_whole_frames(tmp_path):
    path = tmp_path / "frames.raw"
    path.write_bytes(counts("uint16", seed=12).tobytes() + b"\0")
    with pytest.raises(StackImportError, match=r"frames\.raw.*whole"):
        read_stack(path, shape=(H, W), dtype="<u2")
    with pytest.raises(StackImportError, match=r"frames\.raw"):
        read_stack(path, shape=(H, W), dtype="<u2", offset=2)


def test_negative_counts_refused(tmp_path):
    sample = counts("int32", seed=13)
    sample[2, 3, 4] = -7
    np.save(tmp_path / "data.npy", sample)
    np.save(tmp_path / "flat.npy", counts("int32", seed=14))
    with pytest.raises(StackImportError, match=r"data\.npy.*negative"):
        import_stepping(tmp_path / "o.h5", sample=tmp_path / "data.npy", reference=tmp_path / "flat.npy",
                        steps_per_period=S)


def test_too_few_steps(tmp_path):
    np.save(tmp_path / "data.npy", counts("uint16", seed=15, n=2))
    np.save(tmp_path / "flat.npy", counts("uint16", seed=16))
    with pytest.raises(StackImportError, match=r"data\.npy.*at least 3"):
        import_stepping(tmp_path / "o.h5", sample=tmp_path / "data.npy", reference=tmp_path / "flat.npy",
                        steps_per_period=S)


def test_phases_length_mismatch(tmp_path):
    np.save(tmp_path / "data.npy", counts("uint16", seed=17))
    np.save(tmp_path / "flat.npy", counts("uint16", seed=18))
    with pytest.raises(StackImportError, match=r"data\.npy.*phases has 4 values for 5 steps"):
        import_stepping(tmp_path / "o.h5", sample=tmp_path / "data.npy", reference=tmp_path / "flat.npy",
                        phases=[0, 1, 2, 3])


@pytest.mark.parametrize("options", [{}, {"steps_per_period": 5, "phases": [0, 1, 2, 3, 4]}])
def test_both_or_neither_phase_rule(tmp_path, options):
    np.save(tmp_path / "data.npy", counts("uint16", seed=19))
    np.save(tmp_path / "flat.npy", counts("uint16", seed=20))
    with pytest.raises(StackImportError, match="steps_per_period.*phases"):
        import_stepping(tmp_path / "o.h5", sample=tmp_path / "data.npy", reference=tmp_path / "flat.npy",
                        **options)


def test_existing_output(tmp_path):
    out = tmp_path / "exists.h5"
    out.write_bytes(b"keep me")
    # The sample glob matches nothing: the output check must come first.
    with pytest.raises(FileExistsError, match="exists.h5") as info:
        import_stepping(out, sample=str(tmp_path / "none_*.npy"), reference=str(tmp_path / "none_*.npy"),
                        steps_per_period=S)
    assert isinstance(info.value, OutputExistsError) and isinstance(info.value, DfxcorrError)
    assert out.read_bytes() == b"keep me"
    np.save(tmp_path / "data.npy", counts("uint16", seed=21))
    import_stepping(out, sample=tmp_path / "data.npy", reference=tmp_path / "data.npy", steps_per_period=S,
                    overwrite=True)
    assert read_scan(out).shape == (S, H, W)


# ---- real data ----------------------------------------------------------------------------------------

@pytest.mark.shared
def test_real_stepping_recording(tmp_path):
    if not REAL.is_dir():
        pytest.skip(f"{REAL} not present")
    out = tmp_path / "ipp.h5"
    import_stepping(out, sample=str(REAL / "data_stepping_*.npy"), reference=str(REAL / "flat_stepping_*.npy"),
                    steps_per_period=11)
    scan = read_scan(out)
    assert scan.shape == (11, 195, 487)
    assert scan.data.dtype == np.uint32
    assert scan.reference.data.shape == (11, 195, 487)
    assert scan.reference.data.dtype == np.uint32
    for k in range(11):
        assert np.array_equal(scan.data[k], np.load(REAL / f"data_stepping_{k:04d}.npy"))
        assert np.array_equal(scan.reference.data[k], np.load(REAL / f"flat_stepping_{k:04d}.npy"))
    np.testing.assert_allclose(scan.phase_step, 2 * np.pi * np.arange(11) / 11, rtol=0, atol=1e-12)
    np.testing.assert_allclose(scan.reference.phase_step, 2 * np.pi * np.arange(11) / 11, rtol=0, atol=1e-12)
