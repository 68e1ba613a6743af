"""The MAP reconstructor for OOPAO's loop (eofnn/interop/map_reconstructor.py): its limits (least squares with no
prior weight, zero with overwhelming noise), its optimality, the estimators behind its two variants, refusals, and
``examples/oopao_loop.py --reconstructor``."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from eofnn.errors import ConfigError
from eofnn.interop import map_reconstructor as mr
from eofnn.sim.sensing.mmse import mmse_reconstructor, von_karman_covariance_nm2

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "oopao_loop.py"


def system(seed: int = 0, s: int = 40, k: int = 25, kept: int = 20):
    """A random interaction matrix ``(s, k)``, its ``kept`` best-seen modes, its truncated pseudo-inverse and a
    random positive definite prior ``(k, k)``."""
    rng = np.random.default_rng(seed)
    d = rng.standard_normal((s, k))
    u, sv, vt = np.linalg.svd(d, full_matrices=False)
    modes = vt[:kept].T
    least_squares = (vt[:kept].T / sv[:kept]) @ u[:, :kept].T
    a = rng.standard_normal((k, k))
    return d, modes, least_squares, a @ a.T / k + 0.1 * np.eye(k)


def test_no_prior_weight_is_the_truncated_least_squares_reconstructor():
    d, modes, least_squares, prior = system()
    for noise in (0.0, 1.0):
        r = mr.map_reconstructor(d, modes, prior, noise, weight=0.0)
        assert np.allclose(r, least_squares, atol=1e-10 * np.abs(least_squares).max())
    tiny = mr.map_reconstructor(d, modes, prior, 0.0, weight=1e-9)  # no noise: the prior weighs next to nothing
    assert np.allclose(tiny, least_squares, rtol=0, atol=1e-6 * np.abs(least_squares).max())
    assert not np.allclose(mr.map_reconstructor(d, modes, prior, 1.0), least_squares, atol=1e-3)


def test_the_reconstructor_shrinks_as_the_noise_grows_and_stays_in_the_controlled_modes():
    d, modes, least_squares, prior = system(1)
    norms = [np.linalg.norm(mr.map_reconstructor(d, modes, prior, noise)) for noise in (1e-3, 0.1, 1.0, 10.0, 1e4)]
    assert all(b < a for a, b in zip(norms, norms[1:], strict=False)), norms
    assert norms[-1] < 0.01 * np.linalg.norm(least_squares)
    r = mr.map_reconstructor(d, modes, prior, 1.0)
    assert r.shape == (d.shape[1], d.shape[0])
    assert np.allclose(modes @ (modes.T @ r), r)  # nothing outside the modes the loop controls


def test_map_is_the_mmse_of_the_controlled_modes_and_eofnns_formula():
    d, modes, least_squares, prior = system(2)
    noise = np.linspace(0.5, 2.0, d.shape[0])  # per slope
    r = mr.map_reconstructor(d, modes, prior, noise)
    cm, dm = modes.T @ prior @ modes, d @ modes

    def error(rm):  # E|x - R_m (D_m x + n)|^2 for x ~ N(0, C_m), n ~ N(0, diag(noise))
        a = np.eye(len(cm)) - rm @ dm
        return np.trace(a @ cm @ a.T) + np.trace(rm @ np.diag(noise) @ rm.T)

    best = error(modes.T @ r)
    assert best < error(modes.T @ least_squares)
    rng = np.random.default_rng(3)
    for _ in range(5):
        assert best < error(modes.T @ r + 1e-3 * rng.standard_normal((modes.shape[1], d.shape[0])))
    # eofnn's own MMSE form, C D^T (D C D^T + C_n)^-1, with white noise: the same reconstructor
    white = mr.map_reconstructor(d, modes, prior, 0.7 ** 2)
    assert np.allclose(white, modes @ mmse_reconstructor(dm @ cm @ dm.T, cm @ dm.T, 0.7), atol=1e-9)


@pytest.mark.parametrize("args, said", [
    ((np.zeros(5), np.eye(5), np.eye(5), 1.0), "interaction_matrix of shape (5,) is invalid"),
    ((np.zeros((8, 5)), np.eye(4), np.eye(5), 1.0), "modes of shape (4, 4) is invalid"),
    ((np.zeros((8, 5)), np.eye(5), np.eye(4), 1.0), "prior_nm2 of shape (4, 4) is invalid"),
    ((np.zeros((8, 5)), np.eye(5), np.eye(5), np.ones(7)), "noise_var of shape (7,) is invalid"),
    ((np.zeros((8, 5)), np.eye(5), np.eye(5), -np.ones(8)), "variances must be >= 0"),
])
def test_wrong_shapes_are_refused_in_one_line(args, said):
    with pytest.raises(ConfigError) as err:
        mr.map_reconstructor(*args)
    assert said in str(err.value) and "\n" not in str(err.value)


def test_the_fitted_prior_is_the_dense_von_karman_covariance():
    n, pixel = 10, 0.1
    yy, xx = np.mgrid[:n, :n] - (n - 1) / 2
    pupil = np.hypot(xx, yy) <= n / 2
    rng = np.random.default_rng(4)
    fit = rng.standard_normal((6, int(pupil.sum())))
    fit -= fit.mean(1, keepdims=True)  # removes piston, as the DM's fit does
    points = np.argwhere(pupil)
    r = np.hypot(*(points[:, None] - points[None]).transpose(2, 0, 1)) * pixel
    dense = fit @ von_karman_covariance_nm2(r, 0.15, 25.0, 500e-9) @ fit.T
    fast = mr.fitted_prior_nm2(fit, pupil, pixel, 0.15, 25.0, chunk=4)
    assert np.allclose(fast, dense, rtol=1e-6, atol=1e-8 * np.abs(dense).max())
    halved = mr.fitted_prior_nm2(fit, pupil, pixel, 0.30, 25.0)
    assert np.allclose(halved, fast * 2 ** (-5 / 3), rtol=1e-6)  # C ~ r0^(-5/3)


def test_telemetry_estimators_recover_gain_noise_and_r0():
    d, modes, _, prior = system(5, s=60, k=30, kept=25)
    rng = np.random.default_rng(6)
    t = 20000
    sigma = np.linspace(0.05, 0.2, d.shape[0])
    # a smooth turbulence: commands of covariance the prior at r0 = 0.2 m, each a sum of three slow sinusoids
    frequencies = rng.uniform(5e-4, 2e-3, (3, len(prior)))
    starts = rng.uniform(0, 2 * np.pi, (3, len(prior)))
    z = np.sqrt(2 / 3) * np.sin(2 * np.pi * frequencies[:, None] * np.arange(t)[None, :, None] + starts[:, None]).sum(0)
    z -= z.mean(0)
    z = np.linalg.solve(np.linalg.cholesky(z.T @ z / t), z.T).T  # smooth still, and exactly white across modes
    phase = z @ np.linalg.cholesky(prior * 0.2 ** (-5 / 3)).T
    commands = 0.05 * rng.standard_normal((t, d.shape[1]))  # dither
    slopes = (phase + 1.7 * commands) @ d.T + sigma * rng.standard_normal((t, d.shape[0]))
    gain = mr.dm_gain_from_slopes(slopes, commands, d)
    assert gain == pytest.approx(1.7, rel=0.02)
    pol = mr.pseudo_open_loop_slopes(slopes, commands, d, gain)
    noise = mr.slope_noise_from_pol(pol)
    assert np.allclose(np.sqrt(noise), sigma, rtol=0.1)
    assert np.sqrt(mr.slope_noise_from_pol(phase @ d.T)).max() < 0.02  # the smooth signal alone: next to nothing
    found = mr.fit_turbulence(pol, noise, d, modes, {25.0: prior, 10.0: prior @ prior})
    assert found["outer_scale_m"] == 25.0 and found["r0_m"] == pytest.approx(0.2, rel=0.05)


@pytest.mark.cli
@pytest.mark.slow
def test_the_example_refuses_an_unknown_reconstructor(capsys):
    spec = importlib.util.spec_from_file_location("oopao_loop", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    with pytest.raises(SystemExit) as exit_:
        example.main(["--small", "--reconstructor", "mmse"])
    assert exit_.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--reconstructor" in error and "invalid choice: 'mmse'" in error
    with pytest.raises(ConfigError, match="reconstructor='mmse' is invalid"):
        mr.apply_reconstructor(None, "mmse", scan_seed=3, loop_frames=10, settle_frames=1, gains=(0.3,))


def test_in_oopaos_loop_no_weight_is_its_reconstructor_and_its_noise_is_read():
    pytest.importorskip("OOPAO")
    from eofnn.interop.oopao import OopaoLoop

    sim = OopaoLoop(8, 1.6, photon_noise=True, magnitude=10.0)
    before = sim.reconstructor.copy()
    assert mr.apply_reconstructor(sim, "least_squares", scan_seed=3, loop_frames=10, settle_frames=1,
                                  gains=(0.3,)) == {"kind": "least_squares"}
    assert np.array_equal(sim.reconstructor, before)  # the default leaves the loop bit for bit as it was
    assert "truncated pseudo-inverse" in sim.describe()["measurement"]
    prior = mr.sim_prior_nm2(sim, 0.15, 25.0)
    assert prior.shape == (sim.n_actuators,) * 2 and np.all(np.linalg.eigvalsh(prior) > -1e-9 * prior.max())
    r = mr.map_reconstructor(sim.interaction_matrix, sim.controlled_modes, prior, 1.0, weight=0.0)
    assert np.allclose(r, before, atol=1e-9 * np.abs(before).max())
    noise = mr.simulator_slope_noise(sim, n_frames=2, reads=5)
    assert noise.shape == (sim.interaction_matrix.shape[0],) and noise.min() > 0
    sim.photon_noise = False
    assert not mr.simulator_slope_noise(sim, n_frames=1, reads=2).any()
    info = mr.apply_reconstructor(sim, "map", scan_seed=3, loop_frames=10, settle_frames=1, gains=(0.3,),
                                  weights=(1.0,))
    said = sim.describe()["measurement"]  # what the outputs say the loop measured through
    assert "MAP reconstructor (the simulator's r0 and L0, weight 1)" in said and "pseudo-inverse" not in said, said
    assert info["weight"] == 1.0
