"""Subsets of the observations' columns that stand for all of them: evenly spread (the fit's start check, the
identifiability check), or spread by their information (the vibration fit's Hessian, the uncertainty where samples
read between rows)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from . import engine as E
from . import model as M
from .observations import Observations


def spread_columns(obs: Observations, *, most: int) -> Observations:
    """At most ``most`` evenly spread columns of the observations (the outermost two among them); all if fewer."""
    if obs.columns.size <= most:
        return obs
    return obs.subset(np.unique(np.linspace(0, obs.columns.size - 1, most).astype(int)))


def information_columns(info: np.ndarray, *, most: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``most`` columns spread by their information, and how many times its own information each stands for.

    The columns' cumulative information is cut into ``most`` equal strata; each stratum is represented by the column
    whose span holds its centre, which stands for the stratum's information (a column holding several strata's
    centres, for all of them).
    Evenly spread columns misjudge a scan whose columns differ in information: a clinical scan's outer columns, in
    air, hold up to 20x the mean and evenly spread ones with the outermost took 2.7x the information of all.

    Parameters
    ----------
    info : ndarray, shape (C,)
        Information of each column (any non-negative measure the estimate should be exact for; the fit's is that of
        the phase channel, so a column without fringe, whose samples inform only dose and background, is never
        taken). Non-finite entries count as 0.
    most : int

    Returns
    -------
    keep : ndarray of int, shape (n,)
        Positions of the columns, ascending, n <= most.
    stands : ndarray, shape (n,)
        The information each stands for over its own (C / most each where all columns hold the same).
    """
    if most < 1:
        raise ValueError(f"most must be at least 1, got {most}")
    info = np.asarray(info, dtype=np.float64)
    # a column whose information is not a finite number (weights of inf) cannot stand for others
    info = np.where(np.isfinite(info), np.maximum(info, 0.0), 0.0)
    C, total = info.size, float(np.sum(info))
    if C == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    if C <= most or not total > 0:
        keep = np.unique(((np.arange(min(most, C)) + 0.5) * C / min(most, C)).astype(int))
        return keep, np.full(keep.size, C / keep.size)
    # the column whose own span of the cumulative information holds each stratum's centre
    pick = np.minimum(np.searchsorted(np.cumsum(info), (np.arange(most) + 0.5) * total / most, side="right"), C - 1)
    keep, strata = np.unique(pick, return_counts=True)
    return keep, strata * (total / most) / np.maximum(info[keep], 1e-300)


def standing_columns(obs: Observations, weights: np.ndarray, info: np.ndarray | None, *, most: int
                     ) -> tuple[Observations, np.ndarray]:
    """At most ``most`` columns spread by their information (:func:`information_columns`), and their weights times
    the information each stands for: a sum of per-pixel information over them estimates the sum over all columns
    (each pixel's images are the same, its share of the information that many times its own). All, as given, where
    there are no more.

    Parameters
    ----------
    obs : Observations
    weights : ndarray, shape (K, C)
        Inverse variances (counts^-2).
    info : ndarray, shape (C,), or None
        Each column's information (:func:`column_information`); needed only where there are more than ``most``.
    most : int
        Columns to take at most.

    Returns
    -------
    obs : Observations
        The observations of the columns taken (n <= ``most`` of them, ascending).
    weights : ndarray, shape (K, n)
        Their weights (counts^-2) times how many times its own information each stands for
        (:func:`information_columns`' ``stands``), in ``weights``' dtype.
    """
    if obs.columns.size <= most:
        return obs, weights
    if info is None or np.shape(info) != obs.columns.shape:
        raise ValueError(f"choosing {most} of {obs.columns.size} columns needs the information of each, got "
                         f"{'none' if info is None else np.shape(info)}")
    keep, stands = information_columns(info, most=most)
    return obs.subset(keep), (weights[:, keep] * stands).astype(weights.dtype)


def column_information(obs: Observations, params: dict, weights: np.ndarray) -> np.ndarray:
    """Each column's plain Fisher information in the phase channel, the sum over its samples of w (dIbar/dΦ)^2, (C,):
    what :func:`information_columns` spreads columns by (the Hessian's, the uncertainty's between rows). One pass of
    the per-pixel cost kernel (where samples read between rows as well: the images are solved per pixel)."""
    flat = replace(obs, reading=None)
    ch = M.channels(params, x=flat.x, n_frames=flat.n_frames)
    _, sums = E.reduced_cost(flat, ch, weights, square=True, channels=("phase",))
    return np.sum(sums.phase, axis=0)
