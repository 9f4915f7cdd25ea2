"""The one interface of a catalogue effect, and the values the diagnosis passes between effects.

Every effect of ``spec/diagnosis.md`` is one object of a subclass of :class:`EffectBase`, in its own module of
this package (the model's channel effects share one, :mod:`dfxcorr.effects.channel`). The interface has three
lifecycles, each with typed values:

- the correction (what ``reconstruct`` and ``check`` use, :class:`dfxcorr.preparation.Correction`): what a
  configuration asks of the effect and how the one preparation applies it (:meth:`EffectBase.configured`,
  :meth:`EffectBase.apply`);
- the candidate (what the diagnosis's decision loop uses): its :class:`Policy` (a frozen value: how the loop
  orders, tries and judges it), its test at a fit (:meth:`EffectBase.test`, a :class:`Test` whose payload is
  the effect's own frozen type), the hypothesis of its trial refit (:meth:`EffectBase.trial`), and whether it
  is one effect across the recording (:meth:`EffectBase.consistency`, a :class:`Consistency`);
- the finding (what the report renders): :meth:`EffectBase.accepted` returns a frozen :class:`Finding`
  (where, the estimate, its keys of ``diagnosis.json``, the ``reconstruct`` options, its files, its per-frame
  estimate), and :meth:`EffectBase.measure` its estimate with standard errors at any fit (replication).

A :class:`Hypothesis` is a value: what the model holds (its channel effects), the noise model, the pixels left
out, where the flat field is read and the corrections of the counts. A trial returns a new one; a rejected trial
is dropped, never undone. Values computed once per fit live on the fitted state (:meth:`State.cached`), values
computed once per corrected scan on the context (:meth:`Context.cached`).
"""
from __future__ import annotations

from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Generic, Literal, Protocol, TypeVar

import numpy as np

from ..catalogue import Effect
from ..observations import Noise, Observations
from ..preparation import Correctable, Prepared
from ..retrieve import Retrieval
from ..stats import bonferroni, chi2_tail

P = TypeVar("P")
T = TypeVar("T")
K = TypeVar("K", bound=Hashable)

#: The per-frame and global parameters of a fit: effect name -> array.
Params = dict[str, np.ndarray]


@dataclass(frozen=True)
class Test(Generic[P]):
    """An effect's test at the current fit.

    Attributes
    ----------
    statistic : float
        Chi-square-like statistic (what noise alone gives about ``dof`` of).
    dof : int
    p_value, log_p : float
        Its tail probability under noise alone, and the log of it (exact where the p-value underflows).
    payload : P
        What its trial and finding need, of the effect's own type.
    identifiable : bool
        Whether this acquisition can determine the effect at all.
    excess : int
        Information-free directions of its parameters beyond its gauge (0 where identifiable).
    explains : float
        About how much chi-square adding it would remove (ranks candidates).
    material : bool
        Whether the change it would make matters (a gain within the practical floor does not).
    flagged : ndarray of bool, shape (H, W), or None
        The pixels a localised effect flags (left out of the other effects' tests in its round).
    shared : int
        Directions of its parameters that it shares with the model's effects (each alone determines them, together
        the data do not): it is tested and fitted in the rest, and its estimate there is the fit's gauge.
    """

    statistic: float
    dof: int
    p_value: float
    log_p: float
    payload: P
    identifiable: bool = True
    excess: int = 0
    explains: float = 0.0
    material: bool = True
    flagged: np.ndarray | None = None
    shared: int = 0


def chi2_test(statistic: float, dof: int, payload: P, **kw: Any) -> Test[P]:
    """A :class:`Test` whose statistic is chi-square with ``dof`` degrees of freedom under noise (p = 1 where
    dof = 0)."""
    p, log_p = chi2_tail(statistic, dof)
    return Test(float(statistic), int(dof), p, log_p, payload, **kw)


def strongest(found: Mapping[K, Test[P]]) -> tuple[K, Test[P]]:
    """The test of ``found`` with the least p-value, Bonferroni-corrected for how many were looked at: its key and
    the test with p (and log p) multiplied by that number (at most 1)."""
    keys = list(found)
    i, log_p = bonferroni([found[k].log_p for k in keys])
    t = found[keys[i]]
    return keys[i], replace(t, p_value=min(1.0, len(keys) * t.p_value), log_p=log_p)


#: Where a consistency test stratifies an effect's size.
ConsistencyAxis = Literal["count", "row", "pixel"]


@dataclass(frozen=True)
class Consistency:
    """Whether an effect, in the model of its trial fit, has one size across the recording.

    Attributes
    ----------
    statistic, dof, p_value, log_p
        The test of one size against sizes that differ between strata.
    axis : {'count', 'row', 'pixel'}
        What the strata are cut by: the pixels' expected count, their detector row, or (for a class of pixels)
        their position along the detector's lines.
    strata : tuple of float
        The size in each stratum relative to the shared fit's (1), in the strata's order.
    along : {'rows', 'columns'} or None
        For axis 'pixel': the detector lines the strata follow.
    """

    statistic: float
    dof: int
    p_value: float
    log_p: float
    axis: ConsistencyAxis
    strata: tuple[float, ...]
    along: Literal["rows", "columns"] | None = None

    @property
    def spread(self) -> float:
        """The largest difference between the strata's sizes."""
        return float(np.ptp(self.strata)) if self.strata else 0.0


@dataclass(frozen=True)
class Policy:
    """How the decision loop treats an effect as a candidate.

    Attributes
    ----------
    order : int
        Candidates are tried by order, then by the chi-square they explain; noise-model effects by order, as a
        group (see ``noise_model``).
    noise_model : bool
        It changes the noise model, not the mean: its candidates are tried together just before the first
        localised one (a global variance excess is modelled after the mean effects that explain more, and before
        localised outliers are judged against it); once added, later trials settle its estimate again; it is
        judged on the level of the residuals, which no other effect is.
    localised : bool
        It flags pixels: tested first in each round, and what it flags is left out of the other tests.
    pixelwise : bool
        What it finds belongs to some pixels (a moving part of the sample, a class of pixels), not to the whole
        detector: no part of the detector can replicate it.
    astray_check : bool
        A trial refit with it that raises the reduced chi-square (at the noise model it was tried under) went
        astray and is rejected.
    first_when_unidentifiable : bool
        Significant but not identifiable, it is tried before any identifiable candidate: if its trial explains
        the misfit, nothing is named in its place.
    fresh_start : bool
        Its trial changes the data or their relative weights: the trial fit starts afresh, as the first round did.
    refinements : int
        Refits after the trial, each at the estimate its test gives on the previous refit.
    own_signature : bool
        Its trial is judged on its own test rather than on the residual signatures: accepted where the trial's
        chi-square falls by the share of its statistic that the rule asks (the likelihood ratio confirms the
        score). For an effect whose correction leaves a model error of another kind on the same pixels (the
        images' pixel grid under a moving beam path), which the signatures would still show.
    """

    order: int = 2
    noise_model: bool = False
    localised: bool = False
    pixelwise: bool = False
    astray_check: bool = False
    first_when_unidentifiable: bool = False
    fresh_start: bool = False
    refinements: int = 0
    own_signature: bool = False


@dataclass(frozen=True)
class Pair:
    """Two candidates tested together at a fit: what the data say of each beyond the other.

    Attributes
    ----------
    beyond : mapping
        Each one's name -> its share of the joint statistic beyond the other's test alone, and that share's dof.
    shared : int
        Directions of their parameters that only the two together leave without information (each alone
        determines them; together the data cannot tell which of the two they belong to).
    """

    beyond: Mapping[str, tuple[float, int]]
    shared: int


def dispersion(state: State) -> float:
    """The fit's Pearson chi-square per degree of freedom, at least 1: what scales a standard error from the stated
    noise model to the data's own spread (quasi-likelihood; below 1 the stated model is kept)."""
    return max(state.reduced_chi2, 1.0)


#: The policy of a term of the expected count.
MEAN = Policy(astray_check=True, first_when_unidentifiable=True)

#: Writes one file of a report to the path given.
Writer = Callable[[Path], None]


@dataclass(frozen=True)
class Option:
    """A ``--set`` option of ``reconstruct``: ``key=value``, or where ``file`` the value is the name of a file the
    finding writes (the report puts its folder in front)."""

    key: str
    value: str
    file: bool = False

    def text(self, folder: Path) -> str:
        return f"{self.key}={folder / self.value if self.file else self.value}"


@dataclass(frozen=True)
class Estimate:
    """An effect's estimate at a fit and its standard errors, as arrays of one shape (a scalar: shape ())."""

    value: np.ndarray
    se: np.ndarray


@dataclass(frozen=True)
class Finding:
    """What an effect added to the model reports.

    Attributes
    ----------
    where : str
        Where in the recording its signature sits.
    estimate : str
        One line: its estimated size.
    values : mapping
        Its keys of the ``diagnosis.json`` entry (``spec/diagnosis.md``), beyond the common ones.
    options : tuple of Option
        What makes ``reconstruct`` use it.
    files : mapping
        File name -> writer: what the report writes for it.
    per_frame : ndarray, shape (J, n), or None
        Its per-frame estimate for the report's picture.
    """

    where: str
    estimate: str
    values: Mapping[str, Any] = field(default_factory=dict)
    options: tuple[Option, ...] = ()
    files: Mapping[str, Writer] = field(default_factory=dict)
    per_frame: np.ndarray | None = None


@dataclass(frozen=True)
class Unexplained:
    """A significant misfit that no effect explains: an ``unexplained`` entry of ``diagnosis.json``."""

    axis: str
    statistic: float
    dof: int
    p_value: float
    where: str
    description: str

    def to_json(self) -> dict[str, Any]:
        return {"axis": self.axis, "statistic": self.statistic, "dof": self.dof, "p_value": self.p_value,
                "where": self.where, "description": self.description}


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """What a fit of the diagnosis assumes beyond the prepared scan.

    Attributes
    ----------
    effects : tuple of str
        Channel effects in the model (:mod:`dfxcorr.catalogue`).
    noise : Noise
        The noise model (gain, electronic variance, per-pixel factors).
    motion : ndarray of bool, shape (H, W)
        Pixels left out (sample motion).
    shift : ndarray, shape (J,)
        Rows by which each frame reads the flat field off the prepared alignment.
    corrections : tuple of (str, setting)
        Corrections of the counts beyond the prepared (configured) ones, in order: each effect's
        :meth:`EffectBase.apply` with that setting (e.g. a detector lag fraction).
    """

    effects: tuple[str, ...]
    noise: Noise
    motion: np.ndarray
    shift: np.ndarray
    corrections: tuple[tuple[str, Any], ...] = ()

    def but(self, **changes: Any) -> Hypothesis:
        """The same hypothesis with some fields changed."""
        return replace(self, **changes)

    def without(self, name: str) -> Hypothesis:
        """The same hypothesis without the correction of the counts by the effect ``name``."""
        return replace(self, corrections=tuple(c for c in self.corrections if c[0] != name))


class State(Protocol):
    """A fitted hypothesis, as effects see it: the hypothesis, its parameters and their standard errors,
    chi-square (sum and reduced), residual signatures, the retrieval of the held columns (every column, or on a
    large scan a band of them: ``diagnose.max_held_samples``; images and chi-square, no per-sample arrays: a test
    that needs their expected counts makes them a run of columns at a time, :meth:`Observations.column_chunks`),
    the samples of the held columns and of the fit's columns under it, and the retrieval of the fit's columns
    (with the inverse normal matrices, expected counts and weights)."""

    @property
    def hypothesis(self) -> Hypothesis: ...
    @property
    def params(self) -> Params: ...
    @property
    def uncertainty(self) -> Params: ...
    @property
    def chi2(self) -> float: ...
    @property
    def reduced_chi2(self) -> float: ...
    @property
    def signatures(self) -> list[dict[str, Any]]: ...
    @property
    def rec(self) -> Retrieval: ...
    @property
    def obs(self) -> Observations: ...
    @property
    def fit_obs(self) -> Observations: ...
    @property
    def fit_rec(self) -> Retrieval: ...

    def cached(self, make: Callable[..., T], *args: np.ndarray) -> T:
        """``make(self, *args)``, computed once for this state and these arguments (``make`` a module-level function:
        its identity is the key; arrays compared by value)."""
        ...


#: (observations, shift (J,) rows) -> the same samples with the flat field read that far off the prepared alignment.
Realign = Callable[[Observations, "np.ndarray | float"], Observations]


class Context(Protocol):
    """What a diagnosis offers the effects it tests."""

    cfg: dict[str, Any]
    #: Columns of the observations that the per-frame parameters are fitted on, (C,) bool.
    fitted: np.ndarray
    #: Frames that set the gauge (:func:`dfxcorr.frames.well_determined`), (J,) bool.
    good_frames: np.ndarray
    #: A phase-stepping recording (no scan positions).
    stepping: bool
    #: Why visibility effects cannot be determined here (paper Sec. II-F), or None.
    visibility_why: str | None

    def corrected(self, hypothesis: Hypothesis) -> Prepared:
        """The prepared scan with the hypothesis's corrections of the counts applied."""
        ...

    def realigner(self, hypothesis: Hypothesis) -> Realign:
        """Realignment of samples of the hypothesis's corrected scan."""
        ...

    def cached(self, make: Callable[[Prepared], T], hypothesis: Hypothesis, key: Hashable = None) -> T:
        """``make(self.corrected(hypothesis))``, computed once per corrected scan (and ``key``)."""
        ...


class EffectBase(Generic[P]):
    """An effect of the catalogue: its entry, its correction, its candidacy in the diagnosis and its finding.

    Attributes
    ----------
    entry : Effect
        The catalogue entry (name, parameters, metadata).
    policy : Policy
        How the decision loop treats it.
    files : tuple of str
        Names of every file its finding may write (checked before a diagnosis computes anything).
    """

    entry: Effect
    policy: Policy = Policy()
    files: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        return self.entry.name

    # ---- correction ------------------------------------------------------------------------------

    def configured(self, cfg: dict[str, Any], *, n_frames: int, detector: tuple[int, int]) -> Any:
        """What the configuration asks of this effect, read and checked before any computation (None: nothing)."""
        return None

    def apply(self, data: Correctable, setting: Any) -> Correctable:
        """``data`` with the configured ``setting`` (not None) applied (default: unchanged)."""
        return data

    # ---- candidate -------------------------------------------------------------------------------

    def test(self, ctx: Context, state: State, flagged: np.ndarray) -> Test[P] | None:
        """The effect's test at the fit ``state`` (None: does not apply to this acquisition or hypothesis).

        ``flagged`` (H, W) bool: pixels that a localised effect flagged in this round (left out of global
        variance tests: a localised misfit must not pose as a global one).
        """
        return None

    def trial(self, ctx: Context, state: State, test: Test[P]) -> Hypothesis:
        """The hypothesis a trial refit with this effect fits."""
        raise NotImplementedError(f"{self.name} has no trial")

    def consistency(self, ctx: Context, before: State, state: State) -> Consistency | None:
        """Whether the effect, in the model of its trial fit ``state`` (from ``before``), is one effect across the
        recording: of one size wherever the count or the detector row or column differs (None: not tested).

        A detector effect in no catalogue can leave the signature of a catalogue effect (a non-linearity a
        second harmonic, a ghost of an earlier frame a change of dose) but not with one size everywhere: a
        significant test whose sizes, estimated stratum by stratum, span more than ``diagnose.proxy_spread`` the
        loop refuses as a proxy, and its signature is reported as unexplained.
        """
        return None

    def beside(self, ctx: Context, state: State, other: str) -> Pair | None:
        """This effect and the candidate ``other`` tested together at the fit ``state`` (None: not tested so)."""
        return None

    def joined(self, hypothesis: Hypothesis) -> Hypothesis | None:
        """``hypothesis`` (another candidate's trial) with this effect added too, for a trial of both together
        (None: it cannot be added so)."""
        return None

    def unexplained(self, test: Test[P]) -> Unexplained | None:
        """The ``unexplained`` entry of a significant test of it that was not added (a localised misfit), or None."""
        return None

    # ---- finding ---------------------------------------------------------------------------------

    def accepted(self, ctx: Context, before: State, after: State, test: Test[P]) -> Finding:
        """What it reports once added (``after``: the final state for a noise-model effect, which later trials
        settle again)."""
        raise NotImplementedError(f"{self.name} has no finding")

    def measure(self, ctx: Context, state: State) -> Estimate | None:
        """Its estimate and standard errors in a fit whose model holds it (None: not measurable by itself)."""
        return None
