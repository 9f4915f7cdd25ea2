"""``detector_lag``: the detector carries a fraction a of the previous frame's signal into the next.

I_j(i) = S_j(i) + a S_(j-1)(i), S the lag-free signal of the same pixel (0 where it was not lit). The
counts are corrected, not modelled: S_j = I_j - dark - a S_(j-1) (:func:`lag_free`), applied where the
counts are read (``load.detector_lag``). The lag carries the previous frame's detected signal, its noise
included, so the recursion with the true a returns the lag-free frames exactly (bar the storage's
rounding) and every later stage, the compiled kernels included, sees Poisson data as if there had been
no lag; a mean term a Ibar_(j-1) would also need the lagged noise in the variance and would couple the
frames of every pixel in the fit. a is measured where the model has nothing to say: the rows the active
area has just left (read in the same hyperslab as the lit rows, :class:`dfxcorr.align.LitStore`).
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from numba import njit

from ..align import LitStore
from ..catalogue import Effect
from ..preparation import Correctable
from .base import Context, EffectBase, Estimate, Finding, Hypothesis, Option, Policy, State, Test, chi2_test


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
             *, blocks: np.ndarray | None = None, dtype: type = np.float32) -> np.ndarray:
    """Undo detector lag recursively: S_j = (I_j - dark) - a S_(j-1), S = 0 where the pixel was not lit.

    Parameters
    ----------
    counts : ndarray, shape (K, W)
        Measured counts I of (row, frame) blocks sorted by row, frames ascending within a row.
    dark : ndarray, shape (H, W)
        Dark signal of the detector's pixels (counts), read at each block's row; it carries no lag.
    row, frame : ndarray of int, shape (K,)
    fraction : float
        The lag fraction a (``spec/diagnosis.md``: I_j = S_j + a S_(j-1)).
    blocks : ndarray of int, shape (K',), optional
        Only these blocks' result, in this order (default every block; repeats allowed): the recursion still runs
        through every block, holding one.
    dtype : numpy dtype
        Of the result, and of the recursion (I - dark in it, as the result's values were).

    Returns
    -------
    ndarray, shape (K, W) or (K', W)
        S + dark: the counts the detector would have given without lag. Where frame j - 1 did not
        light the pixel the lag-free signal of j - 1 is 0 and I_j is returned unchanged.
    """
    K = row.size
    if blocks is None:
        want, again = np.arange(K), None
    else:
        blocks = np.asarray(blocks, dtype=np.int64)
        if blocks.size and not 0 <= blocks.min() <= blocks.max() < K:
            raise ValueError(f"blocks outside 0..{K - 1}")
        # each block once (the kernel writes a block's row once), then as asked
        blocks, again = np.unique(blocks, return_inverse=True)
        want = np.full(K, -1)
        want[blocks] = np.arange(blocks.size)
    out: np.ndarray = np.empty((want.size if blocks is None else blocks.size, counts.shape[1]), dtype)
    # the fraction in the result's dtype, as numpy's products of an array and a Python float are
    dark = np.asarray(dark, np.float64)
    _lag_free(counts, dark, dark.astype(dtype), row, previous_block(row, frame), out.dtype.type(fraction), want, out)
    return out if again is None else out[again]


@njit(cache=True, nogil=True)
def _lag_free(counts: np.ndarray, dark: np.ndarray, dark_t: np.ndarray, row: np.ndarray, prev: np.ndarray,
              fraction: Any, want: np.ndarray, out: np.ndarray) -> None:
    # in storage order: block k - 1 is (row, j - 1) of block k where that exists, already lag-free in ``s``. Compiled:
    # frame by frame in numpy (gathers and scatters of every block, the dark gathered per block in float64) was 1.9 s
    # of a binned clinical scan's diagnosis, which measures the lag four times a round
    if out.shape[0] == 0:
        return
    s = np.zeros_like(out[0])
    v = np.empty_like(s)
    for k in range(counts.shape[0]):
        r, chained = row[k], prev[k] >= 0
        for c in range(counts.shape[1]):
            v[c] = counts[k, c]  # in the result's dtype: the store casts
        for c in range(counts.shape[1]):
            x = v[c] - dark_t[r, c]
            s[c] = x - fraction * s[c] if chained else x
        if want[k] >= 0:
            o = out[want[k]]
            for c in range(counts.shape[1]):
                o[c] = s[c] + dark[r, c]


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


def without_lag(store: LitStore, fraction: float) -> LitStore:
    """The same samples with detector lag ``fraction`` taken out (:func:`lag_free`), float32.

    Raises
    ------
    ValueError
        If lag was already taken out of this store.
    """
    if store.lag:
        raise ValueError("the detector lag was already taken out of these samples")
    counts = lag_free(store.counts, store.dark, store.row, store.frame, fraction)
    return replace(store, counts=counts, lag=float(fraction))


def measured_lag(store: LitStore) -> tuple[float, float]:
    """Lag fraction a and its standard error from the pixels the active area has just left (:func:`lag_estimate`).

    The previous frame's lag-free signal depends on a itself (S_(j-1) = I_(j-1) - a S_(j-2)): a few
    fixed-point iterations, each a's error times a. (nan, inf) without such pixels (phase stepping).
    """
    if store.left_counts is None or store.left_prev is None or store.left_prev.size == 0:
        return float("nan"), float("inf")
    prev_row = store.row[store.left_prev]
    # detector faults take no part: a frame read twice would read as a lag of 1
    keep = np.ones(store.left_counts.shape, bool) if store.good is None else store.good[store.left_prev].copy()
    keep[np.isin(store.frame[store.left_prev] + 1, store.bad_frames)] = False
    signal = np.where(keep, store.left_counts.astype(np.float64) - store.dark[prev_row], 0.0)
    a, se = 0.0, float("inf")
    for _ in range(4):
        prev = lag_free(store.counts, store.dark, store.row, store.frame, store.lag or a, blocks=store.left_prev)
        a, se = lag_estimate(signal, np.where(keep, prev - store.dark[prev_row], 0.0))
        if store.lag:
            break
    return a, se


def lag_test(store: LitStore) -> Test[Estimate]:
    """Detector lag measured in the pixels the active area has just left.

    Without lag they hold the dark signal only; with lag a they hold a S_(j-1), the previous frame's
    lag-free signal (:func:`measured_lag`). The statistic is (a / se)^2, chi-square with 1 dof. Not
    identifiable without such pixels (phase stepping: every pixel is lit in every frame). Measured on the
    small test scan with a = 3 %: a estimated to 1e-5; the reduced chi-square of the paper's model drops from
    about 1.09 to that of the same scan without lag. Payload: a and its standard error.
    """
    a, se = measured_lag(store)
    if not np.isfinite(a) or store.lag:
        return Test(0.0, 1, 1.0, 0.0, Estimate(np.asarray(0.0), np.asarray(se)), identifiable=bool(np.isfinite(a)))
    stat = (a / se) ** 2 if se > 0 else (np.inf if a else 0.0)
    return chi2_test(float(stat), 1, Estimate(np.asarray(a), np.asarray(se)), explains=float(stat))


class DetectorLag(EffectBase[Estimate]):
    entry = Effect("detector_lag", None, False, ("a",), 0.0, "none",
                   "the detector carries a fraction a of the previous frame's signal into the next: "
                   "I_j = S_j + a S_(j-1)")
    # measured directly outside the active area: the mean effects would only soak up its traces
    policy = Policy(order=0, fresh_start=True, astray_check=True)

    def configured(self, cfg: dict[str, Any], *, n_frames: int, detector: tuple[int, int]) -> Any:
        return cfg["load"]["detector_lag"] or None

    def apply(self, data: Correctable, setting: Any) -> Correctable:
        return replace(data, store=without_lag(data.store, setting))

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test[Estimate] | None:
        return lag_test(ctx.corrected(state.hypothesis).store)

    def trial(self, ctx: Context, state: State, test: Test[Estimate]) -> Hypothesis:
        return state.hypothesis.but(corrections=(*state.hypothesis.corrections, (self.name, float(test.payload.value))))

    def accepted(self, ctx: Context, before: State, after: State, test: Test[Estimate]) -> Finding:
        a, se = float(test.payload.value), float(test.payload.se)
        return Finding("all frames; signal in the rows the active area has just left",
                       f"a = {100 * a:.4g} % (se {100 * se:.2g} %)", {"value": a, "se": se},
                       options=(Option("load.detector_lag", f"{a:.6g}"),))

    def measure(self, ctx: Context, state: State) -> Estimate | None:
        # measured in the rows the active area has just left, over the whole detector: a fit on part of it does
        # not measure it again
        return None


EFFECT = DetectorLag()
