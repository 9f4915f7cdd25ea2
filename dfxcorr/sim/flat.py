"""The simulator's flat field: analytic along the scan, read where each pixel is.

The reference holds the field at its row centres; a frame's pixels see it where they are, a fraction of a row off
when the frame's position is (``reference_offset``, ``position_error``): the analytic field is evaluated there, by
the simulator's own means, never by the alignment's interpolation of the reference rows that the model uses.
"""
from __future__ import annotations

import numpy as np

from ..io import Reference
from ..observations import lateral_coordinate

__all__ = ["NONLINEARITY", "flat_field", "pixel_flat_field"]

#: Relative variation of t^f and v^f along the scan, and phase departure / 2 pi, of ``flat_nonlinearity: 1``.
NONLINEARITY = 0.02


def _analytic(cfg: dict, u: np.ndarray, A: int, W: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """t^f (counts), v^f and phi^f (rad) at continuous local rows ``u`` (K, 1) (row centres at k + 0.5), (K, W)."""
    s = cfg["simulate"]
    x = lateral_coordinate(np.arange(W), W)[None, :]
    n = s["tiles"]
    tile = np.minimum((np.arange(W) * n) // W, n - 1)[None, :] if n else np.zeros((1, W), int)
    if n:
        rng = np.random.default_rng([s["seed"], 1])
        centre = lateral_coordinate((np.arange(n) + 0.5) * W / n - 0.5, W)
        jitter = rng.uniform(-1, 1, (4, n))
        fringes = (s["fringes_centre"] + (s["fringes_edge"] - s["fringes_centre"]) * centre ** 2
                   + s["tile_fringes"] * jitter[0])[tile]
        phase0 = (np.pi * jitter[1])[tile]
        tf_tile, vf_tile = (1 + s["tile_contrast"] * jitter[2])[tile], (1 + s["tile_contrast"] * jitter[3])[tile]
    else:
        fringes = s["fringes_centre"] + (s["fringes_edge"] - s["fringes_centre"]) * x ** 2
        phase0, tf_tile, vf_tile = 0.0, 1.0, 1.0
    flux = s["flux"] * (1 + s["flat_gradient"] * (u / A - 0.5)) * np.ones((1, W))
    vis = np.full((u.shape[0], W), float(s["visibility"]))
    phase = 2 * np.pi * fringes * u / A + phase0
    a = NONLINEARITY * s["flat_nonlinearity"]
    if a:
        # one period of variation over the active area, shifted from tile to tile
        wave = 2 * np.pi * u / A + tile
        flux = flux * (1 + a * np.sin(wave))
        vis = vis * (1 + a * np.cos(wave))
        phase = phase + 2 * np.pi * a * 4 * (u / A - 0.5) ** 2
    return flux * tf_tile, vis * vf_tile, phase


def flat_field(cfg: dict, A: int, W: int) -> Reference:
    """Flat field with a fringe count growing from the centre to the edges (paper Sec. III-A), at the row centres.

    With ``simulate.tiles`` the gratings are tiled across the width: each tile has its own fringe count
    (the value at its centre, varied by up to +- ``tile_fringes``), phase at u = 0, t^f and v^f, so the
    phase gradient along the scan is piecewise constant across the width. ``flat_nonlinearity`` adds the
    departures from linearity along u that real flat fields have: phase curvature, and t^f and v^f
    varying along u (differently in each tile). The tiles draw from their own stream of the seed, so the
    other random draws of a scan do not change.
    """
    tf, vf, phase = _analytic(cfg, (np.arange(A) + 0.5)[:, None], A, W)
    return Reference(transmission=tf, visibility=vf, phase=phase)


def pixel_flat_field(cfg: dict, u: np.ndarray, A: int, W: int, *, step: float = 0.0
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The flat field that pixels centred at local rows ``u`` see (the reference's own rows at u = k + 0.5).

    Parameters
    ----------
    cfg : dict
        Resolved simulation configuration.
    u : ndarray, shape (K,)
        Local rows of the pixels' centres (continuous; beyond [0, A) the analytic field goes on).
    A, W : int
        Active rows and detector columns.
    step : float
        Phase added to the fringe (rad; the frame's nominal phase step).

    Returns
    -------
    tf, vf, phif : ndarray, shape (K, W)
        t^f (counts), v^f and phi^f + step (rad).
    """
    tf, vf, phase = _analytic(cfg, np.asarray(u, float)[:, None], A, W)
    return tf, vf, phase + step
