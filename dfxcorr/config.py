"""The configuration schema: every option of every stage with its default, type, help and validation.

A run's configuration is the defaults, overlaid by YAML files (``-c``) in order, overlaid by
``--set section.key=value``. Unknown sections or keys are refused with the nearest valid name; the
fully resolved configuration is written into every result so that feeding it back reproduces the run.
"""
from __future__ import annotations

import copy
import difflib
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from .catalogue import config_keys
from .errors import DfxcorrError, gain_problem, require_regular_file


class ConfigError(DfxcorrError, ValueError):
    """A configuration key or value is not valid; the message names it."""


@dataclass(frozen=True)
class Option:
    """One configuration option.

    Attributes
    ----------
    default : object
    help : str
    kind : type or tuple of types
        Accepted Python types (after YAML parsing); None is accepted when ``nullable``.
    choices : tuple, optional
    check : callable, optional
        Returns an error text for a bad value, or None.
    nullable : bool
    """

    default: Any
    help: str
    kind: Any
    choices: tuple | None = None
    check: Callable[[Any], str | None] | None = None
    nullable: bool = False


def _positive(v):
    return None if math.isfinite(v) and v > 0 else "must be positive and finite"


def _nonneg(v):
    return None if math.isfinite(v) and v >= 0 else "must not be negative or infinite"


def _fraction(v):
    return None if 0 < v <= 1 else "must lie in (0, 1]"


def _within(lo, hi):
    """A check for ``lo <= v <= hi``: counts and sizes beyond what any scan needs are typing errors (``10**31``
    would overflow the arrays they size, or run for ever)."""
    return lambda v: None if lo <= v <= hi else f"must lie in [{lo:g}, {hi:g}]"


_NUM = (int, float)
#: Largest scatter per unit primary (load.scatter, effects.scatter): thick samples reach several times the primary;
#: beyond this the primary behind it is lost in the scatter's noise (a field scaled by 1e300 underflows to zero).
MAX_SCATTER = 100.0
#: Vibration estimators (``fit.method``): this paper's, its two baselines, and no correction.
METHODS = ("ml", "alternating", "correlation", "none")

SCHEMA: dict[str, dict[str, Option]] = {
    "load": {
        "gain": Option(None, "detector units per photon; null takes /entry/instrument/detector/gain of the file "
                             "(dfxcorr diagnose estimates it as detector_gain)", _NUM, check=gain_problem,
                       nullable=True),
        "electronic": Option(0.0, "electronic noise variance per sample (counts^2), added to gain * mean in the "
                                  "noise weights (dfxcorr diagnose estimates it)", _NUM, check=_nonneg),
        "detector_lag": Option(0.0, "detector lag fraction a (frame j records S_j + a S_(j-1)): taken out of the "
                                    "counts recursively before anything else (dfxcorr diagnose estimates it as "
                                    "detector_lag); 0: none", _NUM, check=lambda v: None if 0 <= v < 1
                               else "must lie in [0, 1)"),
        "pixel_noise": Option(None, "TIFF of per-pixel noise variance factors f (variance f * gain * mean + "
                                    "electronic), e.g. the pixel_noise.tif that dfxcorr diagnose writes; null: 1",
                              str, nullable=True),
        "scatter": Option(0.0, "Compton scatter per unit primary s (1 or more for thick samples): s times the "
                               "superposition of each frame's primary (t^f t on its lit rows, t estimated from the "
                               "scan) under a normalised Gaussian of scatter_width_mm, nothing renormalised (a narrow "
                               "band under a wide kernel gets less than s times its primary), is added to the model's "
                               "unmodulated offset (dfxcorr diagnose estimates it as scatter); 0: none", _NUM,
                          check=_within(0, MAX_SCATTER)),
        "scatter_width_mm": Option(50.0, "std of the scatter's Gaussian kernel at the detector (mm; the scan file's "
                                         "pixel size converts it to pixels)", _NUM, check=_positive),
        "saturation": Option(None, "counts at or above this are saturated (the panel's direct beam) and left out of "
                                   "the fit and the images, with a warning; null: the frames' integer maximum "
                                   "(65535 for uint16), none for float frames", _NUM, check=_positive,
                             nullable=True),
        "allow_external": Option(False, "follow HDF5 external links, external raw storage and virtual datasets of "
                                        "the scan file (each file read is hashed into the provenance); false "
                                        "refuses them", bool),
    },
    "align": {
        "min_frames": Option(3, "detector rows lit in fewer frames are left out (at least the per-pixel unknowns)",
                             int, check=_within(3, 1e6)),
        "min_visibility": Option("auto", "samples whose reference visibility is below this carry no fringe and are "
                                         "left out (region of interest, NaN in the images); auto: a quarter of the "
                                         "95th percentile of the reference visibility; 0 keeps all", (int, float, str),
                                 check=lambda v: None if v == "auto" or (not isinstance(v, str) and 0 <= v < 1)
                                 else "must be auto or lie in [0, 1)"),
        "reference_offset": Option(0.0, "rows by which the whole interferometer sat off during the scan relative to "
                                        "the reference: the flat field is read at u - offset (reference_offset of "
                                        "dfxcorr diagnose)", _NUM,
                                   check=_within(-1e6, 1e6)),
        "position_errors": Option(None, "file (.npy, or text with one number per frame) of per-frame errors delta_j "
                                        "of the recorded positions (rows): frame j's flat field is read at "
                                        "u - delta_j (position_errors.txt of dfxcorr diagnose); null: none", str,
                                  nullable=True),
    },
    "geometry": {
        "parallax": Option(0.0, "rows by which a frame sees the sample displaced along the scan per row the active "
                                "area travels from the detector's centre, kappa (a source that moves with the "
                                "gratings: the sample's height over the source-to-sample distance; beam_path of "
                                "dfxcorr diagnose); 0: the beam paths stay fixed, as in the paper", _NUM,
                           check=_within(-0.9, 0.9)),
    },
    "mask": {
        "enabled": Option(True, "leave pixels whose frames disagree (sample motion, paper Sec. II-E) out of the "
                                "vibration fit (only of it)", bool),
        "threshold": Option(None, "absolute threshold on the motion score (residual relative to what noise and "
                                  "vibration explain); null derives it from the data", _NUM, check=_positive,
                            nullable=True),
        "sigma": Option(6.0, "data-driven threshold: median + sigma robust standard deviations of the score",
                        _NUM, check=_positive),
        "dilate": Option(1, "grow the motion mask by this many pixels", int, check=_within(0, 1e6)),
        "between_rows": Option(0.25, "where the samples read the images between rows (geometry.parallax), also leave "
                                     "out of the vibration fit the pixels where that reading misses more than this "
                                     "many noise standard deviations (the sample's detail finer than a row, moving "
                                     "across the pixels); null: none", _NUM, check=_positive, nullable=True),
    },
    "vibration": {
        "phase_offset": Option(True, "fit phi0_j, the grating shift between exposures", bool),
        "tilt": Option(True, "fit phi1_j, the grating rotation (x phi1_j added to the phase)", bool),
        "visibility": Option("auto", "fit v^s_j, the visibility loss from motion during the exposure; auto: where "
                                     "the acquisition can identify it (not in phase stepping, paper Sec. II-F)",
                             (bool, str), check=lambda v: None if v in (True, False, "auto") else "must be true, false "
                                                                                                  "or auto"),
        "curvature": Option(False, "fit phi2_j (x^2 phi2_j added to the phase)", bool),
        "visibility_tilt": Option(False, "fit v1_j, v2_j (visibility factor v^s_j + x v1_j + x^2 v2_j)", bool),
        "dose": Option(False, "fit d_j, a per-frame factor on the whole expected count", bool),
        "background": Option(False, "fit a smooth additive background b0 + b1 x + b2 y", bool),
        "harmonic": Option(False, "fit a second harmonic of the stepping curve", bool),
    },
    "reference": {
        "step_errors": Option(True, "estimate per-step phase errors of a reference stepping series by the same "
                                    "maximum-likelihood fit (otherwise the nominal steps are taken as exact)", bool),
        "dose": Option("auto", "estimate per-step dose of a reference stepping series (auto: where identifiable, "
                               "i.e. some pixels carry no fringe)", (bool, str),
                       check=lambda v: None if v in (True, False, "auto") else "must be true, false or auto"),
    },
    "fit": {
        "method": Option("ml", "vibration estimator: ml (this paper), alternating, correlation, none", str,
                         choices=METHODS),
        "subsample": Option("auto", "fit on every n-th detector column (paper Sec. II-D.1); auto: the most "
                                    "columns fit.max_samples holds, or the fewest predicted (from a pilot's Fisher "
                                    "information) to reach fit.target_uncertainty, or the most within "
                                    "fit.time_budget (never beyond fit.max_samples nor the alias limit W / 4)",
                            (int, str),
                            check=lambda v: None if v == "auto" or (not isinstance(v, str) and 0 < v <= 10 ** 6)
                            else "must be auto or an integer in [1, 1e6]"),
        "target_uncertainty": Option(None, "subsample auto: predicted median one-sigma uncertainty of phi0 and "
                                            "phi1 (rad) to reach, the fit ending there; null: the Cramer-Rao level "
                                            "of the scan, every column fit.max_samples holds", _NUM,
                                     check=_within(1e-9, 10), nullable=True),
        "time_budget": Option(None, "subsample auto: instead of fit.target_uncertainty, the most columns whose "
                                    "fit is predicted to take at most this many seconds", _NUM,
                              check=_within(1e-3, 1e7),
                              nullable=True),
        "time_floor": Option(None, "subsample auto with fit.target_uncertainty set: at least the columns with which "
                                   "the whole reconstruction is predicted to take this many seconds (the fit and, "
                                   "at their cost per sample of the scan, the other stages), for precision beyond "
                                   "the target where it is cheap; null: none, the fit ends at the target (without "
                                   "a target the fit already takes the most columns)", _NUM,
                             check=_within(0, 1e7), nullable=True),
        "coarse": Option("auto", "from the neutral values (fit.start), run the fit's stages on every n-th of its "
                                 "columns first, then only its last stages on all of them from there (the same "
                                 "minimum in fewer passes over all); auto: n for about a million samples in the "
                                 "first pass; 1: off", (int, str),
                         check=lambda v: None if v == "auto" or (not isinstance(v, str) and 0 < v <= 10 ** 6)
                         else "must be auto or an integer in [1, 1e6]"),
        "max_samples": Option(7_000_000, "subsample auto: most lit samples (rows x frames x columns) the fit "
                                         "may hold (bounds the fit's memory)", int, check=_within(1, 1e12)),
        "column_offset": Option(None, "first column of the subsampled grid; null: subsample // 2", int,
                                check=_nonneg, nullable=True),
        "maxiter": Option(300, "iterations (Gauss-Newton trial steps or L-BFGS iterations) per stage", int,
                          check=_within(1, 1e5)),
        "gtol": Option(1e-3, "stop when the preconditioned gradient is below this (cost per parameter sigma)",
                       _NUM, check=_positive),
        "circmean_iterations": Option(10, "first iterations with the phase image at its circular mean (eq. 36)",
                                      int, check=_within(0, 1e5)),
        "staged": Option(True, "from the neutral values (fit.start), fit phases first, add visibility and other "
                               "effects afterwards (Sec. II-E)", bool),
        "start": Option("pilot", "where reconstruct's maximum-likelihood fit (fit.method: ml) starts. pilot: at "
                                 "the motion mask's pilot estimate where every well-determined frame fits there "
                                 "within noise (the stages of fit.staged and the first pass of fit.coarse are then "
                                 "skipped: it is in the basin of the minimum), else at the neutral values; neutral: "
                                 "always there (diagnose's fits start there or at the previous round's estimate)",
                        str, choices=("pilot", "neutral")),
        "precondition": Option(True, "rescale the fit's variables by the Fisher information", bool),
        "preconditioner": Option("profiled", "profiled: whiten by the whole profiled Fisher information (same "
                                             "minimum, far fewer iterations); diagonal: its plain diagonal, the "
                                             "paper's eq. 34", str, choices=("profiled", "diagonal")),
        "optimizer": Option("gauss-newton", "gauss-newton: Levenberg-Marquardt steps on the profiled Fisher "
                                            "information (a handful of cost evaluations per stage, L-BFGS where "
                                            "they stall); lbfgs: L-BFGS alone (the same minimum)", str,
                            choices=("gauss-newton", "lbfgs")),
        "reweight": Option(1, "refits with noise weights from the fitted model", int, check=_within(0, 100)),
        "visibility_gauge": Option("max", "normalise v^s to a robust maximum of 1 (max) or a median of 1 "
                                          "(median, eq. 22)", str, choices=("max", "median")),
        "visibility_quantile": Option(0.99, "quantile of v^s set to 1 by the max gauge", _NUM, check=_fraction),
        "gauge_fraction": Option(0.5, "frames lighting at least this fraction of the active area define the "
                                      "gauge", _NUM, check=_fraction),
    },
    "retrieve": {
        "iterations": Option(2, "solves with noise weights from the previous model (1: data weights, eq. 6)",
                             int, check=_within(1, 100)),
        "uncorrected": Option(False, "also retrieve the images without vibration correction (written to "
                                     "uncorrected/ and shown by --preview, which turns this on); off by default: "
                                     "it doubles the retrieval's time", bool),
        "block_mb": Option(256, "memory for one block of detector rows in the retrieval and the motion mask (MB): "
                                "pixels are independent there, so the scan is processed in blocks that fit",
                           _NUM, check=_within(1e-9, 1e6)),
    },
    "diagnose": {
        "alpha": Option(0.01, "family-wise false-alarm probability per round (Holm over the effects tried)", _NUM,
                        check=_fraction),
        "subsample": Option(4, "the diagnosis fits and tests on every n-th column (finer than fit.subsample: the "
                               "parameter noise of a coarse fit would read as misfit)", int, check=_within(1, 1e6)),
        "max_samples": Option(5e5, "the diagnosis fits and tests on every n-th column, n at least diagnose.subsample "
                                   "and large enough that they hold at most this many samples (bounds the "
                                   "diagnosis's time on a large scan)", _NUM, check=_within(1e3, 1e12)),
        "max_held_samples": Option(7e6, "the per-pixel tests (sample motion, pixel noise, reference offset, the "
                                        "residual maps) hold at most this many samples, as many as a "
                                        "reconstruction's fit (fit.max_samples): on a larger scan (a clinical one) "
                                        "they see a band of contiguous columns in the middle of the detector, and "
                                        "the fit and the residual signatures still see columns spread over all of "
                                        "it (bounds the diagnosis's memory)", _NUM,
                                   check=_within(1e4, 1e12)),
        "max_rounds": Option(8, "at most this many effects are added", int, check=_within(1, 100)),
        "motion_p": Option(1e-6, "per-pixel p-value below which a pixel's frames disagree", _NUM, check=_fraction),
        "min_pixels": Option(5, "sample_motion needs at least this many flagged pixels", int, check=_within(1, 1e9)),
        "explain_share": Option(0.25, "a significant candidate is added only if a trial refit with it removes at least "
                                      "this share of the excess chi-square of the residual signatures that were "
                                      "significant (it must explain the misfit's signature, not merely some of its "
                                      "chi-square)", _NUM, check=_fraction),
        "order": Option("mean-first", "which candidates a round tries first: the mean effects, then the noise model "
                                      "before the localised ones (mean-first), or the noise model first (noise-first);"
                                      " the decisions must not depend on it", str,
                        choices=("mean-first", "noise-first")),
        "proxy_spread": Option(1.0, "a candidate whose size, estimated on pixels in strata of count or of detector "
                                    "row or column, spans more than this many times the shared fit's (and "
                                    "significantly) is refused as a proxy for an effect in no catalogue: a real "
                                    "effect has one size",
                               _NUM, check=_nonneg),
        "replicate": Option(True, "refit the final model on disjoint halves of the detector (by columns; by rows too "
                                  "in phase stepping) and report whether each finding's estimates agree within their "
                                  "errors there; a finding that does not replicate is left out of the recommended "
                                  "reconstruction", bool),
        "min_gain_change": Option(0.01, "detector_gain is reported only when the gain also moves by more than this "
                                        "fraction (a practical floor: with millions of samples smaller changes are "
                                        "significant but immaterial)", _NUM, check=_nonneg),
    },
    "export": {
        "compression": Option("gzip", "HDF5 compression of the images", str, choices=("gzip", "lzf", "none")),
    },
}

#: Configuration keys of the vibration section -> catalogue effects (from the catalogue's entries).
VIBRATION_EFFECTS = config_keys("vibration")


def option(key: str, schema: dict = SCHEMA) -> Option:
    """The option of a dotted key 'section.key'."""
    section, name = key.split(".", 1)
    return schema[section][name]


def get(cfg: dict, key: str) -> Any:
    """The value of a dotted key 'section.key' in a resolved configuration."""
    section, name = key.split(".", 1)
    return cfg[section][name]


def reference_effects(cfg: dict) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The per-step effects a reference stepping series is fitted with (``reference.*``), and those only where
    identifiable ('auto')."""
    asked = (("phase_offset", cfg["reference"]["step_errors"]), ("dose", cfg["reference"]["dose"]))
    return tuple(e for e, on in asked if on is not False), tuple(e for e, on in asked if on == "auto")


def defaults(schema: dict = SCHEMA) -> dict:
    """The default configuration as a nested dict."""
    return {sec: {k: copy.deepcopy(o.default) for k, o in opts.items()} for sec, opts in schema.items()}


#: Longest excerpt of a value or name quoted in a message.
SHOW_CHARS = 60
#: Largest configuration file read (bytes); a real one is a few kB.
MAX_FILE_BYTES = 1 << 20


def show(value: Any, *, quote: bool = True, limit: int = SHOW_CHARS) -> str:
    """A value for a message (repr, or the text itself without ``quote``), cut to ``limit`` characters."""
    text = value if isinstance(value, str) and not quote else repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


class _StrictLoader(yaml.SafeLoader):
    """YAML that cannot expand: aliases (``*name``, what "billion laughs" files are made of) and repeated
    keys (a repeated section would silently drop the earlier one) are refused, naming the line."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.MarkedYAMLError(problem=f"line {event.start_mark.line + 1}: aliases "
                                               f"(*{show(event.anchor, quote=False)}) "
                                               f"are not accepted in a configuration; write the value out")
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            try:
                if key in seen:
                    raise yaml.MarkedYAMLError(problem=f"line {line}: duplicate key {show(key)} "
                                                       f"(first on line {seen[key]})")
                seen[key] = line
            except TypeError:  # an unhashable key: SafeLoader refuses it with its own message
                break
        return super().construct_mapping(node, deep=deep)


# YAML 1.1 reads 1e-5 (an exponent without a decimal point) as a string; YAML 1.2 and every user read a number
_StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float",
                                    re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
                                    list("-+0123456789"))


class _TextLoader(_StrictLoader):
    """:class:`_StrictLoader` reading every scalar as text: identifiers stay as written (YAML 1.1 would read
    00123 as the octal 83 and 14:30:00 as seconds)."""


_TextLoader.yaml_implicit_resolvers = {}


def parse_yaml(text: str, *, as_text: bool = False) -> Any:
    """Parse configuration YAML with :class:`_StrictLoader` (no aliases, no duplicate keys).

    ``as_text`` reads every scalar as a string (no numbers, booleans, dates or nulls).
    """
    loader = (_TextLoader if as_text else _StrictLoader)(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def _yaml_problem(exc: yaml.YAMLError) -> str:
    problem = getattr(exc, "problem", None) or str(exc)
    mark = getattr(exc, "problem_mark", None)
    where = f"line {mark.line + 1}: " if mark is not None and not problem.startswith("line ") else ""
    return show(where + problem, quote=False, limit=3 * SHOW_CHARS)


def _nearest(word: str, candidates) -> str:
    match = difflib.get_close_matches(word, list(candidates), n=1, cutoff=0.5)
    return f"; did you mean {match[0]!r}?" if match else f"; valid: {', '.join(candidates)}"


def validate_value(section: str, key: str, value: Any, schema: dict = SCHEMA) -> Any:
    """Check one value against the schema; returns it (ints accepted where floats are)."""
    opt = schema[section][key]
    name = f"{section}.{key}"
    if value is None:
        if opt.nullable:
            return None
        raise ConfigError(f"{name} must not be null")
    kinds = opt.kind if isinstance(opt.kind, tuple) else (opt.kind,)
    if (isinstance(value, bool) and bool not in kinds) or not isinstance(value, kinds):
        raise ConfigError(f"{name} must be {' or '.join(k.__name__ for k in kinds)}, got {show(value)}")
    if opt.choices and value not in opt.choices:
        raise ConfigError(f"{name} must be one of {', '.join(map(str, opt.choices))}, got {show(value)}"
                          + (_nearest(value[:SHOW_CHARS], opt.choices) if isinstance(value, str) else ""))
    if opt.check:
        problem = opt.check(value)
        if problem:
            raise ConfigError(f"{name} {problem}, got {show(value)}")
    return value


def merge(base: dict, overlay: dict, *, origin: str = "configuration", schema: dict = SCHEMA) -> dict:
    """Overlay a (partial) configuration onto a full one, validating every key and value."""
    if overlay is None:
        return base
    if not isinstance(overlay, dict):
        raise ConfigError(f"{origin}: expected a mapping of sections, got {type(overlay).__name__}")
    out = copy.deepcopy(base)
    for section, values in overlay.items():
        if section not in schema:
            raise ConfigError(f"{origin}: unknown section {show(section)}{_nearest(str(section)[:SHOW_CHARS], schema)}")
        if values is None:
            continue
        if not isinstance(values, dict):
            raise ConfigError(f"{origin}: section {section!r} must be a mapping")
        for key, value in values.items():
            if key not in schema[section]:
                raise ConfigError(f"{origin}: unknown key {section}.{show(key, quote=False)}"
                                  f"{_nearest(str(key)[:SHOW_CHARS], schema[section])}")
            out[section][key] = validate_value(section, key, value, schema)
    return out


def parse_set(item: str) -> dict:
    """``section.key=value`` (value parsed as YAML) -> {section: {key: value}}."""
    if "=" not in item or "." not in item.split("=", 1)[0]:
        raise ConfigError(f"--set {show(item)}: expected section.key=value")
    path, raw = item.split("=", 1)
    section, key = path.strip().split(".", 1)
    try:
        value = parse_yaml(raw) if raw.strip() else None
    except yaml.YAMLError as exc:
        raise ConfigError(f"--set {show(item)}: value is not valid YAML ({_yaml_problem(exc)})") from None
    return {section: {key: value}}


def load(files=(), sets=(), *, schema: dict = SCHEMA) -> dict:
    """Resolve a configuration: defaults, then each YAML file, then each ``section.key=value``.

    Raises
    ------
    ConfigError
        Naming the file and the bad key or value.
    """
    cfg = defaults(schema)
    for f in files:
        path = Path(f)
        require_regular_file(path, "configuration")
        try:
            with open(path, "rb") as fh:
                raw = fh.read(MAX_FILE_BYTES + 1)
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read ({exc.strerror})") from None
        if len(raw) > MAX_FILE_BYTES:
            raise ConfigError(f"{path}: larger than {MAX_FILE_BYTES // 1024} kB, not a configuration file")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ConfigError(f"{path}: not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start})") from None
        try:
            data = parse_yaml(text)
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML ({_yaml_problem(exc)})") from None
        cfg = merge(cfg, data or {}, origin=str(path), schema=schema)
    for item in sets:
        cfg = merge(cfg, parse_set(item), origin=f"--set {show(item, quote=False)}", schema=schema)
    return cfg


def input_files(cfg: dict) -> list[str]:
    """Files a resolved configuration names as inputs (``load.pixel_noise``, ``align.position_errors``): no output
    may replace them."""
    return [p for p in (cfg["load"]["pixel_noise"], cfg["align"]["position_errors"]) if p is not None]


def effects_of(cfg: dict) -> tuple[str, ...]:
    """Catalogue effects switched on in the vibration section, in catalogue order ('auto' counts as on)."""
    return tuple(effect for key, effect in VIBRATION_EFFECTS.items() if cfg["vibration"][key] is not False)


def dump(cfg: dict) -> str:
    """YAML of a resolved configuration."""
    return yaml.safe_dump(cfg, sort_keys=False)


def as_sets(cfg: dict, *, skip: tuple[str, ...] = (), schema: dict = SCHEMA) -> list[str]:
    """The ``section.key=value`` options (values as YAML) that turn the defaults into ``cfg``, sections in
    ``skip`` left out: what reproduces a resolved configuration on a command line."""
    base = defaults(schema)
    out = []
    for section, opts in cfg.items():
        if section in skip:
            continue
        for key, value in opts.items():
            if value != base[section][key]:
                text = yaml.safe_dump(value, default_flow_style=True, width=1 << 30).strip()
                out.append(f"{section}.{key}={text.removesuffix('...').strip()}")
    return out


def commented_defaults(schema: dict = SCHEMA, *, title: str = "dfxcorr reconstruct SCAN -c this.yaml") -> str:
    """The default configuration as YAML with every option's help as a comment."""
    lines = ["# dfxcorr configuration: every option with its default.",
             f"# Use with `{title}`; override with --set section.key=value.", ""]
    for section, opts in schema.items():
        lines.append(f"{section}:")
        for key, opt in opts.items():
            extra = f" [{' | '.join(map(str, opt.choices))}]" if opt.choices else ""
            lines.append(f"  # {opt.help}{extra}")
            value = yaml.safe_dump({key: opt.default}, default_flow_style=True).strip()[1:-1]
            lines.append(f"  {value}")
        lines.append("")
    return "\n".join(lines)
