"""Validation of model parameters: a bad value raises :class:`ConfigError` naming the field,
the value (with its unit) and the rule it breaks."""
from __future__ import annotations

import numpy as np

from dermis.pipeline.errors import ConfigError

__all__ = ["format_value", "checked_array", "require"]


def format_value(v) -> str:
    """A value on one line for an error message."""
    return str(np.asarray(v).tolist()) if np.ndim(v) else f"{v}"


def checked_array(value, name: str, shape: tuple[int, ...], unit: str = "") -> np.ndarray:
    """``value`` as a float64 array of ``shape`` with finite entries, else ConfigError."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} = {value!r}{unit}: must be numbers of shape {shape}") from None
    if a.shape != shape:
        raise ConfigError(f"{name} = {format_value(a)}{unit}: must have shape {shape}, "
                          f"got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{name} = {format_value(a)}{unit}: must be finite")
    return a


def require(ok, name: str, value, unit: str, rule: str) -> None:
    """ConfigError "``name`` = value unit: ``rule``" unless every entry of ``ok`` holds."""
    if not np.all(ok):
        raise ConfigError(f"{name} = {format_value(value)}{unit}: {rule}")

