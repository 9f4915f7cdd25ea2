"""The simulator: scans of the paper's simulation study (Sec. III-A) with every catalogue effect switchable.

Expected counts come from :mod:`dfxcorr.model` (the one forward model); the simulator adds what the
model leaves out on purpose: photon noise, detector gain, electronic noise and a dark offset (a flat
panel in detector units), Compton scatter, a sample region that changes during the scan
(``sample_motion``), beam paths through the sample that change during the scan (``parallax``: the
phantom evaluated where each frame sees it), and detector effects that no catalogue names (a
non-linearity, a ghost of an earlier frame, line noise). The truth is returned beside the scan with
the same keys as the shared truth files (``image_*``, ``vib_*``).
"""
from __future__ import annotations

import json
import logging
from collections import deque
from typing import Any

import numpy as np
from scipy import signal

from .. import model as M
from ..align import lit_blocks
from ..config import MAX_SCATTER, ConfigError, Option, _fraction, _nonneg, _positive, _within
from ..io import Reference, Scan, SteppingReference, write_scan
from ..observations import Observations, quadratures
from ..reference import stepping_observations
from .flat import flat_field, pixel_flat_field

log = logging.getLogger(__name__)

_NUM = (int, float)

SCHEMA: dict[str, dict[str, Option]] = {
    "simulate": {
        "seed": Option(101, "seed of the random generator (vibrations and noise)", int),
        "geometry": Option("scan", "scanning interferometer (scan) or phase stepping (stepping)", str,
                           choices=("scan", "stepping")),
        "phantom": Option("thorax", "sample: thorax (FORBILD-like, Table I), slab (constant attenuation), blank",
                          str, choices=("thorax", "slab", "blank")),
        "pixel_mm": Option(1.0, "detector pixel pitch (mm)", _NUM, check=_positive),
        "height_mm": Option(450.0, "detector height along the scan (mm)", _NUM, check=_positive),
        "width_mm": Option(510.0, "detector width (mm)", _NUM, check=_positive),
        "active_mm": Option(75.0, "height of the interferometer's active area (mm); stepping: ignored", _NUM,
                            check=_positive),
        "step_mm": Option(2.5, "motion of the active area between exposures (mm)", _NUM, check=_positive),
        "magnification": Option(1.2, "source-detector / source-sample distance (1.8 m / 1.5 m)", _NUM,
                                check=_positive),
        "supersample": Option(2, "thorax: sub-pixel samples per axis averaged into a pixel's t and v (phi's average "
                                 "along the rows is exact); a sample displaced by effects.parallax changes them in "
                                 "steps of 1 / supersample row at its edges", int, check=_within(1, 16)),
        "steps": Option(11, "stepping geometry: number of phase steps", int, check=_within(3, 10000)),
        "steps_per_period": Option(11, "stepping geometry: steps per grating period", _NUM, check=_positive),
        "flux": Option(2e4, "flat-field counts per pixel and frame, t^f", _NUM, check=_within(1e-3, 1e9)),
        "visibility": Option(0.3, "flat-field visibility v^f", _NUM, check=_fraction),
        "flat_gradient": Option(0.0, "relative change of t^f from the top to the bottom of the active area "
                                     "(heel effect, grating shadowing); 0: uniform", _NUM),
        "fringes_centre": Option(2.0, "moire fringes over the active area at the centre", _NUM),
        "fringes_edge": Option(2.5, "moire fringes over the active area at the left and right edges", _NUM),
        "noise": Option(True, "Poisson photon noise", bool),
        "dtype": Option("uint16", "stored frame type", str, choices=("uint16", "uint32", "float32", "float64")),
        "compression": Option("lzf", "HDF5 filter of the frames in the file: lzf reads a 440 x 2880 frame in about "
                                     "3 ms, gzip in 20 ms (4 s more per clinical scan) but is readable outside "
                                     "h5py; none", str, choices=("lzf", "gzip", "none")),
        "reference_steps": Option(0, "0: exact reference maps; S > 2: a noisy S-step reference series", int,
                                  check=_within(0, 10000)),
        "reference_frames": Option(20, "frames averaged per reference step (its dose multiple)", int,
                                   check=_within(1, 1e6)),
        "reference_step_errors": Option(0.0, "std of the phase errors of the reference series' steps (rad)", _NUM,
                                        check=_nonneg),
        "tiles": Option(0, "grating tiles across the width (0: one seamless grating): the flat-field phase gradient "
                           "along the scan is constant within a tile and jumps between tiles, as do t^f and v^f",
                        int, check=_nonneg),
        "tile_fringes": Option(0.3, "tiles: fringe counts over the active area vary by up to +- this between tiles "
                                    "(seeded)", _NUM, check=_nonneg),
        "tile_contrast": Option(0.05, "tiles: t^f and v^f vary by up to +- this fraction between tiles (seeded)",
                                _NUM, check=_nonneg),
        "flat_nonlinearity": Option(0.0, "departure of the flat field from linearity along the scan, in units of "
                                         "a typical one (1: t^f and v^f vary by +- 2 % along u, the phase curves "
                                         "by 2 pi 0.02 rad towards the active area's edges); 0: linear", _NUM,
                                    check=_nonneg),
    },
    "effects": {
        "phase_offset": Option(2 * np.pi / 16, "std of phi0_j (rad) (stepping: of the step errors)", _NUM,
                               check=_nonneg),
        "tilt": Option(2 * np.pi / 16, "std of phi1_j (rad)", _NUM, check=_nonneg),
        "visibility_loss": Option(0.2, "std of u in v^s_j = |1 - |u||; 0: none", _NUM, check=_nonneg),
        "curvature": Option(0.0, "std of phi2_j (rad)", _NUM, check=_nonneg),
        "visibility_tilt": Option(0.0, "std of v1_j and v2_j (v2_j = -|.|)", _NUM, check=_nonneg),
        "dose": Option(0.0, "relative std of the per-frame dose d_j", _NUM, check=_within(0, 1)),
        "background": Option(0.0, "additive background at the detector centre, fraction of the flux", _NUM,
                             check=_nonneg),
        "harmonic": Option(0.0, "amplitude a2 of the stepping curve's second harmonic, fraction of the first's "
                                "(it follows the sample's phase and visibility)", _NUM, check=_nonneg),
        "harmonic_phase": Option(0.5, "phase beta of the second harmonic (rad)", _NUM),
        "sample_motion": Option(0.0, "relative transmission change of a moving region (heart-like disc)", _NUM,
                                check=_nonneg),
        "heart_step_mm": Option(0.0, "the heart moves this far (mm at the sample plane, along the rows) half-way "
                                     "through the scan and stays there; 0: it does not move", _NUM, check=_nonneg),
        "parallax": Option(0.0, "beam paths that change during the scan (a source that travels with the gratings): "
                                "frame j sees the sample displaced by kappa (c_j - c_0) rows, c_j the active "
                                "area's centre row (position + (A - 1) / 2), c_0 = (H - 1) / 2 the detector's; the "
                                "phantom is evaluated at the displaced rows (sample_motion's disc stays on its "
                                "pixels; the moved heart after heart_step_mm's step is not displaced); 0: none",
                           _NUM,
                           check=lambda v: None if -1 < v < 1 else "must lie in (-1, 1)"),
        "detector_gain": Option(1.0, "true detector units per photon (noise variance g * mean)", _NUM,
                                check=_positive),
        "declare_gain": Option(True, "write the true gain into the file (false conceals it: readers assume 1)",
                               bool),
        "read_noise": Option(0.0, "electronic (readout) noise std, Gaussian, on every sample read (detector units); "
                                  "also on unlit rows with full_readout", _NUM, check=_nonneg),
        "dark": Option(0.0, "dark offset added to every sample read and written as the file's dark (detector "
                            "units): a flat panel's offset that keeps read noise at zero signal above 0; 0: none",
                       _NUM, check=_nonneg),
        "full_readout": Option(False, "the detector reads every row of every frame (a flat panel): rows outside "
                                      "the active area hold the dark, read noise and line noise (and any lag or "
                                      "ghost); false: only the lit rows are written, zeros elsewhere", bool),
        "scatter": Option(0.0, "Compton scatter per unit primary s: each lit pixel gains an unmodulated count, s "
                               "times the superposition of its frame's primary (dose x t^f x t on the lit rows) "
                               "under a normalised Gaussian of scatter_width_mm, nothing renormalised (a narrow "
                               "band under a wide kernel gets less than s times its primary); 0: none", _NUM,
                               check=_within(0, MAX_SCATTER)),
        "scatter_width_mm": Option(50.0, "std of the scatter's Gaussian kernel at the detector (mm)", _NUM,
                                   check=_positive),
        "detector_nonlinearity": Option(0.0, "relative count loss beta at the flat-field level simulate.flux: a "
                                             "dark-free signal c is recorded as c (1 - beta c / flux) (the "
                                             "readout's quadratic integral non-linearity); 0: linear", _NUM,
                                        check=lambda v: None if 0 <= v <= 0.25
                                        else "must lie in [0, 0.25] (monotone up to twice the flux)"),
        "ghost": Option(0.0, "fraction of frame j - ghost_frames's detected counts that frame j records "
                             "ghost_shift_mm further along the rows (a displaced ghost image: on other pixels, "
                             "unlike detector_lag); 0: none", _NUM,
                        check=lambda v: None if 0 <= v < 1 else "must lie in [0, 1)"),
        "ghost_frames": Option(1, "how many frames earlier the ghost was recorded", int, check=_positive),
        "ghost_shift_mm": Option(20.0, "displacement of the ghost along the rows at the detector (mm, positive "
                                       "towards higher rows; rounded to whole pixels)", _NUM,
                                 check=lambda v: None if np.isfinite(v) else "must be finite"),
        "line_noise": Option(0.0, "std of an offset common to all columns of one row in one frame (detector "
                                  "units): flat-panel line noise; 0: none", _NUM, check=_nonneg),
        "reference_offset": Option(0.0, "the whole interferometer sat this many rows off during the scan: every "
                                        "frame reads the flat-field maps at u - offset, the file's reference stays "
                                        "unshifted", _NUM,
                                   check=lambda v: None if np.isfinite(v) else "must be finite"),
        "position_error": Option(0.0, "std (rows) of a per-frame error delta_j of the recorded active-area position: "
                                      "frame j reads the flat-field maps at u - delta_j", _NUM, check=_nonneg),
        "detector_lag": Option(0.0, "fraction a of each detected frame carried into the next (first-frame lag): "
                                    "frame j records S_j + a S_(j-1), also in rows lit in j - 1 only", _NUM,
                               check=lambda v: None if 0 <= v < 1 else "must lie in [0, 1)"),
        "pixel_noise": Option(1.0, "noise variance factor of the module-boundary pixels (first and last row and "
                                   "column of each detector module): their noise is scaled around the mean; "
                                   "1: none", _NUM, check=_positive),
        "module_pixels": Option(16, "detector module size (pixels) for pixel_noise", int, check=_positive),
    },
}


#: A flat panel: 2000 counts in the open beam, read noise sd 25 and a dark of 100
#: (detector units), every row read out. Add ``effects.detector_gain`` for counts that are not photons.
FLAT_PANEL = {"simulate.flux": 2000.0, "effects.read_noise": 25.0, "effects.dark": 100.0,
              "effects.full_readout": True}

#: Reconstruct settings that state the flat panel's read noise (variance, detector units squared).
FLAT_PANEL_STATED = [f"load.electronic={FLAT_PANEL['effects.read_noise'] ** 2:g}"]

#: A 5-step phase-stepping recording on that flat panel in detector units (gain 0.5, not stated in the
#: file) with per-step phase errors (std 0.1 rad) and nothing else: no grating rotation, no visibility
#: change between steps (not identifiable in phase stepping, paper Sec. II-F).
FLAT_PANEL_STEPPING = {**FLAT_PANEL, "simulate.geometry": "stepping", "simulate.steps": 5,
                       "simulate.steps_per_period": 5, "effects.phase_offset": 0.1, "effects.tilt": 0.0,
                       "effects.visibility_loss": 0.0, "effects.detector_gain": 0.5, "effects.declare_gain": False}

#: Each catalogue effect as the simulator makes it: the setting that switches it on, a realistic amplitude,
#: smaller ones (for detection limits), further simulator settings it needs, and the reconstruct settings
#: that leave it out of the model where it is one of the paper's three.
CONCEALED = {
    "phase_offset": ("effects.phase_offset", 0.39, [0.1, 0.03, 0.01, 0.003], {}, ["vibration.phase_offset=false"]),
    "tilt": ("effects.tilt", 0.39, [0.1, 0.03, 0.01, 0.003], {}, ["vibration.tilt=false"]),
    "visibility_loss": ("effects.visibility_loss", 0.2, [0.05, 0.02, 0.01, 0.005], {}, ["vibration.visibility=false"]),
    "curvature": ("effects.curvature", 0.2, [0.05, 0.02, 0.01, 0.005], {}, []),
    "visibility_tilt": ("effects.visibility_tilt", 0.05, [0.02, 0.01, 0.005, 0.002], {}, []),
    "dose": ("effects.dose", 0.02, [0.005, 0.002, 0.001, 0.0005], {}, []),
    # an additive term is only told from the transmission where t^f varies along the scan
    "background": ("effects.background", 0.05, [0.02, 0.01, 0.005, 0.002], {"simulate.flat_gradient": 0.3}, []),
    "harmonic": ("effects.harmonic", 0.06, [0.03, 0.02, 0.01, 0.005], {}, []),
    "sample_motion": ("effects.sample_motion", 0.3, [0.1, 0.05, 0.02, 0.01], {}, []),
    "detector_gain": ("effects.detector_gain", 2.0, [1.3, 1.1, 1.05, 1.02], {"effects.declare_gain": False}, []),
    # both are told from the images' phase only where the flat field's gradient jumps (tiled gratings) or
    # is not linear along the scan
    "reference_offset": ("effects.reference_offset", 0.5, [0.2, 0.1, 0.05, 0.02],
                         {"simulate.tiles": 8, "simulate.flat_nonlinearity": 1.0}, []),
    "position_error": ("effects.position_error", 0.5, [0.2, 0.1, 0.05, 0.02],
                       {"simulate.tiles": 8, "simulate.flat_nonlinearity": 1.0}, []),
    "detector_lag": ("effects.detector_lag", 0.03, [0.01, 0.003, 0.001, 0.0003], {}, []),
    "pixel_noise": ("effects.pixel_noise", 1 / 3, [0.6, 0.8, 0.9, 0.95], {}, []),
    # a flat panel at 2000 counts with a dark of 100; the file states the dark, not the noise
    "electronic_noise": ("effects.read_noise", 25.0, [10.0, 5.0, 2.0, 1.0], FLAT_PANEL, []),
    "scatter": ("effects.scatter", 0.1, [0.05, 0.02, 0.01, 0.005], {}, []),
    # a source that travels with the gratings: the sample seen 0.02 rows further per row of travel; edges averaged
    # over 8 x 8 points move in eighths of a row (at 2 x 2 their half-row steps are most of the misfit)
    "beam_path": ("effects.parallax", 0.02, [0.01, 0.005, 0.002, 0.001], {"simulate.supersample": 8}, []),
}

#: Detector effects in no catalogue, in the format of :data:`CONCEALED` (the last entry: reconstruct
#: settings, here what the user knows of the detector): the diagnosis must locate them, not explain them.
UNCATALOGUED = {
    "detector_nonlinearity": ("effects.detector_nonlinearity", 0.02, [0.01, 0.005, 0.002, 0.001], {}, []),
    "ghost": ("effects.ghost", 0.01, [0.005, 0.002, 0.001, 0.0005], {}, []),
    # a flat panel's artefact: on the flat panel, its read noise stated in the configuration
    "line_noise": ("effects.line_noise", 5.0, [2.0, 1.0, 0.5, 0.2], FLAT_PANEL, FLAT_PANEL_STATED),
}


def geometry(cfg: dict) -> dict:
    """Detector and scan geometry in pixels: H, W, A, positions (J,), phase steps (J,)."""
    s = cfg["simulate"]
    px = s["pixel_mm"]
    # sizes as floats first: 1e300 mm would not fit an int
    _check_size(s["height_mm"] / px, s["width_mm"] / px, 1, 3)
    H, W = int(round(s["height_mm"] / px)), int(round(s["width_mm"] / px))
    if s["geometry"] == "stepping":
        J = s["steps"]
        _check_size(H, W, H, J)
        return dict(H=H, W=W, A=H, position=np.zeros(J), phase_step=2 * np.pi * np.arange(J) / s["steps_per_period"])
    A, step = int(round(s["active_mm"] / px)), s["step_mm"] / px
    J = int(round((H + A) / step)) - 1
    _check_size(H, W, A, J)
    position = -A + step * (np.arange(J) + 1)
    return dict(H=H, W=W, A=A, position=position, phase_step=np.zeros(J))


#: Most samples (frames x rows x columns) a simulation holds: 8 GB of uint32 counts in memory; the full-resolution
#: clinical scan (configs/clinical.yaml, 1.6e9 samples, scripts/benchmark.py clinical) is written frame by frame.
MAX_SAMPLES = 2 * 10 ** 9


def _check_size(H: float, W: float, A: float, J: float) -> None:
    """Refuse geometries without a scan in them, or beyond :data:`MAX_SAMPLES`, before anything is allocated."""
    if min(H, W) < 4 or A < 1 or J < 3:
        raise ConfigError(f"simulate.height_mm, width_mm, active_mm, step_mm over pixel_mm give {int(J)} frames of "
                          f"{int(H)} x {int(W)} pixels with an active area of {int(A)} rows; a scan needs at least 3 "
                          f"frames of 4 x 4 pixels and 1 row")
    if J * H * W > MAX_SAMPLES:
        raise ConfigError(f"simulate.height_mm, width_mm, step_mm over pixel_mm give {J:.3g} frames of {H:.3g} x "
                          f"{W:.3g} pixels, more than {MAX_SAMPLES:.0e} samples")


def sample_images(cfg: dict, H: int, W: int, *, rows: np.ndarray | None = None,
                  shift: float = 0.0) -> dict[str, np.ndarray]:
    """t, v, phi (rad) of the configured phantom on an H x W detector, each (n, W), at ``rows`` (ascending
    detector rows without repeats, also beyond [0, H); default all H), the sample displaced by ``shift`` rows:
    row u shows what row u + shift shows undisplaced (:func:`~dfxcorr.sim.phantom.thorax`; the slab and the
    blank are the same everywhere)."""
    from . import phantom

    s = cfg["simulate"]
    if s["phantom"] == "thorax":
        return phantom.thorax(shape=(H, W), rows=rows, shift=shift, pixel_mm=s["pixel_mm"],
                              magnification=s["magnification"], supersample=s["supersample"])
    n = H if rows is None else len(rows)
    if s["phantom"] == "slab":
        return phantom.slab(shape=(n, W), pixel_mm=s["pixel_mm"], magnification=s["magnification"])
    return phantom.blank(shape=(n, W))


def parallax_shift(cfg: dict, position: np.ndarray, A: int, H: int) -> np.ndarray:
    """Displacement d_j = kappa (c_j - c_0) (rows, shape (J,)) of the sample each frame sees (``effects.parallax``):
    c_j = position_j + (A - 1) / 2 is the centre row of frame j's active area (its first row at position_j, as in
    lit_blocks), c_0 = (H - 1) / 2 the detector's."""
    return cfg["effects"]["parallax"] * (np.asarray(position, dtype=float) + (A - 1) / 2 - (H - 1) / 2)


def draw_effects(cfg: dict, J: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Per-frame and global effect parameters (catalogue names) drawn as configured."""
    e, s = cfg["effects"], cfg["simulate"]
    p = {"phase_offset": rng.normal(0, e["phase_offset"], (J, 1)), "tilt": rng.normal(0, e["tilt"], (J, 1))}
    if s["geometry"] == "stepping":
        p["tilt"][:] = rng.normal(0, e["tilt"], (J, 1)) if e["tilt"] else 0.0
    p["visibility_loss"] = (np.abs(1 - np.abs(rng.normal(0, e["visibility_loss"], (J, 1)))) if e["visibility_loss"]
                            else np.ones((J, 1)))
    if e["curvature"]:
        p["curvature"] = rng.normal(0, e["curvature"], (J, 1))
    if e["visibility_tilt"]:
        v1 = rng.normal(0, e["visibility_tilt"], J)
        p["visibility_tilt"] = np.stack([v1, -np.abs(rng.normal(0, e["visibility_tilt"], J))], axis=1)
    if e["dose"]:
        p["dose"] = np.clip(1 + rng.normal(0, e["dose"], (J, 1)), 0.05, None)
    if e["background"]:
        b0 = e["background"] * s["flux"]
        p["background"] = np.array([b0, 0.3 * b0, -0.2 * b0])
    if e["harmonic"]:
        a2 = e["harmonic"]
        p["harmonic"] = np.array([a2 * np.cos(e["harmonic_phase"]), a2 * np.sin(e["harmonic_phase"])])
    return p


def gaussian_kernel(sigma: float, reach: int) -> np.ndarray:
    """The normalised Gaussian of std ``sigma`` (pixels) sampled at offsets -reach ... reach, shape (2 reach + 1,).

    Normalised over every integer offset, not only those sampled: its sum is below 1 by the tails beyond ``reach``.
    """
    x = np.arange(-reach, reach + 1, dtype=float)
    if sigma < 1.0:
        # a narrow kernel: its sum over the integers directly (the terms beyond 12 sigma + 2 are below 1e-30)
        n = np.arange(-int(12 * sigma) - 2, int(12 * sigma) + 3, dtype=float)
        total = float(np.sum(np.exp(-0.5 * (n / max(sigma, 1e-300)) ** 2)))
    else:
        # Poisson summation: sum_n exp(-n^2 / 2 sigma^2) = sigma sqrt(2 pi) (1 + 2 sum_k exp(-2 pi^2 sigma^2 k^2)),
        # the k >= 1 terms below 3e-9 from sigma = 1 on
        total = float(sigma * np.sqrt(2 * np.pi) * (1 + 2 * np.exp(-2 * np.pi ** 2 * sigma ** 2)))
    return np.exp(-0.5 * (x / max(sigma, 1e-300)) ** 2) / total


def scatter_field(primary: np.ndarray, row: np.ndarray, sigma: float, *, width: int) -> np.ndarray:
    """Compton scatter per unit s of one frame at its lit rows: the superposition of the primary of every lit pixel
    under a normalised Gaussian, nothing renormalised (what falls off the lit rows or the detector is lost).

    Parameters
    ----------
    primary : ndarray, shape (n, W)
        The frame's unmodulated primary (counts) at its lit rows; none elsewhere.
    row : ndarray of int, shape (n,)
        Their detector rows (any order, no repeats).
    sigma : float
        The kernel's std (pixels), the same along both axes.
    width : int
        Detector columns W.

    Returns
    -------
    ndarray, shape (n, W)
        S(r, c) = sum over lit (r', c') of P(r', c') K(r - r') K(c - c') at the lit rows (counts per unit s).
    """
    row = np.asarray(row)
    # between rows a dense sum over the lit rows at their exact offsets; along the rows an FFT convolution of each
    # row with the kernel over every offset the detector holds, zeros beyond its edges
    reach = int(row.max() - row.min()) if row.size else 0
    along_rows = gaussian_kernel(sigma, reach)[row[:, None] - row[None, :] + reach] @ primary
    return signal.fftconvolve(along_rows, gaussian_kernel(sigma, width - 1)[None, :], mode="same", axes=1)


def motion_region(H: int, W: int) -> np.ndarray:
    """A disc in the left lung next to the heart, bool (H, W): bright and modulated, where motion misleads a fit."""
    r, c = np.mgrid[:H, :W]
    return (r - 0.55 * H) ** 2 + (c - 0.32 * W) ** 2 < (0.1 * min(H, W)) ** 2


class Simulation:
    """One simulated acquisition, produced one frame at a time.

    Everything except the frames (geometry, flat field, phantom images, effect parameters, the
    reference series) is drawn on construction; :meth:`frames` then yields the counts of each frame's
    lit rows, computed by :mod:`dfxcorr.model` for those rows only, so that memory does not grow
    with the number of frames. Frame j's noise comes from its own random stream (spawned from the
    seed), so a frame's counts do not depend on the order in which frames are made.

    Parameters
    ----------
    cfg : dict
        Resolved configuration of :data:`SCHEMA` (``config.load(..., schema=SCHEMA)``).
    """

    def __init__(self, cfg: dict):
        s, e = cfg["simulate"], cfg["effects"]
        self.cfg = cfg
        rng = np.random.default_rng(s["seed"])
        g = self.geometry = geometry(cfg)
        H, W, A, J = g["H"], g["W"], g["A"], g["position"].size
        self.shape = (J, H, W)
        self.flat = flat_field(cfg, A, W)
        self.images = sample_images(cfg, H, W)
        #: Rows by which frame j sees the sample displaced (``effects.parallax``), shape (J,).
        self.displacement = parallax_shift(cfg, g["position"], A, H)
        self.params = draw_effects(cfg, J, rng)
        self.moving = motion_region(H, W) if e["sample_motion"] else np.zeros((H, W), bool)
        self.after = None
        if e["heart_step_mm"]:
            self.after = _heart_step(self.images, cfg)
            self.moving = self.after["region"]
        self.reference: Reference | SteppingReference
        self.reference, self.reference_steps = self.flat, np.zeros(0)
        if s["reference_steps"]:
            self.reference, self.reference_steps = _reference_series(self.flat, s, rng, dark=e["dark"])
        self.noise_factor = pixel_noise_map(H, W, factor=e["pixel_noise"], module=e["module_pixels"])
        self._streams = np.random.SeedSequence(s["seed"]).spawn(J)
        self.dtype = np.dtype(s["dtype"])
        # a stream of its own: switching the position errors on leaves every other draw as it was
        self.jitter = (np.random.default_rng([s["seed"], 2]).normal(0, e["position_error"], J)
                       if e["position_error"] else np.zeros(J))
        #: Rows by which frame j reads the flat-field maps off its nominal local rows (maps at u - shift[j]).
        self.shift = e["reference_offset"] + self.jitter
        #: Line noise: the offset of each (frame, detector row), shape (J, H), from a stream of its own.
        self.line_offset = (np.random.default_rng([s["seed"], 3]).normal(0, e["line_noise"], (J, H))
                            if e["line_noise"] else np.zeros((J, H)))

    def frame_counts(self, j: int) -> tuple[int, np.ndarray]:
        """Detected counts (float64, before storage) of frame j's lit rows: (r0, array (n, W))."""
        g, e = self.geometry, self.cfg["effects"]
        J, H, W = self.shape
        row, _, u = lit_blocks(g["position"][j:j + 1], g["A"], H)
        if row.size == 0:
            return 0, np.zeros((0, W))
        cols = np.arange(W)
        u = u - self.shift[j]
        # the analytic field at each displaced pixel's centre, not an interpolation of the reference's rows
        tf, vf, phif = pixel_flat_field(self.cfg, u, g["A"], W, step=g["phase_step"][j])
        zeros = np.zeros((row.size, W))
        fc, fs = quadratures(tf, vf, phif)
        obs = Observations(counts=zeros, tf=tf, fc=fc, fs=fs, dark=zeros,
                           use=np.ones((row.size, W), bool), row=row, frame=np.full(row.size, j), columns=cols,
                           shape=self.shape)
        keys = ("transmission", "dark_field", "differential_phase")
        # the heart has moved from the middle frame on
        moved = self.after if self.after is not None and j >= J // 2 else None
        img = self.images if moved is None else moved
        t, v, phi = (img[k][row] for k in keys)
        if self.displacement[j]:
            seen = sample_images(self.cfg, H, W, rows=row, shift=self.displacement[j])
            # the moved heart is a shift of the static images: no parallax inside it
            keep = np.zeros((row.size, W), bool) if moved is None else moved["region"][row]
            t, v, phi = (np.where(keep, a, seen[k]) for a, k in zip((t, v, phi), keys, strict=True))
        images = M.Images(np.stack([t, t * v * np.cos(phi), t * v * np.sin(phi)], axis=-1), np.ones(t.shape, bool))
        dsg = M.design(obs, self.params)
        ibar = M.expected(obs, dsg, images)
        # the unmodulated primary (dose x t^f x t), the source of the scatter
        primary = dsg.A * t
        if e["sample_motion"]:
            # the region's transmission beats about 7 times over the scan, like a heart during a 7 s scan
            swing = 1 + e["sample_motion"] * np.sin(2 * np.pi * 7 * j / J)
            ibar = np.where(self.moving[row], (ibar - dsg.offset) * swing + dsg.offset, ibar)
            primary = np.where(self.moving[row], primary * swing, primary)
        if e["scatter"]:
            # computed here, not by the model's coarse field: a simulator that shares the model's code cannot test it
            ibar = ibar + e["scatter"] * scatter_field(primary, row, e["scatter_width_mm"] / self.cfg["simulate"][
                "pixel_mm"], width=W)
        return int(row[0]), _detect(ibar, self.cfg, np.random.default_rng(self._streams[j]),
                                    factor=self.noise_factor[row])

    def frames(self):
        """Yield (j, r0, counts (n, W)) in the stored dtype for every frame; warns once if counts are clipped.

        With ``effects.detector_lag`` = a, frame j records its detected counts plus a times those of
        frame j - 1, over the rows lit in either. With ``effects.ghost`` = q, it also records q times the
        detected counts of frame j - k (k = ``ghost_frames``) ``ghost_shift_mm`` further along the rows,
        over its own rows and those the ghost lands on. Then :meth:`readout` adds what the readout does.
        """
        clipped = 0
        e = self.cfg["effects"]
        lag, H = e["detector_lag"], self.shape[1]
        ghost_rows = int(round(e["ghost_shift_mm"] / self.cfg["simulate"]["pixel_mm"]))
        previous = (0, np.zeros((0, self.shape[2])))
        earlier: deque[tuple[int, np.ndarray]] = deque(maxlen=e["ghost_frames"])
        for j in range(self.shape[0]):
            r0, counts = detected = self.frame_counts(j)
            if lag:
                r0, counts = _add_rows(detected, previous, lag)
                previous = detected
            if e["ghost"]:
                if len(earlier) == earlier.maxlen:
                    g0, ghost = earlier[0]
                    r0, counts = _add_rows((r0, counts), (g0 + ghost_rows, ghost), e["ghost"], height=H)
                earlier.append(detected)
            r0, counts = self.readout(j, r0, counts)
            stored, n = _store(counts, self.dtype)
            clipped += n
            yield j, r0, stored
        if clipped:
            log.warning("%d counts above the range of %s were clipped", clipped, self.dtype)

    def readout(self, j: int, r0: int, counts: np.ndarray) -> tuple[int, np.ndarray]:
        """What reading frame j adds to its detected rows (r0, counts (n, W)), all in detector units.

        In this order: the non-linearity c (1 - beta c / flux) (``effects.detector_nonlinearity``); with
        ``effects.full_readout`` the whole frame, whose rows outside the lit ones get read noise of their own
        (the lit rows have theirs from detection); the line noise of frame j's rows; the dark.

        Returns
        -------
        r0 : int
            First row (0 with ``full_readout``).
        counts : ndarray, shape (n, W) or (H, W)
        """
        s, e = self.cfg["simulate"], self.cfg["effects"]
        beta = e["detector_nonlinearity"]
        if beta:
            counts = counts * (1 - beta * counts / s["flux"])
        if e["full_readout"]:
            H, W = self.shape[1:]
            frame = np.zeros((H, W))
            frame[r0:r0 + counts.shape[0]] = counts
            if e["read_noise"]:
                lit, _, _ = lit_blocks(self.geometry["position"][j:j + 1], self.geometry["A"], H)
                dark_rows = np.setdiff1d(np.arange(H), lit)
                # a stream of its own (seed, 4, frame): the lit rows' noise stays as without full_readout
                noise = np.random.default_rng([s["seed"], 4, j]).normal(0, e["read_noise"], (dark_rows.size, W))
                frame[dark_rows] += noise
            r0, counts = 0, frame
        if e["line_noise"]:
            counts = counts + self.line_offset[j, r0:r0 + counts.shape[0], None]
        if e["dark"]:
            counts = counts + e["dark"]
        return r0, counts

    def scan(self, data=None) -> Scan:
        """The acquisition with ``data`` as frames (default: all zero, a placeholder to write frames into)."""
        s, e = self.cfg["simulate"], self.cfg["effects"]
        g = self.geometry
        J = self.shape[0]
        data = np.broadcast_to(np.zeros((), self.dtype), self.shape) if data is None else data
        return Scan(data=data, position=g["position"], reference=self.reference, phase_step=g["phase_step"],
                    dark=np.full(self.shape[1:], float(e["dark"])) if e["dark"] else None,
                    gain=e["detector_gain"] if e["declare_gain"] else 1.0, exposure_time=np.full(J, 0.033),
                    pixel_size=(s["pixel_mm"] * 1e-3, s["pixel_mm"] * 1e-3))

    def truth(self) -> dict:
        """The truth beside the scan (keys as documented in :func:`simulate`)."""
        J = self.shape[0]
        p, e, ref = self.params, self.cfg["effects"], self.flat
        truth: dict[str, Any] = {f"image_{k}": self.images[k] for k in ("transmission", "dark_field",
                                                                           "differential_phase")}
        if self.after is not None:
            truth["image_transmission_after"] = self.after["transmission"]
        truth.update(vib_phase_offset=p["phase_offset"][:, 0], vib_tilt=p["tilt"][:, 0],
                     vib_visibility=p["visibility_loss"][:, 0],
                     vib_curvature=p.get("curvature", np.zeros((J, 1)))[:, 0],
                     vib_dose=p.get("dose", np.ones((J, 1)))[:, 0],
                     vib_visibility_tilt=p.get("visibility_tilt", np.zeros((J, 2))),
                     background=p.get("background", np.zeros(3)), harmonic=p.get("harmonic", np.zeros(2)),
                     motion_mask=self.moving, gain=np.float64(e["detector_gain"]),
                     detector_lag=np.float64(e["detector_lag"]), pixel_noise=self.noise_factor,
                     reference_steps=self.reference_steps, reference_transmission=ref.transmission,
                     reference_visibility=ref.visibility, reference_phase=ref.phase,
                     reference_offset=np.float64(e["reference_offset"]), vib_position_jitter=self.jitter,
                     beam_path=np.float64(e["parallax"]),
                     electronic_noise=np.float64(e["read_noise"]), dark=np.float64(e["dark"]),
                     scatter=np.float64(e["scatter"]), detector_nonlinearity=np.float64(e["detector_nonlinearity"]),
                     ghost=np.float64(e["ghost"]), line_offset=self.line_offset, config=json.dumps(self.cfg))
        return truth


def simulate(cfg: dict) -> tuple[Scan, dict]:
    """Simulate one acquisition in memory.

    Parameters
    ----------
    cfg : dict
        Resolved configuration of :data:`SCHEMA` (``config.load(..., schema=SCHEMA)``).

    Returns
    -------
    scan : Scan
    truth : dict
        ``image_transmission``, ``image_dark_field``, ``image_differential_phase`` (H, W); per frame
        ``vib_phase_offset``, ``vib_tilt``, ``vib_visibility``, ``vib_curvature``, ``vib_dose``
        (J,), ``vib_visibility_tilt`` (J, 2); ``background`` (3,), ``harmonic`` (2,),
        ``motion_mask`` (H, W), ``gain``, ``detector_lag`` (the fraction a), ``pixel_noise`` (H, W)
        variance factors; ``reference_offset`` (rows) and ``vib_position_jitter`` (J, rows: frame j read
        the flat-field maps at u - reference_offset - vib_position_jitter[j]); ``reference_steps`` (actual
        step phases of a simulated reference series, else empty) and the exact flat-field maps
        ``reference_*``; ``electronic_noise`` (read noise std) and ``dark`` (detector units);
        ``scatter`` (s, the scatter per unit primary before the lit band's loss); ``detector_nonlinearity``
        (beta), ``ghost`` (the fraction) and ``line_offset`` (J, H)
        (detector units); ``beam_path`` (kappa of ``effects.parallax``: frame j saw the sample at row
        u + kappa (c_j - c_0), :func:`parallax_shift`; the ``image_*`` are the sample undisplaced, what
        every frame sees at kappa = 0); ``config`` (JSON, every setting).
    """
    sim = Simulation(cfg)
    data = np.zeros(sim.shape, sim.dtype)
    for j, r0, counts in sim.frames():
        data[j, r0:r0 + counts.shape[0]] = counts
    return sim.scan(data), sim.truth()


def simulate_file(cfg: dict, path, *, compression: str | None = None, overwrite: bool = False) -> tuple[Scan, dict]:
    """Simulate one acquisition straight into a scan file, one frame at a time (memory: one frame's lit rows).

    Parameters
    ----------
    cfg : dict
        Resolved configuration of :data:`SCHEMA`.
    path : str or path-like
        Scan file to write (atomically).
    compression : str, optional
        HDF5 filter of the frames (default ``simulate.compression``).
    overwrite : bool
        Replace an existing file.

    Returns
    -------
    scan : Scan
        The acquisition's description (its ``data`` is a zero placeholder; the frames are in the file).
    truth : dict
        As :func:`simulate`.
    """
    sim = Simulation(cfg)
    scan = sim.scan()
    comp = cfg["simulate"]["compression"] if compression is None else compression
    write_scan(path, scan, frames=sim.frames(), compression=None if comp == "none" else comp, overwrite=overwrite)
    return scan, sim.truth()


def _heart_step(img: dict, cfg: dict) -> dict[str, np.ndarray]:
    """The images after the heart moved by ``heart_step_mm`` along the rows (from the middle frame on).

    Approximation: inside the heart's ellipse (grown by the shift) the images are those of the whole
    phantom shifted by the step; outside it they stay. Also returns that ``region`` (H, W) bool.
    """
    from scipy import ndimage

    from .phantom import _HEART

    s, e = cfg["simulate"], cfg["effects"]
    H, W = img["transmission"].shape
    p = s["pixel_mm"] / s["magnification"]  # pixel size at the sample plane (mm)
    shift = e["heart_step_mm"] / p
    x0, y0, _, a, b, _ = _HEART
    r, c = np.mgrid[:H, :W]
    region = ((((c + 0.5 - W / 2) * p - x0) / (a + e["heart_step_mm"])) ** 2
              + (((r + 0.5 - H / 2) * p - y0) / (b + e["heart_step_mm"])) ** 2 < 1)
    out = {k: np.where(region, ndimage.shift(v, (shift, 0), order=1, mode="nearest"), v) for k, v in img.items()}
    out["region"] = region
    return out


def pixel_noise_map(height: int, width: int, *, factor: float, module: int) -> np.ndarray:
    """Variance factor of each pixel: ``factor`` on the first and last row and column of each module, else 1."""
    def edge(n):
        k = np.arange(n) % module
        return (k == 0) | (k == module - 1)
    return np.where(edge(height)[:, None] | edge(width)[None, :], float(factor), 1.0)


def _detect(mean: np.ndarray, cfg: dict, rng: np.random.Generator, *, factor: np.ndarray | None = None) -> np.ndarray:
    """Detector response to a mean signal in detector units: g * Poisson(mean / g) + electronic noise.

    ``factor`` (same shape): per-pixel variance factor of the photon noise (``effects.pixel_noise``), the
    noise scaled around the mean by its square root.
    """
    s, e = cfg["simulate"], cfg["effects"]
    g = e["detector_gain"]
    mean = np.maximum(mean, 0.0)
    out = g * rng.poisson(mean / g).astype(np.float64) if s["noise"] else mean.copy()
    if factor is not None and s["noise"] and np.any(factor != 1):
        out = mean + np.sqrt(factor) * (out - mean)
    if e["read_noise"]:
        out += rng.normal(0, e["read_noise"], out.shape)
    return out


def _add_rows(current: tuple[int, np.ndarray], other: tuple[int, np.ndarray], fraction: float, *,
              height: int | None = None) -> tuple[int, np.ndarray]:
    """Detected rows (r0, counts) of a frame plus ``fraction`` times rows (r0, counts) of another, over both's rows.

    The other rows are the previous frame's (lag) or an earlier frame's, displaced (ghost); with ``height``
    those outside the detector's rows [0, height) are dropped.
    """
    if height is not None:
        o0, c = other
        lo, hi = min(max(o0, 0), height), min(max(o0 + c.shape[0], 0), height)
        other = (lo, c[lo - o0:hi - o0])
    spans = [(r0, c) for r0, c in (current, other) if c.shape[0]]
    if len(spans) < 2:
        return current if current[1].shape[0] else (other[0], fraction * other[1])
    lo = min(r0 for r0, _ in spans)
    hi = max(r0 + c.shape[0] for r0, c in spans)
    out = np.zeros((hi - lo, current[1].shape[1]))
    out[current[0] - lo:current[0] - lo + current[1].shape[0]] += current[1]
    out[other[0] - lo:other[0] - lo + other[1].shape[0]] += fraction * other[1]
    return lo, out


def _reference_series(ref: Reference, s: dict, rng: np.random.Generator, *, dark: float = 0.0
                      ) -> tuple[SteppingReference, np.ndarray]:
    """A noisy S-step series of the unloaded interferometer (the average of ``reference_frames`` frames).

    ``dark`` (detector units) is added to every frame and stated as the series' dark. Returns the series
    (with nominal steps) and the actual step phases (rad).
    """
    S = s["reference_steps"]
    steps = 2 * np.pi * np.arange(S) / S
    actual = steps + rng.normal(0, s["reference_step_errors"], S)
    obs = stepping_observations(np.zeros((S, *ref.transmission.shape)), actual)
    t, v, phi = (m[obs.rows] for m in (ref.transmission, ref.visibility, ref.phase))
    images = M.Images(np.stack([t, t * v * np.cos(phi), t * v * np.sin(phi)], axis=-1), np.ones(t.shape, bool))
    mean = np.zeros((S, *ref.transmission.shape))
    mean[obs.frame[:, None], obs.row[:, None], obs.columns[None, :]] = M.expected(obs, M.design(obs, {}), images)
    n = s["reference_frames"]
    data = rng.poisson(mean * n) / n if s["noise"] else mean
    return SteppingReference(data=data.astype(np.float64) + dark, phase_step=steps,
                             dark=np.full(mean.shape[1:], dark) if dark else None), actual


def _store(frames: np.ndarray, dtype: np.dtype) -> tuple[np.ndarray, int]:
    """Cast to the stored type; integer types are rounded and clipped to their range. Returns the number clipped."""
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return np.maximum(frames, 0).astype(dt), 0
    top = np.iinfo(dt).max
    return np.clip(np.rint(frames), 0, top).astype(dt), int(np.count_nonzero(frames > top))
