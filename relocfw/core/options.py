"""Checks for plugin constructor arguments: one message naming the option."""

from __future__ import annotations

import math
from typing import Any

from relocfw.core.errors import ConfigError


def integer_at_least(name: str, value: Any, minimum: int) -> int:
    """`value` as an int >= minimum, or a ConfigError naming `name`."""
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise ConfigError(f"{name} must be an integer, got {value!r}")
    try:
        number = int(value)
    except ValueError:
        raise ConfigError(f"{name} must be an integer, got {value!r}") from None
    if number != float(value):
        raise ConfigError(f"{name} must be an integer, got {value!r}")
    if number < minimum:
        raise ConfigError(f"{name} must be at least {minimum}, got {number}")
    return number


def probability(name: str, value: Any) -> float:
    """`value` as a float in [0, 1], or a ConfigError naming `name`."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number in [0, 1], got {value!r}") from None
    if not 0.0 <= number <= 1.0:
        raise ConfigError(f"{name} must be a probability in [0, 1], got {number}")
    return number


def real_number(name: str, value: Any) -> float:
    """`value` as a finite float, or a ConfigError naming `name`."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    if number != number or number in (float("inf"), float("-inf")):
        raise ConfigError(f"{name} must be finite, got {value!r}")
    return number


def positive_number(key: str, value: Any, most: float | None = None) -> float:
    """`value` as a finite float > 0 (and <= `most`), or a ConfigError naming `key`."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{key} must be a number, got {value!r}") from None
    if not (math.isfinite(number) and number > 0 and (most is None or number <= most)):
        bound = f" and at most {most:g}" if most is not None else ""
        raise ConfigError(f"{key} must be above 0{bound}, got {value!r}")
    return number
