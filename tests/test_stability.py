"""Analytic stability margins of linear controllers against closed forms and against simulated loops."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from eofnn.analysis.stability import LoopSetup, analyse, analyse_filter, analyse_integrator
from eofnn.control.baselines import critical_gain
from eofnn.data.history import HistorySpec
from eofnn.data.stream import DataConfig
from eofnn.errors import ConfigError
from eofnn.reporting.stability import plot_stability
from eofnn.sim import ActuatorGrid, run_loop
from eofnn.training.fit import fit_predictor

FAST = DataConfig(frames=3000, val_frames=500, sequence_frames=1000, dither_nm=10.0)


def fractional_integrator_peak(gain: float, delay_frames: float, n_frames: int = 6000, seed: int = 0) -> float:
    """Largest |eps| over the last 500 frames of a scalar integrator loop with a fractional delay, driven by white s.

    The simulator has integer delays only, so this is the fractional plant written out: the controller receives
    ``eps(n - d)``, and the DM acting during frame ``n`` is ``(1 - f) y(n) + f y(n - 1)``.
    """
    d = math.floor(delay_frames)
    f = delay_frames - d
    s = np.random.default_rng(seed).standard_normal(n_frames)
    y, eps = np.zeros(n_frames + 1), np.zeros(n_frames)  # y[n + 1] is y(n); y[0] = y(-1) = 0
    for n in range(n_frames):
        measured = eps[n - d] if n >= d else 0.0
        y[n + 1] = y[n] - gain * measured
        eps[n] = s[n] + (1 - f) * y[n + 1] + f * y[n]
        if not abs(eps[n]) < 1e12:
            return math.inf
    return float(np.abs(eps[-500:]).max())


@pytest.mark.physics
@pytest.mark.parametrize("delay", [1, 2, 3])
def test_integrator_critical_gain_is_the_closed_form(delay):
    result = analyse_integrator(0.5, 0.0, LoopSetup(delay_frames=delay))
    lower, upper = result.gain_margin
    assert result.stable
    assert 0.5 * upper == pytest.approx(critical_gain(delay), rel=1e-9)
    assert lower == pytest.approx(0.0, abs=1e-12)  # a pure integrator is marginal at zero gain (pole at z = 1)
    # The pole pair leaves at w = pi / (2d - 1) rad/frame.
    assert float(result.gain_crossing_hz[0, 1]) == pytest.approx(1000.0 / (2 * (2 * delay - 1)), rel=1e-9)
    # Whole extra frames tolerated: the number of larger delays whose critical gain stays above 0.5.
    expected = next(j for j in range(10) if critical_gain(delay + j + 1) <= 0.5)
    assert int(result.integer_delay_margin_frames[0]) == expected


@pytest.mark.physics
def test_fractional_delay_integrator_matches_its_derivation_and_a_simulation():
    """Delay 1.5: z^2 + (k/2 - 1) z + k/2 has a pole pair on the unit circle (at +-i, fs/4) when k/2 = 1: k = 2."""
    result = analyse_integrator(1.0, 0.0, LoopSetup(delay_frames=1.5))
    assert result.gain_margin[1] == pytest.approx(2.0, rel=1e-9)
    assert float(result.gain_crossing_hz[0, 1]) == pytest.approx(250.0, rel=1e-9)
    # Delay 1.25: the Schur-Cohn conditions k f < 1 and k (1 - 2f) < 2 give k = 4.
    assert analyse_integrator(1.0, 0.0, LoopSetup(delay_frames=1.25)).gain_margin[1] == pytest.approx(4.0, rel=1e-9)
    assert fractional_integrator_peak(0.95 * 2.0, 1.5) < 100
    assert fractional_integrator_peak(1.05 * 2.0, 1.5) > 1e4


@pytest.mark.physics
def test_delay_margin_lands_on_the_critical_delay():
    """At the plant delay plus the fractional delay margin, the same gain is exactly critical."""
    result = analyse_integrator(0.5, 0.0, LoopSetup(delay_frames=2))
    margin = float(result.delay_margin_frames[0])
    assert 1 < margin < 2  # between the critical gains of delays 3 (0.618) and 4 (0.445)
    at_edge = analyse_integrator(0.5, 0.0, LoopSetup(delay_frames=2 + margin - 1e-9))
    assert at_edge.gain_margin[1] == pytest.approx(1.0, abs=1e-6)
    assert not analyse_integrator(0.5, 0.0, LoopSetup(delay_frames=2 + margin + 1e-6)).stable


def simulated_divergence(scenario, controller, dm_gain: float, predicted_modulus: float) -> bool:
    """Whether ``run_loop`` diverges at ``dm_gain``; long enough for a pole of ``predicted_modulus`` to grow 1e10x."""
    n_frames = 3000 if predicted_modulus < 1 else int(min(20000, max(1500, 25 / math.log(predicted_modulus))))
    plant = scenario.with_plant(dm_gain=dm_gain).plant
    return run_loop(scenario.turbulence(9), plant, controller, n_frames, record=()).diverged


@pytest.mark.physics
@pytest.mark.slow
@pytest.mark.parametrize("kind, history_length", [("open_loop", 4), ("closed_loop", 5)])
def test_fitted_eof_gain_margin_matches_simulation(small_scenario, kind, history_length):
    scenario = small_scenario.with_plant(wfs_noise_nm=5.0)
    spec = HistorySpec(kind, history_length, 2)
    predictor = fit_predictor(scenario, kind, history_length, data=FAST).predictor
    result = analyse_filter(predictor.network, spec, LoopSetup.from_plant(scenario.plant))
    lower, upper = result.gain_margin
    assert result.stable and 0 < lower < 1 < upper < 3
    for bound in (lower, upper):
        for factor, diverges in ((0.95, bound < 1), (1.05, bound > 1)):
            gain = factor * bound
            modulus = float(analyse_filter(predictor.network, spec, LoopSetup(2, dm_gain=gain)).max_root_modulus.max())
            assert (modulus >= 1) == diverges
            assert simulated_divergence(scenario, predictor.controller(), gain, modulus) == diverges, (bound, factor)
    # Classification far from the edges agrees too (the study: open-loop EOF fails at twice the DM gain).
    for gain in (0.2, 2.0):
        modulus = float(analyse_filter(predictor.network, spec, LoopSetup(2, dm_gain=gain)).max_root_modulus.max())
        assert modulus > 1
        assert simulated_divergence(scenario, predictor.controller(), gain, modulus)


@pytest.mark.slow
def test_neighbourhood_block_system():
    """A coupled integrator y = y(n-1) - k (I + e A) u: modes of I + e A are integrators of gain k (1 + e lambda)."""
    grid = ActuatorGrid(2.0, 6)
    neighbours = grid.neighbours(1.0)
    n_act, slots = neighbours.shape
    gain, coupling = 0.4, 0.1
    weights = torch.zeros(n_act, slots, 2, dtype=torch.float64)  # taps per slot: [y(n-1), u(n)]
    weights[:, 0, 0] = 1.0
    weights[:, 0, 1] = -gain
    weights[:, 1:, 1] = -gain * coupling
    result = analyse(weights.flatten(1), "closed_loop", 1, LoopSetup(delay_frames=2), structure="neighbourhood",
                     neighbours=neighbours)
    adjacency = np.zeros((n_act, n_act))
    for k in range(n_act):
        for j in neighbours[k, 1:].tolist():
            if j < n_act:
                adjacency[k, j] = 1.0
    largest = np.linalg.eigvalsh(np.eye(n_act) + coupling * adjacency).max()
    assert result.stable
    assert result.gain_margin[1] == pytest.approx(critical_gain(2) / (gain * largest), rel=1e-6)
    # Self-only weights reproduce the per-actuator analysis.
    weights[:, 1:] = 0
    weights[:, 0, 1] = -gain * torch.linspace(0.5, 1.5, n_act, dtype=torch.float64)
    block = analyse(weights.flatten(1), "closed_loop", 1, LoopSetup(delay_frames=2), structure="neighbourhood",
                    neighbours=neighbours)
    single = analyse(weights[:, 0], "closed_loop", 1, LoopSetup(delay_frames=2))
    assert float(block.max_root_modulus[0]) == pytest.approx(float(single.max_root_modulus.max()), rel=1e-9)
    assert block.gain_margin[1] == pytest.approx(single.gain_margin[1], rel=1e-6)
    assert float(block.delay_margin_frames[0]) == pytest.approx(float(single.delay_margin_frames.min()), rel=1e-6)


@pytest.mark.slow
def test_transfer_functions_json_and_figure(tmp_path):
    result = analyse_integrator(0.5, 0.0, LoopSetup(delay_frames=2))
    s, n = result.rejection[0], result.noise_transfer[0]
    # With unit gains the noise transfer is S - 1 (the residual sees the commands driven by the noise).
    torch.testing.assert_close(n, s - 1)
    # Rejects low frequencies (|S| ~ 2 pi f / (k fs)), amplifies some (the waterbed); at Nyquist S = 2 / 2.5.
    assert float(s.abs()[0]) == pytest.approx(2 * math.pi * 0.5 / 0.5 / 1000, rel=0.01)
    assert float(s.abs().max()) > 1.2 and float(s.abs()[-1]) == pytest.approx(0.8, rel=1e-9)
    data = json.loads(result.to_json())
    assert data["stable"] and data["dm_gain_interval"][1] == pytest.approx(2.0)
    assert len(data["transfer"]["worst_rejection_abs"]) == len(result.frequencies_hz)
    unstable = json.loads(analyse_integrator(1.5, 0.0, LoopSetup(delay_frames=2)).to_json())
    assert not unstable["stable"] and unstable["dm_gain_interval"] == [None, None]
    path = plot_stability(result, tmp_path / "bode.png", "integrator")
    assert path.stat().st_size > 10_000


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: analyse(torch.zeros(5, 3, dtype=torch.float64), "open_loop", 4), r"shape \(5, 3\)"),
        (lambda: analyse(torch.zeros(2, 4, dtype=torch.float64), "open_loop", 4, structure="shared"), "shared"),
        (lambda: analyse(torch.zeros(5, 4), "closed_loop", 1, LoopSetup(delay_frames=0)), "delay_frames=0"),
        (lambda: LoopSetup(delay_frames=0.5), "delay_frames=0.5"),
        (lambda: analyse(torch.zeros(5, 4), "sideways", 4), "kind='sideways'"),
        (lambda: analyse(torch.zeros(5, 8), "open_loop", 4, structure="neighbourhood"), "neighbourhood weights"),
        (lambda: analyse(torch.full((5, 4), math.nan), "open_loop", 4), "non-finite"),
        (lambda: LoopSetup(dm_gain=math.inf), "dm_gain=inf"),
    ],
)
def test_bad_inputs_are_one_line_errors(call, match):
    with pytest.raises(ConfigError, match=match) as info:
        call()
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("value, match", [(1e30, "weights reach 1e\\+30"), (1e150, "weights reach 1e\\+150"),
                                          (float("nan"), "non-finite")])
def test_weights_that_cannot_be_a_predictor_are_refused(value, match):
    weights = torch.zeros(3, 4, dtype=torch.float64)
    weights[1, 0] = value
    with pytest.raises(ConfigError, match=match):
        analyse(weights, "open_loop", 4)
