"""The decision loop of the diagnosis: test, rank, trial refit, accept or reject, stop.

Each round tests every effect that applies and is not in the model yet (:meth:`EffectBase.test`). A
significant effect that the acquisition cannot identify is tried first: if a trial refit with it explains
the misfit, nothing is named in its place and the diagnosis stops there. Otherwise the significant
identifiable candidates (Holm's first threshold over the effects tested in the round) are tried in
turn (:func:`ranked`): each gets a trial refit (:meth:`EffectBase.trial`), and is added only if it explains
the misfit's signature (:func:`accepts`), does not raise the reduced chi-square and has one size across the
recording. Candidates that share directions of their parameters are decided together (:func:`confounded`);
the noise model is not judged while the mean model is grossly off (:func:`gross`). The loop stops when no
candidate qualifies.

Everything here is a decision on values: the fits are done by the ``fit`` the caller passes, so the
rules can be tested with made-up effects and fits.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..effects.base import Consistency, Context, EffectBase, Hypothesis, Pair, State, Test, dispersion
from ..progress import stage
from ..stats import chi2_tail

log = logging.getLogger(__name__)

#: fit(hypothesis, start parameters (empty: from scratch), label) -> the fitted state.
Fit = Callable[[Hypothesis, dict[str, np.ndarray], str], State]
#: A residual signature (:func:`dfxcorr.analysis.signatures.signatures`).
Signature = dict[str, Any]
Effects = Mapping[str, EffectBase[Any]]


@dataclass(frozen=True)
class Step:
    """One effect added: its test, the fits before and after, and the share of the signatures' excess it removed."""

    name: str
    test: Test[Any]
    before: State
    after: State
    share: float | None
    #: Candidates this acquisition cannot tell from it (their trial fits): the finding is "one of these".
    alternatives: tuple[tuple[str, State], ...] = ()
    #: Candidates added with it in one trial (each significant beyond the other, sharing directions with it).
    together: tuple[str, ...] = ()

    @property
    def names(self) -> tuple[str, ...]:
        return (self.name, *self.together)


@dataclass(frozen=True)
class Rejection:
    """A candidate a trial refit did not justify: the share of the signatures' excess it removed (None: none was
    significant), and whether the trial went astray (raised the reduced chi-square, to ``reduced_chi2_with``)."""

    share: float | None
    astray: bool
    reduced_chi2_with: float


@dataclass(frozen=True)
class Blind:
    """A significant effect this acquisition cannot identify, tried first: whether a trial refit with it explains the
    misfit (the share it removed, the reduced chi-square it reached), and whether the naming stopped there."""

    explains_misfit: bool
    explained_share: float | None
    reduced_chi2_with: float
    stopped: bool = False


@dataclass
class Outcome:
    """What the loop decided.

    Attributes
    ----------
    state : State
        The final fit.
    steps : list of Step
        The effects added, in order.
    tests : dict
        The last test of every effect tested, in the order first tested.
    rejected : dict of Rejection
        Candidates a trial refit did not justify in the last round.
    blind : dict of Blind
        Unidentifiable effects tried: whether and how far a trial refit with them explained the misfit.
    rounds : list of dict
    inconsistent : dict
        Candidates refused as proxies (:meth:`EffectBase.consistency`): their test and the consistency test.
    held : dict
        Significant candidates of the last round not tried, and why ('gross': the noise model while the mean model
        is grossly off; otherwise the candidate whose share beyond them explains what they share).
    """

    state: State
    steps: list[Step] = field(default_factory=list)
    tests: dict[str, Test[Any]] = field(default_factory=dict)
    rejected: dict[str, Rejection] = field(default_factory=dict)
    blind: dict[str, Blind] = field(default_factory=dict)
    rounds: list[dict[str, Any]] = field(default_factory=list)
    inconsistent: dict[str, tuple[Test[Any], Consistency]] = field(default_factory=dict)
    held: dict[str, str] = field(default_factory=dict)


def significant(tests: Mapping[str, Test[Any]], alpha: float) -> list[str]:
    """The candidates whose test beats Holm's first threshold alpha / m (m = candidates tested in the round)."""
    return [k for k, t in tests.items() if t.log_p < np.log(alpha / len(tests))]


def ranked(tests: Mapping[str, Test[Any]], effects: Effects, alpha: float, *, noise_first: bool = False) -> list[str]:
    """Significant, identifiable and material candidates in the order they are tried.

    By their policy's order, then by the chi-square they explain; the noise-model effects (by order) just before
    the first localised one: a global variance excess is modelled after the mean effects that explain more, and
    before localised outliers are judged against it. A significant localised test places them so even where what
    it flags is no candidate (not material: scattered pixels are outliers all the same). ``noise_first``: the
    noise-model effects before all others (the decisions must not depend on the order: a test runs both).
    """
    sig = [k for k in significant(tests, alpha) if tests[k].identifiable]
    main = sorted((k for k in sig if not effects[k].policy.noise_model),
                  key=lambda k: (effects[k].policy.order, -tests[k].explains))
    noise = sorted((k for k in sig if effects[k].policy.noise_model), key=lambda k: effects[k].policy.order)
    at = 0 if noise_first else next((i for i, k in enumerate(main) if effects[k].policy.localised), len(main))
    return [k for k in main[:at] + noise + main[at:] if tests[k].material]


def strongest_unidentifiable(tests: Mapping[str, Test[Any]], effects: Effects, alpha: float,
                             tried: Mapping[str, Blind]) -> str | None:
    """The significant effect this acquisition cannot identify whose policy tries it first
    (:attr:`Policy.first_when_unidentifiable`), not tried yet, that explains the most; or None."""
    cands = [k for k in significant(tests, alpha) if not tests[k].identifiable and k not in tried
             and effects[k].policy.first_when_unidentifiable]
    return max(cands, key=lambda k: tests[k].explains) if cands else None


Judge = Callable[[Signature], bool]

#: A reduced chi-square beyond this, with the residuals' mean significant or their tails heavy, is a gross misfit
#: of the mean model.
GROSS = 2.0
#: Kurtosis of the standardized residuals beyond which their tails are a mean misfit's, not a noise model's: a
#: misstated noise model scales them (kurtosis 3 for one scale, measured 7.5 with read noise 25 unstated at 40-2000
#: photons, 12 on a flat panel with its step errors unmodelled too), while a misfit of the mean concentrated in some
#: samples makes heavy tails (measured 37 with the frames in reversed order, 32 for a moving part of the sample).
HEAVY_TAILS = 25.0


def kurtosis(state: State) -> float:
    """The kurtosis of the standardized residuals of the fit's used samples of solved pixels (3 for Gaussian)."""
    obs, rec = state.fit_obs, state.fit_rec
    sel = obs.use & obs.gather_valid(rec.images.valid)
    z2 = ((obs.counts - rec.expected) ** 2 * rec.weights)[sel]
    m2 = float(np.mean(z2)) if z2.size else 0.0
    return float(np.mean(z2 ** 2)) / m2 ** 2 if m2 > 0 else 0.0


def gross(state: State) -> bool:
    """Whether the mean model is grossly off at ``state``: a reduced chi-square beyond :data:`GROSS` with a
    significant signature of the residuals' mean (by frame, or by frame and row) or tails heavier than any noise
    model gives (:data:`HEAVY_TAILS`). A noise model judged then would absorb the misfit (any misfit is matched by a
    variance large enough)."""
    if state.reduced_chi2 <= GROSS:
        return False
    return (any(s["significant"] and s["kind"] == "mean" for s in state.signatures)
            or kurtosis(state) > HEAVY_TAILS)


def _all(signature: Signature) -> bool:
    return True


def judge(effect: EffectBase[Any]) -> Judge:
    """The residual signatures a trial of ``effect`` is judged on.

    An effect must explain the signature that its own test is about, not just any misfit. The level of the
    residuals against the stated noise model (kind 'level') is the noise model's business: any other effect is
    never judged on it (while the noise model is off, every mean effect that takes variance out of the residuals
    would seem to make it worse, or a proxy would seem to explain it).
    """
    return _all if effect.policy.noise_model else (lambda s: s["kind"] != "level")


def _excess(sigs: list[Signature], keys: set[tuple[str, str]]) -> float:
    return sum(max(s["statistic"] - s["dof"], 0.0) for s in sigs if (s["axis"], s["kind"]) in keys)


def explained_share(before: list[Signature], after: list[Signature], judged: Judge = _all) -> float | None:
    """Share of the excess chi-square of the significant signatures (those ``judged`` on) that a change removed
    (None: none significant)."""
    keys = {(s["axis"], s["kind"]) for s in before if s["significant"] and judged(s)}
    if not keys:
        return None
    return 1.0 - _excess(after, keys) / _excess(before, keys)


def silences(before: list[Signature], after: list[Signature], judged: Judge = _all) -> bool:
    """Whether a significant signature (of those ``judged`` on) became insignificant."""
    now = {(s["axis"], s["kind"]): s["significant"] for s in after}
    return any(s["significant"] and judged(s) and not now.get((s["axis"], s["kind"]), False) for s in before)


def accepts(before: list[Signature], after: list[Signature], *, explain_share: float, judged: Judge = _all) -> bool:
    """The acceptance rule: the trial removes at least ``explain_share`` of the excess of the significant
    signatures it is ``judged`` on, or silences one of them without adding excess (or none of them was
    significant to begin with: then its own test decides)."""
    share = explained_share(before, after, judged)
    return share is None or share >= explain_share or (share >= 0 and silences(before, after, judged))


def confirms(before: State, after: State, test: Test[Any], *, explain_share: float) -> bool:
    """The acceptance rule of an effect judged on its own signature: its trial lowers the chi-square (in units of
    the fit's dispersion, :func:`~dfxcorr.effects.base.dispersion`) by at least ``explain_share`` of what its test
    said it would: the likelihood ratio confirms the score."""
    return (before.chi2 - after.chi2) / dispersion(before) >= explain_share * test.statistic


def round_tests(effects: Effects, ctx: Context, state: State, done: list[str],
                seconds: dict[str, float] | None = None) -> tuple[dict[str, Test[Any]], np.ndarray]:
    """Every applicable effect's test at ``state``, those in ``done`` left out, in the registry's order; and the
    pixels flagged by the localised effects, which are tested first: what they flag is left out of the others'
    tests. ``seconds`` accumulates each effect's test time under 'test <name>' (where the time goes).
    """
    seconds = {} if seconds is None else seconds

    def timed(n: str, e: EffectBase[Any], flagged: np.ndarray) -> Test[Any] | None:
        t0 = time.perf_counter()
        out = e.test(ctx, state, flagged)
        seconds[f"test {n}"] = seconds.get(f"test {n}", 0.0) + time.perf_counter() - t0
        return out

    localised = {n: timed(n, e, state.hypothesis.motion) for n, e in effects.items()
                 if e.policy.localised and n not in done}
    masks = [t.flagged for t in localised.values() if t is not None and t.flagged is not None]
    flagged = np.logical_or.reduce(masks) if masks else state.hypothesis.motion
    tests = {}
    for n, e in effects.items():
        t = localised.get(n) if n in localised else (timed(n, e, flagged) if n not in done else None)
        if t is not None:
            tests[n] = t
    return tests, flagged


@dataclass(frozen=True)
class Trial:
    """A trial refit and whether it went astray: an effect whose policy checks it (every effect but the noise
    model's) and whose fit, at the noise model it was tried under, raises the reduced chi-square (read on every
    column, the fit saw a few: an overfit or a fit gone astray). An astray trial's noise model is not settled
    again: that would hide the rise."""

    state: State
    astray: bool


def _trial(effect: EffectBase[Any], ctx: Context, state: State, test: Test[Any], flagged: np.ndarray, *, fit: Fit,
           label: str, settle: Effects, alpha: float, together: tuple[EffectBase[Any], ...] = ()) -> Trial:
    """A trial refit with ``effect``, then its refinements: each a refit at the estimate its test gives on the
    trial's own fit (an estimate from a fit under the wrong model is biased, most so for the noise model).

    ``settle``: the noise effects in the model, whose estimates are settled again on the trial's fit where their
    test (at ``alpha``) says they moved materially: a noise model estimated while a mean effect was missing is too
    wide once it is added (without this, a 5-step flat panel whose noise model is decided first ends at a reduced
    chi-square of 0.93 with four signatures unexplained), so the decisions do not depend on the order."""
    policy = effect.policy
    hypothesis = effect.trial(ctx, state, test)
    for other in together:
        hypothesis = other.joined(hypothesis) or hypothesis
    trial = fit(hypothesis, {} if policy.fresh_start else state.params, label)
    for k in range(policy.refinements):
        again = effect.test(ctx, trial, flagged)
        if again is None:
            break
        trial = fit(effect.trial(ctx, trial, again), {} if policy.fresh_start else trial.params,
                    f"{label} (refined {k + 1})")
    # a correction of the data themselves (a fresh start) compares two data sets: its chi-square may rise by its
    # noise (5 sigma of a reduced chi-square of these dof); a model's term on the same data may not rise at all
    slack = 5 * np.sqrt(2 / max(state.chi2 / max(state.reduced_chi2, 1e-300), 1.0)) if policy.fresh_start else 0.0
    if policy.astray_check and trial.reduced_chi2 > state.reduced_chi2 + slack:
        return Trial(trial, True)
    for name, noise in settle.items():
        moved = noise.test(ctx, trial, flagged)
        if moved is not None and moved.material and moved.log_p < np.log(alpha):
            log.info("%s: %s moved on the trial's fit (S = %.4g): settled again", label, name, moved.statistic)
            trial = fit(noise.trial(ctx, trial, moved), {} if noise.policy.fresh_start else trial.params,
                        f"{label} ({name} settled)")
    return Trial(trial, False)


def _blind(effect: EffectBase[Any], ctx: Context, state: State, test: Test[Any], flagged: np.ndarray, *, fit: Fit,
           label: str, settle: Effects, alpha: float, explain_share: float) -> Blind:
    """A trial refit with an effect this acquisition cannot identify (:func:`_trial`): whether it explains the
    misfit (removes at least ``explain_share`` of the excess of the signatures it is judged on)."""
    tried = _trial(effect, ctx, state, test, flagged, fit=fit, label=label, settle=settle, alpha=alpha).state
    share = explained_share(state.signatures, tried.signatures, judge(effect))
    return Blind(share is None or share >= explain_share, share, tried.reduced_chi2)


def _admitted(effect: EffectBase[Any], ctx: Context, before: State, trial: Trial, test: Test[Any], *,
              explain_share: float, alpha: float, proxy_spread: float) -> tuple[bool, Consistency | None]:
    """Whether a trial justifies adding ``effect``: not astray, explains the signatures it is judged on
    (:func:`accepts`; for an effect judged on its own signature, :func:`confirms`), and of one size across the
    recording (:meth:`EffectBase.consistency`: refused as a proxy where that test is significant and its sizes span
    more than ``proxy_spread``). Also the consistency test that refused it, or None."""
    if trial.astray:
        return False, None
    if effect.policy.own_signature:
        if not confirms(before, trial.state, test, explain_share=explain_share):
            return False, None
    elif not accepts(before.signatures, trial.state.signatures, explain_share=explain_share, judged=judge(effect)):
        return False, None
    odd = effect.consistency(ctx, before, trial.state)
    if odd is not None and odd.spread > proxy_spread and odd.log_p < np.log(alpha):
        return False, odd
    return True, None


def _settled(name: str, effects: Effects, steps: list[Step]) -> dict[str, EffectBase[Any]]:
    """The noise-model effects in the model that a trial of ``name`` settles again (none for one's own trial)."""
    if effects[name].policy.noise_model:
        return {}
    return {s.name: effects[s.name] for s in steps if effects[s.name].policy.noise_model}


def contenders(first: str, later: list[str], tests: Mapping[str, Test[Any]], effects: Effects, *,
               close: float = 0.9) -> list[str]:
    """The candidates of ``later`` that the tests can hardly tell from ``first``: of the same policy, explaining at
    least ``close`` times as much (collinear effects: on a phase-stepping flat panel a per-step curvature x^2 phi2_j
    took 326 of the 321 chi-square that the true per-step phase offsets explain)."""
    e, t = effects[first], tests[first]
    return [n for n in later if effects[n].policy == e.policy and tests[n].explains >= close * t.explains]


def confounded(name: str, order: list[str], tests: Mapping[str, Test[Any]], effects: Effects, ctx: Context,
               state: State, *, threshold: float) -> tuple[str, list[str], list[str], dict[str, Pair]]:
    """Of ``name`` and the later candidates of ``order`` that share directions of their parameters with it
    (:meth:`EffectBase.beside`: each alone is determined, together some directions are not), the one to try, the
    ones it cannot be told from, the ones tried together with it, and the pairs looked at.

    Decided on what the data identify of each beyond the other (its share of their joint statistic beyond the
    other's test alone, significant where its log p is below ``threshold``), never on which explains a little more:
    where only the other's share is significant, the other is tried instead; where neither is, they are one finding
    ("one of these"); where both are, both are tried together (one at a time, each would absorb what the other
    shares with it, and be refused as of another size in other strata). Fitted together, the shared directions stay
    where the fit starts them (a gauge).
    """
    others: list[str] = []
    pairs: dict[str, Pair] = {}
    both: list[str] = []
    for other in order[order.index(name) + 1:]:
        pair = effects[name].beside(ctx, state, other)
        if pair is None or pair.shared <= 0:
            continue
        pairs[other] = pair
        mine, theirs = (_significant(pair.beyond[n], threshold) for n in (name, other))
        log.info("%s and %s share %d direction(s): beyond the other %s S = %.4g (dof %d), %s S = %.4g (dof %d)",
                 name, other, pair.shared, name, *pair.beyond[name], other, *pair.beyond[other])
        if theirs and not mine:
            return confounded(other, [other, *[n for n in order if n not in (name, other)]], tests, effects, ctx,
                              state, threshold=threshold)
        if not theirs and not mine:
            others.append(other)
        if theirs and mine and effects[other].joined(state.hypothesis) is not None:
            both.append(other)
    return name, others, both, pairs


def _significant(statistic_dof: tuple[float, int], threshold: float) -> bool:
    statistic, dof = statistic_dof
    return dof > 0 and chi2_tail(statistic, dof)[1] < threshold


def _best_of(first: Step, others: list[str], tests: Mapping[str, Test[Any]], effects: Effects,
             ctx: Context, flagged: np.ndarray, *, fit: Fit, explain_share: float, label: str,
             settle: Effects, alpha: float, proxy_spread: float) -> Step:
    """Of an accepted candidate and its close contenders (same policy), the admitted one (:func:`_admitted`) whose
    trial fits best (least chi-square); each trial settles the noise model as ``first``'s did."""
    best = first
    for name in others:
        effect = effects[name]
        trial = _trial(effect, ctx, first.before, tests[name], flagged, fit=fit,
                       label=f"{label}: trial {name} (beside {first.name})", settle=settle, alpha=alpha)
        if trial.state.chi2 < best.after.chi2 and _admitted(effect, ctx, first.before, trial, tests[name],
                                                            explain_share=explain_share, alpha=alpha,
                                                            proxy_spread=proxy_spread)[0]:
            best = Step(name, tests[name], first.before, trial.state,
                        explained_share(first.before.signatures, trial.state.signatures, judge(effect)))
    return best


def run(effects: Effects, ctx: Context, start: State, *, fit: Fit, alpha: float, explain_share: float,
        proxy_spread: float, max_rounds: int, timings: dict[str, float] | None = None,
        noise_first: bool = False, superseded: Callable[[State], None] | None = None) -> Outcome:
    """Add effects to the model of ``start`` until no candidate explains what is left (see the module's text).

    ``proxy_spread``: a candidate whose consistency test is significant and whose sizes span more than this is
    refused as a proxy (:meth:`EffectBase.consistency`); ``timings`` receives the seconds of each round's tests;
    ``noise_first``: see :func:`ranked`; ``superseded``: called with each fit the loop moves on from (no round
    tests it again)."""
    out = Outcome(state=start)
    for rnd in range(max_rounds):
        state = out.state
        with stage(f"round {rnd}: tests", {} if timings is None else timings):
            tests, flagged = round_tests(effects, ctx, state, [n for s in out.steps for n in s.names],
                                         seconds=None if timings is None else timings)
        out.tests.update(tests)
        log.info("round %d: reduced chi-square %.4f; %s", rnd, state.reduced_chi2,
                 ", ".join(f"{k} S={t.statistic:.4g} (dof {t.dof}{'' if t.identifiable else ', n.i.'})"
                           for k, t in sorted(tests.items(), key=lambda kv: -kv[1].statistic)))
        blind: tuple[str, float] | None = None  # an unidentifiable effect that explains the misfit, and its share
        while (suspect := strongest_unidentifiable(tests, effects, alpha, out.blind)) is not None:
            # an effect this acquisition cannot determine may still be what the data show: if a trial refit with
            # it explains the misfit, no identifiable proxy may be named for it
            out.blind[suspect] = _blind(effects[suspect], ctx, state, tests[suspect], flagged, fit=fit,
                                        label=f"round {rnd}: trial {suspect} (not identifiable)",
                                        settle=_settled(suspect, effects, out.steps), alpha=alpha,
                                        explain_share=explain_share)
            if out.blind[suspect].explains_misfit:
                share = out.blind[suspect].explained_share
                blind = suspect, 1.0 if share is None else share
                break
        step = None
        order = ranked(tests, effects, alpha, noise_first=noise_first)
        out.held = {}
        if gross(state) and any(effects[n].policy.noise_model for n in order):
            log.info("round %d: the mean model is grossly off (reduced chi-square %.4g, the residuals' mean "
                     "significant): the noise model is not judged in this round", rnd, state.reduced_chi2)
            out.held = {n: "gross" for n in order if effects[n].policy.noise_model}
            order = [n for n in order if n not in out.held]
        threshold = float(np.log(alpha / max(len(tests), 1)))
        passed: set[str] = set()  # decided in a pair: tried in another's place, or one finding with it
        trial: Trial | None = None
        for i, first in enumerate(order):
            if first in out.rejected or first in passed:
                continue
            left = [n for n in order[i:] if n not in out.rejected and n not in passed]
            name, alternatives, together, pairs = confounded(first, left, tests, effects, ctx, state,
                                                             threshold=threshold)
            passed.update({first, *alternatives, *together} - {name})
            if first != name:
                out.held[first] = name
            effect = effects[name]
            trial = _trial(effect, ctx, state, tests[name], flagged, fit=fit,
                           label=f"round {rnd}: trial {'+'.join((name, *together))}",
                           settle=_settled(name, effects, out.steps), alpha=alpha,
                           together=tuple(effects[n] for n in together))
            share = explained_share(state.signatures, trial.state.signatures, judge(effect))
            # where an unidentifiable effect explains the misfit, only an effect that explains as much (within the
            # share a candidate must explain) is no proxy for it
            as_much = blind is None or (share if share is not None else 1.0) >= blind[1] - explain_share
            admitted, odd = _admitted(effect, ctx, state, trial, tests[name], explain_share=explain_share,
                                      alpha=alpha, proxy_spread=proxy_spread)
            if as_much and admitted:
                # one finding of several: each one's own trial fit, for its estimate
                others = tuple((n, _trial(effects[n], ctx, state, tests[n], flagged, fit=fit,
                                          label=f"round {rnd}: trial {n} (beside {name})",
                                          settle=_settled(n, effects, out.steps), alpha=alpha).state)
                               for n in alternatives)
                if alternatives:
                    log.info("round %d: %s or %s: this acquisition cannot tell them apart here", rnd, name,
                             " or ".join(alternatives))
                close = contenders(name, [n for n in left if n != name and n not in passed and n not in pairs], tests,
                                   effects)
                step = _best_of(Step(name, tests[name], state, trial.state, share, others, tuple(together)), close,
                                tests, effects,
                                ctx, flagged, fit=fit, explain_share=explain_share, label=f"round {rnd}",
                                settle=_settled(name, effects, out.steps), alpha=alpha,
                                proxy_spread=proxy_spread)
                break
            if odd is not None:
                where = f"detector {odd.along}" if odd.along else f"{odd.axis}s"
                log.info("round %d: %s has another size in pixels of other %s (S = %.4g, dof %d): what its test "
                         "sees is not this effect: rejected", rnd, name, where, odd.statistic, odd.dof)
                out.inconsistent[name] = (tests[name], odd)
            else:
                log.info("round %d: %s removes %.0f %% of the significant residual signatures' excess%s: rejected",
                         rnd, name, 100 * (share or 0.0), f", less than {blind[0]}"
                         if blind is not None and not as_much else (", and raises the reduced chi-square to "
                                                                    f"{trial.state.reduced_chi2:.4f}"
                                                                    if trial.astray else ""))
            out.rejected[name] = Rejection(share, trial.astray, trial.state.reduced_chi2)
        # a rejected trial's fit is not needed beyond its round: held, it would be one more fit beside the next
        # round's tests, at the diagnosis's peak memory
        trial = None
        if step is None:
            if blind is not None:
                out.blind[blind[0]] = replace(out.blind[blind[0]], stopped=True)
                log.warning("round %d: the misfit is what %s explains (reduced chi-square %.4f with it), which "
                            "this acquisition cannot identify: nothing else is named in its place", rnd, blind[0],
                            out.blind[blind[0]].reduced_chi2_with)
            break
        # a candidate that did not explain the misfit then may, now that the model changed (and one refused as a proxy
        # is retried, or no longer significant)
        out.rejected.clear()
        out.inconsistent.clear()
        out.steps.append(step)
        out.rounds.append({"round": rnd, "added": "+".join(step.names), "chi2_before": state.chi2,
                           "reduced_chi2_before": state.reduced_chi2, "reduced_chi2_after": step.after.reduced_chi2,
                           "delta_chi2": state.chi2 - step.after.chi2, "explained_share": step.share})
        log.info("round %d: adding %s", rnd, " and ".join(step.names))
        if superseded is not None:
            superseded(state)
        out.state = step.after
    return out
