"""Which effects can an acquisition determine? Counting information-free directions of the Fisher matrix.

An effect is identifiable when adding it to a model adds no direction of its parameters that the data
cannot see, beyond its exact gauge (a shift or scale that the images take up, paper eq. 22). Such
directions are the null space of the Fisher information with the images profiled out
(:func:`dfxcorr.model.fisher_matrix`). Examples: per-frame visibility loss in a phase-stepping
recording (paper Sec. II-F, eqs. 42-47: four extra null directions); per-step dose in a stepping
series whose every pixel is modulated (the per-step vector d_j (1, cos psi_j, sin psi_j) lies on a
cone whose Lorentz boosts the images absorb: two extra); an additive background when the flat field
does not vary (absorbed by the transmission image).

The policy built on it (:func:`dfxcorr.planning.resolve_effects`) decides which configured effects a
reconstruction fits.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import engine as E
from . import kernels as K
from . import model as M
from .catalogue import effect, neutral_params
from .fit import initial_weights
from .observations import Observations
from .subsets import spread_columns


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


def information(obs: Observations, ch: M.Channels, images: M.Images, weights: np.ndarray, names) -> Information:
    """Fisher information of ``names`` at the given channel values and images (``images.inverse`` needed).

    From the compiled kernel (:func:`dfxcorr.fisher_pixels.fisher`, held to :func:`dfxcorr.model.fisher_matrix`
    by the tests): the plain information and the profiled correction in one pass.
    """
    K.set_threads()
    plain_matrix, corr = E.fisher(obs, ch, weights, images.coef, images.inverse, names)
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


def conditional(inf: Information, name: str | tuple[str, ...], base) -> Conditional:
    """The information of the parameters of ``name`` (an effect, or several together) once those of ``base`` are
    estimated too.

    For a positive semi-definite matrix the null space of [base, candidate] is that of the base plus
    that of the candidate's Schur complement, so what the candidate adds beyond its gauge and carries
    no information shows as a rank deficit of the Schur complement.
    """
    names = (name,) if isinstance(name, str) else tuple(name)
    sel, bmask = inf.mask(names), inf.mask(base)
    projector = inf.matrix[np.ix_(sel, bmask)] @ inf.base_inverse(base)
    schur = inf.matrix[np.ix_(sel, sel)] - projector @ inf.matrix[np.ix_(bmask, sel)]
    inverse, dof = pinv_rank(schur, inf.plain[sel])
    excess = int(sel.sum()) - dof - sum(effect(n).gauge_dims for n in names)
    return Conditional(sel, bmask, projector, inverse, dof, Identifiability("+".join(names), excess <= 0 and dof > 0,
                                                                          max(excess, 0)))


def select(obs: Observations, names, *, max_columns: int = 64) -> list[Identifiability]:
    """Judge effects in turn, each given the identifiable ones before it, at their neutral values.

    Identifiability is structural, so at most ``max_columns`` evenly spread columns are used. The images
    come from the compiled retrieval (:func:`dfxcorr.kernels.retrieve`) with the noise weights of the model without
    per-frame effects (:func:`dfxcorr.fit.initial_weights`), made for those columns only.
    """
    names = list(names)
    if not names:
        return []
    obs = spread_columns(obs, most=max_columns)
    weights = initial_weights(obs, {})
    ch = M.channels(neutral_params(names, obs.n_frames), x=obs.x, n_frames=obs.n_frames)
    K.set_threads()
    solved = E.retrieve(obs, ch, weights=weights, keep_inverse=True)
    inf = information(obs, ch, M.Images(solved["coef"], solved["valid"], solved["inverse"]), weights, names)
    chosen: list[str] = []
    out = []
    for name in names:
        verdict = conditional(inf, name, chosen).verdict
        out.append(verdict)
        if verdict.identifiable:
            chosen.append(name)
    return out
