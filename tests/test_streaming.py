"""Streaming: frames read lazily, row blocks, one preparation for every analysis, every column of a small scan,
frame-by-frame simulation."""
import itertools
import json
import subprocess
import sys
from dataclasses import replace

import h5py
import numpy as np
import pytest

from dfxcorr import align, pipeline, planning
from dfxcorr import config as C
from dfxcorr import model as M
from dfxcorr.analysis import diagnose as D
from dfxcorr.catalogue import PAPER_MODEL
from dfxcorr.fit import fit_vibrations
from dfxcorr.io import H5Frames, Reference, Scan, read_scan, write_scan
from dfxcorr.retrieve import retrieve
from dfxcorr.sim import simulate as S

from conftest import ROOT, prepare, sim_config


def _open_files() -> int:
    return h5py.h5f.get_obj_count(h5py.h5f.OBJ_ALL, h5py.h5f.OBJ_FILE)


def test_lazy_scan_reads_only_the_lit_rows_and_those_just_left_and_closes_the_file(tmp_path, small_scan, monkeypatch):
    scan, _ = small_scan()
    write_scan(tmp_path / "s.h5", scan)
    lazy = read_scan(tmp_path / "s.h5")
    assert isinstance(lazy.data, H5Frames) and _open_files() == 0
    reads = []
    real = align.frame_rows
    monkeypatch.setattr(align, "frame_rows", lambda data, j, r0, r1: reads.append((j, r0, r1)) or real(data, j, r0, r1))
    store = align.collect_lit_rows(lazy)
    assert _open_files() == 0
    row, frame, _ = align.lit_blocks(scan.position, scan.active_rows, scan.shape[1])
    lit = {(int(f), int(r)) for r, f in zip(row, frame, strict=True)}
    read = {(j, r) for j, r0, r1 in reads for r in range(r0, r1)}
    # the rows the active area has just left (lit in j - 1, not in j), which measure the detector lag
    left = {(f + 1, r) for f, r in lit if (f + 1, r) not in lit and f + 1 < scan.shape[0]}
    # one hyperslab per frame, and nothing but lit rows and those just left (rows lit too rarely to enter
    # are skipped)
    assert len(reads) == len({j for j, _, _ in reads}) and read <= lit | left
    held = {(int(f), int(r)) for r, f in zip(store.row, store.frame, strict=True)}
    held_left = {(int(store.frame[k]) + 1, int(store.row[k])) for k in store.left_prev}
    assert held | held_left == read and held_left <= left
    np.testing.assert_array_equal(store.counts, scan.data[store.frame, store.row])
    np.testing.assert_array_equal(store.left_counts, scan.data[store.frame[store.left_prev] + 1,
                                                               store.row[store.left_prev]])


@pytest.mark.slow
def test_reading_a_scan_holds_a_fraction_of_its_frames(tmp_path):
    # 100 frames of 800 x 800 uint16 (128 MB) with a 40-row active area: the lit rows are 5 MB
    J, H, W, A = 100, 800, 800, 40
    position = np.linspace(-A + 1, H - 1, J)
    ref = Reference(np.full((A, W), 1e3), np.full((A, W), 0.3), np.zeros((A, W)))
    rng = np.random.default_rng(7)
    shell = Scan(data=np.broadcast_to(np.zeros((), np.uint16), (J, H, W)), position=position, reference=ref)
    write_scan(tmp_path / "big.h5", shell, compression="lzf",
               frames=((j, 0, rng.integers(0, 2000, (H, W), dtype=np.uint16)) for j in range(J)))
    code = f"""
import resource, json
from dfxcorr.io import read_scan
from dfxcorr.align import collect_lit_rows
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
store = collect_lit_rows(read_scan({str(tmp_path / 'big.h5')!r}))
print(json.dumps([base, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, store.counts.nbytes]))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    base_kb, peak_kb, store_bytes = json.loads(out.stdout)
    data_mb, grown_mb = J * H * W * 2 / 2 ** 20, (peak_kb - base_kb) / 1024
    assert grown_mb < store_bytes / 2 ** 20 + 0.25 * data_mb, (grown_mb, data_mb)


@pytest.fixture(scope="module")
def prepared_scan():
    scan, truth = S.simulate(sim_config(**{"simulate.seed": 4}))
    return scan, truth


@pytest.mark.slow
def test_row_blocks_give_the_images_of_one_pass(prepared_scan):
    scan, _ = prepared_scan
    base = ["fit.subsample=3", "fit.maxiter=60", "retrieve.uncorrected=true"]
    tiny = pipeline.reconstruct(scan, C.load([], base + ["retrieve.block_mb=0.000001"]))
    huge = pipeline.reconstruct(scan, C.load([], base + ["retrieve.block_mb=100000"]))
    for name in ("transmission", "dark_field", "differential_phase"):
        np.testing.assert_allclose(tiny.__dict__[name], huge.__dict__[name], rtol=1e-10, atol=1e-12, equal_nan=True)
        np.testing.assert_allclose(tiny.uncorrected[name], huge.uncorrected[name], rtol=1e-10, atol=1e-12,
                                   equal_nan=True)
    np.testing.assert_array_equal(tiny.motion_mask, huge.motion_mask)
    assert tiny.reduced_chi2 == pytest.approx(huge.reduced_chi2, rel=1e-10)
    # and both equal one retrieval holding every sample (in float32, as the pipeline's), with reduced_chi2's own
    # degrees of freedom
    prep = prepare(scan, C.defaults())
    obs = prep.observations(dtype=np.float32)
    fitted = {k: v for k, v in tiny.params.items() if tiny.estimated[k]}
    whole = retrieve(replace(obs, use=obs.roi), fitted)
    assert tiny.reduced_chi2 == pytest.approx(whole.reduced_chi2, rel=1e-10)
    np.testing.assert_allclose(tiny.dark_field, obs.to_image(whole.images.v * np.where(whole.images.valid, 1, np.nan)),
                               rtol=1e-10, equal_nan=True)


def test_observations_are_c_ordered_whatever_the_store(prepared_scan):
    """The kernels walk one sample row at a time: a Fortran-ordered store must not reach them as such."""
    scan, _ = prepared_scan
    prep = prepare(scan, C.defaults())
    prep.store.counts = np.asfortranarray(prep.store.counts)
    for columns in (None, np.arange(0, scan.shape[2], 3)):
        obs = prep.observations(columns=columns, dtype=np.float32)
        assert all(getattr(obs, n).flags["C_CONTIGUOUS"] for n in ("counts", "tf", "fc", "fs", "dark", "use"))


def test_row_blocks_follow_the_memory_budget(prepared_scan):
    scan, _ = prepared_scan
    store = prepare(scan, C.defaults()).store
    for mb in (1e-6, 0.05, 0.3, 1e5):
        blocks = planning.row_blocks(store, mb)
        assert blocks[0][0] == store.row.min() and blocks[-1][1] == store.row.max() + 1
        assert all(a[1] == b[0] for a, b in itertools.pairwise(blocks))
        per_row = np.bincount(store.row)
        cap = mb * 1e6 / (planning.BYTES_PER_SAMPLE * scan.shape[2])
        # a block exceeds the budget only when it is a single row
        assert all(r1 - r0 == 1 or per_row[r0:r1].sum() <= cap for r0, r1 in blocks)


@pytest.mark.slow
def test_float32_fit_agrees_with_float64_within_its_uncertainty(prepared_scan):
    scan, _ = prepared_scan
    prep = prepare(scan, C.defaults())
    cols = np.arange(1, scan.shape[2], 3)
    fits = {dt: fit_vibrations(prep.observations(columns=cols, dtype=dt), effects=PAPER_MODEL)
            for dt in (np.float32, np.float64)}
    assert fits[np.float32].converged and fits[np.float64].converged
    good = fits[np.float64].well_determined
    for name in ("phase_offset", "tilt"):
        diff = np.abs(fits[np.float32].params[name] - fits[np.float64].params[name])[good]
        assert diff.max() < 0.1 * np.median(fits[np.float64].uncertainty[name][good])


@pytest.mark.slow
def test_diagnose_and_reconstruct_see_the_same_data(monkeypatch):
    # a reference stepping series with non-default reference options and region of interest
    scan, _ = S.simulate(sim_config(**{"simulate.reference_steps": 5, "simulate.reference_step_errors": 0.05,
                                       "simulate.seed": 8}))
    # (the per-frame terms are left out: with v^f cut at random, some edge frames see no fringe at all)
    cfg = C.load([], ["reference.step_errors=false", "align.min_visibility=0.28", "diagnose.max_rounds=1",
                      "vibration.phase_offset=false", "vibration.tilt=false", "vibration.visibility=false",
                      "fit.method=none", "mask.enabled=false"])
    seen, real = [], pipeline.prepare

    def spy(*args, **kwargs):
        seen.append(real(*args, **kwargs))
        return seen[-1]
    monkeypatch.setattr(pipeline, "prepare", spy)
    monkeypatch.setattr(D, "prepare", spy)
    pipeline.reconstruct(scan, cfg)
    D.diagnose(scan, cfg)
    assert len(seen) == 2
    a, b = (p.observations() for p in seen)
    for name in ("counts", "tf", "fc", "fs", "dark", "row", "frame", "columns"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(a.roi, b.roi)
    assert a.gain == b.gain and a.electronic == b.electronic
    # the options took effect: another reference (nominal steps) and a region of interest cut by v^f
    default = prepare(scan, C.defaults())
    assert not np.allclose(default.reference.phase, seen[0].reference.phase)
    assert 0 < a.roi.mean() < 1 and np.all(a.fc[~a.roi] == 0) and np.all(a.fs[~a.roi] == 0)


@pytest.mark.slow
def test_subsample_auto_fits_every_column_of_a_small_scan(small_scan):
    scan, _ = small_scan()
    result = pipeline.reconstruct(scan, C.load([], ["fit.maxiter=30", "retrieve.uncorrected=false"]))
    lit = np.isfinite(result.transmission).any(axis=0)
    assert np.all(result.fit_mask.any(axis=0)[lit])


def test_simulated_file_holds_the_in_memory_frames(tmp_path):
    cfg = sim_config(**{"simulate.seed": 5, "effects.sample_motion": 0.2})
    scan, truth = S.simulate(cfg)
    _, truth_file = S.simulate_file(cfg, tmp_path / "s.h5")
    back = read_scan(tmp_path / "s.h5")
    with back.data.open() as dset:
        np.testing.assert_array_equal(dset[()], scan.data)
    for key, value in truth.items():
        np.testing.assert_array_equal(truth_file[key], value)
    # each frame draws its noise from its own stream: any order gives the same frames
    sim = S.Simulation(cfg)
    for j in (40, 3, 77):
        r0, counts = sim.frame_counts(j)
        np.testing.assert_array_equal(np.rint(counts), scan.data[j, r0:r0 + counts.shape[0]])


def test_simulated_noise_is_poisson_about_the_model():
    cfg = sim_config(**{"simulate.seed": 6})
    sim = S.Simulation(cfg)
    scan, _ = S.simulate(cfg)
    obs = align.build_observations(scan, sim.flat, min_frames=1)
    t, v, phi = (sim.images[k][obs.rows] for k in ("transmission", "dark_field", "differential_phase"))
    images = M.Images(np.stack([t, t * v * np.cos(phi), t * v * np.sin(phi)], axis=-1), np.ones(t.shape, bool))
    ibar = M.expected(obs, M.design(obs, sim.params), images)
    z = (obs.counts - ibar) ** 2 / ibar
    # every lit sample is simulated, and its Pearson residual has mean 1 (rounding adds 1 / (12 Ibar))
    assert np.all(ibar > 0) and abs(z.mean() - 1) < 5 * np.sqrt(2 / z.size)
