"""Parameter rules, without importing torch: ``(check, expectation)`` pairs.

A rule is read twice from one place: the config checks (``resireg_train.checks.train`` and ``.eval``) report
``key=value: expected <expectation>`` for a bad config value before anything heavy loads, and
the classes (:class:`resireg.method.full.ReSiRegFull`, ...) raise
``<name> must be <expectation>, got <value>`` for a bad keyword from Python
(:func:`check_kwargs`). The tables of :mod:`resireg.specs` hold the rules of each kind.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from typing import Any

__all__ = [
    "BATCH_SIZE",
    "DEVICE",
    "DEVICE_KINDS",
    "Rule",
    "check_batch_size",
    "check_kwargs",
    "checked",
    "finite",
    "integer",
    "interval",
    "is_int",
    "is_num",
    "number",
    "one_of",
    "optional_int",
]

#: ``(check, what is expected)``: ``check(value)`` is True for an accepted value.
Rule = tuple[Callable[[Any], bool], str]


def is_int(v: Any) -> bool:
    """An integer, not a bool."""
    return isinstance(v, int) and not isinstance(v, bool)


def is_num(v: Any) -> bool:
    """An int or float, not a bool (NaN and inf included)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def integer(minimum: int) -> Rule:
    return (lambda v: is_int(v) and v >= minimum), f"an integer >= {minimum}"


def optional_int(minimum: int) -> Rule:
    return (lambda v: v is None or (is_int(v) and v >= minimum)), f"null or an integer >= {minimum}"


def number(minimum: float, strict: bool = False, finite: bool = False) -> Rule:
    """A number ``>= minimum`` (``> minimum`` if ``strict``; not inf if ``finite``)."""

    def check(v: Any) -> bool:
        if not is_num(v) or math.isnan(v) or (finite and not math.isfinite(v)):
            return False
        return v > minimum if strict else v >= minimum

    what = f"a number {'>' if strict else '>='} {minimum:g}{' (finite)' if finite else ''}"
    return check, what


def finite() -> Rule:
    """Any finite number (not NaN, not inf)."""
    return (lambda v: is_num(v) and math.isfinite(v)), "a finite number"


def interval(low: float, high: float) -> Rule:
    """A number in ``[low, high]`` (NaN fails every comparison)."""
    return (lambda v: is_num(v) and low <= v <= high), f"a number in [{low:g}, {high:g}]"


def one_of(choices: Iterable[Any]) -> Rule:
    choices = tuple(choices)
    return (lambda v: v in choices), f"one of {list(choices)}"


def checked(name: str, value: Any, rule: Rule) -> Any:
    """``value`` if ``rule`` accepts it, else ``ValueError("<name> must be <expected>, got
    <value>")``."""
    check, expected = rule
    if not check(value):
        raise ValueError(f"{name} must be {expected}, got {value!r}")
    return value


def check_kwargs(rules: Mapping[str, Rule], values: Mapping[str, Any]) -> None:
    """:func:`checked` for each of ``values`` that ``rules`` has a rule for."""
    for name, value in values.items():
        if name in rules:
            checked(name, value, rules[name])


#: The devices a ``device`` setting names: ``auto`` (cuda where available), ``cpu``, ``cuda``
#: (``cuda:N``) or ``mps``.
DEVICE_KINDS = ("auto", "cpu", "cuda", "mps")
#: The rule of every ``device`` setting (the CLIs' config checks and the live node's).
DEVICE: Rule = (
    lambda v: isinstance(v, str) and v.split(":")[0] in DEVICE_KINDS,
    "auto, cpu, cuda, cuda:N or mps",
)

#: Images (3D: frames) per batch: the rule of every ``batch_size`` (the config checks'
#: ``batch_size`` keys and :func:`check_batch_size`, which every loader, task and the prototype
#: heuristic call).
BATCH_SIZE: Rule = integer(1)


def check_batch_size(value: Any, name: str = "batch_size") -> int:
    """``value`` if it is a batch size (:data:`BATCH_SIZE`), else ``ValueError("<name> must be an
    integer >= 1, got <value>")``: the one batch-size check of the library and the engines."""
    return checked(name, value, BATCH_SIZE)
