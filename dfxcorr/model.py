"""The forward model: paper eq. 19 extended by the effect catalogue of ``spec/diagnosis.md``.

This module is the only definition of the expected count, its derivatives and the per-frame effects;
the simulator, the baselines and the diagnosis call it. The fit and the retrieval run the compiled
loops of :mod:`dfxcorr.kernels`, which evaluate the same model from the channel values of
:func:`channels`; the numpy expressions here are their definition and the tests' oracle.

For detector pixel i (row r, column c) in frame j the expected count is

    Ibar = D_j tf t_i (1 + vf V_ij v_i (cos psi + a2 cos(2 psi + beta))) + b(x_i, y_i) + dark_i
    psi = θ + phi_i,   θ = phi^f + phase_step_j + Φ_ij

with the *channels*

    Φ_ij = sum over phase effects of   p_j(e) * x_i^k   (phase_offset k=0, tilt k=1, curvature k=2)
    V_ij = sum over visibility effects (visibility_loss: v0_j, default 1; visibility_tilt: x v1_j + x^2 v2_j)
    D_j  = dose, default 1
    b    = background, a smooth additive term (coefficients of 1, x, y in counts)
    hc, hs = (a2 cos beta, a2 sin beta), the second harmonic of the stepping curve (global)

The second harmonic follows the full fringe phase psi (the sample's refraction included) and carries
the product of all visibilities, like the first (``spec/diagnosis.md`` version 2).

Written in the per-pixel unknowns (t, c, s) = (t, t v cos phi, t v sin phi) (paper eq. 8), m = sqrt(c^2 + s^2),

    Ibar = t A + c Bc + s Bs + Hc (c^2 - s^2) / m - Hs 2 c s / m + offset,
    A = D tf,  Bc = D tf vf V cos θ,  Bs = -D tf vf V sin θ,
    Hc = D tf vf V (hc cos 2θ - hs sin 2θ),  Hs = D tf vf V (hc sin 2θ + hs cos 2θ),  offset = b + dark.

Without the harmonic the model is linear in (t, c, s) and the images follow in closed form (weighted
linear least squares, eq. 9) for given per-frame parameters; v = sqrt(c^2 + s^2) / t, phi = atan2(s, c)
(eq. 10). The harmonic term is homogeneous of degree 1 in (c, s) but not linear: the images are then
refined by Gauss-Newton steps (:func:`solve_images`), each again a closed-form solve whose columns are
the model's derivatives at the current direction of (c, s) (by Euler's identity the linearised model
has no constant term), so the solution is the least-squares optimum and the envelope theorem holds.

Data layout
-----------
A scan is handled as an :class:`Observations` stack: one block per (illuminated detector row, frame)
pair, ``K`` blocks sorted by row, each holding the ``C`` selected detector columns. Per-pixel sums are
segment sums over the blocks of one row; per-frame sums are bincounts over the blocks' frames.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from . import kernels

# --------------------------------------------------------------------------------------------------
# The effect catalogue
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Effect:
    """One entry of the effect catalogue.

    Attributes
    ----------
    name : str
        Catalogue name (``spec/diagnosis.md``), also the result dataset name.
    channel : str or None
        Which term of the model it enters: 'phase', 'visibility', 'dose', 'background', 'harmonic';
        None for effects that change the noise ('detector_gain') or the pixel set ('sample_motion').
    per_frame : bool
        One parameter set per frame (shape (J, n)) or one global set (shape (n,)).
    components : tuple of str
        Names of the n parameter components; for per-frame effects 'x^k' gives the power of the
        lateral coordinate that multiplies the parameter.
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

    @property
    def powers(self) -> tuple[int, ...]:
        """Powers of x for per-frame components ('x^k')."""
        return tuple(int(c.split("^")[1]) for c in self.components)

    @property
    def size(self) -> int:
        return len(self.components)


CATALOGUE: dict[str, Effect] = {e.name: e for e in (
    Effect("phase_offset", "phase", True, ("x^0",), 0.0, "shift",
           "grating shift between exposures (or phase-step error): phi0_j added to the phase", scale=1.0),
    Effect("tilt", "phase", True, ("x^1",), 0.0, "shift",
           "grating rotation about the optical axis: x * phi1_j added to the phase", scale=1.0),
    Effect("curvature", "phase", True, ("x^2",), 0.0, "shift",
           "second-order grating deformation: x^2 * phi2_j added to the phase", scale=1.0),
    Effect("visibility_loss", "visibility", True, ("x^0",), 1.0, "scale",
           "grating motion during the exposure: v^s_j multiplies the visibility", scale=1.0, lower=1e-3),
    Effect("visibility_tilt", "visibility", True, ("x^1", "x^2"), 0.0, "shift",
           "rotation during the exposure: visibility factor v0_j + x v1_j + x^2 v2_j", scale=1.0),
    Effect("dose", "dose", True, ("x^0",), 1.0, "scale",
           "source output or exposure-time fluctuation: d_j multiplies the expected count", scale=1.0, lower=1e-3),
    Effect("background", "background", False, ("1", "x", "y"), 0.0, "none",
           "additive signal not modulated by the gratings: b0 + b1 x + b2 y (counts)", scale=1e6),
    Effect("harmonic", "harmonic", False, ("cos", "sin"), 0.0, "none",
           "non-sinusoidal stepping curve: v cos psi becomes v (cos psi + a2 cos(2 psi + beta))", scale=1.0),
    Effect("sample_motion", None, False, (), 0.0, "none",
           "part of the sample moved during the scan: pixels whose frames disagree"),
    Effect("detector_gain", None, False, (), 1.0, "none",
           "noise is not Poisson in the file's units: variance = g * mean (+ electronic noise)"),
    # read where the flat field is aligned (align.reference_offset, align.position_errors), not in the model's
    # channels
    Effect("reference_offset", None, False, ("delta",), 0.0, "none",
           "the interferometer sat delta rows off during the scan: the flat field is read at u - delta"),
    Effect("position_error", None, True, ("delta",), 0.0, "shift",
           "the recorded position of frame j is off by delta_j rows: its flat field is read at u - delta_j"),
    Effect("detector_lag", None, False, ("a",), 0.0, "none",
           "the detector carries a fraction a of the previous frame's signal into the next: I_j = S_j + a S_(j-1)"),
    Effect("pixel_noise", None, False, (), 1.0, "none",
           "the noise variance differs from pixel to pixel: variance_i = f_i * g * mean (+ electronic)"),
)}

#: The paper's model (eq. 19).
PAPER_MODEL = ("phase_offset", "tilt", "visibility_loss")
#: Effects that enter the expected count, in the order the fit stages them.
MEAN_EFFECTS = tuple(n for n, e in CATALOGUE.items() if e.channel is not None)


def effect(name: str) -> Effect:
    """Catalogue entry by name; ValueError naming the valid names otherwise."""
    try:
        return CATALOGUE[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; the catalogue has {', '.join(CATALOGUE)}") from None


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
        if e.channel is None:
            continue
        shape = (n_frames, e.size) if e.per_frame else (e.size,)
        out[name] = np.full(shape, e.neutral, dtype=np.float64)
    return out


# --------------------------------------------------------------------------------------------------
# Observations: the aligned data
# --------------------------------------------------------------------------------------------------


def lateral_coordinate(columns: np.ndarray, width: int) -> np.ndarray:
    """x = (2c + 1) / W - 1: -1 and +1 at the outer edges of the first and last column."""
    return (2.0 * np.asarray(columns, dtype=np.float64) + 1.0) / width - 1.0


@dataclass
class Observations:
    """Illuminated samples of a scan with their flat field, as blocks of (row, frame).

    Attributes
    ----------
    counts : ndarray, shape (K, C)
        Measured counts (detector units).
    tf, vf, phif : ndarray, shape (K, C)
        Flat-field transmission (counts), visibility and phase (rad, the nominal phase step included)
        at each sample, aligned to the frame's position.
    dark : ndarray, shape (K, C)
        Dark signal (counts).
    use : ndarray of bool, shape (K, C)
        Samples that enter the fit (False for masked pixels).
    row, frame : ndarray of int, shape (K,)
        Detector row and frame of each block, sorted by row.
    columns : ndarray of int, shape (C,)
        Detector columns held.
    shape : tuple
        (J, H, W) of the scan.
    gain : float
        Detector units per photon.
    electronic : float
        Electronic noise variance (counts^2); the variance of a sample is gain * (Ibar - dark) + electronic.
    noise : ndarray, shape (R, C), or None
        Variance factor f of each pixel held (``pixel_noise``): the variance is f * gain * (Ibar - dark)
        + electronic; None: 1 everywhere.
    """

    counts: np.ndarray
    tf: np.ndarray
    vf: np.ndarray
    phif: np.ndarray
    dark: np.ndarray
    use: np.ndarray
    row: np.ndarray
    frame: np.ndarray
    columns: np.ndarray
    shape: tuple
    gain: float = 1.0
    electronic: float = 0.0
    noise: np.ndarray | None = None
    rows: np.ndarray = field(init=False)
    starts: np.ndarray = field(init=False)
    pixel: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        if np.any(np.diff(self.row) < 0):
            raise ValueError("observation blocks must be sorted by row")
        self.rows, self.starts, counts = np.unique(self.row, return_index=True, return_counts=True)
        self.pixel = np.repeat(np.arange(self.rows.size), counts)

    @property
    def x(self) -> np.ndarray:
        """Lateral coordinate of the held columns, shape (C,)."""
        return lateral_coordinate(self.columns, self.shape[2])

    @property
    def y(self) -> np.ndarray:
        """Detector-row coordinate of each block in [-1, 1], shape (K,)."""
        return (2.0 * self.row + 1.0) / self.shape[1] - 1.0

    @property
    def n_frames(self) -> int:
        return self.shape[0]

    def segment_sum(self, a: np.ndarray) -> np.ndarray:
        """Sum over the blocks of each row: (K, ...) -> (R, ...), R = number of rows held."""
        return np.add.reduceat(a, self.starts, axis=0)

    def frame_sum(self, a: np.ndarray) -> np.ndarray:
        """Sum of per-block values (K,) over the blocks of each frame -> (J,)."""
        return np.bincount(self.frame, weights=a, minlength=self.n_frames)

    def to_image(self, values: np.ndarray, *, fill: float = np.nan) -> np.ndarray:
        """Place per-pixel values (R, C) into a detector image (H, W), ``fill`` elsewhere."""
        out = np.full(self.shape[1:], fill, dtype=np.result_type(values, type(fill)))
        out[np.ix_(self.rows, self.columns)] = values
        return out

    def subset(self, columns: np.ndarray) -> Observations:
        """The same blocks restricted to the given positions of ``self.columns``."""
        idx = np.asarray(columns)
        return Observations(self.counts[:, idx], self.tf[:, idx], self.vf[:, idx], self.phif[:, idx],
                            self.dark[:, idx], self.use[:, idx], self.row, self.frame, self.columns[idx],
                            self.shape, self.gain, self.electronic, None if self.noise is None else self.noise[:, idx])

    def pixel_gain(self, gain: float | None = None) -> np.ndarray:
        """Detector units per photon of each pixel held, f * gain (``pixel_noise``), shape (R, C)."""
        g = self.gain if gain is None else gain
        return g * (np.ones((self.rows.size, self.columns.size)) if self.noise is None else self.noise)


# --------------------------------------------------------------------------------------------------
# Channels and design
# --------------------------------------------------------------------------------------------------


@dataclass
class Channels:
    """Values of the model's channels on the (frame, column) grid.

    Attributes
    ----------
    phase : ndarray, shape (J, C)
        Φ, added to the fringe phase (rad).
    vis : ndarray, shape (J, C)
        V, multiplies the flat-field visibility.
    dose : ndarray, shape (J,)
        D, multiplies the expected count without background.
    background : ndarray, shape (3,)
        Coefficients of (1, x, y) of the additive background (counts).
    harmonic : ndarray, shape (2,)
        (hc, hs) of the stepping curve's second harmonic.
    """

    phase: np.ndarray
    vis: np.ndarray
    dose: np.ndarray
    background: np.ndarray
    harmonic: np.ndarray


def channels(params: dict[str, np.ndarray], *, x: np.ndarray, n_frames: int) -> Channels:
    """Map effect parameters to channel values: the catalogue's parameterisation, written once.

    Parameters
    ----------
    params : dict
        Effect name -> parameters (see :func:`neutral_params`); effects not listed are absent.
    x : ndarray, shape (C,)
        Lateral coordinate of the columns.
    n_frames : int
        J.

    Returns
    -------
    Channels
        Φ = sum of p_j x^k over phase effects; V = 1 + sum over visibility effects of (their field -
        their neutral value), so visibility_loss replaces the 1 and visibility_tilt adds x-dependent
        terms; D likewise (1 + sum of p_j - neutral over dose effects); background and harmonic are
        their parameters. Every channel is linear in the parameters.
    """
    C = x.size
    out = Channels(np.zeros((n_frames, C)), np.ones((n_frames, C)), np.ones(n_frames), np.zeros(3), np.zeros(2))
    for name, p in params.items():
        e = effect(name)
        if e.channel in ("phase", "visibility"):
            field_ = sum(p[:, m, None] * x[None, :] ** k for m, k in enumerate(e.powers))
            if e.channel == "phase":
                out.phase = out.phase + field_
            else:
                out.vis = out.vis + field_ - e.neutral
        elif e.channel == "dose":
            out.dose = out.dose + p[:, 0] - e.neutral
        elif e.channel == "background":
            out.background = out.background + p
        elif e.channel == "harmonic":
            out.harmonic = out.harmonic + p
    return out


def channel_adjoint(names: Sequence[str], grad: Channels, *, x: np.ndarray, square: bool = False
                    ) -> dict[str, np.ndarray]:
    """Pull channel gradients back to effect parameters (the adjoint of :func:`channels`).

    Parameters
    ----------
    names : sequence of str
        Effects whose gradients are wanted.
    grad : Channels
        d(cost)/d(channel value) for every channel value.
    x : ndarray, shape (C,)
    square : bool
        ``grad`` holds Gauss-Newton sums sum w F^2 per channel value: apply the squared Jacobian,
        giving the diagonal of the information of the parameters.

    Returns
    -------
    dict
        name -> array shaped like that effect's parameters, e.g. dcost/dp_{j,k} = sum_c gΦ[j, c] x_c^k.
    """
    power = 2 if square else 1
    out = {}
    for name in names:
        e = effect(name)
        if e.channel in ("phase", "visibility"):
            g = grad.phase if e.channel == "phase" else grad.vis
            out[name] = np.stack([g @ x ** (power * k) for k in e.powers], axis=-1)
        elif e.channel == "dose":
            out[name] = np.asarray(grad.dose, dtype=np.float64)[:, None].copy()
        elif e.channel == "background":
            out[name] = np.asarray(grad.background, dtype=np.float64).copy()
        elif e.channel == "harmonic":
            out[name] = np.asarray(grad.harmonic, dtype=np.float64).copy()
        else:
            raise ValueError(f"effect {name!r} does not enter the expected count")
    return out


def component_table(names: Sequence[str]) -> tuple[np.ndarray, np.ndarray, int, list[tuple[str, int]]]:
    """The parameter components of ``names`` as the Fisher kernel reads them.

    Returns
    -------
    channel : ndarray of int, shape (Q,)
        :data:`dfxcorr.kernels.CHANNEL_IDS` of each component, per-frame components first.
    power : ndarray of int, shape (Q,)
        Power of x (per-frame components) or index into the effect's basis (global ones).
    n_per_frame : int
    components : list of (name, component)
    """
    order = [n for n in names if effect(n).per_frame] + [n for n in names if not effect(n).per_frame]
    comps = [(n, m) for n in order for m in range(effect(n).size)]
    channel = np.array([_channel_id(n) for n, _ in comps], dtype=np.int64)
    power = np.array([effect(n).powers[m] if effect(n).per_frame else m for n, m in comps], dtype=np.int64)
    return channel, power, sum(effect(n).size for n in names if effect(n).per_frame), comps


def _channel_id(name: str) -> int:
    """:data:`dfxcorr.kernels.CHANNEL_IDS` of an effect with parameters (those without a channel have none)."""
    channel = effect(name).channel
    if channel is None:
        raise ValueError(f"effect {name!r} does not enter the expected count")
    return kernels.CHANNEL_IDS[channel]


def fisher_index(names: Sequence[str], n_frames: int) -> list[tuple[str, int, int]]:
    """(name, frame, component) of each axis entry of the Fisher matrix; frame is -1 for global effects."""
    _, _, n_per_frame, comps = component_table(names)
    return [(n, j, m) for j in range(n_frames) for n, m in comps[:n_per_frame]] + \
        [(n, -1, m) for n, m in comps[n_per_frame:]]


@dataclass
class Design:
    """Per-sample coefficients of the per-pixel model Ibar = t A + c Bc + s Bs + Hc e - Hs f + offset.

    e = (c^2 - s^2) / m, f = 2 c s / m (:func:`harmonic_factors`). All arrays have shape (K, C)
    (``dose`` (K, 1)); ``theta`` is the fringe phase without the sample; ``Hc``, ``Hs`` are zero without
    the harmonic. ``channels`` holds the channel values they were made from.
    """

    A: np.ndarray
    Bc: np.ndarray
    Bs: np.ndarray
    Hc: np.ndarray
    Hs: np.ndarray
    offset: np.ndarray
    theta: np.ndarray
    dose: np.ndarray
    vis: np.ndarray
    harmonic: tuple[float, float]
    channels: Channels


def design(obs: Observations, params: dict[str, np.ndarray]) -> Design:
    """Evaluate the channels of the model for given effect parameters.

    Parameters
    ----------
    obs : Observations
    params : dict
        Effect name -> parameters (see :func:`neutral_params`); effects not listed are absent.

    Returns
    -------
    Design
    """
    ch = channels(params, x=obs.x, n_frames=obs.n_frames)
    dose = ch.dose[obs.frame][:, None]
    vis = ch.vis[obs.frame]
    background = sum(ch.background[m] * b for m, b in enumerate(background_basis(obs))) if np.any(ch.background) \
        else np.zeros(obs.counts.shape)
    hc, hs = float(ch.harmonic[0]), float(ch.harmonic[1])
    theta = obs.phif + ch.phase[obs.frame]
    amp = dose * obs.tf
    Bv = amp * obs.vf * vis
    Hc, Hs = np.zeros_like(theta), np.zeros_like(theta)
    if hc or hs:
        c2, s2 = np.cos(2 * theta), np.sin(2 * theta)
        Hc, Hs = Bv * (hc * c2 - hs * s2), Bv * (hc * s2 + hs * c2)
    return Design(A=amp * np.ones_like(theta), Bc=Bv * np.cos(theta), Bs=-Bv * np.sin(theta), Hc=Hc, Hs=Hs,
                  offset=background + obs.dark, theta=theta, dose=dose, vis=vis, harmonic=(hc, hs), channels=ch)


def background_basis(obs: Observations) -> list[np.ndarray]:
    """The smooth basis of the background effect (1, x, y), each broadcast to (K, C)."""
    K, C = obs.counts.shape
    return [np.ones((K, C)), np.broadcast_to(obs.x[None, :], (K, C)), np.broadcast_to(obs.y[:, None], (K, C))]


def harmonic_factors(c: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Direction of (c, s) and the sample's factors of the harmonic term.

    Parameters
    ----------
    c, s : ndarray
        t v cos phi, t v sin phi (any shape).

    Returns
    -------
    u, w : ndarray
        cos phi, sin phi (0 where c = s = 0: no modulation, no harmonic).
    e, f : ndarray
        (c^2 - s^2) / m = m cos 2 phi and 2 c s / m = m sin 2 phi, m = sqrt(c^2 + s^2).
    """
    m = np.hypot(c, s)
    with np.errstate(divide="ignore", invalid="ignore"):
        u, w = np.where(m > 0, c / m, 0.0), np.where(m > 0, s / m, 0.0)
    return u, w, c * u - s * w, s * u + c * w


def image_columns(dsg: Design, c: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dIbar/dc and dIbar/ds at images (c, s) given per sample, each (K, C).

    Bc and Bs plus the harmonic term's derivatives: d e/dc = u (1 + 2 w^2), d e/ds = -w (1 + 2 u^2),
    d f/dc = 2 w^3, d f/ds = 2 u^3. By Euler's identity c dIbar/dc + s dIbar/ds is the whole modulated
    part, so a Gauss-Newton step is a closed-form solve with these columns.
    """
    if not any(dsg.harmonic):
        return dsg.Bc, dsg.Bs
    u, w, _, _ = harmonic_factors(c, s)
    return (dsg.Bc + dsg.Hc * u * (1 + 2 * w * w) - dsg.Hs * 2 * w ** 3,
            dsg.Bs - dsg.Hc * w * (1 + 2 * u * u) - dsg.Hs * 2 * u ** 3)


# --------------------------------------------------------------------------------------------------
# Images: the per-pixel closed-form solve
# --------------------------------------------------------------------------------------------------


@dataclass
class Images:
    """Per-pixel linear unknowns (t, c, s) for the rows held in the observations.

    Attributes
    ----------
    coef : ndarray, shape (R, C, 3)
        t, c = t v cos phi, s = t v sin phi.
    valid : ndarray of bool, shape (R, C)
        Pixels whose normal equations were solvable.
    inverse : ndarray, shape (R, C, 3, 3) or None
        Inverse normal matrix per pixel (for leverages and Fisher information).
    """

    coef: np.ndarray
    valid: np.ndarray
    inverse: np.ndarray | None = None

    @property
    def t(self) -> np.ndarray:
        return self.coef[..., 0]

    @property
    def v(self) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.hypot(self.coef[..., 1], self.coef[..., 2]) / self.coef[..., 0]

    @property
    def phi(self) -> np.ndarray:
        return np.arctan2(self.coef[..., 2], self.coef[..., 1])


def solve_pixels(obs: Observations, columns: list[np.ndarray], target: np.ndarray, weights: np.ndarray,
                 *, keep_inverse: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Weighted linear least squares per pixel: min sum_k w (target - sum_a coef_a X_a)^2.

    Parameters
    ----------
    obs : Observations
        Supplies the grouping of samples into pixels.
    columns : list of p ndarray, each (K, C)
        Design columns X_a.
    target : ndarray, shape (K, C)
    weights : ndarray, shape (K, C)
        Zero for samples that must not count.
    keep_inverse : bool
        Also return the inverse normal matrices.

    Returns
    -------
    coef : ndarray, shape (R, C, p)
    valid : ndarray of bool, shape (R, C)
        False where the first column is absent, fewer samples count than there are unknowns, or the
        normal matrix is singular (coef = 0 there). Other columns that vanish at every sample of a
        pixel are left out of that pixel's unknowns (coefficient 0).
    inverse : ndarray, shape (R, C, p, p) or None
    """
    p = len(columns)
    wX = [weights * X for X in columns]
    N = np.empty(target.shape[:0] + (obs.rows.size, target.shape[1], p, p))
    for a in range(p):
        for b in range(a, p):
            N[..., a, b] = N[..., b, a] = obs.segment_sum(wX[a] * columns[b])
    rhs = np.stack([obs.segment_sum(wXa * target) for wXa in wX], axis=-1)
    n_used = obs.segment_sum((weights > 0).astype(np.float64))
    diag = np.einsum("...ii->...i", N)
    # a column that is zero at every sample of a pixel (no fringe: v^f = 0) is not an unknown there
    present = diag > 0
    scale = np.sqrt(np.where(present, diag, 1.0))
    Ns = N / (scale[..., :, None] * scale[..., None, :])
    Ns = np.where(present[..., :, None] | present[..., None, :], Ns, 0.0) + np.eye(p) * ~present[..., None, :]
    # the determinant of the unit-diagonal matrix is scale-free; tiny means collinear columns
    valid = (n_used >= present.sum(axis=-1)) & present[..., 0] & (np.abs(np.linalg.det(Ns)) > 1e-10)
    Ns[~valid] = np.eye(p)
    inv_s = np.linalg.inv(Ns)
    coef = np.einsum("...ab,...b->...a", inv_s, rhs / scale) / scale
    coef[~valid] = 0.0
    inverse = inv_s / (scale[..., :, None] * scale[..., None, :]) if keep_inverse else None
    if inverse is not None:
        inverse[~valid] = 0.0
    return coef, valid, inverse


def solve_images(obs: Observations, dsg: Design, weights: np.ndarray, *, phase: float | None = None,
                 keep_inverse: bool = False) -> Images:
    """Least-squares images for fixed per-frame parameters (paper eqs. 8-9).

    Closed form without the harmonic. With it, the first solve leaves the harmonic out and each of
    :data:`dfxcorr.kernels.HARMONIC_STEPS` further solves is a Gauss-Newton step with the columns of
    :func:`image_columns` at the previous images.

    Parameters
    ----------
    obs : Observations
    dsg : Design
    weights : ndarray, shape (K, C)
    phase : float, optional
        If given, the phase image is held at this constant (the circular-mean measure of paper eq. 36)
        and only t and t v are solved for.
    keep_inverse : bool
        Keep the inverse normal matrices of the last solve (needed for leverages).

    Returns
    -------
    Images
    """
    target = obs.counts - dsg.offset
    steps = 1 + (kernels.HARMONIC_STEPS if any(dsg.harmonic) else 0)
    coef = np.zeros((obs.rows.size, obs.columns.size, 3))
    for _ in range(steps):
        Xc, Xs = image_columns(dsg, coef[obs.pixel, :, 1], coef[obs.pixel, :, 2])
        if phase is None:
            coef, valid, inv = solve_pixels(obs, [dsg.A, Xc, Xs], target, weights, keep_inverse=keep_inverse)
            continue
        cp, sp = np.cos(phase), np.sin(phase)
        coef2, valid, _ = solve_pixels(obs, [dsg.A, Xc * cp + Xs * sp], target, weights)
        coef, inv = np.stack([coef2[..., 0], coef2[..., 1] * cp, coef2[..., 1] * sp], axis=-1), None
    return Images(coef, valid, inv)


def harmonic_term(obs: Observations, dsg: Design, images: Images) -> np.ndarray:
    """The second harmonic's share of the expected counts, Hc e - Hs f, shape (K, C)."""
    c = images.coef[obs.pixel]
    _, _, e, f = harmonic_factors(c[..., 1], c[..., 2])
    return dsg.Hc * e - dsg.Hs * f


def expected(obs: Observations, dsg: Design, images: Images) -> np.ndarray:
    """Expected counts Ibar, shape (K, C)."""
    c = images.coef[obs.pixel]
    linear = c[..., 0] * dsg.A + c[..., 1] * dsg.Bc + c[..., 2] * dsg.Bs + dsg.offset
    return linear + harmonic_term(obs, dsg, images) if any(dsg.harmonic) else linear


def circular_mean(phi: np.ndarray, weights: np.ndarray | None = None) -> float:
    """arg(sum_k w_k exp(i phi_k)) (paper eq. 37), ignoring non-finite entries."""
    ok = np.isfinite(phi)
    w = np.ones_like(phi) if weights is None else weights
    return float(np.angle(np.sum(w[ok] * np.exp(1j * phi[ok]))))


# --------------------------------------------------------------------------------------------------
# Derivatives
# --------------------------------------------------------------------------------------------------


def sample_derivatives(obs: Observations, dsg: Design, images: Images, name: str) -> list[np.ndarray]:
    """dIbar/d(parameter component) at every sample, before summation over frames.

    For a per-frame effect, component m of frame j acts only on the samples of frame j, so the
    returned field F (K, C) holds dIbar_k/dp_{frame[k], m} at sample k. For a global effect F is the
    derivative with respect to the single parameter.

    Returns
    -------
    list of ndarray, one (K, C) array per component
    """
    e = effect(name)
    c = images.coef[obs.pixel]
    t, cc, ss = c[..., 0], c[..., 1], c[..., 2]
    x = obs.x[None, :]
    hc, hs = dsg.harmonic
    amp = dsg.dose * obs.tf
    bv = amp * obs.vf * dsg.vis
    # m cos(2 psi), m sin(2 psi) of the sample (psi = θ + phi), and the harmonic's a2 m cos, a2 m sin (2 psi + beta)
    ef: np.ndarray | float
    ff: np.ndarray | float
    g: np.ndarray | float
    k: np.ndarray | float
    p2: np.ndarray | float
    q2: np.ndarray | float
    ef = ff = g = k = p2 = q2 = 0.0
    # the harmonic's own derivatives need its factors even where it is absent (hc = hs = 0: a score test)
    if hc or hs or e.channel == "harmonic":
        _, _, ef, ff = harmonic_factors(cc, ss)
        c2, s2 = np.cos(2 * dsg.theta), np.sin(2 * dsg.theta)
        g, k = c2 * ef - s2 * ff, s2 * ef + c2 * ff
        p2, q2 = hc * g - hs * k, hc * k + hs * g
    q = cc * np.cos(dsg.theta) - ss * np.sin(dsg.theta)
    if e.channel == "phase":
        base = cc * dsg.Bs - ss * dsg.Bc - 2 * bv * q2
        return [base * x ** k_ for k_ in e.powers]
    if e.channel == "visibility":
        base = amp * obs.vf * (q + p2)
        return [base * x ** k_ for k_ in e.powers]
    if e.channel == "dose":
        return [(t * dsg.A + cc * dsg.Bc + ss * dsg.Bs + (dsg.Hc * ef - dsg.Hs * ff)) / dsg.dose]
    if e.channel == "background":
        return background_basis(obs)
    if e.channel == "harmonic":
        return [bv * g, -bv * k]
    raise ValueError(f"effect {name!r} does not enter the expected count")


def reduce_component(obs: Observations, name: str, F: np.ndarray) -> np.ndarray:
    """Sum a per-sample field to the parameter it belongs to: (J,) per-frame or a scalar for global effects."""
    if effect(name).per_frame:
        return obs.frame_sum(F.sum(axis=1))
    return np.asarray(F.sum())


def gradient(obs: Observations, dsg: Design, images: Images, weights: np.ndarray, resid: np.ndarray,
             names: Iterable[str]) -> dict[str, np.ndarray]:
    """Gradient of the cost sum w (I - Ibar)^2 with respect to effect parameters at fixed images.

    At the closed-form images this is the gradient of the reduced cost (envelope theorem, paper
    eq. 25).

    Returns
    -------
    dict
        name -> array shaped like that effect's parameters.
    """
    G = -2.0 * weights * resid
    out = {}
    for name in names:
        comps = [reduce_component(obs, name, G * F) for F in sample_derivatives(obs, dsg, images, name)]
        out[name] = np.stack(comps, axis=-1)
    return out


def leverage(obs: Observations, dsg: Design, images: Images, weights: np.ndarray) -> np.ndarray:
    """Leverage of each sample in its pixel's image fit, w x^T N^-1 x, shape (K, C)."""
    if images.inverse is None:
        raise ValueError("leverage needs the inverse normal matrices (solve_images(..., keep_inverse=True))")
    c = images.coef[obs.pixel]
    X = np.stack([dsg.A, *image_columns(dsg, c[..., 1], c[..., 2])], axis=-1)
    return weights * np.einsum("kca,kcab,kcb->kc", X, images.inverse[obs.pixel], X)


def fisher_matrix(obs: Observations, dsg: Design, images: Images, weights: np.ndarray, names: Sequence[str],
                  *, profiled: bool = True) -> tuple[np.ndarray, list[tuple[str, int, int]]]:
    """Fisher information of all effect parameters, with the images profiled out.

    The images are estimated from the same data, so the information of the effect parameters is
    the Schur complement sum_i D_i^T (W - W X (X^T W X)^-1 X^T W) D_i over pixels i, where D_i holds
    the derivatives of the pixel's samples with respect to the effect parameters and X_i its image
    design. Per-frame parameters of different frames are coupled through the pixels they share.
    The information at known images is computed here; the correction for the profiled images, a
    loop over pixels, by :func:`dfxcorr.kernels.fisher`.

    Parameters
    ----------
    obs : Observations
    dsg : Design
    images : Images
        Needs ``inverse`` (``solve_images(..., keep_inverse=True)``) when ``profiled``.
    weights : ndarray, shape (K, C)
    names : sequence of str
        Effects whose parameters are included.
    profiled : bool
        False gives the information at known images (no Schur complement).

    Returns
    -------
    info : ndarray, shape (P, P)
        For the log-likelihood -sum w r^2 / 2.
    index : list of (name, frame, component)
        Meaning of each axis entry; frame is -1 for global effects.
    """
    J = obs.n_frames
    per_frame = [(n, m, F) for n in names if effect(n).per_frame
                 for m, F in enumerate(sample_derivatives(obs, dsg, images, n))]
    glob = [(n, m, F) for n in names if not effect(n).per_frame
            for m, F in enumerate(sample_derivatives(obs, dsg, images, n))]
    Pf, Pg = len(per_frame), len(glob)
    index = fisher_index(names, J)
    info = np.zeros((J * Pf + Pg, J * Pf + Pg))
    Ff = np.stack([F for *_, F in per_frame], axis=-1) if Pf else np.zeros(obs.counts.shape + (0,))
    Fg = np.stack([F for *_, F in glob], axis=-1) if Pg else np.zeros(obs.counts.shape + (0,))
    wFf, wFg = weights[..., None] * Ff, weights[..., None] * Fg
    # information at known images: per-frame blocks, per-frame x global, global x global
    blocks = np.einsum("kca,kcb->kab", wFf, Ff)
    cross = np.einsum("kca,kcb->kab", wFf, Fg)
    fidx = np.arange(J)[:, None] * Pf + np.arange(Pf)[None, :]
    for j in range(J):
        sel = obs.frame == j
        info[np.ix_(fidx[j], fidx[j])] += blocks[sel].sum(axis=0)
        info[np.ix_(fidx[j], J * Pf + np.arange(Pg))] += cross[sel].sum(axis=0)
    info[J * Pf:, J * Pf:] += np.einsum("kca,kcb->ab", wFg, Fg)
    info[J * Pf:, :J * Pf] = info[:J * Pf, J * Pf:].T
    if not profiled:
        return info, index
    # the correction sum_i Y_i^T N_i^-1 Y_i (Y = X^T W D per pixel) couples the frames of each row
    kernels.set_threads()
    _, corr = kernels.fisher(obs, dsg.channels, weights, images.coef, images.inverse, component_table(names)[:3])
    return info - corr, index


def variance(obs: Observations, ibar: np.ndarray, *, gain: float | None = None, floor: float = 1e-3) -> np.ndarray:
    """Noise variance of each sample, f g (Ibar - dark) + electronic (f of ``obs.noise``), shape (K, C)."""
    g = obs.gain if gain is None else gain
    if obs.noise is not None:
        g = g * obs.noise[obs.pixel]
    return g * np.maximum(ibar - obs.dark, floor) + obs.electronic


def pearson(obs: Observations, ibar: np.ndarray, *, gain: float | None = None,
            floor: float = 1e-3) -> np.ndarray:
    """Pearson residual squared (I - Ibar)^2 / variance per sample, shape (K, C)."""
    return (obs.counts - ibar) ** 2 / variance(obs, ibar, gain=gain, floor=floor)


def noise_weights(obs: Observations, ibar: np.ndarray, *, gain: float | None = None,
                  floor: float = 1.0) -> np.ndarray:
    """Inverse noise variance of the used samples (shot noise floored at ``floor`` counts), 0 elsewhere."""
    return np.where(obs.use, 1.0 / variance(obs, ibar, gain=gain, floor=floor), 0.0)


# --------------------------------------------------------------------------------------------------
# Detector lag (a fraction of the previous frame's signal in the next)
# --------------------------------------------------------------------------------------------------


def previous_block(row: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """Index of the block (row, frame - 1) of each (row, frame) block sorted by row, frames ascending; -1 if none.

    Parameters
    ----------
    row, frame : ndarray of int, shape (K,)

    Returns
    -------
    ndarray of int, shape (K,)
    """
    k = np.arange(row.size)
    prev = k - 1
    ok = (k > 0) & (row[prev] == row) & (frame[prev] == frame - 1)
    return np.where(ok, prev, -1)


def lag_free(counts: np.ndarray, dark: np.ndarray, row: np.ndarray, frame: np.ndarray, fraction: float,
             *, dtype: type = np.float32) -> np.ndarray:
    """Undo detector lag recursively: S_j = (I_j - dark) - a S_(j-1), S = 0 where the pixel was not lit.

    Parameters
    ----------
    counts : ndarray, shape (K, W)
        Measured counts I of (row, frame) blocks sorted by row, frames ascending within a row.
    dark : ndarray, shape (K, W)
        Dark signal of each block's pixels (counts); it carries no lag.
    row, frame : ndarray of int, shape (K,)
    fraction : float
        The lag fraction a (``spec/diagnosis.md``: I_j = S_j + a S_(j-1)).
    dtype : numpy dtype
        Of the result.

    Returns
    -------
    ndarray, shape (K, W)
        S + dark: the counts the detector would have given without lag. Where frame j - 1 did not
        light the pixel the lag-free signal of j - 1 is 0 and I_j is returned unchanged.
    """
    out: np.ndarray = np.asarray(counts, dtype=dtype) - np.asarray(dark, dtype=dtype)
    prev = previous_block(row, frame)
    order = np.argsort(frame, kind="stable")
    bounds = np.searchsorted(frame[order], np.arange(int(frame.max(initial=-1)) + 2))
    # frame by frame: frame j - 1's blocks are lag-free before frame j's read them
    for j in range(bounds.size - 1):
        idx = order[bounds[j]:bounds[j + 1]]
        idx = idx[prev[idx] >= 0]
        if idx.size:
            out[idx] -= fraction * out[prev[idx]]
    out += dark
    return out


def lag_estimate(signal: np.ndarray, previous: np.ndarray) -> tuple[float, float]:
    """The lag fraction from pixels the active area has just left: their signal is a times the previous frame's.

    Parameters
    ----------
    signal : ndarray, shape (L, W)
        I_j - dark of pixels lit in frame j - 1 but not in frame j.
    previous : ndarray, shape (L, W)
        Their lag-free signal S_(j-1) in frame j - 1 (counts above dark).

    Returns
    -------
    a : float
        sum signal / sum previous (the maximum-likelihood ratio when the signal is Poisson around a S).
    se : float
        Its standard error from the scatter of the samples around a S (sandwich, whatever the gain
        and electronic noise); 0 when every sample is exactly a S (no noise at all).
    """
    total = float(np.sum(previous, dtype=np.float64))
    if total <= 0:
        return 0.0, np.inf
    a = float(np.sum(signal, dtype=np.float64)) / total
    se = float(np.sqrt(np.sum((signal - a * previous) ** 2, dtype=np.float64))) / total
    return a, se
