"""Analytic stability of linear predictors in the loop: margins, rejection and noise transfer.

A linear controller is ``D(z) y = N(z) u`` on the measurement ``u(n)`` it receives at frame ``n`` (the WFS
reading of ``eps(n - d)``), with polynomials in ``z^-1`` from the filter weights (taps ordered as in
:mod:`eofnn.data.history`):

- closed-loop EOF, taps ``[y(n-1..n-p), u(n..n-p+1)]``: ``D = 1 - sum_j a_j z^-j``, ``N = sum_j b_j z^-j``;
- open-loop EOF, taps ``[s_hat(n..n-p+1)]`` with ``s_hat(n) = u(n) - g_model y(n - d_c)``:
  ``D = 1 + g_model z^-d_c F(z)``, ``N = F(z)``;
- the leaky integrator ``y(n) = (1 - leak) y(n-1) - k u(n)`` is the closed-loop EOF with one tap each:
  ``D = 1 - (1 - leak) z^-1``, ``N = -k``.

The plant closes the loop: ``eps = s + g H y``, ``u = z^-d (w eps + v)`` with DM gain ``g``, WFS gain ``w``,
delay ``tau = d + f`` frames and ``H = (1 - f) + f z^-1`` (the command acting during a frame is the average over
it). Writing ``Q = w z^-d H``, every signal of the loop obeys ``P(z) = D - g Q N`` (no cancellation of common
factors, so hidden controller modes count), and

- rejection (sensitivity) ``eps / s = D / P``; noise transfer ``eps / v = g z^-d H N / P`` (nm per nm of WFS noise);
- stability: every root of ``P`` inside the unit circle;
- DM gain interval: ``P`` is affine in ``g``, so a root crosses the unit circle where ``D / (Q N)`` is real; those
  gains are found exactly (:func:`~eofnn.analysis.polynomials.real_crossings`), the interval the one around nominal;
- delay margin: between integer delays ``m`` and ``m + 1`` the plant polynomial is affine in ``f``: the first delay
  at which a root reaches the unit circle is found the same way (fractional), and the whole extra frames tolerated.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import ClassVar

import torch

from eofnn.analysis import polynomials as poly
from eofnn.analysis.block import block_analysis
from eofnn.analysis.checks import MAX_WEIGHT, STRUCTURES, check_filter, check_weights  # noqa: F401 (re-exported)
from eofnn.control.adaptive import integrator_filter
from eofnn.data.history import HistorySpec
from eofnn.models.linear import LinearFilter
from eofnn.validation import FINITE, Constraint, Interval, OrNone, validated


@dataclass(frozen=True)
@validated
class LoopSetup:
    """The plant and the controller's own assumptions for a stability analysis.

    Parameters
    ----------
    delay_frames : float
        Plant delay ``tau >= 1`` in frames, integer or fractional (``d + f``: the controller receives the WFS
        reading of ``eps(n - d)``, and a fraction ``f`` of each frame still sees the previous command).
    dm_gain : float
        DM gain ``g`` of the plant (1 nominal).
    wfs_gain : float
        WFS gain ``w`` (1 nominal).
    dm_gain_model : float
        DM gain the controller assumes in its pseudo-open-loop reconstruction (open loop only).
    controller_delay_frames : float or None
        Delay the controller was built for (in its POL reconstruction ``wfs(n) - g_model z^-d ((1 - f) + f z^-1)
        y``, as eofnn's controllers do); ``delay_frames`` if not given.
    frame_rate_hz : float
        Loop rate in Hz, for frequencies.
    max_extra_delay_frames : int
        Extra delay searched for the delay margin, in frames.
    """

    delay_frames: float = 2.0
    dm_gain: float = 1.0
    wfs_gain: float = 1.0
    dm_gain_model: float = 1.0
    controller_delay_frames: float | None = None
    frame_rate_hz: float = 1000.0
    max_extra_delay_frames: int = 10

    _constraints: ClassVar[dict[str, Constraint]] = {
        "delay_frames": Interval(1, 100, unit="frames"),
        "dm_gain": FINITE,
        "wfs_gain": FINITE,
        "dm_gain_model": FINITE,
        "controller_delay_frames": OrNone(Interval(1, 100, unit="frames")),
        "frame_rate_hz": Interval(0, None, closed="neither", unit="Hz"),
        "max_extra_delay_frames": Interval(1, 100, integer=True, unit="frames"),
    }

    @classmethod
    def from_plant(cls, plant, frame_rate_hz: float = 1000.0, dm_gain_model: float = 1.0,
                   controller_delay_frames: float | None = None, **kwargs) -> LoopSetup:
        """The setup of a :class:`~eofnn.sim.loop.plant.Plant` (its delay, DM gain and WFS gain)."""
        return cls(plant.delay_frames, plant.dm_gain, plant.wfs_gain, dm_gain_model, controller_delay_frames,
                   frame_rate_hz, **kwargs)

    @property
    def controller_delay(self) -> float:
        """The delay of the controller's POL reconstruction: ``controller_delay_frames``, else ``delay_frames``."""
        return self.controller_delay_frames if self.controller_delay_frames is not None else self.delay_frames

    def plant_polynomial(self, delay_frames: float | None = None) -> torch.Tensor:
        """``Q = w z^-d ((1 - f) + f z^-1)`` for this setup's delay (or ``delay_frames``)."""
        return self.wfs_gain * poly.fractional_delay(self.delay_frames if delay_frames is None else delay_frames)


@dataclass
class StabilityResult:
    """Stability margins and transfer functions of a linear controller in the loop, per group.

    Groups are the actuators (``per_actuator``), one filter (``shared``) or the whole coupled system
    (``neighbourhood``: one group). Tensors have the groups as first dimension.

    Attributes
    ----------
    max_root_modulus : Tensor
        Largest closed-loop pole modulus (spectral radius); ``< 1`` is stable.
    gain_interval : Tensor
        ``(groups, 2)`` DM gains between which the loop stays stable around the nominal one (NaN if unstable).
    gain_crossing_hz : Tensor
        ``(groups, 2)`` frequency in Hz at which a pole leaves the unit circle at each end of the interval.
    delay_margin_frames : Tensor
        Extra delay (fractional model) before the loop goes unstable, frames (``inf``: beyond the search range).
    integer_delay_margin_frames : Tensor
        Whole extra frames of delay tolerated.
    frequencies_hz, rejection, noise_transfer : Tensor
        Frequency grid (Hz) and the complex ``eps / s`` and ``eps / v`` on it, ``(groups, F)`` (empty if skipped).
    """

    kind: str
    structure: str
    history_length: int
    setup: LoopSetup
    max_root_modulus: torch.Tensor
    gain_interval: torch.Tensor
    gain_crossing_hz: torch.Tensor
    delay_margin_frames: torch.Tensor
    integer_delay_margin_frames: torch.Tensor
    frequencies_hz: torch.Tensor
    rejection: torch.Tensor
    noise_transfer: torch.Tensor
    analysis_seconds: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def stable(self) -> bool:
        return bool((self.max_root_modulus < 1).all())

    @property
    def gain_margin(self) -> tuple[float, float]:
        """The DM gain interval over which every group is stable (NaN if the nominal loop is unstable)."""
        if not self.stable:
            return math.nan, math.nan
        return float(self.gain_interval[:, 0].max()), float(self.gain_interval[:, 1].min())

    @property
    def worst_group(self) -> int:
        """The group closest to instability: smallest upper gain interval relative to nominal, else largest pole."""
        if self.stable:
            return int(self.gain_interval[:, 1].argmin())
        return int(self.max_root_modulus.argmax())

    @property
    def median_group(self) -> int:
        key = self.gain_interval[:, 1] if self.stable else self.max_root_modulus
        return int(key.argsort()[len(key) // 2])

    def to_dict(self) -> dict:
        lower, upper = self.gain_margin
        worst = self.worst_group
        out = {
            "kind": self.kind, "structure": self.structure, "history_length": self.history_length,
            "setup": asdict(self.setup), "stable": self.stable, "groups": len(self.max_root_modulus),
            "max_root_modulus": float(self.max_root_modulus.max()),
            "dm_gain_interval": [_finite(lower), _finite(upper)],
            "gain_margin_db": _finite(20 * math.log10(upper / self.setup.dm_gain))
            if self.stable and self.setup.dm_gain > 0 and upper > 0 else None,
            "worst_group": worst, "median_group": self.median_group,
            "worst_crossing_hz": [_finite(v) for v in self.gain_crossing_hz[worst].tolist()],
            "delay_margin_frames": _finite(float(self.delay_margin_frames.min())),
            "integer_delay_margin_frames": int(self.integer_delay_margin_frames.min()),
            "analysis_seconds": self.analysis_seconds,
            "per_group": {
                "max_root_modulus": self.max_root_modulus.tolist(),
                "dm_gain_interval": [[_finite(v) for v in row] for row in self.gain_interval.tolist()],
                "delay_margin_frames": [_finite(v) for v in self.delay_margin_frames.tolist()],
            },
            "notes": list(self.notes),
        }
        if self.rejection.numel():
            out["transfer"] = {"frequencies_hz": self.frequencies_hz.tolist()}
            for name, group in (("worst", worst), ("median", self.median_group)):
                out["transfer"][f"{name}_rejection_abs"] = self.rejection[group].abs().tolist()
                out["transfer"][f"{name}_noise_transfer_abs"] = self.noise_transfer[group].abs().tolist()
        return out

    def to_json(self, indent: int | None = 1) -> str:
        """JSON text; infinite or undefined values are ``null``."""
        return json.dumps(self.to_dict(), indent=indent)


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def controller_delay_polynomial(controller_delay_frames: float) -> torch.Tensor:
    """The DM response the controller's POL reconstruction assumes: ``z^-d``, or ``z^-d ((1 - f) + f z^-1)``."""
    if float(controller_delay_frames).is_integer():
        return poly.delay(int(controller_delay_frames))
    return poly.fractional_delay(controller_delay_frames)


def controller_polynomials(weights: torch.Tensor, kind: str, history_length: int, dm_gain_model: float = 1.0,
                           controller_delay_frames: float = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """``(D, N)`` with ``D(z) y = N(z) u`` for per-group weights ``(groups, taps)`` of a ``kind`` history.

    ``u(n) = wfs(n - d)`` is the reading the controller receives; an open-loop filter ``W`` reads the POL values
    ``u - g_model z^-d F y`` (``F = (1 - f) + f z^-1``), so ``D = 1 + g_model z^-d F W`` and ``N = W``.
    """
    p = history_length
    w = weights.detach().to(poly.DTYPE).cpu()
    ones = torch.ones(w.shape[0], 1, dtype=poly.DTYPE)
    if kind == "closed_loop":
        return torch.cat([ones, -w[:, :p]], 1), w[:, p:]
    return poly.add(ones, dm_gain_model * poly.multiply(controller_delay_polynomial(controller_delay_frames), w)), w


def integrator_weights(gain: float, leak: float = 0.0) -> torch.Tensor:
    """The leaky integrator ``y(n) = (1 - leak) y(n-1) - gain u(n)`` as closed-loop EOF weights ``(1, 2)``."""
    return integrator_filter(HistorySpec("closed_loop", 1), gain, leak)


def default_frequencies_hz(frame_rate_hz: float, n: int = 256) -> torch.Tensor:
    """Log-spaced frequencies from ``frame_rate / 2000`` to Nyquist, Hz."""
    return torch.logspace(math.log10(frame_rate_hz / 2000), math.log10(frame_rate_hz / 2), n, dtype=poly.DTYPE)


def analyse(weights: torch.Tensor, kind: str, history_length: int, setup: LoopSetup | None = None, *,
            structure: str = "per_actuator", neighbours: torch.Tensor | None = None,
            frequencies_hz: torch.Tensor | None = None, delay_margin: bool = True) -> StabilityResult:
    """Stability margins and transfer functions of linear filter ``weights`` in the loop ``setup``.

    Parameters
    ----------
    weights : Tensor
        ``LinearFilter.weight``: ``(K, taps)`` per actuator, ``(1, taps)`` shared, ``(K, M * taps)`` neighbourhood.
    kind : {"open_loop", "closed_loop"}
        History kind of the filter.
    history_length : int
        Frames of history ``p`` per signal.
    setup : LoopSetup
        Plant and controller assumptions (nominal, 2 frames of delay by default).
    structure : str
        ``per_actuator``, ``shared``, ``modal`` (groups are modes, decoupled when the DM acts as ``g y``) or
        ``neighbourhood`` (then ``neighbours``, the ``(K, M)`` index of
        :meth:`~eofnn.sim.grid.ActuatorGrid.neighbours`, is required).
    frequencies_hz : Tensor, optional
        Where to evaluate the transfer functions (:func:`default_frequencies_hz` by default).
    delay_margin : bool
        Whether to find the delay margins (``False``: NaN and -1, for a caller that wants the DM-gain interval only).
    """
    check_weights(weights, kind, history_length, structure, neighbours)
    return _analyse(weights, kind, history_length, setup, structure, neighbours, frequencies_hz, delay_margin)


def _analyse(weights: torch.Tensor, kind: str, history_length: int, setup: LoopSetup | None, structure: str,
             neighbours: torch.Tensor | None, frequencies_hz: torch.Tensor | None, delay_margin: bool = True
             ) -> StabilityResult:
    """:func:`analyse` of weights already checked (given weights by :func:`analyse`, a filter's by
    :func:`analyse_filter`) or built here (:func:`analyse_integrator`'s)."""
    setup = setup or LoopSetup()
    start = time.perf_counter()
    freqs = default_frequencies_hz(setup.frame_rate_hz) if frequencies_hz is None else frequencies_hz.to(poly.DTYPE)
    if structure == "neighbourhood":
        result = StabilityResult(kind, structure, history_length, setup,
                                 *block_analysis(weights, neighbours, kind, history_length, setup, freqs,
                                                 delay_margin))
    else:
        d_poly, n_poly = controller_polynomials(weights, kind, history_length, setup.dm_gain_model,
                                                setup.controller_delay)
        result = analyse_polynomials(d_poly, n_poly, setup, freqs, kind=kind, structure=structure,
                                     history_length=history_length, delay_margin=delay_margin)
    result.analysis_seconds = time.perf_counter() - start
    return result


def analyse_filter(network: LinearFilter, spec: HistorySpec, setup: LoopSetup | None = None,
                   frequencies_hz: torch.Tensor | None = None) -> StabilityResult:
    """:func:`analyse` for a fitted :class:`~eofnn.models.linear.LinearFilter` reading ``spec`` histories."""
    check_filter(network, spec)
    setup = setup or LoopSetup(delay_frames=spec.delay_frames)
    if setup.controller_delay_frames is None:
        setup = replace(setup, controller_delay_frames=spec.delay_frames)
    # The analysis reads the weights' values: no gradient flows through it (a float of a Parameter warns).
    return _analyse(network.weight.detach(), spec.kind, spec.history_length, setup, network.structure,
                    getattr(network, "neighbours", None), frequencies_hz)


def analyse_integrator(gain: float, leak: float = 0.0, setup: LoopSetup | None = None) -> StabilityResult:
    """The leaky integrator through the same analysis (its critical gain is ``gain * gain_margin[1]``); ``gain`` and
    ``leak`` as the controller's config has checked them."""
    return _analyse(integrator_weights(gain, leak), "closed_loop", 1, setup, "shared", None, None)


def analyse_polynomials(d_poly: torch.Tensor, n_poly: torch.Tensor, setup: LoopSetup, frequencies_hz: torch.Tensor,
                        *, kind: str = "closed_loop", structure: str = "per_actuator", history_length: int = 1,
                        delay_margin: bool = True) -> StabilityResult:
    """Analysis of any controller ``D(z) y = N(z) u`` given per group as ``(groups, L)`` polynomials; no
    ``delay_margin``: delay margins undefined (NaN, -1)."""
    groups = d_poly.shape[0]
    g = setup.dm_gain
    q_n = poly.multiply(setup.plant_polynomial(), n_poly)  # Q N
    characteristic = poly.add(d_poly, -g * q_n)
    modulus = poly.max_root_modulus(characteristic)
    stable = modulus < 1
    # Gain: P(g) = D + g (-Q N).
    rows, gains, omega = poly.real_crossings(d_poly, -q_n)
    lower, upper = poly.nearest_around(rows, gains, torch.full((groups,), g, dtype=poly.DTYPE), groups)
    interval = torch.stack([lower, upper], 1)
    interval[~stable] = math.nan
    crossing_hz = torch.full((groups, 2), math.nan, dtype=poly.DTYPE)
    hz = omega * setup.frame_rate_hz / (2 * math.pi)
    for column, bound in enumerate((lower, upper)):
        hit = gains == bound[rows]
        crossing_hz[:, column].scatter_reduce_(0, rows[hit], hz[hit], "amin", include_self=False)
    delay_margins, integer_margin = (_delay_margins(d_poly, n_poly, setup) if delay_margin else (
        torch.full((groups,), math.nan, dtype=poly.DTYPE), torch.full((groups,), -1, dtype=torch.int64)))
    delay_margins[~stable], integer_margin[~stable] = math.nan, -1
    omega_grid = 2 * math.pi * frequencies_hz / setup.frame_rate_hz
    p_value = poly.evaluate(characteristic, omega_grid)
    rejection = poly.evaluate(d_poly, omega_grid) / p_value
    noise = g * poly.evaluate(poly.multiply(poly.fractional_delay(setup.delay_frames), n_poly), omega_grid) / p_value
    return StabilityResult(kind, structure, history_length, setup, modulus, interval, crossing_hz, delay_margins,
                           integer_margin, frequencies_hz, rejection, noise)


def _delay_margins(d_poly: torch.Tensor, n_poly: torch.Tensor, setup: LoopSetup) -> tuple[torch.Tensor, torch.Tensor]:
    """Fractional and integer extra delay (frames) before a pole reaches the unit circle, per group."""
    groups, tau = d_poly.shape[0], float(setup.delay_frames)
    gw, first = setup.dm_gain * setup.wfs_gain, math.floor(tau)
    delay_margin = torch.full((groups,), math.inf, dtype=poly.DTYPE)
    for m in range(first, first + setup.max_extra_delay_frames + 1):
        left = torch.isinf(delay_margin).nonzero().squeeze(-1)  # groups whose margin is not found yet
        if not len(left):
            break
        # Between m and m + 1 frames: P = D - g w z^-m ((1 - f) + f z^-1) N = a + f b.
        n_left = n_poly[left]
        a = poly.add(d_poly[left], -gw * poly.multiply(poly.delay(m), n_left))
        b = -gw * poly.multiply(poly.add(poly.delay(m + 1), -poly.delay(m)), n_left)
        rows, fraction, _ = poly.real_crossings(a, b)
        critical = m + fraction
        ok = (fraction >= 0) & (fraction <= 1) & (critical > tau)
        found = torch.full((len(left),), math.inf, dtype=poly.DTYPE).scatter_reduce(0, rows[ok], critical[ok] - tau,
                                                                                     "amin")
        delay_margin[left] = found
    # Whole extra frames at the same fraction: consecutive stable delays tau + 1, tau + 2, ...
    integer = torch.full((groups,), setup.max_extra_delay_frames, dtype=torch.int64)
    for j in range(1, setup.max_extra_delay_frames + 1):
        left = (integer == setup.max_extra_delay_frames).nonzero().squeeze(-1)
        if not len(left):
            break
        p = poly.add(d_poly[left], -setup.dm_gain * poly.multiply(setup.plant_polynomial(tau + j), n_poly[left]))
        integer[left[poly.max_root_modulus(p) >= 1]] = j - 1
    return delay_margin, integer
