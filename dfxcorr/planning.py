"""Planning a run: which configured effects a reconstruction fits, and why some cannot be.

An effect the acquisition cannot determine (its Fisher information has directions without information
beyond its gauge, :mod:`dfxcorr.identify`; visibility effects in phase stepping, paper Sec. II-F) is
dropped with a log line where the configuration leaves it to ``auto``, and refused with an
:class:`IdentifiabilityError` where the configuration asks for it explicitly. ``dfxcorr check`` plans with
the same rules, without fitting.
"""
from __future__ import annotations

import logging

import numpy as np

from . import config as C
from . import model as M
from .catalogue import CATALOGUE
from .errors import DfxcorrError
from .fit import initial_weights
from .identify import select
from .io import Scan

log = logging.getLogger("dfxcorr")

#: Effects whose parameters multiply the fringe's visibility (paper Sec. II-F: not determined in phase stepping).
VISIBILITY_EFFECTS = tuple(n for n, e in CATALOGUE.items() if e.channel == "visibility")


class IdentifiabilityError(DfxcorrError, ValueError):
    """An effect was asked for that the acquisition cannot determine."""


def separable_flat_field(reference, *, tol: float = 1e-3) -> bool:
    """True if the flat field cannot tell per-frame visibility loss from the images (paper eq. 48).

    That is the case when t^f and v^f do not change along the scan direction and the flat-field phase is
    f(column) + a * row with one slope a for all columns.
    """
    A = reference.transmission.shape[0]
    if A < 2:
        return True
    phase = np.unwrap(reference.phase, axis=0)
    u = np.arange(A) - (A - 1) / 2
    slope = np.sum(u[:, None] * (phase - phase.mean(axis=0))) / (np.sum(u ** 2) * phase.shape[1])
    resid = phase - phase.mean(axis=0) - slope * u[:, None]
    flat = [np.std(m, axis=0).max() / np.abs(m).mean() for m in (reference.transmission, reference.visibility)]
    return bool(np.sqrt(np.mean(resid ** 2)) < tol and max(flat) < tol)


def visibility_unidentifiable(scan: Scan, reference) -> str | None:
    """Why per-frame visibility loss cannot be told apart from the images here, or None (paper Sec. II-F)."""
    if scan.is_stepping:
        why = ("in a phase-stepping recording the flat field is the same in every frame, so a per-frame "
               "visibility loss trades off exactly against the transmission and dark-field images (paper Sec. II-F)")
    elif separable_flat_field(reference):
        why = ("the flat-field phase of this scan is separable (paper eq. 48) and t^f, v^f do not vary along the "
               "scan, so per-frame visibility loss cannot be told apart from the images")
    else:
        why = None
    return why


def refuse_if_asked(cfg: dict, name: str, why: str) -> None:
    """Refuse an effect the acquisition cannot determine if the configuration asks for it explicitly.

    Raises
    ------
    IdentifiabilityError
        If ``vibration.<key of name>`` is true (not auto).
    """
    key = M.effect(name).config
    if key is not None and C.get(cfg, key) is True:
        raise IdentifiabilityError(f"{name} is not identifiable here: {why}; set {key}=false"
                                   + (" (or auto)" if C.option(key).default == "auto" else ""))


def drop_visibility(cfg: dict, effects, why: str | None) -> tuple[list[str], dict[str, str]]:
    """The effects without the visibility ones where ``why`` (paper Sec. II-F) says they cannot be determined.

    Returns
    -------
    kept : list of str
    dropped : dict
        Effect -> reason.

    Raises
    ------
    IdentifiabilityError
        If the configuration explicitly asks for a visibility effect that ``why`` rules out.
    """
    kept, dropped = [], {}
    for name in effects:
        if why and name in VISIBILITY_EFFECTS:
            refuse_if_asked(cfg, name, why)
            dropped[name] = why
        else:
            kept.append(name)
    return kept, dropped


def resolve_effects(cfg: dict, scan: Scan, reference, fit_obs: M.Observations) -> tuple[str, ...]:
    """The effects to fit: the configured ones that this acquisition can determine.

    Every enabled effect is checked in turn against the Fisher information of the fit's samples
    (:mod:`dfxcorr.identify`); visibility effects in a stepping recording or over a separable flat
    field are refused with the paper's reason. An effect set to ``auto`` is dropped with a log line.

    Raises
    ------
    IdentifiabilityError
        If the configuration explicitly asks for an effect the acquisition cannot determine.
    """
    def refuse_or_drop(name, why):
        refuse_if_asked(cfg, name, why)
        log.info("%s is not fitted: %s", name, why)

    names, dropped = drop_visibility(cfg, C.effects_of(cfg), visibility_unidentifiable(scan, reference))
    for name, why in dropped.items():
        log.info("%s is not fitted: %s", name, why)
    chosen: list[str] = []
    for verdict in select(fit_obs, initial_weights(fit_obs, {}), names):
        if verdict.identifiable:
            chosen.append(verdict.name)
        else:
            refuse_or_drop(verdict.name, f"the Fisher information of this acquisition has {verdict.excess} "
                                         f"direction(s) of its parameters without information beyond its gauge "
                                         f"(they trade off exactly against the images"
                                         f"{' or ' + ', '.join(chosen) if chosen else ''})")
    return tuple(chosen)
