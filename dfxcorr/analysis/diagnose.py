"""Model-discrepancy diagnosis: where does a recording disagree with the model, and which physics is missing?

Each round fits the current model, then tests every catalogue effect the model lacks:

- mean effects (phase_offset ... harmonic) by Neyman's efficient-score (C(alpha)) test at the current
  fit: the score of the candidate's parameters, corrected for the model's own parameters through
  the profiled Fisher information (:func:`dfxcorr.model.fisher_matrix`), S = U*^T I*^+ U* / phi,
  chi-square with rank(I*) degrees of freedom. No refit is needed, the subsampled fit's estimates
  suffice, and dividing by the dispersion phi (Pearson chi-square per degree of freedom) keeps an
  unmodelled detector gain from posing as a mean effect;
- sample_motion by the per-pixel chi-square: pixels far beyond what noise allows, in numbers no
  chance explains (binomial test);
- detector_gain by a likelihood-ratio test of the variance model g (Ibar - dark) + electronic
  against the current one, considered only when no structured effect is left.

Whether an effect can be identified at all comes from the null space of the Fisher information
(:mod:`dfxcorr.analysis.identify`). The significant structured effect that explains the most chi-square is
added (Holm's correction over the effects tried in the round), the model refitted, and the loop
repeats until nothing significant is left.
"""
from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy import ndimage, stats

from .. import config as C
from .. import model as M
from .. import plots
from ..align import subsample_columns
from ..fit import fit_vibrations
from ..io import Scan, atomic_path
from ..mask import motion_score
from ..pipeline import Prepared, prepare, stage
from ..retrieve import retrieve
from . import identify
from .identify import resolve_effects, visibility_unidentifiable

log = logging.getLogger("dfxcorr")

#: Effects tested, in catalogue order.
CANDIDATES = tuple(M.CATALOGUE)


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
        d.update(self.extra)
        return d


@dataclass
class Residuals:
    """Where the model and the recording disagree: mean squared standardized residual by location.

    Attributes
    ----------
    pixel : ndarray, shape (H, W)
        Per pixel, normalised by its degrees of freedom (1 = noise); NaN where not lit.
    frame : ndarray, shape (J,)
    x, x_value : ndarray
        Against the lateral coordinate (per held column).
    phase, phase_value : ndarray
        Against the fringe phase theta + phi, in 16 bins over (-pi, pi].
    count, count_value : ndarray
        Against the expected count, in logarithmic bins.
    """

    pixel: np.ndarray
    frame: np.ndarray
    x: np.ndarray
    x_value: np.ndarray
    phase: np.ndarray
    phase_value: np.ndarray
    count: np.ndarray
    count_value: np.ndarray


@dataclass
class Diagnosis:
    """The outcome of :func:`diagnose`."""

    scan: str
    base_model: list
    initial_chi2: float
    final_chi2: float
    effects: list
    final_model: list
    before: Residuals
    after: Residuals
    params: dict
    gain: float
    electronic: float
    motion_mask: np.ndarray
    criterion: str
    rounds: list

    def to_json(self) -> dict:
        """The ``diagnosis.json`` document of ``spec/diagnosis.md``."""
        return {"format": "dfxcorr-diagnosis", "format_version": 1, "scan": self.scan, "base_model": self.base_model,
                "reduced_chi2": {"initial": self.initial_chi2, "final": self.final_chi2},
                "effects": [e.to_json() for e in self.effects], "final_model": self.final_model,
                "criterion": self.criterion, "rounds": self.rounds}


# --------------------------------------------------------------------------------------------------
# Locating the mismatch
# --------------------------------------------------------------------------------------------------


def locate(obs: M.Observations, dsg: M.Design, images: M.Images, ibar: np.ndarray) -> Residuals:
    """Mean squared standardized residual per pixel, frame, lateral position, fringe phase and count."""
    z2 = np.where(obs.use, M.pearson(obs, ibar), np.nan)
    used = obs.use.astype(float)
    n = obs.segment_sum(used)
    with np.errstate(invalid="ignore", divide="ignore"):
        pixel = obs.to_image(obs.segment_sum(np.nan_to_num(z2)) / (n - 3))
        frame = obs.frame_sum(np.nansum(z2, axis=1)) / obs.frame_sum(used.sum(axis=1))
        xs = np.nansum(z2, axis=0) / used.sum(axis=0)
    psi = np.angle(np.exp(1j * (dsg.theta + images.phi[obs.pixel])))
    edges = np.linspace(-np.pi, np.pi, 17)
    phase = _binned(psi, z2, edges)
    lo, hi = np.nanpercentile(np.where(obs.use, ibar, np.nan), [0.5, 99.5])
    cedges = np.geomspace(max(lo, 1e-3), max(hi, 2 * max(lo, 1e-3)), 13)
    count = _binned(ibar, z2, cedges)
    # a retrieval with 3 unknowns per pixel leaves (n - 3) / n of the variance in the residuals
    scale = float(np.nansum(n) / np.nansum(np.maximum(n - 3, 0)))
    return Residuals(pixel=pixel, frame=frame * scale, x=xs * scale, x_value=obs.x, phase=phase * scale,
                     phase_value=0.5 * (edges[1:] + edges[:-1]), count=count * scale,
                     count_value=np.sqrt(cedges[1:] * cedges[:-1]))


def _binned(value, z2, edges):
    ok = np.isfinite(z2)
    idx = np.digitize(value[ok], edges) - 1
    inside = (idx >= 0) & (idx < edges.size - 1)
    s = np.bincount(idx[inside], weights=z2[ok][inside], minlength=edges.size - 1)
    c = np.bincount(idx[inside], minlength=edges.size - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return s / c


# --------------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------------


def score_tests(obs: M.Observations, params: dict, weights: np.ndarray, model, candidates, *,
                dispersion: float) -> dict[str, dict]:
    """Efficient-score tests of mean effects at the current fit.

    Parameters
    ----------
    obs : Observations
        Samples for the test (their ``use`` decides which count).
    params : dict
        Current parameters of the model's effects.
    weights : ndarray, shape (K, C)
        Inverse noise variances of the current noise model.
    model, candidates : sequence of str
        Mean effects in the model, and those to test.
    dispersion : float
        Pearson chi-square per degree of freedom (scales the statistic).

    Returns
    -------
    dict
        name -> {'statistic', 'dof', 'p_value', 'log_p', 'explains', 'identifiable', 'excess', 'frames'}
        where 'explains' approximates the chi-square that adding the effect removes and 'frames' the
        per-frame share of the statistic (per-frame effects).
    """
    names = list(model) + [c for c in candidates if c not in model]
    full = {**M.neutral_params(names, obs.n_frames), **params}
    dsg = M.design(obs, full)
    images = M.solve_images(obs, dsg, weights, keep_inverse=True)
    resid = obs.counts - M.expected(obs, dsg, images)
    inf = identify.information(obs, dsg, images, weights, names)
    grad = M.gradient(obs, dsg, images, weights, resid, names)
    U = -0.5 * np.array([grad[n][(j, m) if j >= 0 else m] for n, j, m in zip(inf.owner, inf.frame, inf.component)])
    out = {}
    for name in candidates:
        cond = identify.conditional(inf, name, model)
        sel, inv, dof = cond.sel, cond.inverse, cond.dof
        # the efficient score: the candidate's score with what the model's own parameters explain taken out
        eff_score = U[sel] - cond.projector @ U[cond.base]
        stat = float(eff_score @ inv @ eff_score) / dispersion
        contrib = eff_score * (inv @ eff_score) / dispersion
        fr = inf.frame[sel]
        frames = np.bincount(fr[fr >= 0], weights=contrib[fr >= 0], minlength=obs.n_frames)
        out[name] = {"statistic": stat, "dof": dof, "p_value": float(stats.chi2.sf(stat, dof)) if dof else 1.0,
                     "log_p": float(stats.chi2.logsf(stat, dof)) if dof else 0.0, "explains": stat * dispersion,
                     "identifiable": cond.verdict.identifiable, "excess": cond.verdict.excess, "frames": frames}
    return out


def motion_test(obs: M.Observations, params: dict, *, p_pixel: float = 1e-6, min_pixels: int = 5) -> dict:
    """Pixels whose frames disagree beyond noise and remaining vibration misfit, in clusters.

    The per-pixel score is :func:`dfxcorr.mask.motion_score` at the current model (a reduced
    chi-square once what the fringe sensitivity explains is divided out); a pixel is flagged when that
    score is in the chi-square tail beyond ``p_pixel``, and counts only in a cluster of three or more.

    Returns
    -------
    dict
        'statistic' (chi-square in excess of its dof over the flagged pixels), 'dof' (flagged pixels),
        'p_value', 'log_p' (binomial: that many pixels below ``p_pixel`` by chance), 'explains',
        'mask' (H, W) bool.
    """
    score = motion_score(obs, params)
    dof = np.maximum(obs.segment_sum(obs.use.astype(float)) - 3, 1)
    ok = np.isfinite(score)
    logp = np.where(ok, stats.chi2.logsf(np.nan_to_num(score) * dof, dof), 0.0)
    flag = obs.to_image(ok & (logp < np.log(p_pixel)), fill=False).astype(bool)
    labels, count = ndimage.label(flag)
    if count:
        # a moving sample covers neighbouring pixels; isolated tail pixels are noise or outliers
        sizes = ndimage.sum(flag, labels, index=np.arange(1, count + 1))
        flag = np.isin(labels, 1 + np.flatnonzero(sizes >= 3))
    k = int(flag.sum())
    excess = obs.to_image(np.nan_to_num(score - 1) * dof, fill=0.0)
    log_p = float(stats.binom.logsf(k - 1, int(ok.sum()), p_pixel)) if k >= min_pixels else 0.0
    return {"statistic": float(excess[flag].sum()), "dof": k, "p_value": float(np.exp(log_p)), "log_p": log_p,
            "explains": float(excess[flag].sum()), "mask": flag, "identifiable": True, "excess": 0}


def noise_model(obs: M.Observations, ibar: np.ndarray, images: M.Images, dsg: M.Design,
                weights: np.ndarray) -> dict:
    """Gain and electronic variance from the residuals: E[r^2 / (1 - h)] = g (Ibar - dark) + sigma_e^2.

    Squared residuals are divided by 1 - h (h the leverage of the sample in its pixel's image fit):
    fitting the images removes that share of each sample's variance. Weighted least squares with
    weights 1 / variance^2 (the variance of a squared Gaussian residual).

    Returns
    -------
    dict
        'gain', 'electronic', and the per-sample 'r2' (leverage-corrected), 'mean' (Ibar - dark) and
        current 'variance' of the used samples.
    """
    h = M.leverage(obs, dsg, images, weights)
    sel = obs.use & (h < 0.99)
    r2 = ((obs.counts - ibar) ** 2 / (1 - h))[sel]
    mu = np.maximum(ibar - obs.dark, 1e-3)[sel]
    v0 = M.variance(obs, ibar)[sel]
    w = 1.0 / v0 ** 2
    A = np.stack([mu, np.ones_like(mu)], axis=1) * np.sqrt(w)[:, None]
    (g, e), *_ = np.linalg.lstsq(A, r2 * np.sqrt(w), rcond=None)
    if e < 0:
        g, e = float(np.sum(w * mu * r2) / np.sum(w * mu * mu)), 0.0
    return {"gain": float(g), "electronic": float(e), "r2": r2, "mean": mu, "variance": v0}


def gain_test(obs: M.Observations, ibar: np.ndarray, images, dsg, weights) -> dict:
    """Likelihood-ratio test of the estimated noise model against the current one (Gaussian, 2 dof)."""
    fit = noise_model(obs, ibar, images, dsg, weights)
    r2, v0 = fit["r2"], fit["variance"]
    v1 = fit["gain"] * fit["mean"] + fit["electronic"]
    stat = max(float(np.sum(np.log(v0 / v1) + r2 / v0 - r2 / v1)), 0.0)
    return {"statistic": stat, "dof": 2, "p_value": float(stats.chi2.sf(stat, 2)),
            "log_p": float(stats.chi2.logsf(stat, 2)), "gain": fit["gain"], "electronic": fit["electronic"],
            "identifiable": True, "excess": 0}


# --------------------------------------------------------------------------------------------------
# The loop
# --------------------------------------------------------------------------------------------------


def _chi2(obs: M.Observations, params: dict, *, n_params: int) -> tuple[float, float, object]:
    rec = retrieve(obs, params, n_frame_params=n_params)
    sel = rec.images.valid[obs.pixel] & obs.use
    return float(M.pearson(obs, rec.expected)[sel].sum()), rec.reduced_chi2, rec


def _where(name: str, test: dict, obs: M.Observations) -> str:
    if name == "sample_motion":
        rows, cols = np.nonzero(test["mask"])
        return (f"{rows.size} pixels in rows {rows.min()}-{rows.max()}, columns {cols.min()}-{cols.max()}"
                if rows.size else "nowhere")
    if name == "detector_gain":
        return "all pixels (noise, not the mean)"
    if not M.effect(name).per_frame:
        return "the whole detector (global parameters)"
    share = np.clip(test["frames"], 0, None)
    if share.sum() <= 0:
        return "no frame in particular"
    order = np.argsort(share)[::-1]
    top = np.sort(order[: max(1, int(np.searchsorted(np.cumsum(share[order]) / share.sum(), 0.5)) + 1)])
    spread = "all frames" if top.size > 0.3 * obs.n_frames else "few frames"
    return f"{spread}; half of the statistic in {top.size} frames, {top.min()}-{top.max()}"


def _estimate(name: str, params: dict, good: np.ndarray, extra: dict) -> str:
    if name == "detector_gain":
        return f"g = {extra['gain']:.3f}, electronic sigma = {np.sqrt(extra['electronic']):.3g} counts"
    if name == "sample_motion":
        return f"{extra['pixels']} pixels"
    p = params.get(name)
    if p is None:
        return ""
    e = M.effect(name)
    if e.per_frame:
        sd = np.std(p[good], axis=0)
        unit = " %" if name in ("dose", "visibility_loss") else (" rad" if e.channel == "phase" else "")
        factor = 100.0 if unit == " %" else 1.0
        return ", ".join(f"std {factor * s:.3g}{unit}" + (f" ({c})" if e.size > 1 else "")
                         for s, c in zip(sd, e.components))
    if name == "harmonic":
        return f"a2 = {np.hypot(*p):.4g}, beta = {np.arctan2(p[1], p[0]):.3f} rad"
    return ", ".join(f"{c}: {v:.4g}" for c, v in zip(e.components, p)) + " counts"


def diagnose(scan: Scan | str | Path | Prepared, cfg: dict | None = None, *, base: str = "configured") -> Diagnosis:
    """Locate model-data mismatch, name the missing effects, add them and refit until nothing is left.

    Parameters
    ----------
    scan : Scan, path or Prepared
        Prepared by :func:`dfxcorr.pipeline.prepare` (reference options, region of interest), as for
        a reconstruction.
    cfg : dict, optional
        Resolved configuration; its vibration section is the base model, its diagnose section the
        test settings.
    base : {'configured', 'none'}
        Start from the configured model, or from plain retrieval with no per-frame terms.

    Returns
    -------
    Diagnosis
    """
    cfg = C.defaults() if cfg is None else cfg
    d = cfg["diagnose"]
    timings: dict = {}
    prep = scan if isinstance(scan, Prepared) else prepare(scan, cfg, timings=timings)
    name = str(prep.path) if prep.path else prep.name
    scan, reference = prep.scan, prep.reference
    # the tests need every pixel: the diagnosis holds the whole scan (the reconstruction streams it)
    obs, roi = prep.observations()
    # the fit uses the tests' columns: a coarser fit's parameter noise would read as misfit
    fit_obs = obs.subset(subsample_columns(scan.shape[2], d["subsample"]))
    model = list(resolve_effects(cfg, scan, reference, fit_obs)) if base == "configured" else []
    base_model = list(model)
    good_frames = np.bincount(fit_obs.frame, minlength=scan.shape[0]) >= 0.5 * np.bincount(fit_obs.frame).max()
    params: dict = {}
    motion = np.zeros(scan.shape[1:], bool)
    modelled_noise = False
    reports: dict[str, EffectReport] = {}
    detected: list[str] = []
    rounds = []
    last_tests: dict[str, dict] = {}
    initial = None
    paper_why = visibility_unidentifiable(scan, reference)
    for rnd in range(d["max_rounds"] + 1):
        # as in reconstruct: the tests see the region of interest, the fit also the samples without fringe
        # (they monitor dose and background)
        obs = replace(obs, use=roi & ~motion[obs.row][:, obs.columns])
        fit_obs = replace(fit_obs, use=~motion[fit_obs.row][:, fit_obs.columns])
        with stage(f"round {rnd}: fit {'+'.join(model) or 'images only'}", timings):
            if model:
                # after the first round the fit starts next to its optimum: no staging against local minima
                warm = bool(params)
                fitted = fit_vibrations(fit_obs, effects=model, start=params, gtol=cfg["fit"]["gtol"],
                                        staged=not warm, circmean_iterations=0 if warm else
                                        cfg["fit"]["circmean_iterations"], reweight=0 if warm else 1,
                                        visibility_gauge=cfg["fit"]["visibility_gauge"],
                                        visibility_quantile=cfg["fit"]["visibility_quantile"])
                params = {k: v for k, v in fitted.params.items() if k in model}
            n_par = sum(np.size(p) for p in params.values())
            chi2_sum, chi2_red, rec = _chi2(obs, params, n_params=n_par)
        if initial is None:
            initial = chi2_red
            before = locate(obs, M.design(obs, params), rec.images, rec.expected)
        if rounds:
            rounds[-1].update(reduced_chi2_after=chi2_red, delta_chi2=rounds[-1]["chi2_before"] - chi2_sum)
            added = rounds[-1]["added"]
            reports[added].delta_chi2 = rounds[-1]["delta_chi2"]
            reports[added].reduced_chi2_after = chi2_red
            reports[added].estimate = _estimate(added, params, good_frames, reports[added].extra)
        if rnd == d["max_rounds"]:
            break
        with stage(f"round {rnd}: tests", timings):
            dispersion = max(chi2_red, 1e-6)
            weights = M.noise_weights(fit_obs, retrieve(fit_obs, params).expected)
            mean_candidates = [c for c in CANDIDATES if M.effect(c).channel is not None and c not in model]
            tests = score_tests(fit_obs, params, weights, model, mean_candidates, dispersion=dispersion)
            for c in ("visibility_loss", "visibility_tilt"):
                if paper_why and c in tests:
                    tests[c]["identifiable"] = False
            if not motion.any():
                tests["sample_motion"] = motion_test(obs, params, p_pixel=d["motion_p"], min_pixels=d["min_pixels"])
            if not modelled_noise:
                dsg = M.design(obs, params)
                tests["detector_gain"] = gain_test(obs, rec.expected, M.solve_images(obs, dsg, rec.weights,
                                                                                       keep_inverse=True),
                                                   dsg, rec.weights)
        last_tests.update(tests)
        m = len(tests)
        structured = {k: t for k, t in tests.items() if k != "detector_gain"}
        # Holm: the most significant of m tests at alpha / m
        threshold = np.log(d["alpha"] / m)
        winners = [k for k, t in structured.items() if t["identifiable"] and t["log_p"] < threshold]
        choice = max(winners, key=lambda k: structured[k]["explains"]) if winners else None
        if choice is None and "detector_gain" in tests:
            t = tests["detector_gain"]
            if t["log_p"] < threshold and abs(t["gain"] / obs.gain - 1) > d["min_gain_change"]:
                choice = "detector_gain"
        log.info("round %d: reduced chi-square %.4f; %s", rnd, chi2_red,
                 ", ".join(f"{k} S={t['statistic']:.4g} (dof {t['dof']}{'' if t['identifiable'] else ', n.i.'})"
                           for k, t in sorted(tests.items(), key=lambda kv: -kv[1]["statistic"])))
        if choice is None:
            break
        t = tests[choice]
        extra = {}
        if choice == "sample_motion":
            motion = ndimage.binary_dilation(t["mask"], iterations=1)
            extra["pixels"] = int(motion.sum())
        elif choice == "detector_gain":
            obs, fit_obs = (replace(o, gain=t["gain"], electronic=t["electronic"]) for o in (obs, fit_obs))
            modelled_noise = True
            extra = {"gain": t["gain"], "electronic": t["electronic"]}
        else:
            model.append(choice)
        detected.append(choice)
        reports[choice] = EffectReport(choice, True, True, t["statistic"], int(t["dof"]), t["p_value"],
                                       where=_where(choice, t, fit_obs), extra=extra)
        rounds.append({"round": rnd, "added": choice, "chi2_before": chi2_sum, "reduced_chi2_before": chi2_red})
        log.info("round %d: adding %s", rnd, choice)
    after = locate(obs, M.design(obs, params), rec.images, rec.expected)
    effects = [reports[n] for n in detected]
    for n, t in sorted(last_tests.items(), key=lambda kv: -kv[1]["statistic"]):
        if n in reports:
            continue
        effects.append(EffectReport(n, False, bool(t["identifiable"]), t["statistic"], int(t["dof"]), t["p_value"],
                                    extra={"excess_null_directions": t["excess"]} if t["excess"] else {}))
    criterion = (f"an effect is detected when its p-value beats Holm's threshold alpha / m (alpha = {d['alpha']}, "
                 f"m = effects tested in the round), it is identifiable, and it explains the most chi-square among "
                 f"those; detector_gain only when no structured effect is left and the gain moves by more than "
                 f"{100 * d['min_gain_change']:.0f} %; sample_motion needs {d['min_pixels']} or more pixels in "
                 f"clusters of 3 whose per-pixel chi-square has p < {d['motion_p']}")
    return Diagnosis(scan=name, base_model=base_model, initial_chi2=initial, final_chi2=chi2_red, effects=effects,
                     final_model=base_model + [n for n in detected if n in model and n not in base_model]
                     + [n for n in detected if n not in model],
                     before=before, after=after, params=params, gain=obs.gain, electronic=obs.electronic,
                     motion_mask=motion, criterion=criterion, rounds=[{k: v for k, v in r.items()} for r in rounds])


def write_report(diag: Diagnosis, out_dir: Path, *, overwrite: bool = False) -> list[Path]:
    """Write ``diagnosis.json``, ``report.md``, ``residuals.png`` and (if detected) ``motion_mask.tif``."""
    import tifffile

    from ..export import check_output

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {k: out_dir / k for k in ("diagnosis.json", "report.md", "residuals.png")}
    for p in paths.values():
        check_output(p, overwrite=overwrite)
    with atomic_path(paths["diagnosis.json"]) as tmp:
        tmp.write_text(json.dumps(diag.to_json(), indent=2, default=float) + "\n")
    plots.plot_diagnosis(diag, paths["residuals.png"])
    written = list(paths.values())
    if diag.motion_mask.any():
        with atomic_path(out_dir / "motion_mask.tif") as tmp:
            tifffile.imwrite(tmp, diag.motion_mask.astype(np.uint8))
        written.append(out_dir / "motion_mask.tif")
    with atomic_path(paths["report.md"]) as tmp:
        tmp.write_text(_markdown(diag))
    return written


def _markdown(diag: Diagnosis) -> str:
    lines = [f"# dfxcorr diagnose: {diag.scan}", "",
             f"Base model: {', '.join(diag.base_model) or 'none (plain retrieval)'}. "
             f"Final model: {', '.join(diag.final_model) or 'none'}.", "",
             f"Reduced chi-square: {diag.initial_chi2:.4f} initially, {diag.final_chi2:.4f} at the end.", "",
             "![where the model and the data disagree](residuals.png)", "",
             "Top row: mean squared standardized residual per pixel before and after (1 = photon noise). "
             "Below: the same by frame, lateral position, fringe phase and expected count.", "",
             "| effect | detected | identifiable | statistic | dof | p-value | delta chi2 | reduced chi2 after | where | "
             "estimate |", "|---|---|---|---|---|---|---|---|---|---|"]
    for e in diag.effects:
        fmt = (lambda v, f: "" if v is None else format(v, f))
        lines.append(f"| {e.name} | {'yes' if e.detected else 'no'} | {'yes' if e.identifiable else 'no'} | "
                     f"{e.statistic:.4g} | {e.dof} | {e.p_value:.3g} | {fmt(e.delta_chi2, '.4g')} | "
                     f"{fmt(e.reduced_chi2_after, '.4f')} | {e.where or ''} | {e.estimate or ''} |")
    lines += ["", f"Criterion: {diag.criterion}.", "",
              "delta chi2 is the change of the Pearson chi-square sum when the effect was added; for detector_gain it "
              "is negative when the noise is below Poisson (the reduced chi-square then rises towards 1).", "",
              "Not identifiable means the Fisher information has directions of that effect's parameters without "
              "information beyond its gauge: the acquisition cannot tell it from the images or the model's other "
              "effects (paper Sec. II-F), so it is never reported as detected.", ""]
    if diag.motion_mask.any():
        lines += [f"The pixels taken as moving are in motion_mask.tif ({int(diag.motion_mask.sum())} pixels).", ""]
    sets = reconstruct_settings(diag)
    lines += ["To reconstruct with the final model:", "",
              f"    dfxcorr reconstruct {diag.scan} -o result.h5" + "".join(f" --set {s}" for s in sets), ""]
    return "\n".join(lines)


def reconstruct_settings(diag: Diagnosis) -> list[str]:
    """The ``--set`` options that make ``reconstruct`` use the diagnosis's final model."""
    keys = {e: k for k, e in C.VIBRATION_EFFECTS.items()}
    sets = [f"vibration.{keys[n]}=true" for n in diag.final_model if n in keys and n not in diag.base_model]
    sets += [f"vibration.{keys[n]}=false" for n in M.PAPER_MODEL if n not in diag.final_model]
    if "sample_motion" in diag.final_model:
        sets.append("mask.enabled=true")
    if "detector_gain" in diag.final_model:
        sets += [f"load.gain={diag.gain:.4g}", f"load.electronic={diag.electronic:.4g}"]
    return sets


