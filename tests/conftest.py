"""Shared fixtures: small simulated scans and the location of ../shared/data."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dfxcorr import config as C
from dfxcorr.sim import simulate as S

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared_path(*parts) -> Path:
    """A path under ../shared/data, skipping the test where it is absent (a fresh clone)."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"{p} is absent")
    return p


def real_ipp_scan(tmp_path) -> Path:
    """The shared real phase-stepping recording imported into ``tmp_path / 'ipp.h5'`` (skips where it is absent)."""
    from dfxcorr.importer import import_stepping

    folder = shared_path("real", "tum-ipp-stepping")
    import_stepping(tmp_path / "ipp.h5", sample=str(folder / "data_stepping_*.npy"),
                    reference=str(folder / "flat_stepping_*.npy"), steps_per_period=11)
    return tmp_path / "ipp.h5"


def sim_config(**overrides) -> dict:
    """A small scan: 5 mm pixels (90 x 102), active area 15 rows moving 1 row per frame (104 frames).

    ``overrides`` are 'section.key' -> value (dots as double underscores in keyword form are not needed:
    pass a dict via **{"effects.dose": 0.02}).
    """
    cfg = C.defaults(S.SCHEMA)
    cfg["simulate"].update(pixel_mm=5.0, step_mm=5.0, seed=1)
    for key, value in overrides.items():
        section, name = key.split(".")
        cfg = C.merge(cfg, {section: {name: value}}, schema=S.SCHEMA)
    return cfg


@pytest.fixture
def small_scan():
    """Factory: (scan, truth) of :func:`sim_config` with overrides."""
    def make(**overrides):
        return S.simulate(sim_config(**overrides))
    return make


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
