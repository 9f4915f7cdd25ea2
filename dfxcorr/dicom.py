"""DICOM export: the three images of a result as one study of three series, for a PACS.

Object. Each image is a Secondary Capture Image (SOP class 1.2.840.10008.5.1.4.1.1.7), the one image
object that every PACS stores and every viewer opens, and whose IOD leaves the Modality LUT free: Rescale
Slope and Intercept recover the physical value of every stored pixel. The Digital X-Ray classes would
name the modality better, but their DX Image module fixes Rescale Slope to 1 and Intercept to 0, so the
stored pixels could not carry t, v or phi. The Parametric Map class (float pixels) is made for
quantitative maps, but few PACS viewers display it. highdicom, which writes it, is therefore not needed:
pydicom alone writes the Secondary Capture object.

Values. Pixels are stored as uint16: the finite values of an image span the stored values 1 ... 65535
linearly, so a value comes back within (max - min) / 131068 of what the result holds. The stored value
0 is the PixelPaddingValue: NaN pixels (never lit, no fringe) map to it, outside the valid range, never
to a valid value. Two mappings give the values back. The RealWorldValueMappingSequence gives them in the
result's units, at full double precision, with UCUM units: t and v as ratios, phi in rad. Rescale Slope
and Intercept (what a viewer shows and windows) give them in percent for t and v (RescaleType PCT) and in
mrad for phi (MRAD): a viewer's linear window must be at least 1 wide in these units, which ratios and
radians would not allow.

Transmission, not attenuation. The first series holds the transmission t: it is what the result holds,
it is defined for every lit pixel (-ln t is not where noise makes t <= 0, and would need values
invented there), and written with MONOCHROME1 it looks like a radiograph (dense tissue, low t, bright).
The dark field v is MONOCHROME1 too (strong scattering, the lung, shows bright, as in clinical dark-field
images); the differential phase is MONOCHROME2.

Geometry. Rows and columns are the detector's; ImagerPixelSpacing and PixelSpacing are the detector's
pixel pitch (row, column spacing in mm) where the scan records it: equal values mean measurements in the
detector plane, without a magnification correction. PatientOrientation is left empty unless the sidecar
gives it.

Identity. The study, series and instance UIDs derive from the result (its three images, its provenance,
its pixel size) and from the sidecar's attributes: the same result written twice gives the same UIDs
(sent to a PACS again, they are the same images, not new ones), another result or other patient
attributes give others. A sidecar's StudyInstanceUID joins the series to an existing study.

Patient and study. Attributes come only from the optional sidecar (YAML or JSON, :data:`SIDECAR_KEYS`);
the type-2 attributes it does not give are present and empty, never invented. The program, its version,
the result file and the configuration's SHA-256 are in SecondaryCaptureDeviceSoftwareVersions,
DerivationDescription and ImageComments.
"""
from __future__ import annotations

import datetime
import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from . import config as C
from .errors import DfxcorrError
from .export import PROVENANCE_KEYS, check_output, read_result_h5
from .io import atomic_path
from .result import Result

SC_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.7"
EXPLICIT_VR_LITTLE_ENDIAN = "1.2.840.10008.1.2.1"
#: Stored value of pixels without a value (NaN in the result).
PADDING = 0
#: Largest stored value; the finite values span 1 ... TOP.
TOP = 65535
INSTALL = 'pip install "dfxcorr[dicom]"'


class DicomError(DfxcorrError, ValueError):
    """DICOM export refused: pydicom absent, or a sidecar that is not valid; the message names the key."""


@dataclass(frozen=True)
class Quantity:
    """How one image is written: its series, its units and its display."""

    description: str       # SeriesDescription, LUTExplanation
    label: str             # LUTLabel and ImageType value 3 (at most 16 characters)
    ucum: tuple[str, str]  # units of the result's values: (code value, code meaning)
    rescale_type: str      # units of the Rescale Slope and Intercept's output
    rescale_factor: float  # Rescale output / the result's value
    photometric: str


#: The series in order, by Result.IMAGES name.
QUANTITIES = {
    "transmission": Quantity("Transmission t", "TRANSMISSION", ("{ratio}", "ratio"), "PCT", 100.0, "MONOCHROME1"),
    "dark_field": Quantity("Dark field v (visibility reduction)", "DARK FIELD", ("{ratio}", "ratio"), "PCT", 100.0,
                           "MONOCHROME1"),
    "differential_phase": Quantity("Differential phase phi", "DIFF PHASE", ("rad", "radian"), "MRAD", 1000.0,
                                   "MONOCHROME2"),
}

#: Sidecar keys (DICOM keywords) and their value representations.
SIDECAR_KEYS = {
    "PatientName": "PN", "PatientID": "LO", "IssuerOfPatientID": "LO", "PatientBirthDate": "DA",
    "PatientSex": "CS", "PatientAge": "AS", "PatientWeight": "DS", "PatientSize": "DS",
    "StudyInstanceUID": "UI", "StudyDate": "DA", "StudyTime": "TM", "AccessionNumber": "SH", "StudyID": "SH",
    "ReferringPhysicianName": "PN", "StudyDescription": "LO", "OperatorsName": "PN",
    "InstitutionName": "LO", "StationName": "SH", "Manufacturer": "LO", "ManufacturerModelName": "LO",
    "DeviceSerialNumber": "LO", "BodyPartExamined": "CS", "Laterality": "CS", "PatientOrientation": "CS",
}
#: Type-2 attributes: present in every file, empty unless the sidecar gives them.
TYPE2 = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate", "StudyTime",
         "ReferringPhysicianName", "StudyID", "AccessionNumber", "Manufacturer", "PatientOrientation")
_ORIENTATION = re.compile(r"^[APRLHF]{1,3}$")


def require_pydicom():
    """The pydicom module; a :class:`DicomError` naming the install command where it is absent."""
    try:
        import pydicom
    except ImportError:
        raise DicomError(f"DICOM export needs pydicom, which is not installed: {INSTALL}") from None
    return pydicom


def dicom_paths(directory, stem: str) -> list[Path]:
    """The files :func:`write_dicom` writes: ``<stem>_<image>.dcm``, one per series."""
    return [Path(directory) / f"{stem}_{name}.dcm" for name in QUANTITIES]


# --------------------------------------------------------------------------------------------------
# Sidecar
# --------------------------------------------------------------------------------------------------


def read_sidecar(path) -> dict[str, Any]:
    """Read and validate a sidecar of patient and study attributes (YAML or JSON).

    Parameters
    ----------
    path : str or Path
        A mapping of DICOM keywords (:data:`SIDECAR_KEYS`) to values.

    Returns
    -------
    dict
        Keyword -> value in DICOM form (see :func:`validate_sidecar`).

    Raises
    ------
    DicomError
        If the file is not a mapping, or a key or value is not valid (one line naming it).
    """
    path = Path(path)
    with open(path, "rb") as fh:
        raw = fh.read(C.MAX_FILE_BYTES + 1)
    if len(raw) > C.MAX_FILE_BYTES:
        raise DicomError(f"{path}: more than {C.MAX_FILE_BYTES} bytes; a sidecar holds a few attributes")
    try:
        data = C.parse_yaml(raw.decode("utf-8"), as_text=True)
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        problem = C._yaml_problem(exc) if isinstance(exc, yaml.YAMLError) else "not UTF-8 text"
        raise DicomError(f"{path}: {problem}") from None
    try:
        return validate_sidecar({} if data is None else data)
    except DicomError as exc:
        raise DicomError(f"{path}: {exc}") from None


def validate_sidecar(data: dict) -> dict[str, Any]:
    """Check a sidecar's attributes and bring them to DICOM form.

    Dates may be written YYYYMMDD, YYYY-MM-DD or as dates, times HHMMSS[.ffffff] or HH:MM:SS;
    PatientOrientation is two values (row and column direction, e.g. ``[L, F]``). None and empty values
    count as absent. :func:`read_sidecar` reads every value of a file as text, so that 00123 stays 00123.

    Parameters
    ----------
    data : dict
        Keyword -> value.

    Returns
    -------
    dict
        Keyword -> str (a list of str for PatientOrientation), absent keys left out.

    Raises
    ------
    DicomError
        For an unknown keyword (naming the nearest valid one) or a value DICOM does not accept.
    """
    require_pydicom()
    from pydicom.config import RAISE
    from pydicom.valuerep import validate_value

    if not isinstance(data, dict):
        raise DicomError(f"expected a mapping of DICOM keywords to values, got {C.show(data)}")
    out: dict[str, Any] = {}
    for key, value in data.items():
        if key not in SIDECAR_KEYS:
            raise DicomError(f"unknown sidecar key {C.show(key)}{C._nearest(str(key), SIDECAR_KEYS)}")
        if value is None or value == "":
            continue
        try:
            value = _dicom_value(SIDECAR_KEYS[key], key, value)
            for v in value if isinstance(value, list) else [value]:
                validate_value(SIDECAR_KEYS[key], v, RAISE)
        except (ValueError, TypeError) as exc:
            raise DicomError(f"sidecar {key} {C.show(data[key])}: {exc}") from None
        out[key] = value
    return out


def _dicom_value(vr: str, key: str, value: Any) -> Any:
    """One sidecar value in DICOM form; ValueError where it cannot be one."""
    if key == "PatientOrientation":
        parts = value.split("\\") if isinstance(value, str) else value
        if not (isinstance(parts, list) and len(parts) == 2 and all(_ORIENTATION.match(str(p)) for p in parts)):
            raise ValueError("expected two directions from A P R L H F, e.g. [L, F]")
        return [str(p) for p in parts]
    if isinstance(value, (list, dict, bool)):
        raise ValueError("expected one value")
    if vr == "DA":
        if not isinstance(value, datetime.date):
            text = str(value)
            fmt = "%Y-%m-%d" if "-" in text else "%Y%m%d"
            value = datetime.datetime.strptime(text, fmt).date()
        return value.strftime("%Y%m%d")
    if vr == "TM":
        text = str(value).replace(":", "")
        if not re.fullmatch(r"\d{6}(\.\d{1,6})?|\d{4}|\d{2}", text) or int(text[:2]) > 23:
            raise ValueError("expected a time HHMMSS or HH:MM:SS")
        return text
    if vr == "DS":
        number = float(value)
        if not np.isfinite(number) or number <= 0:
            raise ValueError("expected a positive number")
        return _ds(number)
    if key == "PatientSex" and str(value) not in ("M", "F", "O"):
        raise ValueError("expected M, F or O")
    if key == "Laterality" and str(value) not in ("R", "L"):
        raise ValueError("expected R or L")
    if vr == "UI" and not re.fullmatch(r"(0|[1-9]\d*)(\.(0|[1-9]\d*))+", str(value)):
        raise ValueError("expected a UID (digits and dots)")
    return str(value)


# --------------------------------------------------------------------------------------------------
# Values
# --------------------------------------------------------------------------------------------------


def _ds(x: float) -> str:
    """A number as a DICOM decimal string (at most 16 characters)."""
    require_pydicom()
    from pydicom.valuerep import format_number_as_ds

    return format_number_as_ds(float(x))


def quantize(image: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Stored values of an image and the linear map back to its values.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Values; NaN (and any non-finite value) where a pixel has none.

    Returns
    -------
    stored : ndarray of uint16, shape (H, W)
        1 ... :data:`TOP` where finite, :data:`PADDING` elsewhere.
    slope, intercept : float
        ``value = slope * stored + intercept`` comes back within (max - min) / 131068 of the value.
    """
    values = np.asarray(image, dtype=np.float64)
    finite = np.isfinite(values)
    lo, hi = (float(values[finite].min()), float(values[finite].max())) if finite.any() else (0.0, 0.0)
    slope = (hi - lo) / (TOP - 1) if hi > lo else 1.0
    intercept = lo - slope
    stored = np.full(values.shape, PADDING, dtype=np.uint16)
    stored[finite] = np.clip(np.rint((values[finite] - intercept) / slope), 1, TOP)
    return stored, slope, intercept


def window(image: np.ndarray) -> tuple[float, float]:
    """Window centre and width over the 1st to 99th percentile of the finite values, at least 1 wide.

    Parameters
    ----------
    image : ndarray
        Values in the Rescale output's units.

    Returns
    -------
    centre, width : float
        WindowCenter and WindowWidth in the same units.
    """
    finite = image[np.isfinite(image)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(finite, [1, 99])
    return (lo + hi) / 2, max(hi - lo, 1.0)


# --------------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------------


@dataclass
class _Source:
    """What the DICOM files take from a result, the same read from memory or from its file."""

    images: dict[str, np.ndarray]   # float32, as the results file holds them
    pixel_size: tuple[float, float] | None
    provenance: dict[str, str]
    config_sha256: str
    method: str
    result_file: str


def _source(result, result_file: str | None) -> _Source:
    if isinstance(result, Result):
        images = {n: np.asarray(result.image(n), dtype=np.float32) for n in Result.IMAGES}
        pixel_size, provenance = result.pixel_size, result.provenance
        config, method = result.config, result.method
    else:
        r = read_result_h5(result)
        images = {n: np.asarray(r[n], dtype=np.float32) for n in Result.IMAGES}
        pixel_size, provenance, config, method = r["pixel_size"], r["provenance"], r["configuration"], r["method"]
        result_file = result_file or Path(result).name
    return _Source(images, None if pixel_size is None else (float(pixel_size[0]), float(pixel_size[1])),
                   {k: str(provenance.get(k, "")) for k in PROVENANCE_KEYS}, _config_sha256(config), method,
                   result_file or "")


def _config_sha256(config: dict) -> str:
    return hashlib.sha256(yaml.safe_dump(config, sort_keys=False).encode()).hexdigest()


def _digest(src: _Source, sidecar: dict) -> str:
    """SHA-256 of everything that makes the result and the sidecar what they are."""
    h = hashlib.sha256()
    for name in Result.IMAGES:
        image = np.ascontiguousarray(src.images[name], dtype="<f4")  # the same bytes on every machine
        h.update(f"{name}{image.shape}".encode())
        h.update(image.tobytes())
    h.update(json.dumps([src.provenance, src.pixel_size, sidecar], sort_keys=True).encode())
    return h.hexdigest()


def uids(src_digest: str, quantity: str, *, study: str | None = None) -> dict[str, str]:
    """StudyInstanceUID, SeriesInstanceUID and SOPInstanceUID of one series, derived from a digest.

    Parameters
    ----------
    src_digest : str
        Hex digest of the result and sidecar.
    quantity : str
        Key of :data:`QUANTITIES`.
    study : str, optional
        StudyInstanceUID to use instead of the derived one.
    """
    require_pydicom()
    from pydicom.uid import generate_uid

    return {"StudyInstanceUID": study or str(generate_uid(entropy_srcs=[src_digest, "study"])),
            "SeriesInstanceUID": str(generate_uid(entropy_srcs=[src_digest, "series", quantity])),
            "SOPInstanceUID": str(generate_uid(entropy_srcs=[src_digest, "instance", quantity]))}


def _code(value: str, meaning: str):
    from pydicom.dataset import Dataset

    item = Dataset()
    item.CodeValue, item.CodingSchemeDesignator, item.CodeMeaning = value, "UCUM", meaning
    return item


def build_dataset(name: str, series_number: int, src: _Source, sidecar: dict, digest: str):
    """The Secondary Capture dataset of one image.

    Parameters
    ----------
    name : str
        One of :attr:`Result.IMAGES`.
    series_number : int
    src : _Source
        The result's provenance and pixel size.
    sidecar : dict
        Validated patient and study attributes (:func:`validate_sidecar`).
    digest : str
        :func:`_digest` of the result and sidecar.

    Returns
    -------
    pydicom.dataset.Dataset
    """
    require_pydicom()
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.sequence import Sequence
    from pydicom.uid import UID

    quantity = QUANTITIES[name]
    image = np.asarray(src.images[name], dtype=np.float64)
    stored, slope, intercept = quantize(image)
    ids = uids(digest, name, study=sidecar.get("StudyInstanceUID"))
    ds = Dataset()
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID(SC_IMAGE_STORAGE)
    meta.MediaStorageSOPInstanceUID = UID(ids["SOPInstanceUID"])
    meta.TransferSyntaxUID = UID(EXPLICIT_VR_LITTLE_ENDIAN)
    ds.file_meta = meta
    ds.SpecificCharacterSet = "ISO_IR 192"
    ds.SOPClassUID = SC_IMAGE_STORAGE
    for key, uid in ids.items():
        setattr(ds, key, uid)
    for key in TYPE2:
        setattr(ds, key, sidecar.get(key, ""))
    for key, value in sidecar.items():
        if key not in TYPE2:
            setattr(ds, key, value)
    if "Laterality" not in sidecar and "BodyPartExamined" not in sidecar:
        ds.Laterality = ""  # type 2C: whether the body part is paired is not known
    prov = src.provenance
    version = f"{prov['program'] or 'dfxcorr'} {prov['version']}".strip()
    ds.Modality = "OT"
    ds.ConversionType = "WSD"
    ds.SecondaryCaptureDeviceManufacturerModelName = prov["program"] or "dfxcorr"
    ds.SecondaryCaptureDeviceSoftwareVersions = version
    ds.SeriesNumber = series_number
    ds.SeriesDescription = f"{quantity.description}, {prov['program'] or 'dfxcorr'}"
    ds.InstanceNumber = 1
    ds.ImageType = ["DERIVED", "SECONDARY", quantity.label]
    when = _when(prov["date"])
    if when is not None:
        ds.ContentDate, ds.ContentTime = when.strftime("%Y%m%d"), when.strftime("%H%M%S")
    ds.DerivationDescription = (f"{quantity.description} reconstructed by {version} (method {src.method or '?'}) "
                                f"from {prov['input_file'] or 'a scan'}"[:1024])
    ds.ImageComments = (f"result {src.result_file or '?'}; {version}; configuration sha256 {src.config_sha256}; "
                        f"scan {prov['input_file']} sha256 {prov['input_sha256']}; created {prov['date']}")
    ds.BurnedInAnnotation = "NO"
    ds.LossyImageCompression = "00"

    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = quantity.photometric
    ds.Rows, ds.Columns = stored.shape
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.add_new(0x00280120, "US", PADDING)  # PixelPaddingValue
    if src.pixel_size is not None:
        spacing = [_ds(1e3 * s) for s in src.pixel_size]  # (row, column) spacing in mm
        ds.ImagerPixelSpacing = spacing
        ds.PixelSpacing = spacing

    factor = quantity.rescale_factor
    ds.RescaleIntercept, ds.RescaleSlope = _ds(factor * intercept), _ds(factor * slope)
    ds.RescaleType = quantity.rescale_type
    mapping = Dataset()
    mapping.LUTExplanation = quantity.description
    mapping.LUTLabel = quantity.label
    mapping.MeasurementUnitsCodeSequence = Sequence([_code(*quantity.ucum)])
    mapping.add_new(0x00409216, "US", 1)    # RealWorldValueFirstValueMapped
    mapping.add_new(0x00409211, "US", TOP)  # RealWorldValueLastValueMapped
    mapping.RealWorldValueIntercept = intercept
    mapping.RealWorldValueSlope = slope
    ds.RealWorldValueMappingSequence = Sequence([mapping])
    centre, width = window(factor * image)
    ds.WindowCenter, ds.WindowWidth = _ds(centre), _ds(width)
    ds.WindowCenterWidthExplanation = "1st to 99th percentile"
    ds.PixelData = stored.astype("<u2").tobytes()
    return ds


def _when(date: str) -> datetime.datetime | None:
    """The result's creation time in local time; None if it is not recorded."""
    try:
        return datetime.datetime.fromisoformat(date).astimezone()
    except ValueError:
        return None


def _save(ds, path: Path) -> None:
    pydicom = require_pydicom()
    if int(pydicom.__version__.split(".")[0]) >= 3:
        pydicom.dcmwrite(path, ds, enforce_file_format=True)
    else:
        ds.is_little_endian, ds.is_implicit_VR = True, False
        ds.preamble = b"\0" * 128
        pydicom.dcmwrite(path, ds, write_like_original=False)


def write_dicom(result, out_dir, *, sidecar: dict | None = None, stem: str | None = None,
                result_file: str | None = None, overwrite: bool = False) -> list[Path]:
    """Write a result's three images as DICOM: one study, three series of one image each.

    Parameters
    ----------
    result : Result, str or Path
        The result, or the path of a results file (``spec/results-format.md``).
    out_dir : str or Path
        Target folder (created if needed).
    sidecar : dict, optional
        Patient and study attributes (:func:`read_sidecar` or :func:`validate_sidecar`); validated again.
    stem : str, optional
        File names are ``<stem>_<image>.dcm`` (:func:`dicom_paths`); default: the results file's stem,
        or 'dfxcorr' for a Result.
    result_file : str, optional
        Name of the results file, recorded in ImageComments (default: the file ``result`` names).
    overwrite : bool
        Replace existing files.

    Returns
    -------
    list of Path
        The files written, in series order.

    Raises
    ------
    DicomError
        If pydicom is absent or the sidecar is not valid (before anything is written).
    OutputExistsError
        If a file exists and ``overwrite`` is False (checked before anything is written).
    """
    require_pydicom()
    side = validate_sidecar(sidecar or {})
    if stem is None:
        stem = "dfxcorr" if isinstance(result, Result) else Path(result).stem
    paths = dicom_paths(out_dir, stem)
    for path in paths:
        check_output(path, overwrite=overwrite)
    src = _source(result, result_file)
    digest = _digest(src, side)
    for number, (path, name) in enumerate(zip(paths, QUANTITIES, strict=True), start=1):
        ds = build_dataset(name, number, src, side, digest)
        with atomic_path(path, overwrite=overwrite) as tmp:
            _save(ds, tmp)
    return paths
