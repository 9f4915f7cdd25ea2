"""Statistics the diagnosis shares: tail probabilities, multiple-testing rules, and how a set of indices reads."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import stats


def chi2_tail(statistic: float, dof: int) -> tuple[float, float]:
    """The chi-square tail probability of ``statistic`` with ``dof`` degrees of freedom and its log (exact where
    the probability underflows); (1, 0) where dof <= 0, (0, -inf) for an infinite statistic."""
    if dof <= 0:
        return 1.0, 0.0
    if not np.isfinite(statistic):
        return 0.0, -np.inf
    return float(stats.chi2.sf(statistic, dof)), float(stats.chi2.logsf(statistic, dof))


def bonferroni(log_p: Sequence[float]) -> tuple[int, float]:
    """The index of the least p-value and its log multiplied by how many were looked at (at most 1)."""
    i = int(np.argmin(log_p))
    return i, min(float(log_p[i]) + float(np.log(len(log_p))), 0.0)


def holm(log_p: Sequence[float], alpha: float) -> list[bool]:
    """Holm's step-down verdicts at family-wise level ``alpha`` for tests with these log p-values."""
    order = sorted(range(len(log_p)), key=lambda i: log_p[i])
    out = [False] * len(log_p)
    for rank, i in enumerate(order):
        if not log_p[i] < np.log(alpha / (len(log_p) - rank)):
            break
        out[i] = True
    return out


def ranges(values: np.ndarray | Sequence[int], limit: int | None = None) -> str:
    """'3-7, 12, 40-60' for sorted integers; at most ``limit`` runs, then '...' ('' for none)."""
    idx = np.asarray(values, dtype=np.int64)
    if idx.size == 0:
        return ""
    breaks = np.flatnonzero(np.diff(idx) != 1)
    runs = [f"{a}" if a == b else f"{a}-{b}"
            for a, b in zip(np.r_[idx[0], idx[breaks + 1]], np.r_[idx[breaks], idx[-1]], strict=True)]
    cut = runs if limit is None else runs[:limit]
    return ", ".join(cut) + (", ..." if len(cut) < len(runs) else "")


def frames_where(share: np.ndarray, n_frames: int) -> str:
    """Where a per-frame statistic sits: the fewest frames that carry half of it (``share``, shape (J,))."""
    share = np.clip(share, 0, None)
    if share.sum() <= 0:
        return "no frame in particular"
    order = np.argsort(share)[::-1]
    top = np.sort(order[: max(1, int(np.searchsorted(np.cumsum(share[order]) / share.sum(), 0.5)) + 1)])
    spread = "all frames" if top.size > 0.3 * n_frames else "few frames"
    return f"{spread}; half of the statistic in {top.size} frames, {top.min()}-{top.max()}"


def one_way_anova(y: np.ndarray, w: np.ndarray, group: np.ndarray, n_groups: int
                  ) -> tuple[float, int, int, float, np.ndarray, float]:
    """Weighted one-way analysis of variance of ``y`` (N,) with weights ``w`` (N,) in groups 0..n_groups-1.

    Returns
    -------
    F : float
        Between-group over within-group mean square (the dispersion is the data's own).
    dof_between, dof_within : int
    log_p : float
        log of the F tail probability.
    means : ndarray, shape (n_groups,)
        Weighted group means.
    pooled : float
        Weighted mean of all.
    """
    W = np.bincount(group, weights=w, minlength=n_groups)
    means = np.bincount(group, weights=w * y, minlength=n_groups) / W
    pooled = float(np.sum(w * y) / np.sum(w))
    d1, d2 = n_groups - 1, max(y.size - n_groups, 1)
    between = float(np.sum(W * (means - pooled) ** 2)) / d1
    within = float(np.sum(w * (y - means[group]) ** 2)) / d2
    F = between / within if within > 0 else 0.0
    return F, d1, d2, float(stats.f.logsf(F, d1, d2)), means, pooled
