"""The model's effect catalogue: each effect that enters the expected count, as one entry of data.

An entry says everything the rest of the program needs to know about a term of the model: which
channel of the model it enters (:mod:`dfxcorr.model`), its parameter components, neutral value,
gauge, prior width and bound, and the metadata that other tables would otherwise repeat: the configuration
key that switches it on, the key of its truth in simulated files, the exact gauge directions it
brings (:mod:`dfxcorr.identify`) and its unit. Those tables are derived here (:func:`config_keys`,
:func:`truth_keys`).

The effects that change the noise, the alignment, the counts or the pixel set rather than a channel
(``spec/diagnosis.md``: sample motion, detector gain, ...) use the same :class:`Effect` entry, each in
its own module of :mod:`dfxcorr.effects`.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Effect:
    """One entry of the effect catalogue.

    Attributes
    ----------
    name : str
        Catalogue name (``spec/diagnosis.md``), also the result dataset name.
    channel : str or None
        Which term of the model it enters: 'phase', 'visibility', 'dose', 'background', 'harmonic'
        (:data:`dfxcorr.kernels.CHANNEL_IDS`); None for effects that change the noise, the alignment, the
        counts or the pixel set.
    per_frame : bool
        One parameter set per frame (shape (J, n)) or one global set (shape (n,)).
    components : tuple of str
        Names of the n parameter components; for per-frame channel effects 'x^k' gives the power of the
        lateral coordinate that multiplies the parameter, and 'x^k y^m' (phase and visibility channels) also
        the power of the detector-row coordinate: a term that depends on where on the detector the sample is.
    neutral : float
        Value at which the effect is absent.
    gauge : str
        'shift' (median over well-determined frames set to the neutral value: the images absorb a
        constant), 'scale' (robust normalisation to 1: the images absorb a factor) or 'none'.
    summary : str
        One line for reports.
    scale : float
        Prior width (parameter units) that keeps frames with almost no data near the neutral value.
    lower : float or None
        Physical lower bound for the parameters (None: unbounded).
    config : str or None
        The configuration key ('section.key') that puts the effect in a reconstruction's model.
    truth : str or None
        The key of its per-frame truth in simulated truth files (``data/README.md``).
    gauge_dims : int
        Exact gauge directions its parameters bring (a common shift or scale the images take up).
    unit : str
        Unit of its parameters: 'rad', 'counts', 'rows', or '' (a dimensionless factor or fraction).
    """

    name: str
    channel: str | None
    per_frame: bool
    components: tuple[str, ...]
    neutral: float
    gauge: str
    summary: str
    scale: float = 1.0
    lower: float | None = None
    config: str | None = None
    truth: str | None = None
    gauge_dims: int = 0
    unit: str = ""

    def __post_init__(self) -> None:
        if any(self.row_powers) and self.channel not in ("phase", "visibility"):
            raise ValueError(f"effect {self.name!r}: only the phase and visibility channels take powers of y")

    @property
    def powers(self) -> tuple[int, ...]:
        """Powers of x of per-frame components ('x^k' or 'x^k y^m'); 0 for each component of a global entry (its
        components name a basis, such as background's '1', 'x', 'y')."""
        return self._powers("x")

    @property
    def row_powers(self) -> tuple[int, ...]:
        """Powers of the row coordinate y of per-frame components (0 where a component names none, and for each
        component of a global entry)."""
        return self._powers("y")

    def _powers(self, axis: str) -> tuple[int, ...]:
        return tuple(_power(c, axis) for c in self.components) if self.per_frame else (0,) * self.size

    @property
    def size(self) -> int:
        return len(self.components)


def _power(component: str, axis: str) -> int:
    """The power of ``axis`` in a per-frame component such as 'x^1' or 'x^0 y^2' (0 where it is absent)."""
    return sum(int(f.split("^")[1]) for f in component.split() if f.split("^")[0] == axis)


CATALOGUE: dict[str, Effect] = {e.name: e for e in (
    Effect("phase_offset", "phase", True, ("x^0",), 0.0, "shift",
           "grating shift between exposures (or phase-step error): phi0_j added to the phase",
           config="vibration.phase_offset", truth="vib_phase_offset", gauge_dims=1, unit="rad"),
    Effect("tilt", "phase", True, ("x^1",), 0.0, "shift",
           "grating rotation about the optical axis: x * phi1_j added to the phase",
           config="vibration.tilt", truth="vib_tilt", gauge_dims=1, unit="rad"),
    Effect("curvature", "phase", True, ("x^2",), 0.0, "shift",
           "second-order grating deformation: x^2 * phi2_j added to the phase",
           config="vibration.curvature", truth="vib_curvature", gauge_dims=1, unit="rad"),
    Effect("visibility_loss", "visibility", True, ("x^0",), 1.0, "scale",
           "grating motion during the exposure: v^s_j multiplies the visibility", lower=1e-3,
           config="vibration.visibility", truth="vib_visibility", gauge_dims=1),
    # v1_j, v2_j proportional to v0_j: a factor (1 + a x + b x^2) that the dark-field image takes up
    Effect("visibility_tilt", "visibility", True, ("x^1", "x^2"), 0.0, "shift",
           "rotation during the exposure: visibility factor v0_j + x v1_j + x^2 v2_j",
           config="vibration.visibility_tilt", gauge_dims=2),
    Effect("dose", "dose", True, ("x^0",), 1.0, "scale",
           "source output or exposure-time fluctuation: d_j multiplies the expected count", lower=1e-3,
           config="vibration.dose", truth="vib_dose", gauge_dims=1),
    Effect("background", "background", False, ("1", "x", "y"), 0.0, "none",
           "additive signal not modulated by the gratings: b0 + b1 x + b2 y (counts)", scale=1e6,
           config="vibration.background", unit="counts"),
    Effect("harmonic", "harmonic", False, ("cos", "sin"), 0.0, "none",
           "non-sinusoidal stepping curve: v cos psi becomes v (cos psi + a2 cos(2 psi + beta))",
           config="vibration.harmonic"),
)}

#: The paper's model (eq. 19).
PAPER_MODEL = ("phase_offset", "tilt", "visibility_loss")
#: Effects that enter the expected count, in the order the fit stages them.
MEAN_EFFECTS = tuple(CATALOGUE)


def effect(name: str) -> Effect:
    """Catalogue entry by name; ValueError naming the valid names otherwise."""
    try:
        return CATALOGUE[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; the model's catalogue has {', '.join(CATALOGUE)}") from None


def neutral_params(effects: Iterable[str], n_frames: int) -> dict[str, np.ndarray]:
    """Parameters at which every listed effect is absent.

    Returns
    -------
    dict
        name -> ndarray of shape (J, n) for per-frame effects, (n,) for global ones.
    """
    out = {}
    for name in effects:
        e = effect(name)
        shape = (n_frames, e.size) if e.per_frame else (e.size,)
        out[name] = np.full(shape, e.neutral, dtype=np.float64)
    return out


def config_keys(section: str) -> dict[str, str]:
    """Configuration key within ``section`` -> effect name, for every entry switched on there."""
    out = {}
    for e in CATALOGUE.values():
        if e.config is not None and e.config.split(".")[0] == section:
            out[e.config.split(".", 1)[1]] = e.name
    return out


def truth_keys() -> dict[str, str]:
    """Effect name -> key of its per-frame truth in simulated truth files."""
    return {e.name: e.truth for e in CATALOGUE.values() if e.truth is not None}
