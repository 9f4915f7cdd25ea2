"""Which effects can an acquisition determine? Counting information-free directions of the Fisher matrix.

An effect is identifiable when adding it to a model adds no direction of its parameters that the data
cannot see, beyond its exact gauge (a shift or scale that the images take up, paper eq. 22). Such
directions are the null space of the Fisher information with the images profiled out
(:func:`dfxcorr.model.fisher_matrix`). Examples: per-frame visibility loss in a phase-stepping
recording (paper Sec. II-F, eqs. 42-47: four extra null directions); per-step dose in a stepping
series whose every pixel is modulated (the per-step vector d_j (1, cos psi_j, sin psi_j) lies on a
cone whose Lorentz boosts the images absorb: two extra); an additive background when the flat field
does not vary (absorbed by the transmission image).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import model as M

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


def null_dimension(info: np.ndarray, *, tol: float = 1e-9) -> int:
    """Number of directions without information: eigenvalues of the unit-diagonal matrix below ``tol``.

    Components with zero information on their own count once each.
    """
    d = np.diag(info)
    scale = np.abs(d).max() if d.size else 0.0
    live = d > 1e-12 * scale
    if not np.any(live):
        return int(d.size)
    s = np.sqrt(d[live])
    ev = np.linalg.eigvalsh(info[np.ix_(live, live)] / np.outer(s, s))
    return int((~live).sum() + (ev < tol).sum())


def _information(obs: M.Observations, params: dict, weights: np.ndarray, names) -> np.ndarray:
    dsg = M.design(obs, params)
    images = M.solve_images(obs, dsg, weights, keep_inverse=True)
    info, index = M.fisher_matrix(obs, dsg, images, weights, names)
    used = np.bincount(obs.frame, weights=obs.use.sum(axis=1), minlength=obs.n_frames) > 0
    keep = np.array([j < 0 or used[j] for _, j, _ in index], dtype=bool)  # frames without data say nothing
    return info[np.ix_(keep, keep)]


def check(obs: M.Observations, params: dict, weights: np.ndarray, base, candidates) -> list[Identifiability]:
    """Identifiability of each candidate effect added on its own to the base model.

    Parameters
    ----------
    obs : Observations
    params : dict
        Current parameters of at least the base and candidate effects (others at their neutral value).
    weights : ndarray, shape (K, C)
    base : sequence of str
        Effects already in the model.
    candidates : sequence of str
        Mean effects to judge (noise or mask effects are not judged here).

    Returns
    -------
    list of Identifiability
    """
    base = [n for n in base if M.effect(n).channel is not None]
    full = {**M.neutral_params(list(base) + list(candidates), obs.n_frames), **params}
    n_base = null_dimension(_information(obs, full, weights, base)) if base else 0
    out = []
    for name in candidates:
        names = base + [name]
        excess = null_dimension(_information(obs, full, weights, names)) - n_base - GAUGE_DIMENSIONS.get(name, 0)
        out.append(Identifiability(name, excess <= 0, max(excess, 0)))
    return out
