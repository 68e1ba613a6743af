"""The split controller of the interop studies (eofnn/interop/loop.py): a predictive filter on some modes, the
integrator on the rest, and the measured modes (pseudo-open-loop principal components) that order them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eofnn.errors import ConfigError
from eofnn.interop.loop import SplitControl, pol_modes
from eofnn.runtime import PredictiveFilter
from eofnn.studies.study import StudyConfig, split_candidates
from eofnn.telemetry.record import Telemetry

K = 6


def integrator_filter(gain: float) -> PredictiveFilter:
    """An exported filter that is itself an integrator: ``y(n) = y(n-1) - gain m(n)``."""
    return PredictiveFilter(np.tile([1.0, -gain], (K, 1)), [("y", 1), ("wfs", 2)], 2)


def run(control, measurements: np.ndarray) -> np.ndarray:
    control.reset(K)
    out = []
    for m in measurements:
        y = control.step(m)
        control.applied(y)
        out.append(y)
    return np.array(out)


def test_the_filter_commands_its_modes_and_the_integrator_the_rest():
    rng = np.random.default_rng(0)
    modes = np.linalg.qr(rng.standard_normal((K, 2)))[0]
    projector = modes @ modes.T
    measurements = rng.standard_normal((40, K))
    warmup = 5
    got = run(SplitControl(integrator_filter(0.5), modes, 0.2, warmup_frames=warmup), measurements)
    y = np.zeros(K)
    for n, m in enumerate(measurements):
        step = 0.2 * m if n < warmup else 0.2 * (m - projector @ m) + 0.5 * projector @ m
        y = y - step
        np.testing.assert_allclose(got[n], y, atol=1e-12)


def test_a_mix_shares_the_filters_modes_with_the_integrator():
    rng = np.random.default_rng(3)
    modes = np.linalg.qr(rng.standard_normal((K, 3)))[0]
    projector = modes @ modes.T
    measurements = rng.standard_normal((20, K))
    got = run(SplitControl(integrator_filter(0.6), modes, 0.2, warmup_frames=0, mix=0.25), measurements)
    step = 0.2 * np.eye(K) + 0.25 * (0.6 - 0.2) * projector  # the filter's gain a quarter of the way on its modes
    y = got[3]  # the filter has whole histories from here on
    for n in range(4, 20):
        y = y - step @ measurements[n]
        np.testing.assert_allclose(got[n], y, atol=1e-12)


def test_all_modes_is_the_filter_and_none_the_integrator():
    rng = np.random.default_rng(1)
    measurements = rng.standard_normal((30, K))
    full = run(SplitControl(integrator_filter(0.5), np.eye(K), 0.2, 3), measurements)
    none = run(SplitControl(integrator_filter(0.5), np.zeros((K, 0)), 0.2, 3), measurements)
    np.testing.assert_allclose(none, -0.2 * np.cumsum(measurements, 0), atol=1e-12)
    assert np.abs(np.diff(full[3:], axis=0) + 0.5 * measurements[4:]).max() < 1e-12


def test_wrong_modes_and_gains_are_refused_with_one_line():
    with pytest.raises(ConfigError, match=r"modes have shape \(5, 2\): they must be \(6, M\)") as err:
        SplitControl(integrator_filter(0.5), np.zeros((5, 2)), 0.2)
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="integrator gain"):
        SplitControl(integrator_filter(0.5), np.eye(K), float("nan"))
    with pytest.raises(ConfigError, match="integrated_modes holds 6: the integrator can keep at most 5"):
        split_candidates((0, 6), K)
    with pytest.raises(ConfigError, match="integrated_modes=.* is invalid"):
        StudyConfig(integrated_modes=(-1,))
    with pytest.raises(ConfigError, match="mix"):
        SplitControl(integrator_filter(0.5), np.eye(K), 0.2, mix=0.0)
    with pytest.raises(ConfigError, match="mixes"):
        StudyConfig(mixes=(0.5, 1.5))


def test_auto_candidates_are_none_a_64th_and_a_16th_of_the_actuators():
    assert split_candidates("auto", 1353) == (0, 21, 84)
    assert split_candidates((3, 0, 3), 10) == (0, 3)


def test_pol_modes_are_the_principal_components_of_the_pseudo_open_loop():
    rng = np.random.default_rng(2)
    basis = np.linalg.qr(rng.standard_normal((K, K)))[0]
    frames = 4000
    s = rng.standard_normal((frames, K)) * np.array([10.0, 4.0, 1.0, 0.5, 0.2, 0.1]) @ basis.T
    y = rng.standard_normal((frames, K)) * 20  # large commands: a wrong DM gain would dominate the modes
    telemetry = Telemetry(y=torch.from_numpy(y), wfs=torch.from_numpy(s + 1.7 * y), delay_frames=2)
    modes = pol_modes(telemetry, 1.7)
    np.testing.assert_allclose(modes.T @ modes, np.eye(K), atol=1e-10)
    assert abs(modes[:, 0] @ basis[:, 0]) > 0.999 and abs(modes[:, 1] @ basis[:, 1]) > 0.99
