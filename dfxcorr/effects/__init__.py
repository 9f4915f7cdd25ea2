"""Every effect of ``spec/diagnosis.md`` behind one interface (:class:`~dfxcorr.effects.base.EffectBase`).

The registry :data:`REGISTRY` holds them in the order the diagnosis tests them and the preparation
applies their configured corrections: the model's channel effects (one implementation over the
catalogue, :mod:`dfxcorr.effects.channel`), then one module per effect that acts on the pixel set, the
noise model, the alignment or the counts. Adding an effect is adding a module and a line here.
"""
from __future__ import annotations

from typing import Any

from . import (
               beam_path,
               channel,
               detector_gain,
               detector_lag,
               electronic_noise,
               pixel_noise,
               position_error,
               reference_offset,
               sample_motion,
               scatter,
)
from .base import EffectBase

_ALL: tuple[EffectBase[Any], ...] = (
    *channel.EFFECTS,
    sample_motion.EFFECT,
    detector_gain.EFFECT,
    electronic_noise.EFFECT,
    reference_offset.EFFECT,
    position_error.EFFECT,
    beam_path.EFFECT,
    detector_lag.EFFECT,
    pixel_noise.EFFECT,
    scatter.EFFECT,
)
#: Effect name -> its implementation, in the order they are tested.
REGISTRY: dict[str, EffectBase[Any]] = {e.name: e for e in _ALL}
