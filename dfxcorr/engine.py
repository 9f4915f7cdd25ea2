"""The model evaluated on observations: the compiled kernels of the paper's geometry, or those where samples read
between rows.

Every stage that solves images, evaluates the reduced cost or the Fisher information calls these three functions
(never :mod:`dfxcorr.kernels` directly). Where each sample reads the images of its own pixel (the paper's geometry)
they are the compiled loops of :mod:`dfxcorr.kernels`; where the beam paths move during the scan
(``Observations.reading``, ``beam_path``) the images of neighbouring rows are coupled, one block-tridiagonal solve
per column: the compiled loops of :mod:`dfxcorr.kernels_between` and :mod:`dfxcorr.fisher_between` (the numpy
expressions of :mod:`dfxcorr.model` and :mod:`dfxcorr.banded` are their definition). The signatures and returned
values are the kernels'.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from . import fisher_between as FB
from . import kernels as K
from . import kernels_between as KB
from . import model as M
from .observations import Observations


def retrieve(obs: Observations, ch: M.Channels, *, weights: np.ndarray | None = None, iterations: int = 1,
             gain: float | None = None, keep_inverse: bool = False, keep_expected: bool = True,
             next_weights: bool = False) -> dict:
    """Images, expected counts, weights and Pearson chi-square: :func:`dfxcorr.kernels.retrieve`'s values.

    Where ``obs.reading`` is set, ``inverse`` holds each row's diagonal block of the inverse and the result adds
    ``coupling`` (the blocks between each row and the next).
    """
    if obs.reading is None:
        K.set_threads()
        out = K.retrieve(obs, ch, weights=weights, iterations=iterations, gain=gain, keep_inverse=keep_inverse,
                         keep_expected=keep_expected, next_weights=next_weights)
        out["coupling"] = None
        return out
    K.set_threads()
    return KB.retrieve(obs, ch, weights=weights, iterations=iterations, gain=gain, keep_inverse=keep_inverse,
                       keep_expected=keep_expected, next_weights=next_weights)


def reduced_cost(obs: Observations, ch: M.Channels, weights: np.ndarray, cos_phif: np.ndarray,
                 sin_phif: np.ndarray, *, phase: float | None = None, square: bool = False,
                 channels=tuple(K.CHANNEL_IDS)) -> tuple[float, tuple[np.ndarray, ...]]:
    """Reduced cost and its channel gradients (or Gauss-Newton sums): :func:`dfxcorr.kernels.reduced_cost`'s values."""
    if obs.reading is None:
        return K.reduced_cost(obs, ch, weights, cos_phif, sin_phif, phase=phase, square=square, channels=channels)
    return KB.reduced_cost(obs, ch, weights, cos_phif, sin_phif, phase=phase, square=square, channels=channels)


def fisher(obs: Observations, ch: M.Channels, weights: np.ndarray, coef: np.ndarray, inverse: np.ndarray | None,
           names: Sequence[str], *, profiled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Fisher information of the parameters of ``names`` and its profiled correction, in
    :func:`dfxcorr.model.fisher_index`'s order: :func:`dfxcorr.kernels.fisher`'s values.

    Where ``obs.reading`` is set, :func:`dfxcorr.fisher_between.fisher` (a pixel's images share samples with its
    neighbours', so the correction runs over whole columns; ``inverse`` is not read).
    """
    if obs.reading is None:
        K.set_threads()
        return K.fisher(obs, ch, weights, coef, inverse, M.component_table(names)[:3], profiled=profiled)
    K.set_threads()
    return FB.fisher(obs, ch, weights, coef, M.component_table(names)[:3], profiled=profiled)
