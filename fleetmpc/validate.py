"""Small validators for frozen configuration dataclasses; each error names its field."""

import math
from collections.abc import Sequence

from fleetmpc.errors import ConfigError

__all__ = ["finite", "in_range", "positive", "vector"]


def finite(field: str, value: float) -> float:
    """Return `value` as a float, or raise if it is not a finite number."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ConfigError(field, f"must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise ConfigError(field, f"must be finite, got {value!r}")
    return x


def positive(field: str, value: float, *, allow_zero: bool = False) -> float:
    """Return `value` if it is finite and > 0 (or >= 0 with `allow_zero`)."""
    x = finite(field, value)
    if x < 0 or (x == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ConfigError(field, f"must be {bound}, got {value!r}")
    return x


def in_range(field: str, value: float, lo: float, hi: float) -> float:
    """Return `value` if it is finite and lo <= value <= hi."""
    x = finite(field, value)
    if not lo <= x <= hi:
        raise ConfigError(field, f"must be in [{lo}, {hi}], got {value!r}")
    return x


def vector(field: str, value: Sequence[float], length: int) -> tuple[float, ...]:
    """Return `value` as a tuple of `length` finite floats."""
    if isinstance(value, str) or not isinstance(value, Sequence) or len(value) != length:
        raise ConfigError(field, f"must be a list of {length} numbers, got {value!r}")
    return tuple(finite(f"{field}[{i}]", v) for i, v in enumerate(value))
