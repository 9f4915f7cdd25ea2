"""Preparation: a scan made ready for any analysis, and the one fold that applies corrections to it.

:func:`prepare` loads a scan, resolves and aligns its flat field, holds its lit samples, leaves the detector
faults out and applies each configured correction of the effects it is given (:class:`Correction`); the
result, :class:`Prepared`, is what reconstruct, diagnose and compare read their observations from.
:meth:`Prepared.corrected` is the fold of corrections, the same for the configuration's (here) and for a
diagnosis's hypothesis (:mod:`dfxcorr.analysis.diagnose`).

This module sits below the effects: they read its values, it never imports them.
"""
from __future__ import annotations

import functools
import logging
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from . import config as C
from .align import LitStore, collect_lit_rows, pixel_mm
from .faults import find_faults, saturation_level
from .io import Reference, Scan, read_scan
from .observations import Noise, Observations
from .progress import stage
from .reference import auto_visibility_threshold, resolve_reference

log = logging.getLogger(__name__)

#: Noise standard deviations below the saturation level within which a neighbour's count leaves a sample out.
SATURATION_SIGMAS = 3.0


@dataclass(frozen=True)
class Correctable:
    """What corrections act on: a scan's lit samples, where each frame reads the flat field, the noise model.

    Attributes
    ----------
    store : LitStore
    shift : ndarray, shape (J,)
        Rows by which each frame reads the flat field off the store's alignment.
    noise : Noise
    reference : Reference or None
        The flat-field maps the samples are aligned to (a correction that needs the flat field reads them).
    pixel_mm : (float, float) or None
        Detector pixel pitch (mm) along the columns of the detector (between rows) and along its rows,
        where the scan file states it.
    """

    store: LitStore
    shift: np.ndarray
    noise: Noise
    reference: Reference | None = None
    pixel_mm: tuple[float, float] | None = None


class Correction(Protocol):
    """The correction part of an effect: what a configuration asks of it, and how that changes the samples."""

    @property
    def name(self) -> str: ...

    def configured(self, cfg: dict[str, Any], *, n_frames: int, detector: tuple[int, int]) -> Any:
        """What the configuration asks of this effect, read and checked before any computation (None: nothing)."""
        ...

    def apply(self, data: Correctable, setting: Any) -> Correctable:
        """``data`` with the correction ``setting`` (not None) applied."""
        ...


@dataclass(frozen=True)
class Prepared:
    """A scan made ready for any analysis: flat field resolved and aligned, lit samples held, region of interest.

    Every consumer (reconstruct, diagnose, compare) gets its observations from here, so that they see
    the same data for the same scan and configuration.

    Attributes
    ----------
    scan : Scan
        The acquisition (its frames may stay in the file; the store holds what is needed).
    name : str
        File name, or 'scan' for an in-memory scan.
    path : Path or None
    reference : Reference
        Flat-field maps (retrieved from the scan's stepping series with the ``reference.*`` options).
    store : LitStore
    min_visibility : float
        Samples whose aligned reference visibility is below this carry no fringe (region of interest).
    noise : Noise
        Noise model of the configuration (``load.*``: gain, electronic noise, per-pixel factors).
    """

    scan: Scan
    name: str
    path: Path | None
    reference: Reference
    store: LitStore
    min_visibility: float
    noise: Noise

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.scan.shape

    @functools.cached_property
    def _unwrapped_reference(self) -> Reference:
        """The reference with its phase unwrapped along the scan, once (not again for every block of rows)."""
        return replace(self.reference, phase=np.unwrap(self.reference.phase, axis=0))

    def corrected(self, corrections: Iterable[tuple[Correction, Any]], *, report: bool = False) -> Prepared:
        """This preparation with the corrections applied in order (the one fold of every caller).

        ``corrections``: (effect, setting) pairs, settings not None; ``report``: log each one applied.
        """
        made = Correctable(store=self.store, shift=np.zeros(self.shape[0]), noise=self.noise,
                           reference=self.reference, pixel_mm=pixel_mm(self.scan))
        for effect, setting in corrections:
            made = effect.apply(made, setting)
            if report:
                log.info("%s: the configured correction is applied", effect.name)
        store = made.store.shifted(made.shift) if np.any(made.shift != 0) else made.store
        return replace(self, store=store, noise=made.noise)

    def observations(self, *, columns: np.ndarray | None = None, rows: tuple[int, int] | None = None,
                     dtype: type = np.float64) -> Observations:
        """Observations of some columns and detector rows, with the region of interest of their samples.

        Samples without fringe (outside the region of interest, ``obs.roi`` False) get v^f = 0: they yield
        no images, but in the fit they still monitor dose and background. ``use`` is False for the detector
        faults only (saturated samples, bad frames: :mod:`dfxcorr.faults`).
        """
        return self.store.observations(self._unwrapped_reference, columns=columns, rows=rows, gain=self.noise.gain,
                                       electronic=self.noise.electronic, noise=self.noise.factors, dtype=dtype,
                                       phase_unwrapped=True, min_visibility=self.min_visibility)


def prepare(scan: Scan | str | Path, cfg: dict[str, Any], *, effects: Iterable[Correction],
            timings: dict[str, Any] | None = None) -> Prepared:
    """Load, resolve the reference, align and collect the lit samples: the one preparation of every analysis.

    Parameters
    ----------
    scan : Scan or path
    cfg : dict
        Resolved configuration: ``load``, ``reference`` and ``align`` sections, and what ``effects`` read.
    effects : iterable of Correction
        The effects whose configured corrections are applied (:data:`dfxcorr.effects.REGISTRY` values).
    timings : dict, optional
        Receives the seconds of the load and align stages.

    Returns
    -------
    Prepared
    """
    timings = {} if timings is None else timings
    path = None
    if not isinstance(scan, Scan):
        path = Path(scan)
        with stage("load", timings):
            scan = read_scan(path, allow_external=cfg["load"]["allow_external"])
            log.info("scan %s: %d frames of %d x %d, active area %d rows%s", path.name, *scan.shape,
                     scan.active_rows, ", phase stepping" if scan.is_stepping else "")
    # what the configuration asks of each effect (files it names included) is read and checked before any computation
    settings = [(e, e.configured(cfg, n_frames=scan.shape[0], detector=scan.shape[1:])) for e in effects]
    with stage("align", timings):
        step_effects, optional = C.reference_effects(cfg)
        reference = resolve_reference(scan, effects=step_effects, optional=optional)
        store = collect_lit_rows(scan, active_rows=reference.transmission.shape[0],
                                 min_frames=cfg["align"]["min_frames"])
        faults = find_faults(store.frame_blocks(), shape=scan.shape, dark=store.dark,
                             level=saturation_level(store.counts.dtype, cfg["load"]["saturation"]))
        faults.require_data()
        if faults.any:
            log.warning("%s", faults.summary())
            # noise of a sample at the level: what a neighbour's count may differ by from its own expectation
            gain = cfg["load"]["gain"] or scan.gain
            store = store.without(faults, margin=SATURATION_SIGMAS * np.sqrt(gain * (faults.level or 0.0)
                                                                           + cfg["load"]["electronic"]))
        vmin = cfg["align"]["min_visibility"]
        vmin = auto_visibility_threshold(reference.visibility) if vmin == "auto" else float(vmin)
        raw = Prepared(scan=scan, name=path.name if path else "scan", path=path, reference=reference, store=store,
                       min_visibility=vmin, noise=Noise(cfg["load"]["gain"] or scan.gain, cfg["load"]["electronic"]))
        prep = raw.corrected([(e, s) for e, s in settings if s is not None], report=True)
        log.info("lit samples: %d rows x frames of %d columns (%.0f MB as %s)", prep.store.row.size, scan.shape[2],
                 prep.store.counts.nbytes / 1e6, prep.store.counts.dtype)
    return prep
