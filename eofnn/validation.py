"""Declarative validation of configuration values (scikit-learn's ``_parameter_constraints`` style).

A config dataclass lists its constraints once, ``_constraints = {"r0_m": Interval(0, None, closed="neither",
unit="m")}``, and :func:`check` turns any value that breaks one into a one-line :class:`~eofnn.errors.ConfigError`
that names the value and what is allowed: ``r0_m=-0.1 is invalid: it must be a number > 0 (m)``. Numbers must be
finite and of a numeric type (``bool`` and strings are refused), so ``.nan``, ``.inf``, ``null`` and ``'two'`` in
a YAML file are caught here rather than deep inside a simulation.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from eofnn.errors import ConfigError


class Constraint(ABC):
    """A predicate on one value, with the words that describe what it allows."""

    @abstractmethod
    def accepts(self, value: Any) -> bool:
        """Whether ``value`` is allowed."""

    @abstractmethod
    def describe(self) -> str:
        """What is allowed, as the end of "it must be ..."."""


def _is_number(value: Any, integer: bool) -> bool:
    if isinstance(value, bool):
        return False
    if integer:
        return isinstance(value, numbers.Integral)
    return isinstance(value, numbers.Real) and math.isfinite(float(value))


@dataclass(frozen=True)
class Interval(Constraint):
    """A finite number (or an integer) between ``low`` and ``high``; ``None`` leaves a side open.

    ``closed`` says which ends are allowed: ``"both"``, ``"left"``, ``"right"`` or ``"neither"``.
    """

    low: float | None = None
    high: float | None = None
    closed: str = "both"
    integer: bool = False
    unit: str = ""

    def accepts(self, value: Any) -> bool:
        if not _is_number(value, self.integer):
            return False
        left_ok = self.low is None or (value >= self.low if self.closed in ("both", "left") else value > self.low)
        right_ok = self.high is None or (value <= self.high if self.closed in ("both", "right") else value < self.high)
        return left_ok and right_ok

    def describe(self) -> str:
        kind = "an integer" if self.integer else "a finite number"
        left, right = self.closed in ("both", "left"), self.closed in ("both", "right")
        if self.low is not None and self.high is not None:
            bounds = f" in {'[' if left else '('}{self.low:g}, {self.high:g}{']' if right else ')'}"
        elif self.low is not None:
            bounds = f" {'>=' if left else '>'} {self.low:g}"
        elif self.high is not None:
            bounds = f" {'<=' if right else '<'} {self.high:g}"
        else:
            bounds = ""
        return kind + bounds + (f" ({self.unit})" if self.unit else "")


@dataclass(frozen=True)
class OneOf(Constraint):
    """One of a fixed set of values (strings, usually)."""

    values: tuple

    def accepts(self, value: Any) -> bool:
        try:
            return value in self.values and not isinstance(value, bool)
        except TypeError:  # an unhashable value (a list, a dict) is never one of the options
            return False

    def describe(self) -> str:
        return "one of " + ", ".join(str(v) for v in self.values)


@dataclass(frozen=True)
class IsBool(Constraint):
    """``true`` or ``false``."""

    def accepts(self, value: Any) -> bool:
        return isinstance(value, bool)

    def describe(self) -> str:
        return "true or false"


@dataclass(frozen=True)
class IsString(Constraint):
    """A non-empty string."""

    def accepts(self, value: Any) -> bool:
        return isinstance(value, str) and bool(value)

    def describe(self) -> str:
        return "a non-empty string"


@dataclass(frozen=True)
class OrNone(Constraint):
    """``null``, or a value that ``inner`` accepts."""

    inner: Constraint

    def accepts(self, value: Any) -> bool:
        return value is None or self.inner.accepts(value)

    def describe(self) -> str:
        return f"null or {self.inner.describe()}"


@dataclass(frozen=True)
class Either(Constraint):
    """A value that ``first`` or ``second`` accepts."""

    first: Constraint
    second: Constraint

    def accepts(self, value: Any) -> bool:
        return self.first.accepts(value) or self.second.accepts(value)

    def describe(self) -> str:
        return f"{self.first.describe()}, or {self.second.describe()}"


POSITIVE = Interval(0, None, closed="neither")
NON_NEGATIVE = Interval(0, None)
FINITE = Interval()
COUNT = Interval(1, None, integer=True)
FRACTION = Interval(0, 1, closed="right")


def check_value(name: str, value: Any, constraint: Constraint, where: str = "") -> None:
    """Raise a one-line :class:`ConfigError` unless ``constraint`` accepts ``value``."""
    if not constraint.accepts(value):
        raise ConfigError(f"{where}{name}={value!r} is invalid: it must be {constraint.describe()}")


def check(obj: Any, constraints: dict[str, Constraint], where: str = "") -> None:
    """Check the attributes of ``obj`` named in ``constraints``; the first that fails raises."""
    for name, constraint in constraints.items():
        check_value(name, getattr(obj, name), constraint, where)


def validated(cls: type) -> type:
    """Class decorator (put it under ``@dataclass``): after ``__init__``, check the class's ``_constraints``.

    The class's own ``__post_init__``, if any, runs after the checks, so it may rely on valid field values.
    A decorator rather than a base class keeps config dataclasses *pure* dataclasses (jsonargparse needs that).
    """
    own = cls.__dict__.get("__post_init__")

    def __post_init__(self) -> None:
        check(self, getattr(type(self), "_constraints", {}), getattr(type(self), "_where", ""))
        if own is not None:
            own(self)

    cls.__post_init__ = __post_init__
    return cls


def from_mapping(cls: type, value: Any, where: str, *, sort_allowed: bool = True,
                 check_keys: Callable[[dict], None] | None = None) -> Any:
    """``value`` as a ``cls`` (a config dataclass): an instance as it is, a mapping of its fields built. Anything else,
    an unknown key (the allowed ones listed, sorted unless ``sort_allowed`` is false) and a wrong type deep inside
    are each one line that names ``where``; ``check_keys(value)``, if given, runs after the unknown-key check (e.g.
    for keys that must be there)."""
    if isinstance(value, cls):
        return value
    if not isinstance(value, dict):
        raise ConfigError(f"{where} must be a mapping, got {type(value).__name__}")
    allowed = [f.name for f in dataclasses.fields(cls) if not f.name.startswith("_")]
    unknown = sorted(map(str, set(value) - set(allowed)))
    if unknown:
        raise ConfigError(f"unknown key(s) {', '.join(unknown)} in {where}: allowed are "
                          f"{', '.join(sorted(allowed) if sort_allowed else allowed)}")
    if check_keys is not None:
        check_keys(value)
    try:
        return cls(**value)
    except TypeError as err:  # a wrong type deep inside a comparison
        raise ConfigError(f"invalid value in {where}: {err}") from None
