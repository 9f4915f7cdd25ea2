"""The forward model: paper eq. 19 extended by the effect catalogue of ``spec/diagnosis.md``.

"The paper" throughout this package is "Correction for mechanical inaccuracies in a scanning Talbot-Lau
interferometer", the text the project was built from (its equation and section numbers are cited here; that
text names no authors, journal or DOI, so none are given).

This module is the only definition of the expected count and its derivatives; the effects it is
made of are the entries of :mod:`dfxcorr.catalogue`, the data it is evaluated on are
:class:`dfxcorr.observations.Observations`, and the noise model is :mod:`dfxcorr.noise`. The
simulator, the baselines and the diagnosis call it. The fit and the retrieval run the compiled
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
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from . import fisher_pixels, kernels
from .banded import profiled_correction, solve_read_between
from .catalogue import effect
from .observations import Observations

__all__ = ["Channels", "channels", "channel_adjoint", "component_table", "fisher_index", "Design", "design",
           "design_channels", "channel_fields", "background_basis", "harmonic_factors",
           "image_columns", "Images", "solve_pixels", "solve_images", "harmonic_term", "expected", "circular_mean",
           "sample_derivatives", "reduce_component", "gradient", "leverage", "frame_leverage", "fisher_matrix"]

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
    rows : dict
        (channel id, m) -> ndarray (J, C): the coefficients of y^m (m >= 1, y the detector-row coordinate of
        :attr:`Observations.y <dfxcorr.observations.Observations.y>`) of the phase and visibility channels, whose
        value at a sample of frame j, column c and row coordinate y is phase[j, c] + sum_m rows[(PHASE, m)][j, c]
        y^m (:meth:`phase_at`). Empty where every term is a function of the frame and x alone (what the compiled
        kernels take); for channel gradients, the gradients of these coefficients.
    """

    phase: np.ndarray
    vis: np.ndarray
    dose: np.ndarray
    background: np.ndarray
    harmonic: np.ndarray
    rows: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)

    def phase_at(self, obs: Observations, blocks: np.ndarray | slice = slice(None)) -> np.ndarray:
        """Φ (rad) at every sample of ``blocks`` (indices or a slice of ``obs``'s K blocks, K' of them), shape
        (K', C)."""
        return self._at(kernels.PHASE, self.phase, obs, blocks)

    def phase_quadratures(self, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
        """cos Φ and sin Φ at every sample, each (K, C): made on the (frame, column) grid and read per sample where Φ
        has no term in the detector row."""
        if any(c == kernels.PHASE for c, _ in self.rows):
            phase = self.phase_at(obs)
            return np.cos(phase), np.sin(phase)
        return np.cos(self.phase)[obs.frame], np.sin(self.phase)[obs.frame]

    def vis_at(self, obs: Observations, blocks: np.ndarray | slice = slice(None)) -> np.ndarray:
        """V at every sample of ``blocks`` (as :meth:`phase_at`), shape (K', C)."""
        return self._at(kernels.VISIBILITY, self.vis, obs, blocks)

    def _at(self, cid: int, base: np.ndarray, obs: Observations, blocks: np.ndarray | slice) -> np.ndarray:
        frame, y = obs.frame[blocks], obs.y[blocks]
        out = base[frame]
        for (c, m), coef in self.rows.items():
            if c == cid:
                out = out + coef[frame] * y[:, None] ** m
        return out


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
        their parameters. Components with a power of y go to the coefficients of that power
        (:attr:`Channels.rows`). Every channel is linear in the parameters.
    """
    C = x.size
    out = Channels(np.zeros((n_frames, C)), np.ones((n_frames, C)), np.ones(n_frames), np.zeros(3), np.zeros(2))
    for name, p in params.items():
        e = effect(name)
        cid = _channel_id(name)
        if cid in (kernels.PHASE, kernels.VISIBILITY):
            for q, (k, m) in enumerate(zip(e.powers, e.row_powers, strict=True)):
                term = p[:, q, None] * x[None, :] ** k
                if m:
                    out.rows[(cid, m)] = out.rows.get((cid, m), 0.0) + term
                elif cid == kernels.PHASE:
                    out.phase = out.phase + term
                else:
                    out.vis = out.vis + term
            if cid == kernels.VISIBILITY:
                out.vis = out.vis - e.neutral
        elif cid == kernels.DOSE:
            out.dose = out.dose + p[:, 0] - e.neutral
        elif cid == kernels.BACKGROUND:
            out.background = out.background + p
        else:
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
        d(cost)/d(channel value) for every channel value (and coefficient of a power of y).
    x : ndarray, shape (C,)
    square : bool
        ``grad`` holds Gauss-Newton sums sum w F^2 per channel value: apply the squared Jacobian,
        giving the diagonal of the information of the parameters.

    Returns
    -------
    dict
        name -> array shaped like that effect's parameters, e.g. dcost/dp_{j,k} = sum_c gΦ[j, c] x_c^k (for a
        component x^k y^m, the gradient of the coefficient of y^m in place of gΦ).
    """
    power = 2 if square else 1
    out = {}
    for name in names:
        e = effect(name)
        cid = _channel_id(name)
        if cid in (kernels.PHASE, kernels.VISIBILITY):
            g = grad.phase if cid == kernels.PHASE else grad.vis
            out[name] = np.stack([(grad.rows[(cid, m)] if m else g) @ x ** (power * k)
                                  for k, m in zip(e.powers, e.row_powers, strict=True)], axis=-1)
        elif cid == kernels.DOSE:
            out[name] = np.asarray(grad.dose, dtype=np.float64)[:, None].copy()
        elif cid == kernels.BACKGROUND:
            out[name] = np.asarray(grad.background, dtype=np.float64).copy()
        else:
            out[name] = np.asarray(grad.harmonic, dtype=np.float64).copy()
    return out


def component_table(names: Sequence[str]) -> tuple[np.ndarray, np.ndarray, int, list[tuple[str, int]]]:
    """The parameter components of ``names`` as the Fisher kernel reads them.

    Returns
    -------
    channel : ndarray of int, shape (Q,)
        :data:`dfxcorr.kernels.CHANNEL_IDS` of each component, per-frame components first.
    power : ndarray of int, shape (Q,)
        Power of x (per-frame components; a power of y is not in the table: the compiled kernels take no such
        component, :func:`dfxcorr.engine.compiled`) or index into the effect's basis (global ones).
    n_per_frame : int
    components : list of (name, component)
    """
    order = [n for n in names if effect(n).per_frame] + [n for n in names if not effect(n).per_frame]
    comps = [(n, m) for n in order for m in range(effect(n).size)]
    channel = np.array([_channel_id(n) for n, _ in comps], dtype=np.int64)
    power = np.array([effect(n).powers[m] if effect(n).per_frame else m for n, m in comps], dtype=np.int64)
    return channel, power, sum(effect(n).size for n in names if effect(n).per_frame), comps


def _channel_id(name: str) -> int:
    """:data:`dfxcorr.kernels.CHANNEL_IDS` of an effect of the model's catalogue."""
    channel = effect(name).channel
    if channel is None:
        raise ValueError(f"effect {name!r} does not enter the expected count")
    return kernels.CHANNEL_IDS[channel]


def fisher_index(names: Sequence[str], n_frames: int) -> list[tuple[str, int, int]]:
    """(name, frame, component) of each axis entry of the Fisher matrix; frame is -1 for global effects."""
    _, _, n_per_frame, comps = component_table(names)
    return ([(n, j, m) for j in range(n_frames) for n, m in comps[:n_per_frame]]
            + [(n, -1, m) for n, m in comps[n_per_frame:]])


@dataclass
class Design:
    """Per-sample coefficients of the per-pixel model Ibar = t A + c Bc + s Bs + Hc e - Hs f + offset.

    e = (c^2 - s^2) / m, f = 2 c s / m (:func:`harmonic_factors`). All arrays have shape (K, C)
    (``dose`` (K, 1)); ``Fc``, ``Fs`` are the flat field's fringe at theta, the fringe phase without the sample
    (:func:`fringe_phase`), t^f v^f cos theta and t^f v^f sin theta; ``Hc``, ``Hs`` are zero without the harmonic.
    ``channels`` holds the channel values they were made from.
    """

    A: np.ndarray
    Bc: np.ndarray
    Bs: np.ndarray
    Hc: np.ndarray
    Hs: np.ndarray
    offset: np.ndarray
    Fc: np.ndarray
    Fs: np.ndarray
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
    return design_channels(obs, channels(params, x=obs.x, n_frames=obs.n_frames))


def design_channels(obs: Observations, ch: Channels) -> Design:
    """:func:`design` from channel values (:func:`channels`) rather than effect parameters."""
    dose = ch.dose[obs.frame][:, None]
    vis = ch.vis_at(obs)
    # (K, C) temporaries only where needed: a stepping scan's design of every sample at once is 31 MB each
    offset = (sum(ch.background[m] * b for m, b in enumerate(background_basis(obs))) + obs.dark
              if np.any(ch.background) else obs.dark.astype(np.float64))
    hc, hs = float(ch.harmonic[0]), float(ch.harmonic[1])
    # the fringe at theta by the angle sum from the flat field's quadratures and Φ's (on the (frame, column) grid):
    # no trigonometry per sample, as in the compiled kernels
    fc, fs = obs.fringe
    cp, sp = ch.phase_quadratures(obs)
    Fc, Fs = fc * cp - fs * sp, fs * cp + fc * sp
    amp = dose * obs.tf
    Hc = Hs = np.zeros(Fc.shape)
    Hc.setflags(write=False)  # one array for both
    if hc or hs:
        F2c, F2s = second_harmonic(Fc, Fs)
        Hc, Hs = dose * vis * (hc * F2c - hs * F2s), dose * vis * (hc * F2s + hs * F2c)
    return Design(A=amp, Bc=dose * vis * Fc, Bs=-dose * vis * Fs, Hc=Hc, Hs=Hs, offset=offset, Fc=Fc, Fs=Fs,
                  dose=dose, vis=vis, harmonic=(hc, hs), channels=ch)


def second_harmonic(Fc: np.ndarray, Fs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """t^f v^f cos 2 theta and t^f v^f sin 2 theta from the fringe's quadratures t^f v^f (cos theta, sin theta)
    (counts, each (K, C)): (Fc + i Fs)^2 / |Fc + i Fs|, 0 without fringe."""
    m = np.hypot(Fc, Fs)
    inv = np.divide(1.0, m, out=np.zeros_like(m), where=m > 0)
    return (Fc * Fc - Fs * Fs) * inv, 2.0 * Fc * Fs * inv


def fringe_phase(obs: Observations, ch: Channels) -> np.ndarray:
    """theta = phi^f + Φ, the phase of the fringe each sample sees (rad), shape (K, C); phi^f is derived from the
    fringe's quadratures (:attr:`Observations.phif`), without meaning where a sample carries no fringe."""
    return obs.phif + ch.phase_at(obs)


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
        Inverse normal matrix per pixel (for leverages and Fisher information): where the samples read between rows
        (:class:`dfxcorr.observations.Reading`), the pixel's diagonal block of the column's inverse.
    coupling : ndarray, shape (R, C, 3, 3) or None
        Where the samples read between rows: the block of the inverse between each row and the next.
    """

    coef: np.ndarray
    valid: np.ndarray
    inverse: np.ndarray | None = None
    coupling: np.ndarray | None = None

    @property
    def t(self) -> np.ndarray:
        return self.coef[..., 0]

    def subset(self, columns: np.ndarray) -> Images:
        """The images of some of the held columns (positions, as :meth:`Observations.subset` takes them)."""
        return Images(self.coef[:, columns], self.valid[:, columns],
                      None if self.inverse is None else self.inverse[:, columns],
                      None if self.coupling is None else self.coupling[:, columns])

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
    if obs.reading is not None:
        coef, valid, inverse, _ = solve_read_between(obs, columns, target, weights, keep_inverse=keep_inverse)
        return coef, valid, inverse
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
    valid = (n_used >= present.sum(axis=-1)) & present[..., 0] & (np.abs(np.linalg.det(Ns)) > kernels.SINGULAR)
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
    coupling = None
    for step in range(steps):
        # the first solve leaves the harmonic out: its columns need no images
        at = obs.gather(coef) if step else coef[:0]
        Xc, Xs = image_columns(dsg, at[..., 1], at[..., 2]) if step else (dsg.Bc, dsg.Bs)
        if phase is None and obs.reading is not None:
            coef, valid, inv, coupling = solve_read_between(obs, [dsg.A, Xc, Xs], target, weights,
                                                            keep_inverse=keep_inverse)
            continue
        if phase is None:
            coef, valid, inv = solve_pixels(obs, [dsg.A, Xc, Xs], target, weights, keep_inverse=keep_inverse)
            continue
        cp, sp = np.cos(phase), np.sin(phase)
        coef2, valid, _ = solve_pixels(obs, [dsg.A, Xc * cp + Xs * sp], target, weights)
        coef, inv = np.stack([coef2[..., 0], coef2[..., 1] * cp, coef2[..., 1] * sp], axis=-1), None
    return Images(coef, valid, inv, coupling)


def harmonic_term(obs: Observations, dsg: Design, images: Images, *, at: np.ndarray | None = None) -> np.ndarray:
    """The second harmonic's share of the expected counts, Hc e - Hs f, shape (K, C) (``at``: the images at every
    sample, where the caller has them)."""
    c = obs.gather(images.coef) if at is None else at
    _, _, e, f = harmonic_factors(c[..., 1], c[..., 2])
    return dsg.Hc * e - dsg.Hs * f


def expected(obs: Observations, dsg: Design, images: Images, *, at: np.ndarray | None = None) -> np.ndarray:
    """Expected counts Ibar, shape (K, C) (``at``: the images at every sample, where the caller has them)."""
    c = obs.gather(images.coef) if at is None else at
    linear = c[..., 0] * dsg.A + c[..., 1] * dsg.Bc + c[..., 2] * dsg.Bs + dsg.offset
    return linear + harmonic_term(obs, dsg, images, at=c) if any(dsg.harmonic) else linear


def expected_by_columns(obs: Observations, params: dict, images: Images, *, samples: float = 1e6
                        ) -> Iterator[tuple[np.ndarray, Observations, Images, Design, np.ndarray]]:
    """The expected counts of ``obs`` at ``params`` and ``images``, a run of about ``samples`` samples' columns at a
    time (:meth:`Observations.column_chunks`; views of the samples, for numpy work): each run's column positions,
    samples, images, design and expected counts (K, c). Per-pixel work over many columns holds one run's
    temporaries."""
    for cols in obs.column_chunks(samples):
        sub, im = obs.subset(cols, copy=False), images.subset(cols)
        dsg = design(sub, params)
        yield cols, sub, im, dsg, expected(sub, dsg, im)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped to [-pi, pi), same shape: less the whole turns (the complex exp and angle cost a per-sample
    pass of the residual signatures several times over, numpy's float modulo three times the floor)."""
    t = np.asarray(a) + np.pi
    return t - (2 * np.pi) * np.floor(t / (2 * np.pi)) - np.pi


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
    fields = channel_fields(obs, dsg, images, _channel_id(name))
    if e.channel in ("phase", "visibility"):
        return [fields[0] * obs.x[None, :] ** k_ * obs.y[:, None] ** m for k_, m in zip(e.powers, e.row_powers,
                                                                                          strict=True)]
    return fields


def channel_fields(obs: Observations, dsg: Design, images: Images, cid: int, *, at: np.ndarray | None = None
                   ) -> list[np.ndarray]:
    """dIbar/d(channel value) at every sample, each (K, C): [dIbar/dΦ], [dIbar/dV], [dIbar/dD], the three
    background basis fields, or the two of the harmonic (hc, hs); the channel ``cid`` of
    :data:`dfxcorr.kernels.CHANNEL_IDS`. :func:`sample_derivatives` multiplies them by the powers of x and y.
    ``at``: the images at every sample (``obs.gather(images.coef)``), where the caller has them."""
    c = obs.gather(images.coef) if at is None else at
    t, cc, ss = c[..., 0], c[..., 1], c[..., 2]
    hc, hs = dsg.harmonic
    # t^f v^f times (G, Kh) m (cos, sin)(2 psi), psi = theta + phi, and (P2, Q2) a2 m (cos, sin)(2 psi + beta)
    ef: np.ndarray | float
    ff: np.ndarray | float
    G: np.ndarray | float
    Kh: np.ndarray | float
    P2: np.ndarray | float
    Q2: np.ndarray | float
    ef = ff = G = Kh = P2 = Q2 = 0.0
    # the harmonic's own derivatives need its factors even where it is absent (hc = hs = 0: a score test)
    if hc or hs or cid == kernels.HARMONIC:
        _, _, ef, ff = harmonic_factors(cc, ss)
        F2c, F2s = second_harmonic(dsg.Fc, dsg.Fs)
        G, Kh = F2c * ef - F2s * ff, F2s * ef + F2c * ff
        P2, Q2 = hc * G - hs * Kh, hc * Kh + hs * G
    if cid == kernels.PHASE:
        return [cc * dsg.Bs - ss * dsg.Bc - 2 * dsg.dose * dsg.vis * Q2]
    if cid == kernels.VISIBILITY:
        # t^f v^f D (c cos theta - s sin theta + the harmonic's part)
        return [dsg.dose * (cc * dsg.Fc - ss * dsg.Fs + P2)]
    if cid == kernels.DOSE:
        return [(t * dsg.A + cc * dsg.Bc + ss * dsg.Bs + (dsg.Hc * ef - dsg.Hs * ff)) / dsg.dose]
    if cid == kernels.BACKGROUND:
        return background_basis(obs)
    bv = dsg.dose * dsg.vis
    return [bv * G, -bv * Kh]


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
    c = obs.gather(images.coef)
    X = np.stack([dsg.A, *image_columns(dsg, c[..., 1], c[..., 2])], axis=-1)
    if obs.reading is None:
        return weights * np.einsum("kca,kcab,kcb->kc", X, images.inverse[obs.pixel], X)
    if images.coupling is None:
        raise ValueError("leverage of samples read between rows needs the inverse's coupling blocks")
    # the sample's design on both rows it reads: (1 - f) x on row lo, f x on row lo + 1
    lo, hi, f = obs.read_rows()
    a, b = (1.0 - f[:, None, None]) * X, f[:, None, None] * X
    return weights * (np.einsum("kca,kcab,kcb->kc", a, images.inverse[lo], a)
                      + 2 * np.einsum("kca,kcab,kcb->kc", a, images.coupling[lo], b)
                      + np.einsum("kca,kcab,kcb->kc", b, images.inverse[hi], b))


def frame_leverage(obs: Observations, dsg: Design, images: Images, weights: np.ndarray, names: Iterable[str]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leverage of each sample in the fit of the per-frame parameters of ``names``, at fixed images.

    The share of a sample's residual variance that the per-frame parameters take (per frame,
    w d^T I_j^+ d with I_j the frame's information); with :func:`leverage` (the images') it is what a fit
    removes of each sample's noise.

    Returns
    -------
    h : ndarray, shape (K, C)
    info_inv : ndarray, shape (J, P, P)
        Pseudo-inverse of each frame's information of its P per-frame parameter components.
    scaled : ndarray, shape (K, C, P)
        The derivatives times sqrt(weights).
    """
    D = [d for n in names if effect(n).per_frame for d in sample_derivatives(obs, dsg, images, n)]
    info_inv = np.zeros((obs.n_frames, len(D), len(D)))
    if D:
        info = np.stack([np.stack([obs.frame_sum(np.sum(weights * Da * Db, axis=1)) for Db in D], -1)
                         for Da in D], -2)
        info_inv = np.linalg.pinv(info, rcond=1e-10, hermitian=True)
    scaled = np.stack(D, axis=-1) * np.sqrt(weights)[..., None] if D else np.zeros(weights.shape + (0,))
    return np.einsum("kca,kab,kcb->kc", scaled, info_inv[obs.frame], scaled), info_inv, scaled


def fisher_matrix(obs: Observations, dsg: Design, images: Images, weights: np.ndarray, names: Sequence[str],
                  *, profiled: bool = True) -> tuple[np.ndarray, list[tuple[str, int, int]]]:
    """Fisher information of all effect parameters, with the images profiled out: :func:`fisher_parts`'s plain
    information less its correction, and the meaning of each axis entry."""
    plain, corr, index = fisher_parts(obs, dsg, images, weights, names, profiled=profiled)
    return plain - corr, index


def fisher_parts(obs: Observations, dsg: Design, images: Images, weights: np.ndarray, names: Sequence[str],
                 *, profiled: bool = True) -> tuple[np.ndarray, np.ndarray, list[tuple[str, int, int]]]:
    """Fisher information of all effect parameters, with the images profiled out.

    The images are estimated from the same data, so the information of the effect parameters is
    the Schur complement sum_i D_i^T (W - W X (X^T W X)^-1 X^T W) D_i over pixels i, where D_i holds
    the derivatives of the pixel's samples with respect to the effect parameters and X_i its image
    design. Per-frame parameters of different frames are coupled through the pixels they share.
    The information at known images is computed here; the correction for the profiled images by
    :func:`dfxcorr.fisher_pixels.fisher` (a loop over pixels), or where the samples read between rows or a component
    holds a power of y by :func:`dfxcorr.banded.profiled_correction` (a solve per column).

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
    plain : ndarray, shape (P, P)
        The information at known images, for the log-likelihood -sum w r^2 / 2.
    correction : ndarray, shape (P, P)
        The share the profiled images take (zero without ``profiled``): the information is plain - correction.
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
        return info, np.zeros_like(info), index
    # the correction sum_i Y_i^T N_i^-1 Y_i (Y = X^T W D per pixel) couples the frames of each row
    if obs.reading is not None or any(r for n in names for r in effect(n).row_powers):
        where = ([obs.frame * Pf + q for q in range(Pf)] + [np.full(obs.frame.size, J * Pf + g) for g in range(Pg)])
        F = [F for *_, F in per_frame] + [F for *_, F in glob]
        at = obs.gather(images.coef)
        X = [dsg.A, *image_columns(dsg, at[..., 1], at[..., 2])]
        return info, profiled_correction(obs, X, weights, F, where, J * Pf + Pg), index
    kernels.set_threads()
    _, corr = fisher_pixels.fisher(obs, dsg.channels, weights, images.coef, images.inverse, component_table(names)[:3])
    return info, corr, index
