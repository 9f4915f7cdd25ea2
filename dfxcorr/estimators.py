"""The vibration estimators of ``fit.method``: the paper's maximum likelihood and the published baselines.

Each is a function of the fit's observations with its own typed keyword options; :data:`ESTIMATORS` says
which options of the configuration's ``fit`` section each one takes, so that none is handed options it
does not have.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .baselines import fit_alternating, fit_correlation
from .fit import FitResult, fit_vibrations

#: on_iteration(stage name, cost): a progress callback.
Progress = Callable[[str, float], None]


@dataclass(frozen=True)
class Estimator:
    """A vibration estimator and the options it takes.

    Attributes
    ----------
    fit : callable
        (observations, effects=..., **options) -> FitResult.
    keys : tuple of str
        Keys of the configuration's ``fit`` section passed on as keyword options of the same name.
    progress : bool
        It reports its iterations through ``on_iteration``.
    """

    fit: Callable[..., FitResult]
    keys: tuple[str, ...]
    progress: bool = True

    def options(self, fit_cfg: dict, *, on_iteration: Progress | None = None) -> dict[str, Any]:
        """Its keyword options from the configuration's ``fit`` section (and the progress callback)."""
        out = {k: fit_cfg[k] for k in self.keys}
        if self.progress and on_iteration is not None:
            out["on_iteration"] = on_iteration
        return out


_GAUGE = ("visibility_gauge", "visibility_quantile", "gauge_fraction")

#: The estimator of each ``fit.method`` (:data:`dfxcorr.config.METHODS`) but 'none'.
ESTIMATORS = {
    "ml": Estimator(fit_vibrations, ("circmean_iterations", "staged", "maxiter", "gtol", "precondition",
                                     "preconditioner", "optimizer", "reweight", "coarse", *_GAUGE)),
    "alternating": Estimator(fit_alternating, ("maxiter", "gtol", "reweight", *_GAUGE)),
    "correlation": Estimator(fit_correlation, ("gauge_fraction",), progress=False),
}
