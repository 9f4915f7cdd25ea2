"""Detector faults as data: saturated samples and frames that are empty or repeat their predecessor.

Every clinical radiograph has them: the direct beam beside the body saturates the panel, and now and then
a frame is read out as zeros or read twice. Such samples carry no information the model could explain;
fitted, they dominate the fit (a saturated area's chi-square) or take a frame's vibration estimate with
them. They are found from the lit rows of each frame and left out of the vibration fit, the motion mask and
the retrieval (the observations' ``use``), with a warning that says how many and where.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from .errors import DfxcorrError
from .stats import ranges


class FaultError(DfxcorrError, ValueError):
    """A scan that holds nothing but detector faults."""


#: A frame whose mean signal above the dark over its lit samples is below this share of the median frame's is
#: empty (read out as zeros or as dark): a body attenuates a frame's whole width by far less.
EMPTY_SHARE = 0.01
#: A pixel that keeps less than this share of its samples has no image: left with the fringe's dark half alone
#: (its bright half saturated) it cannot separate transmission from visibility. Its samples still enter the fit.
MIN_KEPT_SHARE = 0.5
#: Bad frames named one by one in the warning; the rest are counted.
SHOW_FRAMES = 10
#: A frame is a repeat of its predecessor when at least this many of the samples that both light (saturated ones
#: aside) are compared and every one is equal: with photon noise, equal counts in so many samples do not happen.
MIN_REPEAT_SAMPLES = 16


def saturated(counts: np.ndarray, level: float, *, margin: float) -> np.ndarray:
    """Samples to leave out for saturation: at or above ``level``, or beside a pixel (same frame and row, the
    next column either side) within ``margin`` of it.

    Leaving out only the samples above the level would keep those of a pixel near it that noise pushed down,
    and bias its images (and the fit through them) low. A neighbour sees nearly the same expected count with
    noise of its own, so choosing by it keeps only samples whose expectation lies well below the level
    (margin: a few noise standard deviations) without selecting on their own noise.

    Parameters
    ----------
    counts : ndarray, shape (K, W)
        Rows of frames (one detector row of one frame each), all W columns.
    level, margin : float

    Returns
    -------
    ndarray of bool, shape (K, W)
    """
    near = counts >= level - margin
    beside = np.zeros_like(near)
    beside[:, 1:] |= near[:, :-1]
    beside[:, :-1] |= near[:, 1:]
    return (counts >= level) | beside


def saturation_level(dtype: np.dtype, configured: float | None) -> float | None:
    """Counts at or above which a sample is saturated: ``load.saturation``, else an integer dtype's maximum
    (65535 for uint16); None for float frames without a configured level."""
    if configured is not None:
        return float(configured)
    return float(np.iinfo(dtype).max) if np.dtype(dtype).kind in "iu" else None


@dataclass
class Faults:
    """What :func:`find_faults` found.

    Attributes
    ----------
    level : float or None
        Saturation level (None: not checked).
    saturated : ndarray of int, shape (J,)
        Saturated samples per frame (in the frames' lit rows).
    saturated_rows : ndarray of int, shape (H,)
        Saturated samples per detector row.
    bad_frames : dict
        Frame -> why it is left out ('empty', 'a repeat of frame j - 1').
    samples : ndarray of int, shape (J,)
        Lit samples per frame.
    """

    level: float | None
    saturated: np.ndarray
    saturated_rows: np.ndarray
    samples: np.ndarray
    bad_frames: dict = field(default_factory=dict)

    def require_data(self) -> None:
        """Refuse a scan in which every lit sample is a fault (``reconstruct`` and ``check`` alike).

        Raises
        ------
        FaultError
        """
        kept = self.samples - self.saturated
        kept[list(self.bad_frames)] = 0
        if not kept.any():
            raise FaultError(f"every lit sample is a detector fault: nothing to fit (dataset "
                             f"/entry/instrument/detector/data; {self.summary().split(': ', 1)[1]})")

    @property
    def any(self) -> bool:
        """Whether anything is left out."""
        return bool(self.saturated.sum()) or bool(self.bad_frames)

    def summary(self) -> str:
        """One line: how many samples and frames are left out, and where."""
        parts = []
        n = int(self.saturated.sum())
        if n:
            parts.append(f"{n} saturated samples (counts >= {self.level:g}) in frames "
                         f"{ranges(np.flatnonzero(self.saturated))}, detector rows "
                         f"{ranges(np.flatnonzero(self.saturated_rows))}")
        if self.bad_frames:
            listed = sorted(self.bad_frames.items())
            parts.append(f"{len(listed)} frame(s) " + ", ".join(f"{j} ({why})" for j, why in listed[:SHOW_FRAMES])
                         + (f" and {len(listed) - SHOW_FRAMES} more" if len(listed) > SHOW_FRAMES else ""))
        return "detector faults left out of the fit and the images: " + "; ".join(parts)


def find_faults(blocks: Iterable[tuple[int, np.ndarray, np.ndarray]], *, shape: tuple[int, int, int],
                dark: np.ndarray, level: float | None) -> Faults:
    """Saturated samples, empty frames and repeated frames, from each frame's lit rows in frame order.

    Parameters
    ----------
    blocks : iterable of (j, rows, counts)
        Frame j's lit detector rows (ascending, shape (n,)) and their counts (n, W), frames ascending; frames
        that light no row may be left out.
    shape : (J, H, W)
    dark : ndarray, shape (H, W)
    level : float or None
        Saturation level (:func:`saturation_level`).

    Returns
    -------
    Faults
    """
    J, H, _ = shape
    saturated, saturated_rows, samples = np.zeros(J, np.int64), np.zeros(H, np.int64), np.zeros(J, np.int64)
    signal = np.full(J, np.nan)
    repeats: dict[int, str] = {}
    previous: tuple[int, np.ndarray, np.ndarray] | None = None
    dark_rows = dark.mean(axis=1)
    for j, rows, counts in blocks:
        samples[j] = counts.size
        sat = counts >= level if level is not None else np.zeros((0, 0), bool)
        n_sat = int(np.count_nonzero(sat))
        if n_sat:
            saturated[j] = n_sat
            saturated_rows[rows] += sat.sum(axis=1)
            ok = ~sat
            if ok.any():
                signal[j] = float(np.mean(counts[ok], dtype=np.float64) - np.mean(dark[rows][ok]))
        else:  # the common case, without a temporary of the block's size in float64
            signal[j] = float(np.mean(counts, dtype=np.float64) - np.mean(dark_rows[rows]))
        if previous is not None and previous[0] == j - 1 and _repeats(rows, counts, *previous[1:], level):
            repeats[j] = f"a repeat of frame {j - 1}"
        previous = j, rows, counts
    typical = np.nanmedian(signal) if np.any(np.isfinite(signal)) else np.nan
    bad = {int(j): "empty" for j in np.flatnonzero(np.isfinite(signal) & (signal <= EMPTY_SHARE * typical))}
    for j, why in repeats.items():
        bad.setdefault(j, why)
    return Faults(level=level, saturated=saturated, saturated_rows=saturated_rows, samples=samples, bad_frames=bad)


def _repeats(rows: np.ndarray, counts: np.ndarray, prev_rows: np.ndarray, prev_counts: np.ndarray,
             level: float | None) -> bool:
    """Whether the rows two frames both light hold equal counts (saturated ones aside) in enough samples."""
    both, here, there = np.intersect1d(rows, prev_rows, return_indices=True)
    if both.size == 0 or not np.array_equal(counts[here[0]], prev_counts[there[0]]):
        return False  # a first row that differs settles it for nearly every frame
    a, b = counts[here], prev_counts[there]
    same = (a < level) & (b < level) if level is not None else np.ones(a.shape, bool)
    return int(same.sum()) >= MIN_REPEAT_SAMPLES and np.array_equal(a[same], b[same])
