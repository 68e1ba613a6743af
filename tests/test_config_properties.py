"""Property tests of the config types (hypothesis): any finite value in a field's range is accepted, anything else
(out of range, non-finite, of the wrong type) is refused with one line that names the field and the value."""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from eofnn.data.stream import DataConfig
from eofnn.errors import ConfigError
from eofnn.evaluation.config import EvaluationConfig
from eofnn.sim.atmosphere.turbulence import Atmosphere, Layer
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.loop.plant import Plant
from eofnn.training.task import OptimizationConfig
from eofnn.validation import Interval, OneOf

#: Fields whose range is their only constraint (no cross-field rule), per config type.
FIELDS = [(cls, name) for cls in (Layer, Atmosphere, Plant, DataConfig, OptimizationConfig)
          for name, c in cls._constraints.items() if isinstance(c, Interval)]
FIELDS += [(ActuatorGrid, "diameter_m"), (EvaluationConfig, "strehl_wavelength_m"),
           (EvaluationConfig, "divergence_factor"), (EvaluationConfig, "seed")]
#: (Atmosphere.kernel is left out: which kernels a model allows is a cross-field rule, tested with the models.)
CHOICES = [(cls, name) for cls in (Atmosphere, Plant, OptimizationConfig)
           for name, c in cls._constraints.items() if isinstance(c, OneOf) and (cls, name) != (Atmosphere, "kernel")]
SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
#: Fields whose largest values make another, derived limit bite (frames x realisations x rounds).
PRODUCT_LIMITED = {(DataConfig, "frames"), (DataConfig, "realisations"), (DataConfig, "refit_rounds")}


def _inside(c: Interval) -> st.SearchStrategy:
    low = c.low if c.low is not None else -1e6
    high = c.high if c.high is not None else 1e6
    if c.integer:
        lo = math.ceil(low) + (0 if c.closed in ("both", "left") or low != math.ceil(low) else 1)
        hi = math.floor(high) - (0 if c.closed in ("both", "right") or high != math.floor(high) else 1)
        return st.integers(lo, hi)
    return st.floats(low, high, allow_nan=False, allow_infinity=False,
                     exclude_min=c.closed in ("neither", "right"), exclude_max=c.closed in ("neither", "left"))


def _outside(c: Interval) -> st.SearchStrategy:
    bad = [st.just(float("nan")), st.just(float("inf")), st.just(float("-inf")), st.text(max_size=5), st.none(),
           st.lists(st.integers(), max_size=2), st.booleans()]
    if c.integer:
        if c.low is not None:
            bad.append(st.integers(max_value=math.ceil(c.low) - 1))
        if c.high is not None:
            bad.append(st.integers(min_value=math.floor(c.high) + 1))
        bad.append(st.floats(allow_nan=False, allow_infinity=False).filter(lambda v: v != int(v)))
        return st.one_of(*bad)
    if c.low is not None:
        bad.append(st.floats(max_value=c.low, allow_nan=False, allow_infinity=False,
                             exclude_max=c.closed in ("both", "left")).filter(lambda v: v < c.low or c.closed in
                                                                               ("neither", "right")))
    if c.high is not None:
        bad.append(st.floats(min_value=c.high, allow_nan=False, allow_infinity=False,
                             exclude_min=c.closed in ("both", "right")).filter(lambda v: v > c.high or c.closed in
                                                                                ("neither", "left")))
    return st.one_of(*bad)


@pytest.mark.parametrize("cls, name", FIELDS, ids=[f"{c.__name__}.{n}" for c, n in FIELDS])
@SETTINGS
@given(data=st.data())
def test_any_value_in_range_is_accepted(cls, name, data):
    constraint = cls._constraints[name]
    value = data.draw(_inside(constraint))
    others = {"frames": 1000, "realisations": 1, "refit_rounds": 0} if (cls, name) in PRODUCT_LIMITED else {}
    obj = cls(**{**others, name: value})
    assert getattr(obj, name) == value


@pytest.mark.parametrize("cls, name", FIELDS, ids=[f"{c.__name__}.{n}" for c, n in FIELDS])
@SETTINGS
@given(data=st.data())
def test_anything_else_is_refused_in_one_line(cls, name, data):
    value = data.draw(_outside(cls._constraints[name]))
    with pytest.raises(ConfigError) as info:
        cls(**{name: value})
    message = str(info.value)
    assert "\n" not in message and f"{name}=" in message and "is invalid" in message


@pytest.mark.parametrize("cls, name", CHOICES, ids=[f"{c.__name__}.{n}" for c, n in CHOICES])
@SETTINGS
@given(value=st.one_of(st.text(max_size=8), st.integers(), st.none(), st.booleans()))
def test_choices_accept_their_options_only(cls, name, value):
    options = cls._constraints[name].values
    for option in options:
        assert getattr(cls(**{name: option}), name) == option
    if value in options and not isinstance(value, bool):
        return
    with pytest.raises(ConfigError, match=f"{name}=.*one of"):
        cls(**{name: value})
