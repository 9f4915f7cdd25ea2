"""Hostile or broken scan files: every one is refused before anything unsized is read, in one line naming the
dataset, with exit code 2 on the command line and no output left behind."""
import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from dfxcorr.cli import main
from dfxcorr.export import read_result_h5
from dfxcorr.io import Reference, Scan, ScanFormatError, read_scan, write_scan

from conftest import cli_capped, one_error_line

DET = "entry/instrument/detector"


def make_scan(rng, J=6, H=8, W=5, A=3):
    ref = Reference(np.full((A, W), 100.0), np.full((A, W), 0.3), rng.uniform(0, 3, (A, W)))
    return Scan(data=rng.poisson(80, (J, H, W)).astype(np.uint16), position=np.linspace(-2, H - 1, J), reference=ref)


@pytest.fixture
def scan_path(tmp_path, rng):
    path = tmp_path / "s.h5"
    write_scan(path, make_scan(rng))
    return path


def edit(path, func):
    with h5py.File(path, "r+") as f:
        func(f)


def put(name, value=None, **kwargs):
    def func(f):
        if name in f or name in f.attrs:
            del f[name]
        f.create_dataset(name, data=value, **kwargs)
    return func


def huge_declaration(f):
    """20000 x 180 x 204 frames declared in a file of a few kB: the chunks were never written."""
    del f[f"{DET}/data"], f["entry/scan/position"]
    f.create_dataset(f"{DET}/data", shape=(20000, 180, 204), dtype=np.uint16, chunks=(1, 180, 204),
                     compression="gzip")
    f.create_dataset("entry/scan/position", data=np.zeros(20000))
    for m, value in (("transmission", 1e4), ("visibility", 0.3), ("phase", 0.0)):  # consistent but for storage
        del f[f"entry/reference/{m}"]
        f.create_dataset(f"entry/reference/{m}", data=np.full((3, 204), value))


def contiguous_unwritten(f):
    del f[f"{DET}/data"]
    f.create_dataset(f"{DET}/data", shape=(6, 8, 5), dtype=np.float64)


def soft(name, target):
    def func(f):
        del f[name]
        f[name] = h5py.SoftLink(target)
    return func


def loop(f):
    del f["entry/scan/position"]
    f["entry/scan/a"] = h5py.SoftLink("/entry/scan/b")
    f["entry/scan/b"] = h5py.SoftLink("/entry/scan/a")
    f["entry/scan/position"] = h5py.SoftLink("/entry/scan/a")


def named_type(f):
    del f["entry/scan/position"]
    f["entry/scan/position"] = np.dtype("f8")


def attr(name, value):
    return lambda f: f.attrs.__setitem__(name, value)


STR = h5py.string_dtype()
CASES = [
    ("declared size without storage", huge_declaration, f"{DET}/data.*chunks"),
    ("contiguous data never written", contiguous_unwritten, f"{DET}/data.*not in the file"),
    ("string position", put("entry/scan/position", np.array(["a"] * 6, dtype=object), dtype=STR),
     "entry/scan/position.*dtype"),
    ("compound gain", put(f"{DET}/gain", np.zeros((), dtype=[("a", "f8"), ("b", "i4")])), f"{DET}/gain.*dtype"),
    ("string dark", put(f"{DET}/dark", "dark", dtype=STR), f"{DET}/dark.*dtype"),
    ("string pixel size", put(f"{DET}/x_pixel_size", "55 um", dtype=STR), f"{DET}/x_pixel_size.*dtype"),
    ("empty gain", put(f"{DET}/gain", np.zeros(0)), f"{DET}/gain.*scalar"),
    ("three gains", put(f"{DET}/gain", np.array([2.0, 3.0, 4.0])), f"{DET}/gain.*scalar"),
    ("format_version string", attr("format_version", "1"), "format_version"),
    ("format_version 1.5", attr("format_version", 1.5), "format_version"),
    ("dangling soft link", soft("entry/scan/position", "/nowhere"), "entry/scan/position.*dangling"),
    ("soft link loop", loop, "entry/scan/position"),
    ("named datatype", named_type, "entry/scan/position.*named datatype"),
    ("position is a group", lambda f: (f.__delitem__("entry/scan/position"), f.create_group("entry/scan/position")),
     "entry/scan/position.*group"),
    ("null dataspace", put(f"{DET}/dark", h5py.Empty("f8")), f"{DET}/dark.*empty"),
    ("reference map declared, not stored",
     lambda f: (f.__delitem__("entry/reference/phase"),
                f.create_dataset("entry/reference/phase", shape=(3, 5), dtype="f8")),
     "entry/reference/phase.*not in the file"),
    ("exposure_time in a system file", put("entry/scan/exposure_time", shape=(6,), dtype="f8",
                                            external=[("/etc/passwd", 0, 48)]), "exposure_time.*external raw"),
    ("dark declared huge", put(f"{DET}/dark", shape=(100000, 100000), dtype="f8", chunks=(100, 100)),
     f"{DET}/dark"),
]


@pytest.mark.parametrize("label,func,match", CASES, ids=[c[0] for c in CASES])
def test_refused_naming_the_dataset(scan_path, label, func, match):
    edit(scan_path, func)
    with pytest.raises(ScanFormatError, match=match):
        read_scan(scan_path)


def test_one_element_gain_and_soft_link_are_accepted(scan_path):
    edit(scan_path, put(f"{DET}/gain", np.array([2.5])))
    edit(scan_path, lambda f: f.move("entry/scan/position", "entry/scan/real_position"))
    edit(scan_path, lambda f: f.__setitem__("entry/scan/position", h5py.SoftLink("real_position")))
    scan = read_scan(scan_path)
    assert scan.gain == 2.5 and scan.position.shape == (6,)


def _outside_file(tmp_path, kind):
    """A scan with one dataset outside the file: an external link, external raw frames or a virtual dataset."""
    path = tmp_path / "s.h5"
    scan = make_scan(np.random.default_rng(3))
    write_scan(path, scan)
    other = tmp_path / "other.h5"
    with h5py.File(path, "r+") as f:
        if kind == "external link":
            with h5py.File(other, "w") as g:
                g["exposure"] = np.full(6, 0.1)
            f["entry/scan/exposure_time"] = h5py.ExternalLink(other.name, "/exposure")
        elif kind == "external raw":
            raw = tmp_path / "frames.raw"
            scan.data.tofile(raw)
            del f[f"{DET}/data"]
            f.create_dataset(f"{DET}/data", shape=scan.data.shape, dtype=scan.data.dtype,
                             external=[(str(raw), 0, scan.data.nbytes)])
        else:
            with h5py.File(other, "w") as g:
                g["frames"] = scan.data
            layout = h5py.VirtualLayout(shape=scan.data.shape, dtype=scan.data.dtype)
            layout[:] = h5py.VirtualSource(other.name, "frames", shape=scan.data.shape)
            del f[f"{DET}/data"]
            f.create_virtual_dataset(f"{DET}/data", layout)
    return path, scan


@pytest.mark.parametrize("kind,match", [("external link", "exposure_time.*external link"),
                                        ("external raw", "data.*external raw"),
                                        ("virtual dataset", "data.*virtual dataset")])
def test_storage_outside_the_file_is_refused_unless_allowed(tmp_path, kind, match):
    path, scan = _outside_file(tmp_path, kind)
    with pytest.raises(ScanFormatError, match=match + ".*load.allow_external"):
        read_scan(path)
    back = read_scan(path, allow_external=True)
    np.testing.assert_array_equal(back.data, scan.data)
    expected = "frames.raw" if kind == "external raw" else "other.h5"
    assert [p.rsplit("/", 1)[1] for p in back.external_files] == [expected]


def test_external_raw_too_short_is_refused(tmp_path):
    path, _ = _outside_file(tmp_path, "external raw")
    (tmp_path / "frames.raw").write_bytes(b"\0" * 10)
    with pytest.raises(ScanFormatError, match="external files hold 10"):
        read_scan(path, allow_external=True)


def test_cli_refuses_in_one_line_and_leaves_nothing(tmp_path):
    path, _ = _outside_file(tmp_path, "external link")
    out = tmp_path / "r.h5"
    res = CliRunner().invoke(main, ["reconstruct", str(path), "-o", str(out)])
    assert res.exit_code == 2 and isinstance(res.exception, SystemExit)
    assert one_error_line(res.stderr, "exposure_time")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.h5", "s.h5"]


@pytest.mark.slow
def test_allowed_external_files_are_hashed_into_the_provenance(tmp_path, small_scan):
    scan, _ = small_scan()
    path = tmp_path / "s.h5"
    write_scan(path, scan)
    raw = tmp_path / "frames.raw"
    scan.data.tofile(raw)
    with h5py.File(path, "r+") as f:
        del f[f"{DET}/data"]
        f.create_dataset(f"{DET}/data", shape=scan.data.shape, dtype=scan.data.dtype,
                         external=[(str(raw), 0, scan.data.nbytes)])
    out = tmp_path / "r.h5"
    res = CliRunner().invoke(main, ["reconstruct", str(path), "-o", str(out), "--method", "none",
                                    "--set", "load.allow_external=true"])
    assert res.exit_code == 0, res.output
    from dfxcorr.pipeline import sha256
    assert read_result_h5(out)["provenance"]["external_files"] == f"{sha256(raw)}  {raw.resolve()}"


def test_huge_declaration_refused_within_memory_cap(tmp_path, rng):
    """The 2 kB file declaring 20000 x 180 x 204 frames took 1.6 GB before being refused."""
    path = tmp_path / "s.h5"
    write_scan(path, make_scan(rng))
    edit(path, huge_declaration)
    out = tmp_path / "r.h5"
    outcome = cli_capped("reconstruct", path, "-o", out, budget=256 << 20)
    assert outcome.traceback == "" and outcome.exit_code == 2
    assert one_error_line(outcome.stderr, "detector/data")
    assert not out.exists()


def npy_declaring(path, shape, descr="<f8"):
    """A .npy file whose header declares ``shape`` but which holds 64 bytes of data."""
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": descr, "fortran_order": False, "shape": shape})
        fh.write(b"\0" * 64)


def tiff_declaring(path, pages, height, width, compression=1):
    """A little-endian TIFF of ``pages`` uint16 pages of ``height`` x ``width`` holding 16 bytes each."""
    import struct

    entries = 9
    ifd_size = 2 + entries * 12 + 4
    out = bytearray(b"II*\0" + struct.pack("<I", 8))
    for p in range(pages):
        start = len(out)
        data = start + ifd_size
        nxt = data + 16 if p < pages - 1 else 0
        tags = [(256, 4, width), (257, 4, height), (258, 3, 16), (259, 3, compression), (262, 3, 1),
                (273, 4, data), (277, 3, 1), (278, 4, height), (279, 4, 16)]
        out += struct.pack("<H", entries)
        for tag, typ, value in tags:
            out += struct.pack("<HHI", tag, typ, 1) + (struct.pack("<HH", value, 0) if typ == 3
                                                        else struct.pack("<I", value))
        out += struct.pack("<I", nxt) + b"\0" * 16
    path.write_bytes(bytes(out))


@pytest.mark.parametrize("kind", ["npy 745 GiB", "tiff 3 x 60000 x 60000", "deflate tiff 3 x 60000 x 60000"])
def test_importer_sizes_files_from_their_headers(tmp_path, kind):
    if kind.startswith("npy"):
        sample = tmp_path / "big.npy"
        npy_declaring(sample, (20000, 2000, 2500))
        words = "big.npy"
    else:
        sample = tmp_path / "big.tif"
        tiff_declaring(sample, 3, 60000, 60000, compression=8 if kind.startswith("deflate") else 1)
        words = "big.tif"
    good = tmp_path / "flat.npy"
    np.save(good, np.ones((3, 4, 4), np.uint16))
    out = tmp_path / "o.h5"
    outcome = cli_capped("import", "stepping", "--sample", sample, "--reference", good, "--steps-per-period", 3,
                         "-o", out, budget=256 << 20)
    assert outcome.traceback == "" and outcome.exit_code == 2, outcome
    assert one_error_line(outcome.stderr, words)
    assert not out.exists()


def test_import_stepping_refuses_infinite_steps(tmp_path):
    np.save(tmp_path / "a.npy", np.ones((3, 4, 4), np.uint16))
    res = CliRunner().invoke(main, ["import", "stepping", "--sample", str(tmp_path / "a.npy"), "--reference",
                                    str(tmp_path / "a.npy"), "--steps-per-period", "1e-310", "-o",
                                    str(tmp_path / "o.h5")])
    assert res.exit_code == 2 and one_error_line(res.stderr, "infinite")
    assert not (tmp_path / "o.h5").exists()
