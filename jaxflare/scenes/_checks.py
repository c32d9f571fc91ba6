"""Validation primitives for scene values: each failure is a :class:`SceneError` naming the key
(``light[1].intensity``) and what would be valid."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np


class SceneError(ValueError):
    """A scene (file or Python object) that cannot be rendered; the message names the key."""


def fail(where: str, message: str):
    raise SceneError(f"{where}: {message}")


def number(
    where: str, value: Any, *, minimum: float | None = None, exclusive: bool = False, allow_inf: bool = False, maximum: float | None = None
) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        fail(where, f"must be a number, got {value!r}")
    try:
        value = float(value)
    except OverflowError:
        fail(where, f"must be finite, got {value!r}")
    if math.isnan(value) or (math.isinf(value) and not allow_inf):
        fail(where, f"must be finite, got {value!r}")
    if minimum is not None and (value < minimum or (exclusive and value == minimum)):
        fail(where, f"must be {'>' if exclusive else '>='} {minimum:g}, got {value:g}")
    if maximum is not None and value > maximum and not (allow_inf and math.isinf(value)):
        fail(where, f"must be at most {maximum:g}, got {value:g}")
    return value


def vector(where: str, value: Any, length: int = 3, *, non_negative: bool = False) -> tuple[float, ...]:
    if isinstance(value, (str, bytes)) or not isinstance(value, (Sequence, np.ndarray)) or len(value) != length:
        fail(where, f"must be a list of {length} numbers, got {value!r}")
    numbers = tuple(number(f"{where}[{k}]", v, minimum=0.0 if non_negative else None) for k, v in enumerate(value))
    return numbers


def choice(where: str, value: Any, choices: Sequence[str]) -> str:
    if not isinstance(value, str) or value not in choices:
        fail(where, f"must be one of {', '.join(repr(c) for c in choices)} (as written), got {value!r}")
    return value


def integer(where: str, value: Any, minimum: int | None = None, maximum: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        fail(where, f"must be an integer, got {value!r}")
    if minimum is not None and value < minimum:
        fail(where, f"must be >= {minimum}, got {value}")
    if maximum is not None and value > maximum:
        fail(where, f"must be at most {maximum:,}, got {value:,}")
    return int(value)


def sequence(where: str, value: Any, what: str) -> list:
    """``value`` as a list, or a :class:`SceneError` saying that a list was expected there."""
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
        fail(where, f"must be a list of {what}, got {value!r}")
    return list(value)
