"""The scan reader refuses everything the format forbids, naming the dataset."""
import h5py
import numpy as np
import pytest

from dfxcorr.io import Reference, Scan, ScanFormatError, SteppingReference, read_scan, write_scan

from conftest import shared_path


def make_scan(rng, J=6, H=8, W=5, A=3, dtype=np.uint16):
    ref = Reference(np.full((A, W), 100.0), np.full((A, W), 0.3), rng.uniform(0, 3, (A, W)))
    return Scan(data=rng.poisson(80, (J, H, W)).astype(dtype), position=np.linspace(-2, H - 1, J), reference=ref)


def test_round_trip_keeps_everything(tmp_path, rng):
    scan = make_scan(rng)
    scan.dark = rng.uniform(0, 2, scan.shape[1:])
    scan.gain = 2.5
    write_scan(tmp_path / "s.h5", scan)
    back = read_scan(tmp_path / "s.h5")
    assert back.data.dtype == np.uint16 and np.array_equal(back.data, scan.data)
    np.testing.assert_array_equal(back.position, scan.position)
    np.testing.assert_array_equal(back.dark, scan.dark)
    assert back.gain == 2.5
    np.testing.assert_array_equal(back.reference.phase, scan.reference.phase)


def test_stepping_reference_round_trip(tmp_path, rng):
    scan = make_scan(rng)
    scan.reference = SteppingReference(data=rng.poisson(90, (5, 3, 5)).astype(np.float32),
                                       phase_step=np.linspace(0, 2 * np.pi, 5, endpoint=False))
    write_scan(tmp_path / "s.h5", scan)
    back = read_scan(tmp_path / "s.h5")
    assert isinstance(back.reference, SteppingReference)
    np.testing.assert_array_equal(back.reference.data, scan.reference.data)


def corrupt(path, edit):
    with h5py.File(path, "r+") as f:
        edit(f)


def replace(path, dataset, value):
    def edit(f):
        if dataset in f:
            del f[dataset]
        f[dataset] = value
    corrupt(path, edit)


CASES = [
    ("missing data", lambda p: corrupt(p, lambda f: f.__delitem__("entry/instrument/detector/data")),
     "entry/instrument/detector/data"),
    ("missing position", lambda p: corrupt(p, lambda f: f.__delitem__("entry/scan/position")), "entry/scan/position"),
    ("missing reference", lambda p: corrupt(p, lambda f: f.__delitem__("entry/reference/phase")),
     "entry/reference/phase"),
    ("position length", lambda p: replace(p, "entry/scan/position", np.zeros(5)), "entry/scan/position"),
    ("position NaN", lambda p: replace(p, "entry/scan/position", np.array([0, 1, np.nan, 3, 4, 5.0])),
     "entry/scan/position"),
    ("phase_step inf", lambda p: replace(p, "entry/scan/phase_step", np.array([0, 1, np.inf, 3, 4, 5.0])),
     "entry/scan/phase_step"),
    ("reference width", lambda p: replace(p, "entry/reference/visibility", np.full((3, 4), 0.3)),
     "entry/reference/visibility"),
    ("visibility above 1", lambda p: replace(p, "entry/reference/visibility", np.full((3, 5), 1.2)),
     "entry/reference/visibility"),
    ("visibility zero", lambda p: replace(p, "entry/reference/visibility", np.zeros((3, 5))),
     "entry/reference/visibility"),
    ("transmission not positive", lambda p: replace(p, "entry/reference/transmission", np.zeros((3, 5))),
     "entry/reference/transmission"),
    ("negative counts", lambda p: replace(p, "entry/instrument/detector/data", -np.ones((6, 8, 5), np.float32)),
     "entry/instrument/detector/data"),
    ("NaN counts", lambda p: replace(p, "entry/instrument/detector/data", np.full((6, 8, 5), np.nan, np.float32)),
     "entry/instrument/detector/data"),
    ("dark shape",
     lambda p: corrupt(p, lambda f: f.create_dataset("entry/instrument/detector/dark", data=np.zeros((2, 2)))),
     "entry/instrument/detector/dark"),
    ("wrong format", lambda p: corrupt(p, lambda f: f.attrs.__setitem__("format", "something-else")), "format"),
    ("int8 frames", lambda p: replace(p, "entry/instrument/detector/data", np.ones((6, 8, 5), np.int8)),
     "entry/instrument/detector/data"),
]


@pytest.mark.parametrize("label,edit,name", CASES, ids=[c[0] for c in CASES])
def test_refusals_name_the_dataset(tmp_path, rng, label, edit, name):
    path = tmp_path / "s.h5"
    write_scan(path, make_scan(rng))
    edit(path)
    with pytest.raises(ScanFormatError, match=name.replace("/", ".")):
        read_scan(path)


def test_not_hdf5_is_refused(tmp_path):
    path = tmp_path / "not.h5"
    path.write_text("hello")
    with pytest.raises(ScanFormatError, match="not an HDF5 file"):
        read_scan(path)


def test_extra_datasets_are_ignored(tmp_path, rng):
    scan = make_scan(rng)
    write_scan(tmp_path / "s.h5", scan, extra={"entry/whatever/thing": np.arange(3)})
    assert read_scan(tmp_path / "s.h5").shape == scan.shape


@pytest.mark.shared
def test_shared_scans_load_as_they_are():
    for name in ("thorax-2.5mm.h5", "blank-2.5mm.h5"):
        scan = read_scan(shared_path("sim", name))
        assert scan.shape == (209, 180, 204) and scan.active_rows == 30 and not scan.is_stepping


# --------------------------------------------------------------------------------------------------
# A folder written as a unit
# --------------------------------------------------------------------------------------------------

RUN_FILES = ("report.md", "diagnosis.json", "pixel_noise.tif")


def _old_run(folder):
    folder.mkdir()
    for name in RUN_FILES:
        (folder / name).write_text("old run")
    (folder / "notes.txt").write_text("the user's")


def _contents(folder):
    return {p.name: p.read_text() for p in folder.iterdir()}


def test_a_folder_is_replaced_as_a_unit_and_other_files_stay(tmp_path):
    from dfxcorr.io import atomic_folder

    out = tmp_path / "diag"
    _old_run(out)
    out.chmod(0o750)
    with atomic_folder(out, names=RUN_FILES, overwrite=True) as tmp:
        (tmp / "report.md").write_text("new run")
        (tmp / "diagnosis.json").write_text("new run")
        assert _contents(out)["report.md"] == "old run"  # nothing of the new run shows before it is complete
    # the previous run's map is gone with it: this run did not write one
    assert _contents(out) == {"report.md": "new run", "diagnosis.json": "new run", "notes.txt": "the user's"}
    assert out.stat().st_mode & 0o777 == 0o750
    assert sorted(p.name for p in tmp_path.iterdir()) == ["diag"]


def test_a_folder_without_overwrite_refuses_a_run_that_appeared_meanwhile(tmp_path):
    from dfxcorr.errors import OutputExistsError
    from dfxcorr.io import atomic_folder

    out = tmp_path / "diag"
    with pytest.raises(OutputExistsError), atomic_folder(out, names=RUN_FILES) as tmp:
        (tmp / "report.md").write_text("new run")
        _old_run(out)
    assert _contents(out)["report.md"] == "old run"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["diag"]


@pytest.mark.parametrize("stop", [KeyboardInterrupt, SystemExit, MemoryError])
def test_an_interrupted_folder_leaves_the_previous_run_and_no_temporary_folder(tmp_path, stop):
    from dfxcorr.io import atomic_folder

    out = tmp_path / "diag"
    _old_run(out)
    before = _contents(out)
    with pytest.raises(stop), atomic_folder(out, names=RUN_FILES, overwrite=True) as tmp:
        (tmp / "report.md").write_text("new run")
        raise stop()
    assert _contents(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["diag"]


@pytest.mark.parametrize("signum", ["SIGINT", "SIGTERM", "SIGHUP"])
def test_a_signal_during_the_swap_is_held_until_it_is_complete(tmp_path, monkeypatch, signum):
    import os
    import signal
    import threading
    import time

    from dfxcorr.io import atomic_folder, write

    sig = getattr(signal, signum)

    def stop(signum, frame):
        raise SystemExit(128 + signum)

    previous = signal.signal(sig, stop)
    rename = os.rename

    def rename_then_signal(a, b):  # the signal arrives between the swap's renames
        rename(a, b)
        os.kill(os.getpid(), sig)

    out = tmp_path / "diag"
    _old_run(out)
    # another thread (numba's, a pool's): the kernel may hand it the signal, Python still acts on it in this one
    threading.Thread(target=time.sleep, args=(1,), daemon=True).start()
    monkeypatch.setattr(write.os, "rename", rename_then_signal)
    try:
        with pytest.raises(SystemExit), atomic_folder(out, names=RUN_FILES, overwrite=True) as tmp:
            (tmp / "report.md").write_text("new run")
    finally:
        signal.signal(sig, previous)
    assert _contents(out) == {"report.md": "new run", "notes.txt": "the user's"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["diag"]


def test_concurrent_runs_into_one_folder_leave_one_run_whole(tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    from dfxcorr.io import atomic_folder

    out = tmp_path / "diag"
    _old_run(out)

    def one(run):
        for k in range(20):
            with atomic_folder(out, names=RUN_FILES, overwrite=True) as tmp:
                for name in RUN_FILES[:2]:
                    (tmp / name).write_text(f"{run} {k}")

    with ThreadPoolExecutor(3) as pool:
        list(pool.map(one, ["run a", "run b", "run c"]))
    # whatever run swapped in last, its files are all there and alone, the user's file kept through 60 swaps
    files = _contents(out)
    assert set(files) == {*RUN_FILES[:2], "notes.txt"} and files["report.md"] == files["diagnosis.json"]
    assert files["notes.txt"] == "the user's"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["diag"]
