"""Model-discrepancy diagnosis: where does a recording disagree with the model, and which physics is missing?

Each round fits the current model, then tests every catalogue effect the model lacks, each by its own
test (:mod:`dfxcorr.effects`: efficient-score tests of the channel effects, per-pixel chi-squares for sample
motion, a likelihood-ratio test of the noise model, direct measurements of detector lag and reference
offsets, ...). The significant candidates are tried in turn by a trial refit, and one is added only if it
explains the misfit's signature: the residual signatures of the fit (:mod:`dfxcorr.analysis.signatures`)
that were significant must lose a set share of their excess (:mod:`dfxcorr.analysis.loop`). Signatures still
significant at the end are the report's ``unexplained`` entries (:mod:`dfxcorr.analysis.report`).

This module runs it: it holds the prepared scan and makes every fit the loop asks for from a
:class:`~dfxcorr.effects.base.Hypothesis`, a value; the observations of a hypothesis are made afresh from
the prepared scan, so a rejected trial leaves nothing to undo.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from .. import config as C
from ..align import realign, subsample_columns
from ..check import require_residuals
from ..effects import REGISTRY
from ..effects.base import Consistency, EffectBase, Hypothesis, Params, Realign, State, Test, Unexplained
from ..effects.residuals import image_leverage
from ..fit import fit_vibrations
from ..frames import well_determined
from ..io import Scan
from ..observations import Observations
from ..planning import column_step, resolve_effects, visibility_unidentifiable
from ..preparation import Prepared, prepare
from ..progress import stage
from ..retrieve import Retrieval, retrieve
from . import loop
from .loop import GROSS
from .replication import Part, replicate
from .report import Diagnosis, EffectReport, Verdict, change_picture, residual_map, residuals
from .signatures import signatures

log = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(frozen=True, eq=False)
class Fitted:
    """A hypothesis fitted: its parameters and their standard errors, chi-square, retrieval and residual
    signatures (at family-wise false-alarm probability ``alpha``), and the samples it was fitted on (the held
    columns, :func:`held_band`, and the fit's columns); values that tests compute from it are kept with it
    (:meth:`cached`)."""

    hypothesis: Hypothesis
    params: Params
    uncertainty: Params
    chi2: float
    reduced_chi2: float
    rec: Retrieval
    alpha: float
    obs: Observations
    fit_obs: Observations
    fit_rec: Retrieval
    _cache: dict[Hashable, Any] = field(default_factory=dict, repr=False)

    def release(self) -> None:
        """Drop the values tests computed from it (a fit the loop moved on from: no round tests it again; what the
        report asks of it later is computed again)."""
        self._cache.clear()

    @property
    def signatures(self) -> list[dict[str, Any]]:
        """The residual signatures of the fit, made when first asked for: a trial that is refined or settled again,
        and a fit on part of the detector, are never judged on theirs."""
        return self.cached(_signatures)

    def cached(self, make: Callable[..., T], *args: np.ndarray) -> T:
        """``make(self, *args)``, computed once for this state and these arguments (arrays, compared by value)."""
        key = (make, *((a.shape, a.tobytes()) for a in args))
        if key not in self._cache:
            self._cache[key] = make(self, *args)
        return self._cache[key]


def _signatures(state: Fitted) -> list[dict[str, Any]]:
    return signatures(state.fit_obs, state.params, alpha=state.alpha, rec=state.fit_rec,
                      leverage=image_leverage(state))


def _release(state: State) -> None:
    if isinstance(state, Fitted):
        state.release()


class Session:
    """One diagnosis of one prepared scan: what its effects may ask (:class:`~dfxcorr.effects.base.Context`) and
    the fits of the hypotheses the loop tries."""

    def __init__(self, prep: Prepared, cfg: dict[str, Any], timings: dict[str, Any],
                 registry: Mapping[str, EffectBase[Any]]):
        d = cfg["diagnose"]
        self.prep, self.cfg, self.timings, self.registry = prep, cfg, timings, registry
        # the per-pixel tests need every pixel: the diagnosis holds the scan's samples (the reconstruction streams
        # them), in float32 as a reconstruction does (the per-pixel tests take a run of columns at a time); a
        # band of columns in the middle where they would exceed diagnose.max_held_samples
        width, per_column = prep.shape[2], prep.store.samples_per_column()
        self.held_columns = held_band(width, per_column, most=d["max_held_samples"])
        self.obs = prep.observations(columns=None if self.held_columns.size == width else self.held_columns,
                                     dtype=np.float32)
        # the fit uses the tests' columns: a coarser fit's parameter noise would read as misfit; on a large scan
        # fewer of them (diagnose.max_samples) still hold more information than the tests need. In float64: a
        # fit under a grossly wrong noise model (reduced chi-square 100) depends on the samples' last bits
        self.fit_columns = subsample_columns(width, max(d["subsample"], column_step(width, per_column,
                                                                                     most=d["max_samples"])))
        self.fit_base = prep.observations(columns=self.fit_columns)
        self.fitted = np.isin(self.obs.columns, self.fit_columns)
        self.good_frames = well_determined(self.fit_base, cfg["fit"]["gauge_fraction"])
        self.stepping = prep.scan.is_stepping
        self.visibility_why = visibility_unidentifiable(prep.scan, prep.reference)
        self._prepared: dict[Hashable, Prepared] = {}
        self._aligned: dict[Hashable, tuple[Observations, Observations]] = {}
        self._values: dict[Hashable, Any] = {}

    def corrected(self, hypothesis: Hypothesis) -> Prepared:
        key = hypothesis.corrections
        if key not in self._prepared:
            self._prepared[key] = self.prep.corrected((self.registry[name], setting) for name, setting in key)
        return self._prepared[key]

    def cached(self, make: Callable[[Prepared], T], hypothesis: Hypothesis, key: Hashable = None) -> T:
        """``make`` of the hypothesis's corrected scan, once per corrected scan (and ``key``)."""
        at = (make, hypothesis.corrections, key)
        if at not in self._values:
            self._values[at] = make(self.corrected(hypothesis))
        return self._values[at]

    def realigner(self, hypothesis: Hypothesis) -> Realign:
        prep = self.corrected(hypothesis)
        return lambda like, shift: realign(prep.store, prep.reference, like, shift)

    def observe(self, hypothesis: Hypothesis) -> tuple[Observations, Observations]:
        """The samples of the held columns (every column, or the band of :func:`held_band`) and of the fit's columns
        under a hypothesis.

        As in reconstruct: the tests count the region of interest, the fit also the samples without fringe
        (they monitor dose and background); the hypothesis's moving pixels count in neither, nor do the samples
        the preparation left out (detector faults).
        """
        key = (hypothesis.corrections, hypothesis.shift.tobytes())
        if key not in self._aligned:
            moved = hypothesis.corrections or np.any(hypothesis.shift)
            # the current alignment and a trial's: older ones are not asked for again
            self._aligned = {k: v for k, v in list(self._aligned.items())[-1:]}
            # the states of one alignment share their samples, and with the prepared scan's those that a correction
            # leaves as they are
            prep = self.corrected(hypothesis)

            def realigned(like: Observations) -> Observations:
                return realign(prep.store, prep.reference, like, hypothesis.shift, base=self.prep.store)

            self._aligned[key] = (realigned(self.obs), realigned(self.fit_base)) if moved else (self.obs, self.fit_base)
        every, fit_columns = self._aligned[key]
        base, fit_obs = every.with_noise(hypothesis.noise), fit_columns.with_noise(hypothesis.noise)
        obs = replace(base, use=base.use & base.in_roi & ~base.pixel_mask(hypothesis.motion))
        return obs, replace(fit_obs, use=fit_obs.use & ~fit_obs.pixel_mask(hypothesis.motion))

    def fit(self, hypothesis: Hypothesis, start: Params, label: str, *, part: Part | None = None) -> Fitted:
        """Fit a hypothesis (from ``start``, or afresh where empty): its chi-square and residual signatures; on the
        samples of one ``part`` of the detector only, where given (:mod:`dfxcorr.analysis.replication`)."""
        obs, fit_obs = (_within(o, part) for o in self.observe(hypothesis))
        model, f = list(hypothesis.effects), self.cfg["fit"]
        params: Params = {}
        unc: Params = {}
        with stage(f"{label}: fit {'+'.join(model) or 'images only'}", self.timings):
            if model:
                # after the first round the fit starts next to its optimum: no staging against local minima
                warm = bool(start)
                fitted = fit_vibrations(fit_obs, effects=model, start=start, gtol=f["gtol"], staged=not warm,
                                        circmean_iterations=0 if warm else f["circmean_iterations"],
                                        reweight=0 if warm else 1, precondition=f["precondition"],
                                        preconditioner=f["preconditioner"], visibility_gauge=f["visibility_gauge"],
                                        visibility_quantile=f["visibility_quantile"],
                                        gauge_fraction=f["gauge_fraction"])
                params = {k: v for k, v in fitted.params.items() if k in model}
                unc = {k: v for k, v in fitted.uncertainty.items() if k in model}
            n_par = sum(np.size(p) for p in params.values())
            # images and chi-square of every column, no per-sample arrays: the states stay small (the tests that
            # need every column's expected counts make them a run of columns at a time)
            rec = retrieve(obs, params, n_frame_params=n_par, keep_expected=False)
            fit_rec = retrieve(fit_obs, params, keep_inverse=True)
        return Fitted(hypothesis, params, unc, rec.chi2_sum, rec.reduced_chi2, rec, self.cfg["diagnose"]["alpha"], obs,
                      fit_obs, fit_rec)


def _within(obs: Observations, part: Part | None) -> Observations:
    """The samples of ``obs`` in one part of the detector (all where None)."""
    if part is None:
        return obs
    if part.axis == "columns":
        return obs.subset(np.flatnonzero((obs.columns >= part.lo) & (obs.columns < part.hi)))
    inside = (obs.rows >= part.lo) & (obs.rows < part.hi)
    return replace(obs, use=obs.use & inside[obs.pixel][:, None])


def held_band(width: int, samples_per_column: int, *, most: float) -> np.ndarray:
    """The detector columns whose samples the per-pixel tests hold: every column, or where they would hold more
    than ``most`` samples, the contiguous band of as many columns as fit, in the middle of the detector."""
    n = min(max(int(most // max(samples_per_column, 1)), 4), width)
    start = (width - n) // 2
    return np.arange(start, start + n)


#: What a catalogue effect of another size along each axis of :meth:`EffectBase.consistency` suggests.
_SUSPECTS = {"count": ("expected count, dimmest", "a detector non-linearity or an additive artefact"),
             "row": ("detector row, top", "an artefact on some rows, as a ghost of an earlier frame"),
             "pixel": ("detector {along}, lowest index",
                       "a patch, as a moving part of the sample or a localised artefact, not a class of pixels "
                       "nor all of them")}


def _proxy(name: str, test: Test[Any], odd: Consistency) -> Unexplained:
    """The ``unexplained`` entry of a candidate refused as a proxy: its signature, located where its size changes."""
    strata, suspect = _SUSPECTS[odd.axis]
    strata = strata.format(along=odd.along or "")
    return Unexplained(odd.axis, odd.statistic, odd.dof, odd.p_value,
                       f"pixels in {len(odd.strata)} strata by {strata} first: size against the shared fit "
                       + ", ".join(f"{v:.2g}" for v in odd.strata),
                       f"the signature of {name} (S = {test.statistic:.4g}, dof {test.dof}), but of a size that "
                       f"changes {'across the detector' if odd.axis == 'pixel' else f'with the {odd.axis}'}: no "
                       f"catalogue effect ({suspect}?)")


def _not_added(name: str, test: Test[Any], out: loop.Outcome, *, alpha: float, tested: int) -> EffectReport:
    """The verdict on an effect tested and not added: why not."""
    verdict: Verdict
    blind = out.blind.get(name)
    held = out.held.get(name)
    if held is not None:
        verdict = "held: gross misfit" if held == "gross" else "explained by another"
        return EffectReport(name, False, bool(test.identifiable), test.statistic, int(test.dof), test.p_value,
                            verdict, explained_by=None if held == "gross" else held, excess=test.excess)
    if blind is not None:
        verdict = "explains, not identifiable" if blind.explains_misfit else "not identifiable"
    elif not test.identifiable:
        verdict = "not identifiable"
    elif name in out.inconsistent:
        verdict = "proxy"
    elif name in out.rejected:
        verdict = "raised chi-square" if out.rejected[name].astray else "rejected"
    elif test.log_p < np.log(alpha / tested) and not test.material:
        verdict = "not material"
    else:
        verdict = "not significant"
    return EffectReport(name, False, bool(test.identifiable), test.statistic, int(test.dof), test.p_value, verdict,
                        rejection=out.rejected.get(name), blind=blind,
                        refused=out.inconsistent[name][1] if name in out.inconsistent else None, excess=test.excess,
                        shared=test.shared)


def _once_per_state(make: Callable[[State], T]) -> Callable[[State], T]:
    """``make`` of a fit, made once per fit: the report draws a step's fit after as the next one's before."""
    kept: dict[int, T] = {}

    def once(state: State) -> T:
        # the states live in the outcome until the report is made: their ids stay theirs
        if id(state) not in kept:
            kept[id(state)] = make(state)
        return kept[id(state)]

    return once


def diagnose(scan: Scan | str | Path | Prepared, cfg: dict[str, Any] | None = None, *, base: str = "configured",
             registry: Mapping[str, EffectBase[Any]] = REGISTRY) -> Diagnosis:
    """Locate model-data mismatch, name the missing effects, add them and refit until nothing is left.

    Parameters
    ----------
    scan : Scan, path or Prepared
        Prepared by :func:`dfxcorr.preparation.prepare` (reference options, region of interest), as for
        a reconstruction.
    cfg : dict, optional
        Resolved configuration; its vibration section is the base model, its diagnose section the
        test settings.
    base : {'configured', 'none'}
        Start from the configured model, or from plain retrieval with no per-frame terms.
    registry : mapping
        The effects to test (default every effect of :data:`dfxcorr.effects.REGISTRY`).

    Returns
    -------
    Diagnosis
    """
    cfg = C.defaults() if cfg is None else cfg
    d = cfg["diagnose"]
    timings: dict[str, Any] = {}
    prep = scan if isinstance(scan, Prepared) else prepare(scan, cfg, effects=registry.values(), timings=timings)
    require_residuals(np.bincount(prep.store.row))
    session = Session(prep, cfg, timings, registry)
    J, H, W = prep.shape
    model = list(resolve_effects(cfg, prep.scan, prep.reference, session.fit_base)) if base == "configured" else []
    start = Hypothesis(tuple(model), prep.noise, np.zeros((H, W), bool), np.zeros(J))
    first = session.fit(start, {}, "round 0")
    located_once = _once_per_state(residuals)
    if session.held_columns.size < W:
        log.info("per-pixel tests on columns %d-%d of %d (diagnose.max_held_samples=%g); the fit on %d columns "
                 "spread over the detector", session.held_columns[0], session.held_columns[-1], W,
                 d["max_held_samples"], session.fit_columns.size)
    before = located_once(first)
    out = loop.run(registry, session, first, fit=session.fit, alpha=d["alpha"], explain_share=d["explain_share"],
                   proxy_spread=d["proxy_spread"], max_rounds=d["max_rounds"], timings=timings,
                   noise_first=d["order"] == "noise-first", superseded=_release)
    final = out.state

    def mapped(state: State) -> np.ndarray:
        # the first and the last fit are located for the report's residual pictures: their maps come with it
        located = state is first or state is final
        return located_once(state).pixel.astype(np.float32) if located else residual_map(state)

    mapped_once = _once_per_state(mapped)
    replicated = {}
    if d["replicate"] and out.steps:
        with stage("replication on halves of the detector", timings):
            # effects fitted together share directions that each half's fit leaves where its path ends: their
            # per-frame estimates differ there by more than the errors of the directions the data fix
            joint = {n: f"fitted together with {', '.join(m for m in s.names if m != n)}, with which it shares "
                        f"directions that neither half fixes: not compared" for s in out.steps if s.together
                     for n in s.names}
            joint.update({s.name: f"shares {s.test.shared} direction(s) with the model's effects, which each half "
                                  f"fixes where its fit's path ends: not compared" for s in out.steps if s.test.shared})
            replicated = replicate({n: registry[n] for s in out.steps for n in s.names}, session, final,
                                   lambda h, p, part: session.fit(h, p, f"replication: {part.label}", part=part),
                                   shape=prep.shape, rows=session.stepping, alpha=d["alpha"], skip=joint)
        for name, r in replicated.items():
            log.info("%s on halves of the detector: %s", name, r.why)
    effects, changes = [], []
    for step in out.steps:
        e, t = registry[step.name], step.test
        # the noise model is settled again in later trials: its finding is what the final model holds
        finding = e.accepted(session, step.before, final if e.policy.noise_model else step.after, t)
        beside = [(n, registry[n].accepted(session, step.before, step.after, out.tests[n])) for n in step.together]
        # one finding of several that this acquisition cannot tell apart: each alternative's estimate from its trial
        others = {n: registry[n].accepted(session, step.before, state, out.tests[n]).estimate
                  for n, state in step.alternatives}
        effects.append(EffectReport(step.name, True, True, t.statistic, int(t.dof), t.p_value, "added",
                                    delta_chi2=step.before.chi2 - step.after.chi2,
                                    reduced_chi2_after=step.after.reduced_chi2, finding=finding,
                                    replication=replicated.get(step.name), alternatives=tuple(others),
                                    alternative_estimates=others))
        # added in the same trial: each significant beyond the other (their delta chi-square is the pair's)
        effects += [EffectReport(n, True, True, out.tests[n].statistic, int(out.tests[n].dof), out.tests[n].p_value,
                                 "added", delta_chi2=step.before.chi2 - step.after.chi2,
                                 reduced_chi2_after=step.after.reduced_chi2, finding=f, replication=replicated.get(n))
                    for n, f in beside]
        changes.append(change_picture(e, step.before, step.after, finding, mapped=mapped_once))
    added = {n for s in out.steps for n in s.names}
    named_with = {n: s.name for s in out.steps for n, _ in s.alternatives}
    for n, t in sorted(out.tests.items(), key=lambda kv: -kv[1].statistic):
        if n in added:
            continue
        if n in named_with:
            effects.append(EffectReport(n, False, bool(t.identifiable), t.statistic, int(t.dof), t.p_value,
                                        "alternative", alternatives=(named_with[n],)))
        else:
            effects.append(_not_added(n, t, out, alpha=d["alpha"], tested=len(out.tests)))
    unexplained = [Unexplained(s["axis"], s["statistic"], s["dof"], s["p_value"], s["where"], s["description"])
                   for s in final.signatures if s["significant"]]
    # what a catalogue effect's test saw but the effect itself did not explain: its size changes across the recording
    unexplained += [_proxy(n, t, odd) for n, (t, odd) in out.inconsistent.items() if n not in added]
    # localised misfits that masking did not explain
    unexplained += [u for n, t in out.tests.items() if n not in added and t.dof and t.log_p < np.log(d["alpha"])
                    and (u := registry[n].unexplained(t)) is not None]
    criterion = (f"an effect is detected when its p-value beats Holm's threshold alpha / m (alpha = {d['alpha']}, "
                 f"m = effects tested in the round), it is identifiable, and, among those, it explains the most "
                 f"chi-square; structured effects first, then detector_gain (when the gain moves by more than "
                 f"{100 * d['min_gain_change']:.0f} %), then sample_motion ({d['min_pixels']} or more pixels in "
                 f"clusters of 3 whose per-pixel deviance has p < {d['motion_p']}, at most 10 % of the pixels and "
                 f"the largest group of them, grown by 2 pixels, at least half). A candidate is added only if it "
                 f"explains the misfit's signature: after a trial refit with it, the excess (statistic - dof) of "
                 f"the residual signatures that were significant (Holm, alpha = {d['alpha']}) must shrink by "
                 f"{100 * d['explain_share']:.0f} % or more, or one of them must become insignificant while the "
                 f"excess does not grow; otherwise it stays out of the model (its explained "
                 f"share is reported) and the next candidate is tried; nor if, fitted, its size differs between "
                 f"strata of the pixels by count or by row (significantly, and spanning more than "
                 f"{d['proxy_spread']:g} times its size): then it stands in for an effect in no catalogue and its "
                 f"signature is reported unexplained there. A trial of a mean effect settles the noise model already "
                 f"added again on its own fit. A significant effect that the acquisition "
                 f"cannot identify gets a trial refit first: if it explains the misfit so, the diagnosis stops "
                 f"there (naming a proxy would be the wrong physics). Candidates that share directions of their "
                 f"parameters are decided on each one's share beyond the other (Holm's first threshold): the one "
                 f"the data show, both fitted together, or one finding naming both. No trial may raise the reduced "
                 f"chi-square, and the noise model is not judged while the mean model is grossly off (reduced "
                 f"chi-square beyond {GROSS:g} with the residuals' mean significant). Every finding is refitted on "
                 f"disjoint halves of the detector; one whose halves disagree (p < {d['alpha']}) is not "
                 f"recommended. What stays significant is listed as unexplained")
    detected = [n for s in out.steps for n in s.names]
    return Diagnosis(scan=str(prep.path) if prep.path else prep.name, base_model=model,
                     initial_chi2=first.reduced_chi2, final_chi2=final.reduced_chi2, effects=effects,
                     final_model=model + [n for n in detected if n in final.hypothesis.effects]
                     + [n for n in detected if n not in final.hypothesis.effects],
                     before=before,
                     after=located_once(final),
                     params=final.params, criterion=criterion, rounds=out.rounds,
                     unexplained=sorted(unexplained, key=lambda u: u.p_value), signatures=final.signatures,
                     shape=prep.shape, final=final.hypothesis, start=start, cfg=cfg, registry=registry,
                     changes=changes, timings=timings,
                     tested_columns=(int(session.held_columns[0]), int(session.held_columns[-1]) + 1))
