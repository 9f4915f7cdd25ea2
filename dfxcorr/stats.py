"""Statistics the diagnosis shares: tail probabilities, multiple-testing rules, and how a set of indices reads."""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy import special

#: Below this a tail probability is taken in log space (its float would lose digits, then underflow).
_TINY = 1e-280


def _continued_fraction(a_term: Callable[[int], float], b_term: Callable[[int], float]) -> float:
    """The value of b_0 + a_1 / (b_1 + a_2 / (b_2 + ...)) by the modified Lentz method, ``a_term(i)`` and
    ``b_term(i)`` its i-th terms; converged to 1e-15 relative (the tails below need at most a few hundred terms)."""
    tiny = 1e-300
    f = b_term(0) or tiny
    c, d = f, 0.0
    for i in range(1, 10_000):
        a, b = a_term(i), b_term(i)
        d = b + a * d
        d = 1.0 / (d or tiny)
        c = b + a / c
        c = c or tiny
        f *= c * d
        if abs(c * d - 1.0) < 1e-15:
            return f
    raise ArithmeticError("continued fraction did not converge")


def log_gamma_q(a: float, z: float) -> float:
    """log of the regularised upper incomplete gamma function Q(a, z), exact where Q underflows (z > a + 1 there:
    Legendre's continued fraction, Q = z^a e^-z / Gamma(a) / (z + 1 - a - 1 (1 - a) / (z + 3 - a - ...)))."""
    q = float(special.gammaincc(a, z))
    if q > _TINY:
        return float(np.log(q))
    cf = _continued_fraction(lambda i: -i * (i - a), lambda i: z + 2 * i + 1 - a)
    return a * np.log(z) - z - float(special.gammaln(a)) - float(np.log(cf))


def log_beta_i(a: float, b: float, x: float) -> float:
    """log of the regularised incomplete beta function I_x(a, b), exact where it underflows (x small there: its
    continued fraction, I = x^a (1 - x)^b / (a B(a, b)) / (1 + d_1 / (1 + d_2 / ...)))."""
    value = float(special.betainc(a, b, x))
    if value > _TINY:
        return float(np.log(value))

    def d(i: int) -> float:
        m = i // 2
        if i % 2:
            return -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))
        return m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m))

    cf = _continued_fraction(d, lambda i: 1.0)
    return a * np.log(x) + b * np.log1p(-x) - np.log(a) - float(special.betaln(a, b)) - float(np.log(cf))


def chi2_log_tails(statistic: np.ndarray | float, dof: np.ndarray | float) -> np.ndarray:
    """log P(chi-square with ``dof`` degrees of freedom > ``statistic``), elementwise over the two arrays
    (broadcast), exact where the probability underflows (:func:`log_gamma_q`)."""
    x, k = np.broadcast_arrays(np.asarray(statistic, dtype=float), np.asarray(dof, dtype=float))
    with np.errstate(divide="ignore"):
        out = np.log(special.gammaincc(k / 2, x / 2))
    for i in np.flatnonzero(np.isneginf(out) & np.isfinite(x) & (k > 0)):
        out.flat[i] = log_gamma_q(k.flat[i] / 2, x.flat[i] / 2)
    return out


def chi2_tail(statistic: float, dof: int) -> tuple[float, float]:
    """The chi-square tail probability of ``statistic`` with ``dof`` degrees of freedom and its log (exact where
    the probability underflows); (1, 0) where dof <= 0, (0, -inf) for an infinite statistic."""
    if dof <= 0:
        return 1.0, 0.0
    if not np.isfinite(statistic):
        return 0.0, -np.inf
    if statistic <= 0:
        return 1.0, 0.0
    return float(special.chdtrc(dof, statistic)), log_gamma_q(dof / 2, statistic / 2)


def chi2_quantile(q: float, dof: int | np.ndarray, *, upper: bool = False) -> np.ndarray:
    """The chi-square distribution's quantile: the value its lower tail (``upper``: its upper tail) reaches at
    probability ``q`` with ``dof`` degrees of freedom, an array of ``dof``'s shape."""
    half = np.asarray(dof, dtype=float) / 2
    return 2.0 * np.asarray(special.gammainccinv(half, q) if upper else special.gammaincinv(half, q))


def binomial_log_tail(k: int, n: int, p: float) -> float:
    """log P(X >= k) of a binomial X of ``n`` trials with success probability ``p`` (0 for k <= 0), exact where the
    probability underflows (P(X >= k) = I_p(k, n - k + 1))."""
    if k <= 0:
        return 0.0
    if k > n:
        return -np.inf
    return log_beta_i(k, n - k + 1, p)


def digitize(value: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """``np.digitize(value, edges)`` for a few increasing ``edges`` (at most 126): the number of edges at or below
    each value, NaN past the last, as numpy's, in int8 of the shape of ``value``.

    Counted by one comparison per edge: numpy's binary search per value mispredicts its branches on unsorted
    values (24 against 2.6 ms for a million values and 17 edges), and the residual signatures bin every sample.
    """
    edges = np.asarray(edges)
    if edges.size > 126:
        raise ValueError(f"{edges.size} edges: at most 126 fit the int8 bins")
    value = np.asarray(value)
    idx = np.zeros(value.shape, np.int8)
    for e in edges:
        idx += value >= e
    return np.where(np.isnan(value), np.int8(edges.size), idx)


def normal_log_tail(z: np.ndarray) -> np.ndarray:
    """log P(Z > z) of a standard normal Z, elementwise, exact far into the tail."""
    return special.log_ndtr(-np.asarray(z, dtype=float))


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
    log_p = log_beta_i(d2 / 2, d1 / 2, d2 / (d2 + d1 * F)) if F > 0 else 0.0
    return F, d1, d2, log_p, means, pooled
