"""Property-based fuzzing of the inputs: random mutations of a small valid scan (shapes, dtypes, values,
attributes, links, missing or unstored datasets) and of a configuration's YAML text. Every outcome is exit 0 with
a valid result or exit 2 with one line and nothing written; never a traceback, always within a memory cap (the
run happens in a forked child, see tests/capped.py). Seeded (derandomize) and bounded; no example database."""
import shutil
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from dfxcorr.export import read_result_h5
from dfxcorr.io import write_scan

from conftest import cli_capped, invoke, one_error_line

DET = "entry/instrument/detector"
DATASETS = [f"{DET}/data", "entry/scan/position", "entry/scan/phase_step", "entry/scan/exposure_time",
            f"{DET}/dark", f"{DET}/gain", f"{DET}/x_pixel_size", f"{DET}/y_pixel_size",
            "entry/reference/transmission", "entry/reference/visibility", "entry/reference/phase"]
GROUPS = ["entry", "entry/scan", "entry/reference", DET]
SETTINGS = {"derandomize": True, "database": None, "deadline": None, "print_blob": True,
            "suppress_health_check": [HealthCheck.too_slow, HealthCheck.function_scoped_fixture]}
# a few ML iterations exercise the fit on whatever passes the checks without taking long
FAST = ["--set", "fit.subsample=4", "--set", "fit.maxiter=3", "--set", "fit.reweight=0",
        "--set", "retrieve.iterations=1"]


@pytest.fixture(scope="module")
def template(tmp_path_factory):
    """A valid scan of 25 frames of 22 x 26 pixels (20 mm pixels), with every optional dataset present."""
    from dfxcorr.sim import simulate as S

    from conftest import sim_config

    scan, _ = S.simulate(sim_config(**{"simulate.pixel_mm": 20, "simulate.step_mm": 20}))
    scan.dark = np.full(scan.shape[1:], 0.5)
    scan.exposure_time = np.full(scan.shape[0], 0.1)
    scan.phase_step = np.linspace(0, 0.1, scan.shape[0])
    path = tmp_path_factory.mktemp("fuzz") / "template.h5"
    write_scan(path, scan)
    # compile the numba kernels here once, so that each forked child does not
    outcome = invoke(["reconstruct", path, "-o", path.with_name("warm.h5"), *FAST])
    assert outcome.exit_code == 0, outcome
    return path


def _replace(f, path, make):
    if path in f or f.get(path, getlink=True) is not None:
        del f[path]
    parent = path.rsplit("/", 1)[0] if "/" in path else "/"
    if parent not in f:
        f.create_group(parent)
    make(f, path)


def _values(shape, rng):
    return rng.uniform(0.2, 0.8, shape) if shape else 0.5


SPECIAL = [np.nan, np.inf, -np.inf, -1.0, 0.0, 1e300, 1e-300, 2.0 ** 40, 1e39]
DTYPES = ["int8", "bool", "float16", "complex64", "uint64", "int64", "string", "compound"]
VERSIONS = ["1", 1.5, 2, 0, -1, True, np.array([1, 1]), np.float64(1.0), b"1"]


def mutate(f, op, path, k, rng):
    """Apply mutation ``op`` (with variant number ``k``) to ``path`` of the open file ``f``."""
    old = f.get(path) if path in f else None
    if op == "delete":
        if old is not None or f.get(path, getlink=True) is not None:
            del f[path]
    elif op == "shape":
        ndim = k % 4
        shape = tuple(int(rng.integers(0, 7)) for _ in range(ndim))
        _replace(f, path, lambda f, p: f.create_dataset(p, data=_values(shape, rng)))
    elif op == "dtype" and isinstance(old, h5py.Dataset) and old.shape is not None:
        kind = DTYPES[k % len(DTYPES)]
        shape = old.shape
        values = None if kind in ("string", "compound") else np.asarray(old[()])

        def make(f, p):
            if kind == "string":
                return f.create_dataset(p, data=np.full(shape, "x", dtype=object), dtype=h5py.string_dtype())
            if kind == "compound":
                return f.create_dataset(p, data=np.zeros(shape, dtype=[("a", "f8"), ("b", "i2")]))
            return f.create_dataset(p, data=np.real(values).astype(kind) if kind != "int64"
                                    else -np.abs(values).astype(kind))
        _replace(f, path, make)
    elif op == "values" and isinstance(old, h5py.Dataset) and old.shape is not None and old.dtype.kind == "f":
        values = np.array(old[()], dtype=np.float64)
        special = SPECIAL[k % len(SPECIAL)]
        if values.ndim == 0 or k % 2:
            values = np.full_like(values, special)
        else:
            values.reshape(-1)[int(rng.integers(values.size))] = special
        _replace(f, path, lambda f, p: f.create_dataset(p, data=values.astype(old.dtype)))
    elif op == "unstored" and isinstance(old, h5py.Dataset) and old.shape:
        shape = (old.shape[0] * (1 + k % 3 * 1000),) + old.shape[1:]
        chunks = (1,) + old.shape[1:] if k % 2 else None
        _replace(f, path, lambda f, p: f.create_dataset(p, shape=shape, dtype=old.dtype, chunks=chunks))
    elif op == "softlink":
        target = ["/nowhere", "/" + path, "/" + DATASETS[k % len(DATASETS)], "/entry"][k % 4]
        _replace(f, path, lambda f, p: f.__setitem__(p, h5py.SoftLink(target)))
    elif op == "extlink":
        target = ["missing.h5", "template.h5"][k % 2]
        _replace(f, path, lambda f, p: f.__setitem__(p, h5py.ExternalLink(target, "/" + path)))
    elif op == "group":
        _replace(f, path, lambda f, p: f.create_group(p))
    elif op == "empty":
        _replace(f, path, lambda f, p: f.create_dataset(p, data=h5py.Empty("f8")))
    elif op == "external_raw" and isinstance(old, h5py.Dataset) and old.shape:
        size = old.size * old.dtype.itemsize
        _replace(f, path, lambda f, p: f.create_dataset(p, shape=old.shape, dtype=old.dtype,
                                                        external=[("frames.raw", 0, size)]))
    elif op == "attribute":
        if k % 6 == 0:
            f.attrs["format"] = "dfxcorr-result"
        elif k % 6 == 1:
            del f.attrs["format_version"]
        elif k % 6 == 2:
            f.attrs["operator"] = np.bytes_(b"M\xfcller")  # not UTF-8
        else:
            f.attrs["format_version"] = VERSIONS[k % len(VERSIONS)]
    elif op == "fault" and f"{DET}/data" in f and isinstance(f[f"{DET}/data"], h5py.Dataset):
        fault(f[f"{DET}/data"], k, rng)
    elif op == "unlit" and isinstance(old, h5py.Dataset) and old.shape:
        # every position far off the detector (or a few frames only on it)
        values = np.full(old.shape, 1e4 if k % 2 else -1e4)
        values[:k % 3] = 0.0
        _replace(f, path, lambda f, p: f.create_dataset(p, data=values))


def fault(frames, k, rng):
    """A detector fault in the frames: a frame of zeros, a frame read twice, saturated samples, a saturated half."""
    if frames.ndim != 3 or frames.dtype.kind not in "uif" or 0 in frames.shape:
        return
    j = int(rng.integers(1, frames.shape[0])) if frames.shape[0] > 1 else 0
    top = np.iinfo(frames.dtype).max if frames.dtype.kind in "ui" else 1e6
    if k % 4 == 0:
        frames[j] = 0
    elif k % 4 == 1 and j:
        frames[j] = frames[j - 1]
    elif k % 4 == 2:
        block = frames[j]
        block[:, : max(block.shape[1] // 4, 1)] = top
        frames[j] = block
    else:
        for i in range(frames.shape[0]):
            block = frames[i]
            block[:, block.shape[1] // 2:] = top
            frames[i] = block


OPS = ["delete", "shape", "dtype", "values", "unstored", "softlink", "extlink", "group", "empty", "external_raw",
       "attribute", "fault", "unlit"]
mutations = st.lists(st.tuples(st.sampled_from(OPS), st.sampled_from(DATASETS + GROUPS), st.integers(0, 99)),
                     min_size=1, max_size=3)


def assert_clean(outcome, out: Path):
    """Exit 0 with a readable result, or exit 2 with one error line and no output; never a traceback."""
    assert outcome.traceback == "", outcome.traceback
    assert outcome.exit_code in (0, 2), outcome
    errors = [ln for ln in outcome.stderr.splitlines() if ln.startswith("error:")]
    event(f"exit {outcome.exit_code}" + (f": {' '.join(errors[0].split()[1:3])}" if errors else ""))
    if outcome.exit_code == 0:
        assert read_result_h5(out)["transmission"].ndim == 2
    else:
        assert one_error_line(outcome.stderr), outcome.stderr
        assert not out.exists() and not list(out.parent.glob(".*part"))


def mutated_scan_ends_cleanly(template, mutations, seed, method):
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = tmp / "scan.h5"
        shutil.copy(template, path)
        shutil.copy(template, tmp / "template.h5")
        with h5py.File(path, "r+") as f:
            for op, name, k in mutations:
                try:
                    mutate(f, op, name, k, rng)
                except (ValueError, KeyError, TypeError, OSError, RuntimeError):
                    pass  # a mutation h5py cannot make here (e.g. a dataset under what became a link)
        out = tmp / "out" / "result.h5"
        out.parent.mkdir()
        assert_clean(cli_capped("reconstruct", path, "-o", out, "--method", method, *FAST), out)


scan_mutations = given(mutations=mutations, seed=st.integers(0, 2 ** 16),
                       method=st.sampled_from(["none", "none", "none", "ml"]))


# a few examples in the fast tier, many in the slow one (80 ms each)
@settings(max_examples=4, **SETTINGS)
@scan_mutations
def test_a_few_mutated_scans_end_cleanly(template, mutations, seed, method):
    mutated_scan_ends_cleanly(template, mutations, seed, method)


@pytest.mark.slow
@settings(max_examples=150, **SETTINGS)
@scan_mutations
def test_mutated_scans_end_cleanly(template, mutations, seed, method):
    mutated_scan_ends_cleanly(template, mutations, seed, method)


VALID_YAML = """fit:
  method: none
  subsample: 4
align:
  min_frames: 3
  min_visibility: auto
vibration:
  tilt: true
"""
YAML_BITS = [":", "-", "[", "]", "{", "}", "\t", "&a", "*a", "!!python/object", "!!binary", "0x1", "1e999", "nan",
             "~", "\n", "  ", "'", '"', "%", "<<: *a", "\x00", "\u2028", "yes", "null", "?", ",", "#"]


def mutated_config_ends_cleanly(edits):
    text = VALID_YAML
    for at, bit, drop in edits:
        text = text[:at] + bit + text[at + drop:]
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "c.yaml"
        cfg.write_text(text, encoding="utf-8", errors="surrogatepass")
        outcome = cli_capped("config", "--check", cfg)
        assert outcome.traceback == "", outcome.traceback
        assert outcome.exit_code in (0, 2), outcome
        if outcome.exit_code == 2:
            assert one_error_line(outcome.stderr), outcome.stderr


yaml_edits = given(edits=st.lists(st.tuples(st.integers(0, len(VALID_YAML)), st.sampled_from(YAML_BITS),
                                            st.integers(0, 3)), min_size=1, max_size=4))


@settings(max_examples=10, **SETTINGS)
@yaml_edits
def test_a_few_mutated_configs_end_cleanly(template, edits):
    mutated_config_ends_cleanly(edits)


@pytest.mark.slow
@settings(max_examples=60, **SETTINGS)
@yaml_edits
def test_mutated_configs_end_cleanly(template, edits):
    mutated_config_ends_cleanly(edits)


#: Configuration numbers beyond what makes sense (fit.reweight=10**31 raised OverflowError).
ABSURD = ["10000000000000000000000000000000", "-10000000000000000000000000000000", "1e300", "-1e300", "0", "-1",
          "9223372036854775808", ".inf", "1e-300"]


def _numeric_keys():
    from dfxcorr import config as C

    return sorted(f"{s}.{k}" for s, opts in C.SCHEMA.items() for k, o in opts.items()
                  if int in (o.kind if isinstance(o.kind, tuple) else (o.kind,)))


def absurd_numbers_end_cleanly(template, sets):
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "r.h5"
        args = [a for key, value in sets for a in ("--set", f"{key}={value}")]
        outcome = cli_capped("reconstruct", template, "-o", out, "--method", "none", *FAST, *args, timeout=60)
        assert_clean(outcome, out)


absurd_sets = given(sets=st.lists(st.tuples(st.sampled_from(_numeric_keys()), st.sampled_from(ABSURD)),
                                  min_size=1, max_size=2))


@settings(max_examples=15, **SETTINGS)
@absurd_sets
def test_a_few_absurd_configuration_numbers_end_cleanly(template, sets):
    absurd_numbers_end_cleanly(template, sets)


@pytest.mark.slow
@settings(max_examples=200, **SETTINGS)
@absurd_sets
def test_absurd_configuration_numbers_end_cleanly(template, sets):
    absurd_numbers_end_cleanly(template, sets)


#: Configurations a careless script passes beside a mutated scan: effects the scan may not determine, a
#: diagnosis subsampling beyond it.
TWISTS = [[], ["vibration.background=true"], ["vibration.dose=true"], ["vibration.curvature=true"],
          ["diagnose.subsample=1000"], ["align.min_frames=4"]]


def judged_alike(template, mutations, seed, twist):
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = tmp / "scan.h5"
        shutil.copy(template, path)
        with h5py.File(path, "r+") as f:
            for op, name, k in mutations:
                try:
                    mutate(f, op, name, k, rng)
                except (ValueError, KeyError, TypeError, OSError, RuntimeError):
                    pass
        out = tmp / "out" / "result.h5"
        out.parent.mkdir()
        args = [*FAST, *(a for s in twist for a in ("--set", s))]
        checked = cli_capped("check", path, "-o", out, *args)
        assert checked.traceback == "", checked.traceback
        done = cli_capped("reconstruct", path, "-o", out, *args)
        assert_clean(done, out)
        assert checked.exit_code == done.exit_code, (checked.stderr, done.stderr)


alike_cases = given(mutations=st.lists(st.tuples(st.sampled_from(["fault", "values", "unlit", "delete"]),
                                                 st.sampled_from(DATASETS), st.integers(0, 99)), max_size=2),
                    seed=st.integers(0, 2 ** 16), twist=st.sampled_from(TWISTS))


@settings(max_examples=3, **SETTINGS)
@alike_cases
def test_check_and_reconstruct_judge_a_few_mutated_scans_alike(template, mutations, seed, twist):
    judged_alike(template, mutations, seed, twist)


@pytest.mark.slow
@settings(max_examples=60, **SETTINGS)
@alike_cases
def test_check_and_reconstruct_judge_mutated_scans_alike(template, mutations, seed, twist):
    judged_alike(template, mutations, seed, twist)
