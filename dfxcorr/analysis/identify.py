"""Which effects can an acquisition determine? Counting information-free directions of the Fisher matrix.

An effect is identifiable when adding it to a model adds no direction of its parameters that the data
cannot see, beyond its exact gauge (a shift or scale that the images take up, paper eq. 22). Such
directions are the null space of the Fisher information with the images profiled out
(:func:`dfxcorr.model.fisher_matrix`). Examples: per-frame visibility loss in a phase-stepping
recording (paper Sec. II-F, eqs. 42-47: four extra null directions); per-step dose in a stepping
series whose every pixel is modulated (the per-step vector d_j (1, cos psi_j, sin psi_j) lies on a
cone whose Lorentz boosts the images absorb: two extra); an additive background when the flat field
does not vary (absorbed by the transmission image).

The policy built on it (:func:`resolve_effects`) decides which configured effects a reconstruction
fits: those the acquisition determines; the others are dropped with a log line, or refused with an
:class:`IdentifiabilityError` where the configuration asks for them explicitly.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from .. import config as C
from .. import kernels as K
from .. import model as M
from ..errors import DfxcorrError
from ..fit import initial_weights, spread_columns
from ..io import Scan

log = logging.getLogger("dfxcorr")

#: Exact gauge directions an effect brings (its per-frame parameters' common shift or scale).
GAUGE_DIMENSIONS = {"phase_offset": 1, "tilt": 1, "curvature": 1, "visibility_loss": 1, "dose": 1,
                    # v1_j, v2_j proportional to v0_j: a factor (1 + a x + b x^2) that the dark-field image takes up
                    "visibility_tilt": 2}


@dataclass
class Identifiability:
    """Verdict for one effect added to a base model.

    Attributes
    ----------
    name : str
    identifiable : bool
    excess : int
        Information-free directions added beyond the effect's gauge.
    """

    name: str
    identifiable: bool
    excess: int


@dataclass
class Information:
    """Profiled Fisher information of a set of effects, arranged to condition one effect on others.

    Attributes
    ----------
    matrix : ndarray, shape (P, P)
        :func:`dfxcorr.model.fisher_matrix` with the images profiled out.
    plain : ndarray, shape (P,)
        Its diagonal at known images: what each component would carry on its own.
    owner : ndarray of str, shape (P,)
        Effect of each entry.
    frame : ndarray of int, shape (P,)
        Frame of each entry (-1 for global effects).
    component : ndarray of int, shape (P,)
        Parameter component of each entry.
    live : ndarray of bool, shape (P,)
        False for entries of frames without usable samples (they say nothing).
    """

    matrix: np.ndarray
    plain: np.ndarray
    owner: np.ndarray
    frame: np.ndarray
    component: np.ndarray
    live: np.ndarray
    _inverses: dict = field(default_factory=dict, repr=False)

    def mask(self, names) -> np.ndarray:
        return self.live & np.isin(self.owner, list(names))

    def base_inverse(self, base) -> np.ndarray:
        """Pseudo-inverse of the information of the ``base`` effects (cached: every candidate needs it)."""
        key = tuple(base)
        if key not in self._inverses:
            m = self.mask(base)
            self._inverses[key] = pinv_rank(self.matrix[np.ix_(m, m)])[0]
        return self._inverses[key]


def information(obs: M.Observations, dsg: M.Design, images: M.Images, weights: np.ndarray, names) -> Information:
    """Fisher information of ``names`` at the given design and images (``images.inverse`` needed).

    From the compiled kernel (:func:`dfxcorr.kernels.fisher`, held to :func:`dfxcorr.model.fisher_matrix`
    by the tests): the plain information and the profiled correction in one pass.
    """
    K.set_threads()
    plain_matrix, corr = K.fisher(obs, dsg.channels, weights, images.coef, images.inverse,
                                  M.component_table(names)[:3])
    info, index = plain_matrix - corr, M.fisher_index(names, obs.n_frames)
    plain = np.diag(plain_matrix)
    used = np.bincount(obs.frame, weights=obs.use.sum(axis=1), minlength=obs.n_frames) > 0
    return Information(matrix=info, plain=plain, owner=np.array([n for n, _, _ in index]),
                       frame=np.array([j for _, j, _ in index]), component=np.array([m for _, _, m in index]),
                       live=np.array([j < 0 or used[j] for _, j, _ in index], dtype=bool))


def pinv_rank(a: np.ndarray, reference: np.ndarray | None = None, tol: float = 1e-9) -> tuple[np.ndarray, int]:
    """Pseudo-inverse and rank of a symmetric positive semi-definite matrix, scaled to unit diagonal first.

    The tolerance is relative to the largest eigenvalue. A component whose diagonal entry is below
    ``tol`` times its ``reference`` (its information before profiling; default the largest diagonal
    entry) counts as empty: what is left of it is rounding.
    """
    if a.size == 0:
        return a, 0
    d = np.diag(a)
    ref = np.full_like(d, max(np.abs(d).max(), 1e-300)) if reference is None else reference
    live = d > tol * ref
    out = np.zeros_like(a)
    if not np.any(live):
        return out, 0
    s = np.sqrt(d[live])
    w, v = np.linalg.eigh(a[np.ix_(live, live)] / np.outer(s, s))
    keep = w > tol * w.max()
    out[np.ix_(live, live)] = ((v[:, keep] / w[keep]) @ v[:, keep].T) / np.outer(s, s)
    return out, int(keep.sum())


@dataclass
class Conditional:
    """One effect's information given the others (Schur complement) and what it needs for a score test."""

    sel: np.ndarray
    base: np.ndarray
    projector: np.ndarray
    inverse: np.ndarray
    dof: int
    verdict: Identifiability


def conditional(inf: Information, name: str, base) -> Conditional:
    """The information of ``name``'s parameters once those of ``base`` are estimated too.

    For a positive semi-definite matrix the null space of [base, candidate] is that of the base plus
    that of the candidate's Schur complement, so what the candidate adds beyond its gauge and carries
    no information shows as a rank deficit of the Schur complement.
    """
    sel, bmask = inf.mask([name]), inf.mask(base)
    projector = inf.matrix[np.ix_(sel, bmask)] @ inf.base_inverse(base)
    schur = inf.matrix[np.ix_(sel, sel)] - projector @ inf.matrix[np.ix_(bmask, sel)]
    inverse, dof = pinv_rank(schur, inf.plain[sel])
    excess = int(sel.sum()) - dof - GAUGE_DIMENSIONS.get(name, 0)
    return Conditional(sel, bmask, projector, inverse, dof, Identifiability(name, excess <= 0 and dof > 0,
                                                                          max(excess, 0)))


def select(obs: M.Observations, weights: np.ndarray, names, *, max_columns: int = 64) -> list[Identifiability]:
    """Judge effects in turn, each given the identifiable ones before it, at their neutral values.

    Identifiability is structural, so at most ``max_columns`` evenly spread columns are used.
    """
    names = [n for n in names if M.effect(n).channel is not None]
    if not names:
        return []
    obs, weights = spread_columns(obs, weights, most=max_columns)
    params = M.neutral_params(names, obs.n_frames)
    dsg = M.design(obs, params)
    inf = information(obs, dsg, M.solve_images(obs, dsg, weights, keep_inverse=True), weights, names)
    chosen: list[str] = []
    out = []
    for name in names:
        verdict = conditional(inf, name, chosen).verdict
        out.append(verdict)
        if verdict.identifiable:
            chosen.append(name)
    return out


# --------------------------------------------------------------------------------------------------
# The policy: which configured effects a reconstruction fits
# --------------------------------------------------------------------------------------------------


class IdentifiabilityError(DfxcorrError, ValueError):
    """An effect was asked for that the acquisition cannot determine."""


def separable_flat_field(reference, *, tol: float = 1e-3) -> bool:
    """True if the flat field cannot tell per-frame visibility loss from the images (paper eq. 48).

    That is the case when t^f and v^f do not change along the scan direction and the flat-field phase is
    f(column) + a * row with one slope a for all columns.
    """
    A = reference.transmission.shape[0]
    if A < 2:
        return True
    phase = np.unwrap(reference.phase, axis=0)
    u = np.arange(A) - (A - 1) / 2
    slope = np.sum(u[:, None] * (phase - phase.mean(axis=0))) / (np.sum(u ** 2) * phase.shape[1])
    resid = phase - phase.mean(axis=0) - slope * u[:, None]
    flat = [np.std(m, axis=0).max() / np.abs(m).mean() for m in (reference.transmission, reference.visibility)]
    return bool(np.sqrt(np.mean(resid ** 2)) < tol and max(flat) < tol)


def visibility_unidentifiable(scan: Scan, reference) -> str | None:
    """Why per-frame visibility loss cannot be told apart from the images here, or None (paper Sec. II-F)."""
    if scan.is_stepping:
        why = ("in a phase-stepping recording the flat field is the same in every frame, so a per-frame "
               "visibility loss trades off exactly against the transmission and dark-field images (paper Sec. II-F)")
    elif separable_flat_field(reference):
        why = ("the flat-field phase of this scan is separable (paper eq. 48) and t^f, v^f do not vary along the "
               "scan, so per-frame visibility loss cannot be told apart from the images")
    else:
        why = None
    return why


def refuse_if_asked(cfg: dict, name: str, why: str) -> None:
    """Refuse an effect the acquisition cannot determine if the configuration asks for it explicitly.

    Raises
    ------
    IdentifiabilityError
        If ``vibration.<key of name>`` is true (not auto).
    """
    key = {e: k for k, e in C.VIBRATION_EFFECTS.items()}[name]
    if cfg["vibration"][key] is True:
        raise IdentifiabilityError(f"{name} is not identifiable here: {why}; set vibration.{key}=false"
                                   + (" (or auto)" if name == "visibility_loss" else ""))


def drop_visibility(cfg: dict, effects, why: str | None) -> tuple[list[str], dict[str, str]]:
    """The effects without the visibility ones where ``why`` (paper Sec. II-F) says they cannot be determined.

    Returns
    -------
    kept : list of str
    dropped : dict
        Effect -> reason.

    Raises
    ------
    IdentifiabilityError
        If the configuration explicitly asks for a visibility effect that ``why`` rules out.
    """
    kept, dropped = [], {}
    for name in effects:
        if why and name in ("visibility_loss", "visibility_tilt"):
            refuse_if_asked(cfg, name, why)
            dropped[name] = why
        else:
            kept.append(name)
    return kept, dropped


def resolve_effects(cfg: dict, scan: Scan, reference, fit_obs: M.Observations) -> tuple[str, ...]:
    """The effects to fit: the configured ones that this acquisition can determine.

    Every enabled effect is checked in turn against the Fisher information of the fit's samples
    (:mod:`dfxcorr.analysis.identify`); visibility effects in a stepping recording or over a separable flat
    field are refused with the paper's reason. An effect set to ``auto`` is dropped with a log line.

    Raises
    ------
    IdentifiabilityError
        If the configuration explicitly asks for an effect the acquisition cannot determine.
    """
    def refuse_or_drop(name, why):
        refuse_if_asked(cfg, name, why)
        log.info("%s is not fitted: %s", name, why)

    names, dropped = drop_visibility(cfg, C.effects_of(cfg), visibility_unidentifiable(scan, reference))
    for name, why in dropped.items():
        log.info("%s is not fitted: %s", name, why)
    chosen: list[str] = []
    for verdict in select(fit_obs, initial_weights(fit_obs, {}), names):
        if verdict.identifiable:
            chosen.append(verdict.name)
        else:
            refuse_or_drop(verdict.name, f"the Fisher information of this acquisition has {verdict.excess} "
                                         f"direction(s) of its parameters without information beyond its gauge "
                                         f"(they trade off exactly against the images"
                                         f"{' or ' + ', '.join(chosen) if chosen else ''})")
    return tuple(chosen)
