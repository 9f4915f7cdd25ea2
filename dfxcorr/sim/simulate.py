"""The simulator: scans of the paper's simulation study (Sec. III-A) with every catalogue effect switchable.

Expected counts come from :mod:`dfxcorr.model` (the one forward model); the simulator adds what the
model leaves out on purpose: photon noise, detector gain and electronic noise, and a sample region
that changes during the scan (``sample_motion``). The truth is returned beside the scan with the
same keys as the shared truth files (``image_*``, ``vib_*``).
"""
from __future__ import annotations

import json
import logging
from typing import Any

import numpy as np

from .. import model as M
from ..align import build_observations, stepping_observations
from ..config import Option, _fraction, _nonneg, _positive
from ..io import Reference, Scan, SteppingReference

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
        "steps": Option(11, "stepping geometry: number of phase steps", int, check=lambda v: None if v >= 3
                        else "must be at least 3"),
        "steps_per_period": Option(11, "stepping geometry: steps per grating period", _NUM, check=_positive),
        "flux": Option(2e4, "flat-field counts per pixel and frame, t^f", _NUM, check=_positive),
        "visibility": Option(0.3, "flat-field visibility v^f", _NUM, check=_fraction),
        "flat_gradient": Option(0.0, "relative change of t^f from the top to the bottom of the active area "
                                     "(heel effect, grating shadowing); 0: uniform", _NUM),
        "fringes_centre": Option(2.0, "moire fringes over the active area at the centre", _NUM),
        "fringes_edge": Option(2.5, "moire fringes over the active area at the left and right edges", _NUM),
        "noise": Option(True, "Poisson photon noise", bool),
        "dtype": Option("uint16", "stored frame type", str, choices=("uint16", "uint32", "float32", "float64")),
        "reference_steps": Option(0, "0: exact reference maps; S > 2: a noisy S-step reference series", int,
                                  check=_nonneg),
        "reference_frames": Option(20, "frames averaged per reference step (its dose multiple)", int,
                                   check=_positive),
        "reference_step_errors": Option(0.0, "std of the phase errors of the reference series' steps (rad)", _NUM,
                                        check=_nonneg),
    },
    "effects": {
        "phase_offset": Option(2 * np.pi / 16, "std of phi0_j (rad) (stepping: of the step errors)", _NUM,
                               check=_nonneg),
        "tilt": Option(2 * np.pi / 16, "std of phi1_j (rad)", _NUM, check=_nonneg),
        "visibility_loss": Option(0.2, "std of u in v^s_j = |1 - |u||; 0: none", _NUM, check=_nonneg),
        "curvature": Option(0.0, "std of phi2_j (rad)", _NUM, check=_nonneg),
        "visibility_tilt": Option(0.0, "std of v1_j and v2_j (v2_j = -|.|)", _NUM, check=_nonneg),
        "dose": Option(0.0, "relative std of the per-frame dose d_j", _NUM, check=_nonneg),
        "background": Option(0.0, "additive background at the detector centre, fraction of the flux", _NUM,
                             check=_nonneg),
        "harmonic": Option(0.0, "amplitude a2 of the second harmonic, fraction of the flux", _NUM, check=_nonneg),
        "harmonic_phase": Option(0.5, "phase beta of the second harmonic (rad)", _NUM),
        "sample_motion": Option(0.0, "relative transmission change of a moving region (heart-like disc)", _NUM,
                                check=_nonneg),
        "heart_step_mm": Option(0.0, "the heart moves this far (mm at the sample plane, along the rows) half-way "
                                     "through the scan and stays there; 0: it does not move", _NUM, check=_nonneg),
        "detector_gain": Option(1.0, "true detector units per photon (noise variance g * mean)", _NUM,
                                check=_positive),
        "declare_gain": Option(True, "write the true gain into the file (false conceals it: readers assume 1)",
                               bool),
        "read_noise": Option(0.0, "electronic noise std (detector units)", _NUM, check=_nonneg),
    },
}


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
    "harmonic": ("effects.harmonic", 0.03, [0.01, 0.005, 0.002, 0.001], {}, []),
    "sample_motion": ("effects.sample_motion", 0.3, [0.1, 0.05, 0.02, 0.01], {}, []),
    "detector_gain": ("effects.detector_gain", 2.0, [1.3, 1.1, 1.05, 1.02], {"effects.declare_gain": False}, []),
}


def geometry(cfg: dict) -> dict:
    """Detector and scan geometry in pixels: H, W, A, positions (J,), phase steps (J,)."""
    s = cfg["simulate"]
    px = s["pixel_mm"]
    H, W = int(round(s["height_mm"] / px)), int(round(s["width_mm"] / px))
    if s["geometry"] == "stepping":
        J = s["steps"]
        return dict(H=H, W=W, A=H, position=np.zeros(J), phase_step=2 * np.pi * np.arange(J) / s["steps_per_period"])
    A, step = int(round(s["active_mm"] / px)), s["step_mm"] / px
    J = int(round((H + A) / step)) - 1
    position = -A + step * (np.arange(J) + 1)
    return dict(H=H, W=W, A=A, position=position, phase_step=np.zeros(J))


def flat_field(cfg: dict, A: int, W: int) -> Reference:
    """Flat field with a fringe count growing from the centre to the edges (paper Sec. III-A)."""
    s = cfg["simulate"]
    u = (np.arange(A) + 0.5)[:, None]
    x = M.lateral_coordinate(np.arange(W), W)[None, :]
    fringes = s["fringes_centre"] + (s["fringes_edge"] - s["fringes_centre"]) * x ** 2
    flux = s["flux"] * (1 + s["flat_gradient"] * (u / A - 0.5)) * np.ones((1, W))
    return Reference(transmission=flux, visibility=np.full((A, W), float(s["visibility"])),
                     phase=2 * np.pi * fringes * u / A)


def sample_images(cfg: dict, H: int, W: int) -> dict[str, np.ndarray]:
    """t, v, phi of the configured phantom, shape (H, W)."""
    from . import phantom

    s = cfg["simulate"]
    if s["phantom"] == "thorax":
        return phantom.thorax(shape=(H, W), pixel_mm=s["pixel_mm"], magnification=s["magnification"])
    if s["phantom"] == "slab":
        return phantom.slab(shape=(H, W), pixel_mm=s["pixel_mm"], magnification=s["magnification"])
    return phantom.blank(shape=(H, W))


def draw_effects(cfg: dict, J: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Per-frame and global effect parameters (catalogue names) drawn as configured."""
    e, s = cfg["effects"], cfg["simulate"]
    p = {"phase_offset": rng.normal(0, e["phase_offset"], (J, 1)), "tilt": rng.normal(0, e["tilt"], (J, 1))}
    if s["geometry"] == "stepping":
        p["tilt"][:] = rng.normal(0, e["tilt"], (J, 1)) if e["tilt"] else 0.0
    p["visibility_loss"] = np.abs(1 - np.abs(rng.normal(0, e["visibility_loss"], (J, 1)))) if e["visibility_loss"] \
        else np.ones((J, 1))
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


def motion_region(H: int, W: int) -> np.ndarray:
    """A disc in the left lung next to the heart, bool (H, W): bright and modulated, where motion misleads a fit."""
    r, c = np.mgrid[:H, :W]
    return (r - 0.55 * H) ** 2 + (c - 0.32 * W) ** 2 < (0.1 * min(H, W)) ** 2


def simulate(cfg: dict) -> tuple[Scan, dict]:
    """Simulate one acquisition.

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
        ``motion_mask`` (H, W), ``gain``; ``reference_steps`` (actual step phases of a simulated
        reference series, else empty) and the exact flat-field maps ``reference_*``; ``config`` (JSON).
    """
    s, e = cfg["simulate"], cfg["effects"]
    rng = np.random.default_rng(s["seed"])
    g = geometry(cfg)
    H, W, A, J = g["H"], g["W"], g["A"], g["position"].size
    ref = flat_field(cfg, A, W)
    img = sample_images(cfg, H, W)
    params = draw_effects(cfg, J, rng)
    frames = np.zeros((J, H, W), dtype=np.float64)
    placeholder = Scan(data=frames, position=g["position"], reference=ref, phase_step=g["phase_step"])
    obs = build_observations(placeholder, ref)
    t, v, phi = (img[k][obs.rows] for k in ("transmission", "dark_field", "differential_phase"))
    images = M.Images(np.stack([t, t * v * np.cos(phi), t * v * np.sin(phi)], axis=-1), np.ones(t.shape, bool))
    dsg = M.design(obs, params)
    ibar = M.expected(obs, dsg, images)
    moving = np.zeros((H, W), bool)
    if e["sample_motion"]:
        moving = motion_region(H, W)
        # the region's transmission beats about 7 times over the scan, like a heart during a 7 s scan
        swing = 1 + e["sample_motion"] * np.sin(2 * np.pi * 7 * obs.frame / J)[:, None]
        ibar = np.where(moving[obs.row][:, obs.columns], (ibar - dsg.offset) * swing + dsg.offset, ibar)
    if e["heart_step_mm"]:
        after = _heart_step(img, cfg)
        t2, v2, phi2 = (after[k][obs.rows] for k in ("transmission", "dark_field", "differential_phase"))
        moved = M.Images(np.stack([t2, t2 * v2 * np.cos(phi2), t2 * v2 * np.sin(phi2)], axis=-1), images.valid)
        ibar = np.where((obs.frame >= J // 2)[:, None], M.expected(obs, dsg, moved), ibar)
        moving = after["region"]
    counts = _detect(ibar - obs.dark, cfg, rng) + obs.dark
    frames[obs.frame[:, None], obs.row[:, None], obs.columns[None, :]] = counts
    reference: Reference | SteppingReference = ref
    reference_steps = np.zeros(0)
    if s["reference_steps"]:
        reference, reference_steps = _reference_series(ref, s, rng)
    data = _store(frames, s["dtype"])
    gain_file = e["detector_gain"] if e["declare_gain"] else 1.0
    scan = Scan(data=data, position=g["position"], reference=reference, phase_step=g["phase_step"],
                gain=gain_file, exposure_time=np.full(J, 0.033),
                pixel_size=(s["pixel_mm"] * 1e-3, s["pixel_mm"] * 1e-3))
    truth: dict[str, Any] = {f"image_{k}": img[k] for k in ("transmission", "dark_field", "differential_phase")}
    if e["heart_step_mm"]:
        truth["image_transmission_after"] = after["transmission"]
    truth.update(vib_phase_offset=params["phase_offset"][:, 0], vib_tilt=params["tilt"][:, 0],
                 vib_visibility=params["visibility_loss"][:, 0],
                 vib_curvature=params.get("curvature", np.zeros((J, 1)))[:, 0],
                 vib_dose=params.get("dose", np.ones((J, 1)))[:, 0],
                 vib_visibility_tilt=params.get("visibility_tilt", np.zeros((J, 2))),
                 background=params.get("background", np.zeros(3)), harmonic=params.get("harmonic", np.zeros(2)),
                 motion_mask=moving, gain=np.float64(e["detector_gain"]), reference_steps=reference_steps,
                 reference_transmission=ref.transmission, reference_visibility=ref.visibility,
                 reference_phase=ref.phase, config=json.dumps(cfg))
    return scan, truth


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
    region = (((c + 0.5 - W / 2) * p - x0) / (a + e["heart_step_mm"])) ** 2 \
        + (((r + 0.5 - H / 2) * p - y0) / (b + e["heart_step_mm"])) ** 2 < 1
    out = {k: np.where(region, ndimage.shift(v, (shift, 0), order=1, mode="nearest"), v) for k, v in img.items()}
    out["region"] = region
    return out


def _detect(mean: np.ndarray, cfg: dict, rng: np.random.Generator) -> np.ndarray:
    """Detector response to a mean signal in detector units: g * Poisson(mean / g) + electronic noise."""
    s, e = cfg["simulate"], cfg["effects"]
    g = e["detector_gain"]
    mean = np.maximum(mean, 0.0)
    out = g * rng.poisson(mean / g).astype(np.float64) if s["noise"] else mean.copy()
    if e["read_noise"]:
        out += rng.normal(0, e["read_noise"], out.shape)
    return out


def _reference_series(ref: Reference, s: dict, rng: np.random.Generator) -> tuple[SteppingReference, np.ndarray]:
    """A noisy S-step series of the unloaded interferometer (the average of ``reference_frames`` frames).

    Returns the series (with nominal steps) and the actual step phases (rad).
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
    return SteppingReference(data=data.astype(np.float64), phase_step=steps), actual


def _store(frames: np.ndarray, dtype: str) -> np.ndarray:
    """Cast to the stored type; integer types are rounded and clipped to their range (with a warning)."""
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return np.maximum(frames, 0).astype(dt)
    top = np.iinfo(dt).max
    if frames.max() > top:
        log.warning("counts above %d are clipped to fit %s", top, dtype)
    return np.clip(np.rint(frames), 0, top).astype(dt)
