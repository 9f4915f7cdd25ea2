"""Effects as one mechanism: the catalogue in one place, layers that point down, the decision loop on values.

The loop's rules are tested here with made-up effects and fits (milliseconds); a toy effect added to a
copy of the registry goes the whole way through ``diagnose`` and its report.
"""
from __future__ import annotations

import ast
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pytest

from dfxcorr import config as C
from dfxcorr.analysis import loop
from dfxcorr.analysis.diagnose import diagnose
from dfxcorr.analysis.report import write_report
from dfxcorr.catalogue import PAPER_MODEL, Effect
from dfxcorr.effects import REGISTRY
from dfxcorr.effects.base import MEAN, Consistency, EffectBase, Finding, Hypothesis, Pair, Policy, chi2_test
from dfxcorr.observations import Noise
from dfxcorr.preparation import Correctable
from dfxcorr.sim import simulate as S
from dfxcorr.stats import holm

from conftest import ROOT, sim_config

PACKAGE = ROOT / "dfxcorr"


# --------------------------------------------------------------------------------------------------
# One place per effect, layers pointing down
# --------------------------------------------------------------------------------------------------


def _string_constants(path: Path):
    """The string constants of a module that are not docstrings."""
    tree = ast.parse(path.read_text())
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and n.body and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    return [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
            and id(n) not in docs]


def test_each_effect_beyond_the_papers_is_named_as_data_in_at_most_two_files():
    """A registry key, a config key or a branch on the name ('name', 'section.name', 'section.name=...') stands in
    at most two files under dfxcorr/ outside the simulator and the kernels' channel table."""
    names = [n for n in REGISTRY if n not in PAPER_MODEL]
    files: dict[str, set] = {n: set() for n in names}
    for path in PACKAGE.rglob("*.py"):
        if "sim" in path.relative_to(PACKAGE).parts or path.name == "kernels.py":
            continue
        for value in _string_constants(path):
            for n in names:
                if re.fullmatch(rf"([a-z_]+\.)?{n}(=.*)?", value):
                    files[n].add(path.relative_to(PACKAGE).as_posix())
    assert all(len(f) <= 2 for f in files.values()), files
    # and the test sees what it counts: the catalogue names its entries
    assert "catalogue.py" in files["curvature"]


def _imports(path: Path) -> set[str]:
    """Every module a file imports (at the top or inside functions), as absolute dotted names."""
    tree = ast.parse(path.read_text())
    package = ".".join(("dfxcorr", *path.relative_to(PACKAGE).parent.parts))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            out.add(module)
            out.update(f"{module}.{a.name}" for a in node.names)
    return out


@pytest.mark.parametrize("module", ["pipeline", "check", "reference", "planning", "identify", "io", "align", "mask",
                                    "fit", "retrieve", "export", "model", "catalogue", "observations", "noise",
                                    "kernels", "baselines", "config", "effects"])
def test_core_layers_import_nothing_from_the_analysis(module):
    path = PACKAGE / f"{module}.py"
    paths = [path] if path.exists() else sorted((PACKAGE / module).glob("*.py"))
    assert paths
    for p in paths:
        bad = sorted(m for m in _imports(p) if m.startswith("dfxcorr.analysis"))
        assert not bad, (p.name, bad)


def test_no_source_file_is_longer_than_750_lines():
    long = {p.relative_to(PACKAGE).as_posix(): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 750}
    assert not long, long


def test_side_tables_come_from_the_catalogue():
    from dfxcorr.analysis.evaluate import TRUTH_KEYS
    from dfxcorr.catalogue import CATALOGUE

    assert {C.VIBRATION_EFFECTS[k] for k in C.VIBRATION_EFFECTS} == set(CATALOGUE)
    assert TRUTH_KEYS["phase_offset"] == "vib_phase_offset" and "visibility_tilt" not in TRUTH_KEYS
    # every configuration key an effect names is an option of the schema, with a help text
    assert all(C.option(e.entry.config).help for e in REGISTRY.values() if e.entry.config)


# --------------------------------------------------------------------------------------------------
# The loop with made-up effects and fits
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class FakeState:
    hypothesis: Hypothesis
    signatures: list
    chi2: float
    reduced_chi2: float
    params: dict = field(default_factory=dict)
    rec: object = None
    obs: object = None
    fit_obs: object = None


def _hypothesis(effects=()) -> Hypothesis:
    return Hypothesis(tuple(effects), Noise(), np.zeros((2, 2), bool), np.zeros(3))


class World:
    """Made-up truth: which effects are really there, and which signature each leaves while left out."""

    def __init__(self, leaves: dict[str, dict[tuple[str, str], float]]):
        self.leaves, self.fits = leaves, []

    def fit(self, hyp: Hypothesis, start: dict, label: str) -> FakeState:
        self.fits.append((hyp.effects, dict(start)))
        sigs = []
        for axis in (("frame", "mean"), ("row", "variance"), ("count", "variance")):
            excess = sum(v.get(axis, 0.0) for name, v in self.leaves.items() if name not in hyp.effects)
            sigs.append({"axis": axis[0], "kind": axis[1], "statistic": 20.0 + excess, "dof": 20,
                         "significant": excess > 30})
        chi2 = 1000.0 + sum(s["statistic"] - s["dof"] for s in sigs)
        return FakeState(hyp, sigs, chi2, chi2 / 1000.0)


class Fake(EffectBase):
    """An effect whose test says what the test is told, and whose trial adds it to the model."""

    def __init__(self, name, statistic, *, dof=1, policy=MEAN, identifiable=True, material=True, until=None):
        self.entry = Effect(name, None, False, (), 0.0, "none", name)
        self.policy, self.until = policy, until
        self._test = replace(chi2_test(statistic, dof, None, explains=statistic), identifiable=identifiable,
                             material=material)

    def test(self, ctx, state, flagged):
        if self.name in state.hypothesis.effects:
            return None
        # a proxy's test is significant only while the effect it stands in for is missing
        return chi2_test(0.5, 1, None) if self.until in state.hypothesis.effects else self._test

    def trial(self, ctx, state, test):
        return state.hypothesis.but(effects=(*state.hypothesis.effects, self.name))


def _run(effects, world, **kw):
    registry = {e.name: e for e in effects}
    start = world.fit(_hypothesis(), {}, "start")
    return loop.run(registry, None, start, fit=world.fit, alpha=kw.get("alpha", 0.01),
                    explain_share=kw.get("explain_share", 0.25), proxy_spread=kw.get("proxy_spread", 1.0),
                    max_rounds=kw.get("max_rounds", 8))


def test_holm_steps_down_and_stops_at_the_first_failure():
    log_p = list(np.log([0.001, 0.04, 0.012, 0.5]))
    # thresholds 0.05/4, 0.05/3, 0.05/2, 0.05 in the order 0.001, 0.012, 0.04, 0.5: 0.04 > 0.025 stops it
    assert holm(log_p, 0.05) == [True, False, True, False]
    assert holm(log_p, 0.09) == [True, True, True, False]
    assert holm(list(np.log([0.02, 0.001])), 0.03) == [True, True]
    assert holm(list(np.log([0.02, 0.001])), 0.019) == [False, True]
    # a large p-value early ends it: nothing after it is significant whatever its own value
    assert holm(list(np.log([0.02, 0.02, 0.02])), 0.05) == [False, False, False]


def test_ranking_tiers_explained_chi_square_and_noise_before_pixels():
    noise = Policy(noise_model=True)
    effects = {e.name: e for e in (Fake("lag", 50, policy=Policy(order=0)),
                                   Fake("offset", 40, policy=Policy(order=1)), Fake("small", 60), Fake("big", 900),
                                   Fake("motion", 300, policy=Policy(localised=True)),
                                   Fake("gain", 5000, policy=replace(noise, order=1)),
                                   Fake("classes", 80, policy=replace(noise, order=0)),
                                   Fake("weak", 1.0), Fake("blind", 800, identifiable=False),
                                   Fake("immaterial", 700, policy=noise, material=False))}
    tests = {n: e.test(None, FakeState(_hypothesis(), [], 0, 0), None) for n, e in effects.items()}
    assert loop.ranked(tests, effects, 0.01) == ["lag", "offset", "big", "classes", "gain", "motion", "small"]
    # scattered outliers (a localised test that names no candidate) place the noise model all the same
    effects["motion"] = Fake("motion", 300, policy=Policy(localised=True), material=False)
    tests["motion"] = effects["motion"].test(None, FakeState(_hypothesis(), [], 0, 0), None)
    assert loop.ranked(tests, effects, 0.01) == ["lag", "offset", "big", "classes", "gain", "small"]
    del effects["motion"], tests["motion"]
    assert loop.ranked(tests, effects, 0.01) == ["lag", "offset", "big", "small", "classes", "gain"]


def test_a_true_effect_is_named_and_a_significant_proxy_is_tried_and_refused():
    world = World({"true": {("frame", "mean"): 400.0}})
    # the proxy's test is stronger, but a trial refit with it removes none of the signature
    out = _run([Fake("true", 200), Fake("proxy", 500, until="true")], world)
    assert [s.name for s in out.steps] == ["true"]
    assert out.state.hypothesis.effects == ("true",)
    assert out.rounds[0]["explained_share"] == pytest.approx(1.0)
    # round 0 tried the proxy first (it explains more chi-square) and refused it; round 1 finds nothing
    assert [h for h, _ in world.fits] == [(), ("proxy",), ("true",)]
    assert out.tests["proxy"].statistic == 0.5


def test_the_acceptance_rule_takes_a_share_or_a_silenced_signature():
    sig = lambda excess, significant: [{"axis": "frame", "kind": "mean", "statistic": 20 + excess, "dof": 20,  # noqa: E731
                                        "significant": significant}]
    assert loop.accepts(sig(100, True), sig(70, True), explain_share=0.25)
    assert not loop.accepts(sig(100, True), sig(80, True), explain_share=0.25)
    # silences the signature while its excess does not grow: accepted whatever the share
    assert loop.accepts(sig(100, True), sig(90, False), explain_share=0.25)
    assert not loop.accepts(sig(100, True), sig(120, False), explain_share=0.25)
    # nothing significant to explain: accepted on its own test
    assert loop.accepts(sig(5, False), sig(5, False), explain_share=0.25)
    assert loop.explained_share(sig(5, False), sig(5, False)) is None


def test_an_unidentifiable_effect_that_explains_the_misfit_stops_the_diagnosis_without_a_proxy():
    world = World({"blind": {("row", "variance"): 300.0}, "proxy": {}})
    # the proxy is significant and identifiable; the truth is not identifiable here but explains the signature
    out = _run([Fake("proxy", 100), Fake("blind", 400, identifiable=False)], world)
    assert out.steps == []
    assert out.blind["blind"].explains_misfit and out.blind["blind"].explained_share == pytest.approx(1.0)
    assert out.blind["blind"].stopped
    # the identifiable candidate was tried, explained less than the unidentifiable one, and was refused
    assert [h for h, _ in world.fits] == [(), ("blind",), ("proxy",)] and "proxy" in out.rejected


def test_an_identifiable_effect_that_explains_as_much_as_an_unidentifiable_one_is_named():
    # a phase-stepping recording: per-step phase errors (identifiable) that a per-step visibility model
    # (not identifiable there) also absorbs
    world = World({"phase": {("frame", "mean"): 300.0}, "visibility": {}})
    world.leaves["visibility"] = {}
    fake_vis = Fake("visibility", 420, identifiable=False)
    fake_vis.trial = lambda ctx, state, test: state.hypothesis.but(effects=(*state.hypothesis.effects, "phase"))
    out = _run([Fake("phase", 400), fake_vis], world)
    assert [s.name for s in out.steps] == ["phase"]
    assert out.blind["visibility"].explains_misfit and not out.blind["visibility"].stopped


def test_of_two_candidates_the_tests_cannot_tell_apart_the_better_fit_is_named():
    world = World({"offset": {("frame", "mean"): 300.0}})

    class Alike(Fake):
        """A collinear proxy: its trial takes four fifths of the truth's signature."""

        def trial(self, ctx, state, test):
            return state.hypothesis.but(effects=(*state.hypothesis.effects, self.name))

    world.leaves["curvature"] = {}
    fit = world.fit

    def partial(hyp, start, label):
        state = fit(hyp, start, label)
        if "curvature" in hyp.effects and "offset" not in hyp.effects:
            sigs = [{**s, "statistic": s["dof"] + 60.0, "significant": True} if s["axis"] == "frame" else s
                    for s in state.signatures]
            return replace(state, signatures=sigs, chi2=state.chi2 + 60.0)
        return state
    world.fit = partial
    out = _run([Fake("offset", 320, until="curvature"), Alike("curvature", 330, until="offset")], world)
    assert [s.name for s in out.steps] == ["offset"]
    # both were tried in the first round: the stronger test first, the better fit named
    assert [h for h, _ in world.fits][1:3] == [("curvature",), ("offset",)]


def test_a_refined_effect_refits_at_the_estimate_of_its_own_trial():
    world = World({"noise": {("count", "variance"): 100.0}})

    class Estimated(Fake):
        """A noise-model effect: its test still gives an estimate once it is in the model."""

        def test(self, ctx, state, flagged):
            return self._test

    effect = Estimated("noise", 500, policy=Policy(noise_model=True, refinements=1))
    out = _run([effect], world)
    assert [s.name for s in out.steps] == ["noise"]
    assert [h for h, _ in world.fits] == [(), ("noise",), ("noise", "noise")]


def test_an_unidentifiable_effect_that_explains_nothing_does_not_stop_it():
    world = World({"true": {("frame", "mean"): 300.0}})
    out = _run([Fake("true", 100), Fake("blind", 400, identifiable=False)], world)
    assert [s.name for s in out.steps] == ["true"]
    assert not out.blind["blind"].explains_misfit


def test_the_loop_stops_without_a_fit_when_nothing_is_significant_and_within_max_rounds():
    world = World({})
    out = _run([Fake("a", 0.5), Fake("b", 2.0)], world)
    assert out.steps == [] and len(world.fits) == 1 and set(out.tests) == {"a", "b"}
    world = World({n: {("frame", "mean"): 100.0} for n in "abc"})
    out = _run([Fake(n, 100 + i) for i, n in enumerate("abc")], world, max_rounds=2)
    assert len(out.steps) == 2 and len(out.rounds) == 2


def test_a_fresh_start_effect_is_fitted_from_scratch():
    world = World({"data": {("count", "variance"): 200.0}})
    effect = Fake("data", 300, policy=Policy(fresh_start=True))
    start = replace(world.fit(_hypothesis(), {}, "start"), params={"phase_offset": np.zeros((3, 1))})
    loop.run({"data": effect}, None, start, fit=world.fit, alpha=0.01, explain_share=0.25, proxy_spread=1.0,
             max_rounds=3)
    assert world.fits[-1] == (("data",), {})


# --------------------------------------------------------------------------------------------------
# A toy effect the whole way: one module's worth of code, one registry line
# --------------------------------------------------------------------------------------------------


class Pedestal(EffectBase[float]):
    """Toy: the detector adds a constant pedestal that the file's dark does not hold. Measured, like detector lag,
    in the rows the active area has just left (they hold dark + pedestal); corrected by adding it to the dark."""

    entry = Effect("toy_pedestal", None, False, ("p",), 0.0, "none", "a constant pedestal missing from the dark",
                   unit="counts")
    policy = Policy(order=-1, fresh_start=True)
    files = ("pedestal.txt",)

    def apply(self, data: Correctable, setting) -> Correctable:
        return replace(data, store=replace(data.store, dark=data.store.dark + setting))

    def test(self, ctx, state, flagged):
        store = ctx.corrected(state.hypothesis).store
        signal = store.left_counts.astype(float) - store.dark[store.row[store.left_prev]]
        # the file's rounding (0.5 count) bounds the error where nothing else is left
        p, se = float(signal.mean()), max(float(signal.std()), 0.5) / np.sqrt(signal.size)
        return chi2_test((p / se) ** 2, 1, p, explains=(p / se) ** 2)

    def trial(self, ctx, state, test):
        return state.hypothesis.but(corrections=(*state.hypothesis.corrections, (self.name, test.payload)))

    def accepted(self, ctx, before, after, test):
        p = test.payload
        return Finding("rows the active area has just left", f"p = {p:.3g} counts", {"value": p},
                       files={"pedestal.txt": lambda path: path.write_text(f"{p}\n")})


@pytest.mark.slow
def test_a_toy_effect_is_found_corrected_and_reported_through_the_one_interface(tmp_path):
    scan, _ = S.simulate(sim_config(**{"simulate.seed": 3}))
    scan = replace(scan, data=scan.data + np.uint16(200))
    registry = {**REGISTRY, "toy_pedestal": Pedestal()}
    diag = diagnose(scan, C.defaults(), registry=registry)
    found = [e for e in diag.effects if e.detected]
    assert [e.name for e in found] == ["toy_pedestal"], [(e.name, e.statistic) for e in diag.effects]
    # the rows just left hold the pedestal and Poisson noise of nothing: exact up to the file's rounding
    assert found[0].values["value"] == pytest.approx(200.0, abs=0.5)
    assert diag.final.corrections == (("toy_pedestal", found[0].values["value"]),)
    assert diag.final_chi2 == pytest.approx(1.0, abs=0.05)
    written = write_report(diag, tmp_path)
    assert tmp_path / "pedestal.txt" in written
    assert "toy_pedestal" in (tmp_path / "report.md").read_text()


def test_a_mean_effect_whose_trial_raises_the_chi_square_is_refused():
    """The chi-square is read on every column and the fit saw a few of them: a rise is an overfit."""
    world = World({})
    fit = world.fit

    def overfit(hyp, start, label):
        state = fit(hyp, start, label)
        if "overfit" in hyp.effects:
            # it silences a signature on the fitted columns, but the chi-square of all of them rises
            sigs = [{**s, "significant": False} for s in state.signatures]
            return replace(state, signatures=sigs, chi2=state.chi2 + 50.0, reduced_chi2=state.reduced_chi2 + 0.05)
        return state

    def start_state(hyp, start, label):
        state = fit(hyp, start, label)
        sigs = [{**s, "statistic": s["dof"] + 40.0, "significant": True} if s["axis"] == "frame" else s
                for s in state.signatures]
        return replace(state, signatures=sigs)

    world.fit = overfit
    registry = {"overfit": Fake("overfit", 200)}
    out = loop.run(registry, None, start_state(_hypothesis(), {}, "start"), fit=world.fit, alpha=0.01,
                   explain_share=0.25, proxy_spread=1.0, max_rounds=3)
    assert out.steps == [] and "overfit" in out.rejected


class OfOneSize(Fake):
    """A fake whose consistency test says whether its size changes across the strata, and how much."""

    def __init__(self, name, statistic, *, p, spread, until=None):
        super().__init__(name, statistic, until=until)
        self.p, self.spread = p, spread

    def consistency(self, ctx, before, state):
        return Consistency(20.0, 1, self.p, float(np.log(self.p)), "count",
                           (1 - self.spread / 2, 1 + self.spread / 2))


@pytest.mark.parametrize(("p", "spread", "named"), [(1e-6, 5.0, False), (1e-6, 0.3, True), (0.5, 5.0, True)])
def test_a_candidate_of_another_size_in_other_strata_is_refused_as_a_proxy(p, spread, named):
    """Refused only when the change of size is both significant and material; the refused one is kept as
    inconsistent (reported unexplained) and the next candidate is tried."""
    world = World({"true": {("frame", "mean"): 400.0}})
    out = _run([OfOneSize("true", 200, p=p, spread=spread)], world)
    assert ([s.name for s in out.steps] == ["true"]) is named
    assert ("true" in out.inconsistent) is not named
    if not named:
        test, odd = out.inconsistent["true"]
        assert test.statistic == 200 and odd.axis == "count"


def test_a_proxy_whose_signature_the_next_effect_explains_is_not_reported():
    """Refused as a proxy in round 0 (its trial explained a third of the misfit, with sizes that differ), the true
    effect added next; in round 1 the proxy's test is no longer significant, so nothing is left unexplained of it."""
    world = World({"true": {("frame", "mean"): 400.0}, "proxy": {("frame", "mean"): 200.0}})
    out = _run([OfOneSize("proxy", 500, p=1e-6, spread=5.0, until="true"), Fake("true", 300)], world)
    assert [s.name for s in out.steps] == ["true"]
    assert out.inconsistent == {}


def test_the_noise_model_is_held_while_the_mean_model_is_grossly_off():
    """A misfit of the residuals' mean that no candidate explains (reduced chi-square 2.5): the noise model, whose
    trial would match any misfit with a variance large enough, is not tried; the report says why."""
    from dfxcorr.analysis.diagnose import _not_added

    world = World({"missing": {("frame", "mean"): 1500.0}})
    out = _run([Fake("noise", 5000, policy=Policy(noise_model=True))], world)
    assert out.steps == [] and out.held == {"noise": "gross"} and len(world.fits) == 1
    report = _not_added("noise", out.tests["noise"], out, alpha=0.01, tested=1)
    assert report.verdict == "held: gross misfit" and "grossly off" in report.verdict_text()
    # at a reduced chi-square within the gross level it is tried
    mild = World({"missing": {("frame", "mean"): 500.0}})
    assert _run([Fake("noise", 5000, policy=Policy(noise_model=True))], mild).held == {}


class Joinable(Fake):
    """A fake that a trial of another candidate can take up too."""

    def joined(self, hypothesis):
        return hypothesis.but(effects=(*hypothesis.effects, self.name))


class Shares(Joinable):
    """A fake whose pair test with another candidate says what it is told."""

    def __init__(self, name, statistic, *, beyond, other, shared=2):
        super().__init__(name, statistic)
        self.pair = Pair({name: beyond[0], other: beyond[1]}, shared)

    def beside(self, ctx, state, other):
        return self.pair if other in self.pair.beyond else None


@pytest.mark.parametrize(("beyond", "named", "alternatives"), [
    (((50.0, 2), (0.5, 2)), ["a"], ()),     # only a's share beyond b: a
    (((0.5, 2), (50.0, 2)), ["b"], ()),     # only b's: b, tried in a's place
    (((0.5, 2), (0.4, 2)), ["a"], ("b",)),  # neither: one finding, 'a or b'
    (((50.0, 2), (60.0, 2)), ["a", "b"], ()),  # both: fitted together
])
def test_confounded_candidates_are_decided_on_their_shares_beyond_each_other(beyond, named, alternatives):
    world = World({"a": {("frame", "mean"): 200.0}, "b": {("frame", "mean"): 200.0}})
    a = Shares("a", 400, beyond=beyond, other="b")
    b = Joinable("b", 390)
    out = _run([a, b], world, max_rounds=1)
    (step,) = out.steps
    assert list(step.names) == named and tuple(n for n, _ in step.alternatives) == alternatives
    if named == ["b"]:
        assert out.held == {"a": "b"}
