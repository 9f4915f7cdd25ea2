"""The diagnosis's report: ``diagnosis.json`` (``spec/diagnosis.md``), ``report.md``, pictures and the files of
the effects added, and the ``reconstruct`` command that uses the final model."""
from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import plots
from ..catalogue import PAPER_MODEL, effect
from ..effects import REGISTRY
from ..effects.base import EffectBase, Hypothesis, fit_counts
from ..io import atomic_folder
from ..retrieve import image_maps
from .signatures import Residuals, locate


@dataclass
class EffectReport:
    """One catalogue effect's verdict (the keys of ``spec/diagnosis.md``)."""

    name: str
    detected: bool
    identifiable: bool
    statistic: float
    dof: int
    p_value: float
    delta_chi2: float | None = None
    reduced_chi2_after: float | None = None
    where: str | None = None
    estimate: str | None = None
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        d = {k: v for k, v in asdict(self).items() if k != "extra" and v is not None}
        # keys with a leading underscore are for the effect's own files, not the report
        d.update({k: v for k, v in self.extra.items() if not k.startswith("_")})
        return d


@dataclass
class Diagnosis:
    """The outcome of :func:`dfxcorr.analysis.diagnose.diagnose`.

    ``final`` is the final model's hypothesis (its effects, noise model, pixels left out, alignment and
    corrections of the counts); ``start`` the one the diagnosis began with (the configuration's); ``cfg`` the
    resolved configuration it ran with; ``registry`` the effects it tested.
    """

    scan: str
    base_model: list
    initial_chi2: float
    final_chi2: float
    effects: list
    final_model: list
    before: Residuals
    after: Residuals
    params: dict
    criterion: str
    rounds: list
    unexplained: list
    signatures: list
    shape: tuple
    final: Hypothesis
    start: Hypothesis
    cfg: dict
    registry: Mapping[str, EffectBase]
    changes: list = field(default_factory=list)
    #: Seconds of each stage (load, align, every fit and its tests), as logged.
    timings: dict = field(default_factory=dict)
    #: The detector columns [first, stop) the per-pixel tests and residual maps saw (``diagnose.max_held_samples``).
    tested_columns: tuple = (0, 0)

    @property
    def band(self) -> str:
        """'' where every column was tested pixel by pixel, else which were."""
        first, stop = self.tested_columns
        return "" if stop - first >= self.shape[2] else f"columns {first}-{stop - 1} of {self.shape[2]}"

    @property
    def gain(self) -> float:
        return self.final.noise.gain

    @property
    def electronic(self) -> float:
        return self.final.noise.electronic

    @property
    def motion_mask(self) -> np.ndarray:
        return self.final.motion

    @property
    def pixel_noise(self) -> np.ndarray | None:
        """The per-pixel variance factors where the diagnosis changed them, else None."""
        factors = self.final.noise.factors
        return None if factors is self.start.noise.factors else factors

    def extras(self) -> dict[str, dict | None]:
        """Every registered effect -> the report keys of its entry where it was added, else None."""
        found = {e.name: e.extra for e in self.effects if e.detected}
        return {name: found.get(name) for name in self.registry}

    def to_json(self) -> dict:
        """The ``diagnosis.json`` document of ``spec/diagnosis.md`` (version 2 keys)."""
        return {"format": "dfxcorr-diagnosis", "format_version": 2, "scan": self.scan, "base_model": self.base_model,
                "reduced_chi2": {"initial": self.initial_chi2, "final": self.final_chi2},
                "effects": [e.to_json() for e in self.effects], "final_model": self.final_model,
                "unexplained": self.unexplained, "criterion": self.criterion, "rounds": self.rounds,
                "tested_columns": list(self.tested_columns)}


def _effect_picture(name: str) -> str:
    return f"effect-{name}.png"


#: Every file the report may write, each name known before the diagnosis runs: its own, one picture per registered
#: effect (``effect-<name>.png``, where the effect is added), and the files the effects write when added.
FIXED_FILES = ("diagnosis.json", "report.md", "residuals.png", "signatures.png",
               *(_effect_picture(name) for name in REGISTRY),
               *(f for e in REGISTRY.values() for f in e.files))


def residuals(state) -> Residuals:
    """Where the fit ``state`` and its observations disagree (:func:`dfxcorr.analysis.signatures.locate`)."""
    return locate(state.obs, state.params, state.rec.images, counts=fit_counts(state))


def change_picture(effect: EffectBase, before, after, extra: dict, *,
                   located: Callable[[Any], Residuals] = residuals) -> dict:
    """What adding ``effect`` changed, for its picture: images and residual maps of the fits ``before`` and
    ``after`` (each on its own observations: the change may alter the data or their noise model) (H, W), and
    its per-frame estimate (J, n) where it has one. ``located``: the residuals of a fit (the caller may keep
    them: one step's fit after is the next one's before). The maps are float32: they are drawn, and six per step
    in float64 were the largest item of a diagnosis's peak memory."""
    out: dict[str, Any] = {"name": effect.name, "reduced_chi2": (before.reduced_chi2, after.reduced_chi2)}
    for key, state in (("before", before), ("after", after)):
        out[key] = {k: v.astype(np.float32) for k, v in image_maps(state.obs, state.rec.images).items()}
        out[key]["residual"] = located(state).pixel
    out["per_frame"] = effect.per_frame(extra, after.params)
    out["components"] = effect.entry.components
    return out


def write_report(diag: Diagnosis, out_dir: Path, *, overwrite: bool = False) -> list[Path]:
    """Write ``diagnosis.json``, ``report.md``, ``residuals.png``, ``signatures.png``, one
    ``effect-<name>.png`` per detected effect and the files of the effects added (their
    :meth:`~dfxcorr.effects.base.EffectBase.artefacts`: a motion mask, position errors, a pixel noise map).

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
    files = {file: writer for name, extra in diag.extras().items()
             for file, writer in diag.registry[name].artefacts(diag.final, extra, diag.cfg).items()}
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
              "| where | estimate |"), "|---|---|---|---|---|---|---|---|---|---|"]

    def fmt(v, f):
        return "" if v is None else format(v, f)

    for e in diag.effects:
        lines.append(f"| {e.name} | {'yes' if e.detected else 'no'} | {'yes' if e.identifiable else 'no'} | "
                     f"{e.statistic:.4g} | {e.dof} | {e.p_value:.3g} | {fmt(e.delta_chi2, '.4g')} | "
                     f"{fmt(e.reduced_chi2_after, '.4f')} | {_verdict_where(e)} | {e.estimate or ''} |")
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
        lines += [f"| {u['axis']} | {u['statistic']:.4g} | {u['dof']} | {u['p_value']:.3g} | {u['where']} | "
                  f"{u['description']} |" for u in diag.unexplained]
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
              f"    dfxcorr reconstruct {diag.scan} -o result.h5" + "".join(f" --set {s}" for s in sets), ""]
    return "\n".join(lines)


#: A final reduced chi-square beyond this, with signatures left unexplained, is reported as a gross misfit.
GROSS = 2.0


def _verdict_where(e: EffectReport) -> str:
    if e.extra.get("explains_misfit"):
        return (f"explains the misfit (a trial refit with it reaches reduced chi-square "
                f"{e.extra['reduced_chi2_with']:.4f}), but this acquisition cannot identify it: "
                + ("nothing else is named in its place" if e.extra.get("stopped") else
                   "an identifiable effect explained as much"))
    if "explained_share" in e.extra:
        return (f"significant, but a trial refit removes only {100 * e.extra['explained_share']:.0f} % of the "
                f"signatures' excess: not added")
    return e.where or ""


def reconstruct_settings(diag: Diagnosis, *, out_dir: Path | None = None) -> list[str]:
    """The ``--set`` options that make ``reconstruct`` use the diagnosis's final model.

    ``out_dir``: where :func:`write_report` put the effects' files (default: the current directory).
    """
    out_dir = Path(out_dir or ".")
    extras = diag.extras()
    # the channel effects in the order they were added, the paper's left out, then the others in registry order
    added = [n for n in diag.final_model if n in extras and diag.registry[n].role == "mean"]
    sets = [s for n in added for s in diag.registry[n].settings(diag.cfg, diag.final, extras[n], out_dir)]
    sets += [f"{effect(n).config}=false" for n in PAPER_MODEL if n not in diag.final_model]
    sets += [s for n, e in diag.registry.items() if e.role != "mean"
             for s in e.settings(diag.cfg, diag.final, extras[n], out_dir)]
    return sets
