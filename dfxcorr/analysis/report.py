"""The diagnosis's report: ``diagnosis.json`` (``spec/diagnosis.md``), ``report.md``, pictures and the files of
the effects added, and the ``reconstruct`` command that uses the final model.

Every verdict is a typed value (:class:`EffectReport`: an effect's :class:`~dfxcorr.effects.base.Finding` where it
was added, else why not), rendered here by its kind, so that no kind of verdict can break the report.
"""
from __future__ import annotations

import json
import shlex
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .. import config as C
from .. import plots
from ..catalogue import CATALOGUE, effect
from ..effects import REGISTRY
from ..effects.base import Consistency, EffectBase, Finding, Hypothesis, Params, State, Unexplained
from ..effects.residuals import fit_counts, pixel_chi2, reduced_map
from ..io import atomic_folder
from ..retrieve import image_maps
from .loop import GROSS, Blind, Rejection
from .replication import Replication
from .signatures import Residuals, locate

#: What the diagnosis decided about an effect it tested.
Verdict = Literal["added", "alternative", "not significant", "not material", "rejected", "raised chi-square", "proxy",
                  "not identifiable", "explains, not identifiable", "held: gross misfit", "explained by another"]


@dataclass(frozen=True)
class EffectReport:
    """One catalogue effect's verdict (the keys of ``spec/diagnosis.md``).

    Attributes
    ----------
    name, detected, identifiable, statistic, dof, p_value
        As in ``diagnosis.json``.
    verdict : str
        What was decided (:data:`Verdict`).
    delta_chi2, reduced_chi2_after : float or None
        Where added: the chi-square it removed and the reduced chi-square after.
    finding : Finding or None
        Where added: what it reports.
    rejection : Rejection or None
        Where a trial refit was tried and not justified.
    blind : Blind or None
        Where not identifiable and tried first.
    refused : Consistency or None
        Where refused as a proxy: the consistency test that refused it.
    excess : int
        Information-free directions of its parameters beyond its gauge.
    shared : int
        Directions it shares with the model's effects (tested and fitted in the rest).
    replication : Replication or None
        Where added: its estimate on disjoint parts of the detector.
    alternatives : tuple of str
        Effects that explain the same misfit and that this acquisition cannot tell from it.
    alternative_estimates : mapping
        Each alternative's estimate (one line).
    explained_by : str or None
        For "explained by another": the candidate it shares directions with whose share beyond it was significant
        (the data tell the two apart: no alternative).
    """

    name: str
    detected: bool
    identifiable: bool
    statistic: float
    dof: int
    p_value: float
    verdict: Verdict
    delta_chi2: float | None = None
    reduced_chi2_after: float | None = None
    finding: Finding | None = None
    rejection: Rejection | None = None
    blind: Blind | None = None
    refused: Consistency | None = None
    excess: int = 0
    shared: int = 0
    replication: Replication | None = None
    alternatives: tuple[str, ...] = ()
    alternative_estimates: Mapping[str, str] = field(default_factory=dict)
    explained_by: str | None = None

    @property
    def values(self) -> Mapping[str, Any]:
        """The effect's own keys of its entry (empty where not added)."""
        return {} if self.finding is None else self.finding.values

    @property
    def where(self) -> str | None:
        return None if self.finding is None else self.finding.where

    @property
    def estimate(self) -> str | None:
        return None if self.finding is None else self.finding.estimate

    @property
    def recommended(self) -> bool:
        """Whether its options go into the recommended ``reconstruct`` command: added, and not refuted by its
        replication on parts of the detector."""
        return self.detected and (self.replication is None or self.replication.replicated is not False)

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"name": self.name, "detected": self.detected, "identifiable": self.identifiable,
                             "statistic": self.statistic, "dof": self.dof, "p_value": self.p_value,
                             "verdict": self.verdict}
        for key in ("delta_chi2", "reduced_chi2_after", "where", "estimate"):
            if (v := getattr(self, key)) is not None:
                d[key] = v
        d.update(self.values)
        if self.excess:
            d["excess_null_directions"] = self.excess
        if self.shared:
            d["shared_directions"] = self.shared
        if self.rejection is not None:
            d["explained_share"] = self.rejection.share
            if self.rejection.astray:
                d["reduced_chi2_with"] = self.rejection.reduced_chi2_with
        if self.refused is not None:
            d["refused_as_proxy"] = self.refused.axis
        if self.blind is not None:
            d.update({"explains_misfit": self.blind.explains_misfit, "explained_share": self.blind.explained_share,
                      "reduced_chi2_with": self.blind.reduced_chi2_with})
            if self.blind.stopped:
                d["stopped"] = True
        if self.replication is not None:
            d["replication"] = self.replication.to_json()
        if self.alternatives:
            d["alternatives"] = list(self.alternatives)
            d["alternative_estimates"] = dict(self.alternative_estimates)
        if self.explained_by is not None:
            d["explained_by"] = self.explained_by
        return d

    def verdict_text(self) -> str:
        """One cell of report.md: where it sits, or why it was not added."""
        if self.verdict == "explains, not identifiable" and self.blind is not None:
            return (f"explains the misfit (a trial refit with it reaches reduced chi-square "
                    f"{self.blind.reduced_chi2_with:.4f}), but this acquisition cannot identify it: "
                    + ("nothing else is named in its place" if self.blind.stopped else
                       "an identifiable effect explained as much"))
        if self.verdict == "raised chi-square" and self.rejection is not None:
            return (f"significant, but a trial refit with it raises the reduced chi-square to "
                    f"{self.rejection.reduced_chi2_with:.4f}: not added")
        if self.verdict == "rejected" and self.rejection is not None:
            share = self.rejection.share
            return ("significant, but a trial refit removes "
                    + ("none of" if share is None else f"only {100 * share:.0f} % of")
                    + " the signatures' excess: not added")
        if self.verdict == "proxy" and self.refused is not None:
            along = f"detector {self.refused.along}" if self.refused.along else f"{self.refused.axis}s"
            return f"significant, but of another size in pixels of other {along}: a proxy, not added (unexplained)"
        if self.verdict == "held: gross misfit":
            return "significant, but not judged: the mean model is grossly off (the noise model would absorb it)"
        if self.verdict == "explained by another":
            return f"significant, but nothing beyond {self.explained_by}, which explains what they share: not tried"
        if self.verdict == "alternative":
            return (f"explains the misfit that {', '.join(self.alternatives)} explains: this acquisition cannot tell "
                    f"them apart (named together)")
        if self.alternatives:
            return (f"{self.where or ''}; or {', '.join(self.alternatives)}: this acquisition cannot tell them "
                    f"apart")
        if self.replication is not None and self.replication.replicated is False:
            return f"{self.where or ''}; does not replicate: {self.replication.why}"
        return self.where or ""


@dataclass
class Diagnosis:
    """The outcome of :func:`dfxcorr.analysis.diagnose.diagnose`.

    ``final`` is the final model's hypothesis (its effects, noise model, pixels left out, alignment and
    corrections of the counts); ``start`` the one the diagnosis began with (the configuration's); ``cfg`` the
    resolved configuration it ran with; ``registry`` the effects it tested.
    """

    scan: str
    base_model: list[str]
    initial_chi2: float
    final_chi2: float
    effects: list[EffectReport]
    final_model: list[str]
    before: Residuals
    after: Residuals
    params: Params
    criterion: str
    rounds: list[dict[str, Any]]
    unexplained: list[Unexplained]
    signatures: list[dict[str, Any]]
    shape: tuple[int, int, int]
    final: Hypothesis
    start: Hypothesis
    cfg: dict[str, Any]
    registry: Mapping[str, EffectBase[Any]]
    changes: list[dict[str, Any]] = field(default_factory=list)
    #: Seconds of each stage (load, align, every fit and its tests), as logged.
    timings: dict[str, float] = field(default_factory=dict)
    #: The detector columns [first, stop) the per-pixel tests and residual maps saw (``diagnose.max_held_samples``).
    tested_columns: tuple[int, int] = (0, 0)

    @property
    def band(self) -> str:
        """'' where every column was tested pixel by pixel, else which were."""
        first, stop = self.tested_columns
        return "" if stop - first >= self.shape[2] else f"columns {first}-{stop - 1} of {self.shape[2]}"

    @property
    def motion_mask(self) -> np.ndarray:
        return self.final.motion

    @property
    def pixel_noise(self) -> np.ndarray | None:
        """The per-pixel variance factors where the diagnosis changed them, else None."""
        factors = self.final.noise.factors
        return None if factors is self.start.noise.factors else factors

    def findings(self) -> dict[str, Finding]:
        """Every effect added -> its finding, in the order added."""
        return {e.name: e.finding for e in self.effects if e.finding is not None}

    def to_json(self) -> dict[str, Any]:
        """The ``diagnosis.json`` document of ``spec/diagnosis.md``."""
        return {"format": "dfxcorr-diagnosis", "format_version": 4, "scan": self.scan, "base_model": self.base_model,
                "reduced_chi2": {"initial": self.initial_chi2, "final": self.final_chi2},
                "effects": [e.to_json() for e in self.effects], "final_model": self.final_model,
                "unexplained": [u.to_json() for u in self.unexplained], "criterion": self.criterion,
                "rounds": self.rounds, "tested_columns": list(self.tested_columns),
                "recommended": reconstruct_settings(self)}


def _effect_picture(name: str) -> str:
    return f"effect-{name}.png"


#: Every file the report may write, each name known before the diagnosis runs: its own, one picture per registered
#: effect (``effect-<name>.png``, where the effect is added), and the files the effects write when added.
FIXED_FILES = ("diagnosis.json", "report.md", "residuals.png", "signatures.png",
               *(_effect_picture(name) for name in REGISTRY),
               *(f for e in REGISTRY.values() for f in e.files))


def residuals(state: State) -> Residuals:
    """Where the fit ``state`` and its observations disagree (:func:`dfxcorr.analysis.signatures.locate`)."""
    return locate(state.obs, state.params, state.rec.images, counts=fit_counts(state))


def residual_map(state: State) -> np.ndarray:
    """Reduced chi-square of each pixel of a fit's held columns, a detector image (H, W) in float32 (drawn; six per
    step in float64 would be the largest item of a diagnosis's peak memory), NaN where nothing counts: the per-pixel
    map of :func:`residuals` from :func:`dfxcorr.effects.residuals.pixel_chi2` alone (a third of its time)."""
    X, dof, _ = pixel_chi2(state.obs, state.params, state.rec.images)
    return reduced_map(X, dof).astype(np.float32)


def change_picture(effect: EffectBase[Any], before: State, after: State, finding: Finding, *,
                   mapped: Callable[[State], np.ndarray] = residual_map) -> dict[str, Any]:
    """What adding ``effect`` changed, for its picture: images and residual maps of the fits ``before`` and
    ``after`` (each on its own observations: the change may alter the data or their noise model) (H, W), and
    its per-frame estimate (J, n) where it has one. ``mapped``: the residual map of a fit (the caller may keep
    them: one step's fit after is the next one's before)."""
    out: dict[str, Any] = {"name": effect.name, "reduced_chi2": (before.reduced_chi2, after.reduced_chi2)}
    for key, state in (("before", before), ("after", after)):
        out[key] = {k: v.astype(np.float32) for k, v in image_maps(state.obs, state.rec.images).items()}
        out[key]["residual"] = mapped(state)
    out["per_frame"] = finding.per_frame
    out["components"] = effect.entry.components
    return out


def write_report(diag: Diagnosis, out_dir: Path, *, overwrite: bool = False) -> list[Path]:
    """Write ``diagnosis.json``, ``report.md``, ``residuals.png``, ``signatures.png``, one
    ``effect-<name>.png`` per detected effect and the files of the effects added (their findings' files: a motion
    mask, position errors, a pixel noise map).

    The folder is written as a unit (:func:`dfxcorr.io.atomic_folder`): every file into a new folder beside it,
    which then takes its place; the files of :data:`FIXED_FILES` a previous run left there go with it, other files
    stay. A reader finds this run's files or the previous run's, never a mix, also after an interrupt.
    """
    from ..check import check_folder
    from ..export import check_output

    out_dir = Path(out_dir)
    check_folder(out_dir)
    names = {k: k for k in ("diagnosis.json", "report.md", "residuals.png", "signatures.png")}
    names.update({c["name"]: _effect_picture(c["name"]) for c in diag.changes})
    files = {file: writer for finding in diag.findings().values() for file, writer in finding.files.items()}
    for name in [*names.values(), *files]:
        check_output(out_dir / name, overwrite=overwrite)
    with atomic_folder(out_dir, names={*FIXED_FILES, *names.values(), *files}, overwrite=overwrite) as tmp:
        paths = {k: tmp / name for k, name in names.items()}
        paths["diagnosis.json"].write_text(json.dumps(diag.to_json(), indent=2, default=float) + "\n")
        plots.plot_diagnosis(diag, paths["residuals.png"])
        plots.plot_signatures(diag.signatures, paths["signatures.png"], n_frames=diag.shape[0],
                              n_rows=diag.shape[1])
        for change in diag.changes:
            plots.plot_effect(change, paths[change["name"]])
        for file, writer in files.items():
            writer(tmp / file)
        paths["report.md"].write_text(_markdown(diag, out_dir))
    return [out_dir / name for name in [*names.values(), *files]]


def _markdown(diag: Diagnosis, out_dir: Path | None = None) -> str:
    lines = [f"# dfxcorr diagnose: {diag.scan}", "",
             (f"Base model: {', '.join(diag.base_model) or 'none (plain retrieval)'}. "
              f"Final model: {', '.join(diag.final_model) or 'none'}."), "",
             f"Reduced chi-square: {diag.initial_chi2:.4f} initially, {diag.final_chi2:.4f} at the end.", "",
             "![where the model and the data disagree](residuals.png)", "",
             ("Top row: mean squared standardized residual per pixel before and after (1 = photon noise)"
              + (f", on {diag.band} (diagnose.max_held_samples: the per-pixel tests hold that band; the fit and "
                 f"the residual signatures see columns spread over the detector)" if diag.band else "")
              + ". Below: the same by frame, lateral position, fringe phase and expected count."), "",
             ("| effect | detected | identifiable | statistic | dof | p-value | delta chi2 | reduced chi2 after "
              "| replicated | where | estimate |"), "|---|---|---|---|---|---|---|---|---|---|---|"]

    def fmt(v: float | None, f: str) -> str:
        return "" if v is None else format(v, f)

    for e in diag.effects:
        lines.append(f"| {e.name} | {'yes' if e.detected else 'no'} | {'yes' if e.identifiable else 'no'} | "
                     f"{e.statistic:.4g} | {e.dof} | {e.p_value:.3g} | {fmt(e.delta_chi2, '.4g')} | "
                     f"{fmt(e.reduced_chi2_after, '.4f')} | {_replicated(e)} | {e.verdict_text()} | "
                     f"{e.estimate or ''} |")
    lines += ["", f"Criterion: {diag.criterion}.", "",
              ("delta chi2 is the change of the Pearson chi-square sum when the effect was added; for detector_gain "
               "it is negative when the noise is below Poisson (the reduced chi-square then rises towards 1)."), "",
              ("Not identifiable means the Fisher information has directions of that effect's parameters without "
               "information beyond its gauge: the acquisition cannot tell it from the images or the model's other "
               "effects (paper Sec. II-F), so it is never reported as detected."), "",
              "## Unexplained", ""]
    if diag.unexplained and diag.final_chi2 > GROSS:
        lines += [(f"**The misfit is gross**: the final model leaves a reduced chi-square of {diag.final_chi2:.4g}, "
                   f"and no effect of the catalogue explains it. It is located below along its own axes; the physics "
                   "behind it is not named here (an effect that would only shave a little off it is not added)."), ""]
    if diag.unexplained:
        lines += [(f"The final model still leaves {len(diag.unexplained)} significant residual signature(s) that no "
                   "catalogue effect explains (significant after Holm's correction over the signatures tested; the "
                   "model is not complete here, whatever the reduced chi-square says):"), "",
                  "| axis | statistic | dof | p-value | where | description |", "|---|---|---|---|---|---|"]
        lines += [f"| {u.axis} | {u.statistic:.4g} | {u.dof} | {u.p_value:.3g} | {u.where} | {u.description} |"
                  for u in diag.unexplained]
    else:
        lines += ["None: no residual signature of the final fit is significant."]
    lines += ["", "![residual signatures of the final fit](signatures.png)", "",
              ("Residual signatures of the final fit on its own columns: per bin, the excess of the squared "
               "(variance) or plain (mean) standardized residual over what noise leaves after the fit took its "
               "share (3 image unknowns per pixel, the per-frame parameters' leverage), in units of its standard "
               "deviation; bins beyond 3 sigma in red, panel titles in red where the signature is significant."), ""]
    if diag.changes:
        lines += ["## What each detected effect changed", ""]
        for c in diag.changes:
            lines += [f"![adding {c['name']}]({_effect_picture(c['name'])})", ""]
        lines += [("Per effect, in the order added: the differential-phase and dark-field images of the fit before "
                   "and after adding it, and their difference; the residual per pixel before and after; its "
                   "per-frame estimate against frame where it has one."), ""]
    if diag.motion_mask.any():
        lines += [f"The pixels taken as moving are in motion_mask.tif ({int(diag.motion_mask.sum())} pixels).", ""]
    sets = reconstruct_settings(diag, out_dir=out_dir)
    lines += ["To reconstruct with the final model:", "",
              f"    dfxcorr reconstruct {shlex.quote(diag.scan)} -o result.h5"
              + "".join(f" --set {shlex.quote(s)}" for s in sets), ""]
    return "\n".join(lines)




def _replicated(e: EffectReport) -> str:
    """The report's 'replicated' cell: yes / no (p-value of the parts' difference), '' where not compared."""
    r = e.replication
    if r is None or r.replicated is None:
        return ""
    return f"{'yes' if r.replicated else 'no'} (p {r.p_value:.2g})"


def _pair(option: str) -> tuple[str, str]:
    key, value = option.split("=", 1)
    return key, value


def reconstruct_settings(diag: Diagnosis, *, out_dir: Path | None = None) -> list[str]:
    """The ``--set`` options that make ``reconstruct`` use the diagnosis's final model.

    The configuration the diagnosis ran with (every option that differs from the defaults, its ``-c`` files'
    and ``--set`` options alike), then each recommended finding's options over it (a finding that does not
    replicate is left out), and the paper's effects the final model lacks switched off. ``out_dir``: where
    :func:`write_report` put the findings' files (default: the current directory).
    """
    folder = Path(out_dir or ".")
    options: dict[str, str] = {}
    for s in C.as_sets(diag.cfg, skip=("diagnose",)):
        key, value = _pair(s)
        options[key] = value
    kept = {e.name for e in diag.effects if e.recommended}
    for name, finding in diag.findings().items():
        if name in kept:
            options.update(_pair(o.text(folder)) for o in finding.options)
    # the configured channel effects that the final model does not hold, or holds only by a finding that did not
    # replicate (the paper's three are on by default; with --base none the configuration's others too)
    findings = diag.findings()
    for name in CATALOGUE:
        config = effect(name).config
        if config is None or C.get(diag.cfg, config) is False:
            continue
        if name not in diag.final_model or (name in findings and name not in kept):
            options[config] = "false"
    return [f"{k}={v}" for k, v in options.items()]
