"""Replication: each finding of a diagnosis refitted on disjoint parts of the detector, its estimates compared.

An effect of the whole detector (a per-frame dose, phase or position error, the detector's gain, a scatter
ratio) has one value whichever part of the detector measures it. The final model is refitted on each half of
the detector's columns (and, in phase stepping, where every frame lights every row, of its rows), each finding
measured on each half (:meth:`~dfxcorr.effects.base.EffectBase.measure`: its estimate and standard errors), and
the halves' difference tested against their errors: chi-square over the compared entries, less the entries of a
gauge (a per-frame effect with a shift or scale gauge is defined up to one constant per component, which each
half fixes on its own frames). A finding whose halves disagree (p below ``diagnose.alpha``) does not replicate.
A pixel-wise finding (a moving part of the sample, a class of pixels) has no whole-detector value to compare.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ..effects.base import Context, EffectBase, Estimate, Hypothesis, Params, State
from ..stats import chi2_tail


@dataclass(frozen=True)
class Part:
    """Detector rows or columns [lo, hi)."""

    axis: Literal["columns", "rows"]
    lo: int
    hi: int

    @property
    def label(self) -> str:
        return f"{self.axis} {self.lo}-{self.hi - 1}"


def halves(shape: tuple[int, int, int], *, rows: bool) -> list[tuple[Part, Part]]:
    """The pairs of disjoint halves a finding is compared on: the detector's columns, and its rows where ``rows``
    (and there are two)."""
    _, H, W = shape
    out = [(Part("columns", 0, W // 2), Part("columns", W // 2, W))]
    if rows and H >= 2:
        out.append((Part("rows", 0, H // 2), Part("rows", H // 2, H)))
    return out


def difference(a: Estimate, b: Estimate, *, gauge: str) -> tuple[float, int]:
    """Chi-square of the difference of two estimates of one effect against their standard errors, and its dof.

    ``gauge``: 'shift' or 'scale' (the catalogue's): a per-frame effect defined up to a constant per component,
    whose weighted mean difference is taken out first (one dof per component); 'none': compared as they are.
    Entries with an infinite or zero standard error on either side are left out.
    """
    d = np.atleast_1d(np.asarray(a.value, float) - np.asarray(b.value, float))
    v = np.atleast_1d(np.asarray(a.se, float) ** 2 + np.asarray(b.se, float) ** 2)
    d, v = (d.reshape(d.shape[0], -1), v.reshape(v.shape[0], -1)) if d.ndim > 1 else (d[:, None], v[:, None])
    ok = np.isfinite(d) & np.isfinite(v) & (v > 0)
    w = np.where(ok, 1.0 / np.where(ok, v, 1.0), 0.0)
    dof = int(ok.sum())
    if gauge in ("shift", "scale") and d.shape[0] > 1:
        live = ok.any(axis=0)
        mean = np.where(live, np.sum(w * np.where(ok, d, 0.0), axis=0) / np.maximum(w.sum(axis=0), 1e-300), 0.0)
        d = d - mean
        dof -= int(live.sum())
    return float(np.sum(w * np.where(ok, d, 0.0) ** 2)), max(dof, 0)


@dataclass(frozen=True)
class Replication:
    """One finding on the halves of the detector.

    Attributes
    ----------
    parts : tuple of dict
        'part' (which detector columns or rows), 'estimate' and 'se' (a number, or a list per frame).
    statistic, dof, p_value
        Chi-square of the halves' differences against their standard errors (NaN where nothing was compared).
    replicated : bool or None
        Whether the halves agree within their errors (None: nothing to compare).
    why : str
        A sentence: what was found, or why nothing was compared.
    """

    parts: tuple[dict[str, Any], ...]
    statistic: float
    dof: int
    p_value: float
    replicated: bool | None
    why: str

    def to_json(self) -> dict[str, Any]:
        """The ``replication`` entry of ``spec/diagnosis.md`` (version 4), with ``why``."""
        return {"halves": list(self.parts), "statistic": self.statistic, "dof": self.dof, "p_value": self.p_value,
                "replicated": self.replicated, "why": self.why}


def _plain(a: np.ndarray) -> Any:
    """An estimate as JSON: a number, or a list (per frame) with non-finite entries as None."""
    a = np.asarray(a, float)
    if a.ndim == 0:
        return float(a) if np.isfinite(a) else None
    return [_plain(x) for x in a]


def replicate(effects: Mapping[str, EffectBase[Any]], ctx: Context, final: State,
              fit_part: Callable[[Hypothesis, Params, Part], State], *, shape: tuple[int, int, int], rows: bool,
              alpha: float, skip: Mapping[str, str] | None = None) -> dict[str, Replication]:
    """Every finding of ``effects`` (the effects added, in the final model of ``final``) on the halves.

    ``fit_part(hypothesis, start, part)`` fits the final model on one part of the detector (warm from ``start``);
    ``skip``: findings not compared, and why.
    """
    skip = {} if skip is None else skip
    out = {}
    for name, effect in effects.items():
        if name in skip or effect.policy.pixelwise:
            why = skip.get(name, "a finding of some pixels, not of the whole detector: no halves to compare")
            out[name] = Replication((), float("nan"), 0, float("nan"), None, why)
    compared = {name: effect for name, effect in effects.items() if name not in out}
    pairs = halves(shape, rows=rows) if compared else []
    measured: dict[Part, dict[str, Estimate | None]] = {}
    for part in (part for pair in pairs for part in pair):
        # one part's fit at a time: each holds its share of the held samples, the diagnosis's largest arrays
        state = fit_part(final.hypothesis, final.params, part)
        measured[part] = {name: effect.measure(ctx, state) for name, effect in compared.items()}
        del state
    for name, effect in compared.items():
        parts: list[dict[str, Any]] = []
        stat, dof = 0.0, 0
        for a, b in pairs:
            ea, eb = measured[a][name], measured[b][name]
            if ea is None or eb is None:
                continue
            s, k = difference(ea, eb, gauge=effect.entry.gauge)
            stat, dof = stat + s, dof + k
            parts += [{"part": p.label, "estimate": _plain(e.value), "se": _plain(e.se)}
                      for p, e in ((a, ea), (b, eb))]
        if not parts:
            out[name] = Replication((), float("nan"), 0, float("nan"), None,
                                   "measured on the whole detector only: no halves to compare")
            continue
        p, _ = chi2_tail(stat, dof)
        agree = dof == 0 or p >= alpha
        why = (f"the halves agree within their errors (chi-square {stat:.4g} for {dof} dof)" if agree else
               f"the halves' estimates differ beyond their errors (chi-square {stat:.4g} for {dof} dof, p {p:.2g})")
        out[name] = Replication(tuple(parts), stat, dof, p, agree if dof else None, why)
    return out
