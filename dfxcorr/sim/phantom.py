"""Analytic projections of a 2-D thorax phantom in the spirit of FORBILD.

The phantom is a 3-D object seen as a coronal (PA) chest radiograph: the beam runs along z
(anterior -> posterior), detector rows are the cranio-caudal direction y (grows downward, the scan
direction) and columns are left-right x. Coordinates are mm at the sample plane with the origin in
the middle of the field of view; patient right is at negative x.

Every solid is chosen so that its chord along a line parallel to z is closed-form:

* body: elliptic cylinder along y (full height), soft tissue;
* lungs: two ellipsoids, carved by the heart ellipsoid (the heart, soft tissue like the body, only
  shows as the region the lungs do not fill, as in a real radiograph); the carve is the overlap of
  two z-intervals, so it is exact;
* spine: stacked vertebral bodies (elliptic cylinders along y, truncated in y) with a marrow core,
  separated by soft-tissue discs; sternum likewise;
* ribs: posterior and anterior half-arcs of a thin elliptic shell around the lungs (cortical bone
  around a marrow core), each restricted to a band around a curve y_c(x): posterior ribs sag
  laterally, anterior ribs slope down medially.

Bones and lungs are disjoint from each other and lie inside the body, so each material's path
length is its solids' chords minus the chords of the solids nested in them. Material constants
are paper Table I (45 keV).
"""
from __future__ import annotations

import numpy as np

MATERIALS: dict[str, dict[str, float]] = {
    "lung": {"mu": 6.35e-3, "delta": 5.90e-3, "eps": 6.49e-3},
    "soft_tissue": {"mu": 2.58e-2, "delta": 2.41e-2, "eps": 0.0},
    "marrow": {"mu": 2.18e-2, "delta": 2.07e-2, "eps": 0.0},
    "bone": {"mu": 9.96e-2, "delta": 8.14e-2, "eps": 0.0},
}

# Geometry in mm. Body: 35 cm wide, 21 cm deep (AP).
_BODY_A, _BODY_C = 175.0, 105.0
# Ellipsoids (x0, y0, z0, a, b, c): semi-axes a along x, b along y, c along z. Right lung slightly
# shorter (higher right hemidiaphragm); the heart sits anteriorly, shifted to the patient's left.
_LUNGS = ((-78.0, -28.0, 0.0, 60.0, 100.0, 70.0), (78.0, -22.0, 0.0, 60.0, 106.0, 70.0))
_HEART = (22.0, 45.0, -32.0, 64.0, 62.0, 55.0)
# Truncated elliptic cylinders (x0, z0, a, c, y_top, y_bottom) of cortical bone, each with a marrow
# core given as (a, c, end-plate thickness).
_SPINE_PITCH, _SPINE_BODY_H = 30.0, 24.0
_VERTEBRAE = tuple(
    ((0.0, 65.0, 22.0, 17.0, yc - _SPINE_BODY_H / 2, yc + _SPINE_BODY_H / 2), (19.0, 14.0, 1.0))
    for yc in _SPINE_PITCH * np.arange(-7, 8)
)
_STERNUM = ((0.0, -95.0, 16.0, 7.0, -150.0, 20.0), (13.0, 5.0, 1.0))
# Rib shell centred at x = z = 0: outer semi-axes, radial thickness, band height and cortex (the
# rest is marrow). Bony only for |x| > x_min (the vertebral body on the posterior side, the costal
# cartilage on the anterior side).
_RIB_A, _RIB_C, _RIB_T, _RIB_H, _RIB_CORTEX = 162.0, 100.0, 7.0, 10.0, 1.5
# Posterior rib centres next to the spine, 12 pairs; the last two are floating (no anterior arc).
_RIB_TOPS = -165.0 + 24.0 * np.arange(12)
_N_ANTERIOR = 10
_RIB_SAG = 0.0018  # mm^-1, posterior rib y_c = y_k + sag * x^2
_RIB_SLOPE = 0.3  # anterior rib descends medially by this much per mm from the lateral join
_RIB_XMIN_POST, _RIB_XMIN_ANT = 25.0, 55.0


def _half_chord(x: np.ndarray, a: float, c: float) -> np.ndarray:
    """Half the z-chord of an x-z ellipse (semi-axes a, c) centred at x = 0, zero outside."""
    return c * np.sqrt(np.clip(1.0 - (x / a) ** 2, 0.0, None))


def _window(v: np.ndarray, lo: float, hi: float) -> slice:
    """Index range of the ascending coordinate vector v within [lo, hi] (bounding-box culling)."""
    return slice(int(np.searchsorted(v, lo, "left")), int(np.searchsorted(v, hi, "right")))


def _ellipsoid_interval(x, y, e):
    """z-interval (lo, hi), each [len(y), len(x)], of the ellipsoid e; lo == hi outside it."""
    x0, y0, z0, a, b, c = e
    s = c * np.sqrt(np.clip(1.0 - ((x[None, :] - x0) / a) ** 2 - ((y[:, None] - y0) / b) ** 2,
                            0.0, None))
    return z0 - s, z0 + s


def _shell_chord(ax, a_out, c_out, t):
    """z-chord of one half (z > 0 or z < 0) of an elliptic shell of radial thickness t at |x|."""
    return _half_chord(ax, a_out, c_out) - _half_chord(ax, a_out - t, c_out - t)


def _add_rib_arc(bone, marrow, x, y, y_k, posterior):
    """Add one rib's posterior or anterior half-arc (both sides) to the bone and marrow lengths."""
    lateral_y = y_k + _RIB_SAG * _RIB_A ** 2  # where the two arcs join at |x| = _RIB_A
    xmin = _RIB_XMIN_POST if posterior else _RIB_XMIN_ANT
    for cs in (_window(x, -_RIB_A, -xmin), _window(x, xmin, _RIB_A)):
        ax = np.abs(x[cs])
        if ax.size == 0:
            continue
        # Outer minus inner half-chord is exact on both sides of |x| = inner semi-axis.
        chord = _shell_chord(ax, _RIB_A, _RIB_C, _RIB_T)
        core = _shell_chord(ax, _RIB_A - _RIB_CORTEX, _RIB_C - _RIB_CORTEX,
                            _RIB_T - 2 * _RIB_CORTEX)
        yc = y_k + _RIB_SAG * ax ** 2 if posterior else lateral_y + _RIB_SLOPE * (_RIB_A - ax)
        rs = _window(y, yc.min() - _RIB_H / 2, yc.max() + _RIB_H / 2)
        dy = np.abs(y[rs, None] - yc[None, :])
        in_core = dy <= _RIB_H / 2 - _RIB_CORTEX
        bone[rs, cs] += (dy <= _RIB_H / 2) * chord - in_core * core
        marrow[rs, cs] += in_core * core


def path_lengths_at(*, x_mm, y_mm) -> dict[str, np.ndarray]:
    """Point-sampled path lengths of each material on a separable grid.

    Parameters
    ----------
    x_mm : array_like, shape (nx,)
        Ascending column (left-right) coordinates at the sample plane, mm, 0 = image centre.
    y_mm : array_like, shape (ny,)
        Ascending row (cranio-caudal, downward) coordinates at the sample plane, mm.

    Returns
    -------
    dict of str to ndarray
        Keys of :data:`MATERIALS`; each float64 [ny, nx], the length in mm of the ray through
        (x, y) along the beam inside that material.
    """
    x = np.asarray(x_mm, dtype=float)
    y = np.asarray(y_mm, dtype=float)
    if x.ndim != 1 or y.ndim != 1 or np.any(np.diff(x) < 0) or np.any(np.diff(y) < 0):
        raise ValueError("x_mm and y_mm must be ascending 1-D coordinate vectors")
    shape = (y.size, x.size)
    lung, bone, marrow = np.zeros(shape), np.zeros(shape), np.zeros(shape)

    for e in _LUNGS:
        x0, y0, _, a, b, _ = e
        rs, cs = _window(y, y0 - b, y0 + b), _window(x, x0 - a, x0 + a)
        lo, hi = _ellipsoid_interval(x[cs], y[rs], e)
        hlo, hhi = _ellipsoid_interval(x[cs], y[rs], _HEART)
        carve = np.clip(np.minimum(hi, hhi) - np.maximum(lo, hlo), 0.0, None)
        lung[rs, cs] += (hi - lo) - carve

    for (x0, _, a, c, y_top, y_bot), (ma, mc, plate) in _VERTEBRAE + (_STERNUM,):
        cs = _window(x, x0 - a, x0 + a)
        bone[_window(y, y_top, y_bot), cs] += 2.0 * _half_chord(x[cs] - x0, a, c)
        core = 2.0 * _half_chord(x[cs] - x0, ma, mc)
        rs = _window(y, y_top + plate, y_bot - plate)
        bone[rs, cs] -= core  # the marrow replaces cortical bone inside the core
        marrow[rs, cs] += core

    for k, y_k in enumerate(_RIB_TOPS):
        _add_rib_arc(bone, marrow, x, y, y_k, posterior=True)
        if k < _N_ANTERIOR:
            _add_rib_arc(bone, marrow, x, y, y_k, posterior=False)

    body = 2.0 * _half_chord(x, _BODY_A, _BODY_C)[None, :]
    # Clip only removes round-off where inner solids fill (nearly) the whole body chord.
    soft = np.clip(body - lung - bone - marrow, 0.0, None)
    return {"lung": lung, "soft_tissue": soft, "marrow": marrow, "bone": bone}


def _axis(n: int, p: float, s: int) -> np.ndarray:
    """Sub-pixel sample centres (s per pixel) of n pixels of size p (mm), centred on 0."""
    return (np.arange(n * s) + 0.5) * (p / s) - n * p / 2.0


def _check_shape(shape) -> tuple[int, int]:
    """(H, W) as positive ints."""
    h, w = (int(v) for v in shape)
    if h < 1 or w < 1:
        raise ValueError(f"shape must be two positive integers, got {shape!r}")
    return h, w


def _sample_pixel(pixel_mm: float, magnification: float) -> float:
    """Pixel size at the sample plane, mm."""
    if pixel_mm <= 0 or magnification <= 0:
        raise ValueError("pixel_mm and magnification must be positive")
    return pixel_mm / magnification


def path_lengths(*, shape, pixel_mm: float = 1.0, magnification: float = 1.2,
                 supersample: int = 2) -> dict[str, np.ndarray]:
    """Pixel-averaged path lengths of each material for a detector.

    Parameters
    ----------
    shape : tuple of int
        Detector shape (H rows, W columns).
    pixel_mm : float
        Detector pixel pitch, mm. The pixel at the sample plane is ``pixel_mm / magnification``.
    magnification : float
        Source-detector over source-sample distance.
    supersample : int
        Sub-pixel samples per axis averaged per pixel (anti-aliasing of edges).

    Returns
    -------
    dict of str to ndarray
        Keys of :data:`MATERIALS`; each float64 [H, W], mean path length over the pixel, mm.
    """
    h, w = _check_shape(shape)
    p = _sample_pixel(pixel_mm, magnification)
    s = int(supersample)
    if s < 1:
        raise ValueError("supersample must be >= 1")
    return _pixel_average(path_lengths_at(x_mm=_axis(w, p, s), y_mm=_axis(h, p, s)), s)


def _pixel_average(fine: dict[str, np.ndarray], s: int) -> dict[str, np.ndarray]:
    """Mean over the s x s sub-pixel samples of each pixel: [n s, w s] -> [n, w]."""
    return {m: v.reshape(v.shape[0] // s, s, v.shape[1] // s, s).mean(axis=(1, 3)) for m, v in fine.items()}


#: Sub-pixel samples of the thorax computed at a time, over the rows times its supersample squared (256 rows of a
#: 2880-column detector at the default 2): the supersampled path lengths of a whole 2880 x 2880 detector would take
#: 1 GB.
_STRIP_SAMPLES = 1024


def _images(lengths, c_v, phi):
    """Transmission and dark-field from path lengths (paper eqs 2-3), bundled with phi."""
    t = np.exp(-sum(MATERIALS[m]["mu"] * v for m, v in lengths.items()))
    v = np.exp(-c_v * sum(MATERIALS[m]["eps"] * v for m, v in lengths.items()))
    return {"transmission": t, "dark_field": v, "differential_phase": phi}


def thorax(*, shape, rows=None, shift: float = 0.0, pixel_mm: float = 1.0, magnification: float = 1.2,
           c_v: float = 1.0, c_phi_mm: float = 0.040, supersample: int = 2) -> dict[str, np.ndarray]:
    """Transmission, dark-field and differential-phase images of the thorax phantom.

    The anatomy is fixed in mm at the sample plane and centred, so any (shape, pixel_mm,
    magnification) shows the same patient; the field of view is ``shape * pixel_mm /
    magnification`` mm (450 x 510 at 1 mm and 1.2 gives 375 x 425 mm with air at both sides).

    Parameters
    ----------
    shape : tuple of int
        Detector shape (H rows, W columns).
    rows : array_like of int, shape (n,), optional
        Ascending detector rows without repeats (:func:`thorax_rows`); default every row.
    shift : float
        Displacement of the sample along the rows, detector rows (:func:`thorax_rows`).
    pixel_mm : float
        Detector pixel pitch, mm.
    magnification : float
        Source-detector over source-sample distance.
    c_v : float
        Dark-field constant: v = exp(-c_v * sum eps_m L_m) with eps in 1/mm and L in mm.
    c_phi_mm : float
        Differential-phase constant, mm: phi = c_phi * d/dy (sum delta_m L_m).
    supersample : int
        Sub-pixel samples per axis averaged per pixel.

    Returns
    -------
    dict of str to ndarray
        'transmission', 'dark_field' (both in (0, 1]) and 'differential_phase' (rad), each
        float64 [n, W] ([H, W] by default), as :func:`thorax_rows` gives them.
    """
    h, w = _check_shape(shape)
    r = np.arange(h) if rows is None else np.asarray(rows)
    out = {k: np.empty((r.size, w)) for k in ("transmission", "dark_field", "differential_phase")}
    step = max(1, _STRIP_SAMPLES // max(1, int(supersample)) ** 2)
    # strips of rows: every solid's chord depends on (x, y) only, so strips give the same pixels
    for i in range(0, r.size, step):
        strip = thorax_rows(rows=r[i:i + step], shape=(h, w), shift=shift, pixel_mm=pixel_mm,
                            magnification=magnification, c_v=c_v, c_phi_mm=c_phi_mm, supersample=supersample)
        for k, v in strip.items():
            out[k][i:i + step] = v
    return out


def thorax_rows(*, rows, shape, shift: float = 0.0, pixel_mm: float = 1.0, magnification: float = 1.2,
                c_v: float = 1.0, c_phi_mm: float = 0.040, supersample: int = 2) -> dict[str, np.ndarray]:
    """The thorax phantom's images at some detector rows, the sample displaced along the rows.

    Row u shows the sample where an undisplaced detector's row u + ``shift`` would see it: the phantom
    is evaluated at y + shift x (pixel size at the sample), so rows beyond the detector's edges still
    see the phantom (it is a function of mm, not of pixels).

    Parameters
    ----------
    rows : array_like of int, shape (n,)
        Ascending detector rows, without repeats; any integers (outside [0, H) too).
    shape : tuple of int
        Detector shape (H rows, W columns): it places the origin at the detector's centre.
    shift : float
        Displacement in detector rows (a fraction of a row too).
    pixel_mm, magnification, c_v, c_phi_mm, supersample
        As :func:`thorax`.

    Returns
    -------
    dict of str to ndarray
        'transmission', 'dark_field' and 'differential_phase' (rad), each float64 [n, W]. t and v
        average the path lengths over ``supersample`` x ``supersample`` points of each pixel; phi is
        the exact pixel average of c_phi times the row derivative of the projected decrement P,
        c_phi * (P(lower edge) - P(upper edge)) / pixel size at the sample, with P averaged over
        ``supersample`` points along x, so it is finite even at truncated (flat-ended) solids.
    """
    h, w = _check_shape(shape)
    p = _sample_pixel(pixel_mm, magnification)
    s = int(supersample)
    if s < 1:
        raise ValueError("supersample must be >= 1")
    r = np.asarray(rows)
    if r.ndim != 1 or r.dtype.kind not in "iu" or np.any(np.diff(r) <= 0):
        raise ValueError("rows must be ascending integers without repeats")
    if not np.isfinite(shift):
        raise ValueError("shift must be finite")
    x = _axis(w, p, s)
    # sub-pixel samples and edges where :func:`_axis` places them on the whole detector, then displaced
    fine = (np.repeat(r * s, s) + np.tile(np.arange(s), r.size) + 0.5) * (p / s) - h * p / 2.0 + shift * p
    top = np.union1d(r, r + 1)
    edges = (top - h / 2.0) * p + shift * p
    lengths = _pixel_average(path_lengths_at(x_mm=x, y_mm=fine), s)
    at_edges = path_lengths_at(x_mm=x, y_mm=edges)
    proj = np.asarray(sum(MATERIALS[m]["delta"] * v for m, v in at_edges.items()))
    upper, lower = np.searchsorted(top, r), np.searchsorted(top, r + 1)
    phi = (c_phi_mm / p) * (proj[lower] - proj[upper]).reshape(r.size, w, s).mean(axis=2)
    return _images(lengths, c_v, phi)


def slab(*, shape, pixel_mm: float = 1.0, magnification: float = 1.2,
         thickness_mm: float = 150.0, material: str = "soft_tissue",
         c_v: float = 1.0) -> dict[str, np.ndarray]:
    """Uniform slab: constant attenuation and dark-field, no phase gradient (paper Fig. 8(c)).

    Parameters
    ----------
    shape : tuple of int
        Detector shape (H rows, W columns).
    pixel_mm, magnification : float
        Accepted so that all phantoms share one call signature; a uniform slab does not depend on
        them.
    thickness_mm : float
        Slab thickness along the beam, mm.
    material : str
        A key of :data:`MATERIALS`.
    c_v : float
        Dark-field constant, as in :func:`thorax`.

    Returns
    -------
    dict of str to ndarray
        'transmission' = exp(-mu T), 'dark_field' = exp(-c_v eps T), 'differential_phase' = 0,
        each float64 [H, W].
    """
    h, w = _check_shape(shape)
    _sample_pixel(pixel_mm, magnification)
    if material not in MATERIALS:
        raise ValueError(f"unknown material {material!r}; choose from {sorted(MATERIALS)}")
    if thickness_mm < 0:
        raise ValueError("thickness_mm must be >= 0")
    lengths = {material: np.full((h, w), float(thickness_mm))}
    return _images(lengths, c_v, np.zeros((h, w)))


def blank(*, shape) -> dict[str, np.ndarray]:
    """No sample: 'transmission' = 1, 'dark_field' = 1, 'differential_phase' = 0, float64 [H, W]."""
    h, w = _check_shape(shape)
    return {"transmission": np.ones((h, w)), "dark_field": np.ones((h, w)),
            "differential_phase": np.zeros((h, w))}
