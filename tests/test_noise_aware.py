"""Noise-aware closed-form fits (``optimization.noise_model``, ``noise_at_deployment_nm``; eofnn.training.noise) and
the modal structure of linear filters, against their definitions and the Wiener predictor of an AR(1) signal."""

from __future__ import annotations

import math

import pytest
import torch

from eofnn.errors import ConfigError
from eofnn.models.linear import LinearFilter, kolmogorov_modes
from eofnn.training.config import OptimizationConfig
from eofnn.training.export import filter_coefficients
from eofnn.training.noise import NOISE_ALPHA_PATH, NoiseTerm, alpha_path, noise_term
from eofnn.training.ridge import NormalEquations, fit_closed_form

GRID = {"diameter_m": 2.0, "n_across": 10, "obstruction": 0.0}


def _equations(features: torch.Tensor, target: torch.Tensor) -> NormalEquations:
    equations = NormalEquations()
    equations.update(features, target)
    return equations


def test_the_errors_in_variables_gram_is_the_noisy_gram_minus_the_noise_covariance():
    gen = torch.Generator().manual_seed(0)
    features = 10.0 * torch.randn(3, 4000, 5, generator=gen, dtype=torch.float64)
    features[1, :, 4] = 0.0  # a structural zero (a neighbourhood slot beyond the pupil): no signal, no noise
    equations = _equations(features, torch.randn(3, 4000, generator=gen, dtype=torch.float64))
    corrected = NoiseTerm("errors_in_variables", 2.0, 0.0).adjust(equations)
    noise = 4000 * 2.0 ** 2 * torch.eye(5, dtype=torch.float64).expand(3, 5, 5).clone()
    noise[1, 4, 4] = 0.0
    torch.testing.assert_close(corrected.gram, equations.gram - noise, rtol=1e-12, atol=1e-6)
    assert corrected.gram[1, 4].abs().max() == 0 and corrected.gram[1, :, 4].abs().max() == 0
    # The cross products, the targets and the samples are the data's: their noise is independent.
    assert torch.equal(corrected.cross, equations.cross) and corrected.n_samples == equations.n_samples
    # Taking away more noise than a feature's variance leaves a positive semi-definite Gram matrix.
    overdone = NoiseTerm("errors_in_variables", 30.0, 0.0).adjust(equations)
    assert float(torch.linalg.eigvalsh(overdone.gram).min()) > -1e-6 * float(equations.gram.abs().max())


def _ar1(n: int, a: float, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    drive = torch.randn(n, generator=gen, dtype=torch.float64)
    s = torch.empty(n, dtype=torch.float64)
    s[0] = drive[0] / math.sqrt(1 - a * a)
    for i in range(1, n):
        s[i] = a * s[i - 1] + drive[i]
    return s


def _one_tap(history: torch.Tensor, target: torch.Tensor, noise: NoiseTerm | None, alpha: float = 0.0) -> float:
    """The one-tap predictor of ``target`` from ``history`` fitted in closed form (fixed absolute alpha)."""
    net = LinearFilter(1, 1, "shared")
    fit_closed_form(net, [(history.view(-1, 1, 1), target.view(-1, 1))], alpha, alpha_relative=noise is not None
                    and noise.snr_ridge, noise=noise)
    return float(net.weight.detach())


def test_the_deployment_noise_fix_recovers_the_wiener_coefficient_of_an_ar1_signal():
    """s(n) = a s(n-1) + e, unit drive: variance 1 / (1 - a²). From a noisy past s(n-1) + v (sigma_v), the minimum-MSE
    one-step predictor is a var / (var + sigma_v²): fitted on noise-free data for sigma_v of deployment noise, the
    fix must land on it; the plain fit stays at a."""
    a, sigma = 0.9, 2.0
    s = _ar1(200_000, a, seed=1)
    variance = 1 / (1 - a * a)
    wiener = a * variance / (variance + sigma ** 2)
    plain = _one_tap(s[:-1], s[1:], None)
    fixed = _one_tap(s[:-1], s[1:], NoiseTerm("none", 0.0, sigma))
    assert plain == pytest.approx(a, abs=0.01)
    assert fixed == pytest.approx(wiener, abs=0.01) and abs(fixed - plain) > 0.2
    # On noisy telemetry (history and target noisy), plain least squares already is that Wiener predictor; the
    # errors-in-variables correction de-attenuates it back to a, the filter for noise-free histories.
    gen = torch.Generator().manual_seed(2)
    noisy = s + sigma * torch.randn(s.shape, generator=gen, dtype=torch.float64)
    assert _one_tap(noisy[:-1], noisy[1:], None) == pytest.approx(wiener, abs=0.01)
    assert _one_tap(noisy[:-1], noisy[1:], NoiseTerm("errors_in_variables", sigma, 0.0)) == pytest.approx(a, abs=0.03)


def test_per_mode_snr_measures_alpha_in_noise_powers():
    """alpha 1 in noise powers adds one more noise's worth: the Wiener filter for twice the noise variance."""
    a, sigma = 0.9, 2.0
    s = _ar1(50_000, a, seed=3)
    snr = _one_tap(s[:-1], s[1:], NoiseTerm("per_mode_snr", 0.0, sigma, snr_ridge=True), alpha=1.0)
    doubled = _one_tap(s[:-1], s[1:], NoiseTerm("none", 0.0, sigma * math.sqrt(2)))
    assert snr == pytest.approx(doubled, rel=1e-10)
    assert alpha_path(OptimizationConfig(noise_model="per_mode_snr"), NoiseTerm("per_mode_snr", 1.0, 1.0, True)) \
        == list(NOISE_ALPHA_PATH)
    assert NOISE_ALPHA_PATH[0] == 1e-4 and NOISE_ALPHA_PATH[-1] == 100.0


def test_noise_terms_follow_the_config_and_refuse_what_they_cannot_model():
    conditions = {"wfs_noise_nm": 2.0}
    assert noise_term(OptimizationConfig(), conditions, "open_loop") is None  # the default: the data as recorded
    assert noise_term(OptimizationConfig(noise_model="errors_in_variables"), conditions, "open_loop") == \
        NoiseTerm("errors_in_variables", 2.0, 0.0)
    assert noise_term(OptimizationConfig(noise_at_deployment_nm=5.0), conditions, "open_loop") == \
        NoiseTerm("none", 2.0, 5.0)
    assert noise_term(OptimizationConfig(noise_model="per_mode_snr"), conditions, "open_loop") == \
        NoiseTerm("per_mode_snr", 2.0, 2.0, True)
    for optimization, conditions_, kind, expected in [
        (OptimizationConfig(noise_at_deployment_nm=1.0), conditions, "closed_loop", "use history: open_loop"),
        (OptimizationConfig(noise_model="errors_in_variables"), {"wfs_noise_nm": None}, "open_loop", "unknown"),
        (OptimizationConfig(noise_model="per_mode_snr"), {"wfs_noise_nm": 0.0}, "open_loop", "noise floor"),
    ]:
        with pytest.raises(ConfigError, match=expected) as err:
            noise_term(optimization, conditions_, kind)
        assert "\n" not in str(err.value)
    for kwargs, expected in [({"noise_model": "errors_in_variables", "noise_at_deployment_nm": 1.0}, "one of the two"),
                             ({"noise_model": "per_mode_snr", "fit_method": "sgd"}, "closed_form"),
                             ({"noise_model": "per_mode_snr", "alpha_relative": False}, "noise power"),
                             ({"noise_model": "wiener"}, "noise_model"),
                             ({"noise_at_deployment_nm": -1.0}, "noise_at_deployment_nm")]:
        with pytest.raises(ConfigError, match=expected):
            OptimizationConfig(**kwargs)


def test_kolmogorov_modes_are_an_orthonormal_basis_by_decreasing_variance_piston_last():
    from eofnn.sim.layout import layout_from_dict

    positions = layout_from_dict(GRID).positions_m
    modes = kolmogorov_modes(positions)
    k = len(positions)
    torch.testing.assert_close(modes.T @ modes, torch.eye(k, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(modes[:, -1].abs(), torch.full((k,), k ** -0.5, dtype=torch.float64))
    # The first two modes are tip and tilt (a plane each: exactly linear in x and y).
    pos = torch.as_tensor(positions, dtype=torch.float64)
    plane = torch.cat([pos, torch.ones(k, 1, dtype=torch.float64)], 1)
    for mode in modes[:, :2].T:
        residual = mode - plane @ torch.linalg.lstsq(plane, mode.unsqueeze(-1)).solution.squeeze(-1)
        assert float(residual.abs().max()) < 0.05 * float(mode.abs().max())


def test_a_modal_filter_fits_per_mode_and_exports_as_a_full_spatial_filter():
    """Data made by a known modal filter is fitted back exactly, and the export applies the same map."""
    net = LinearFilter(80, 3, "modal", grid=GRID)
    gen = torch.Generator().manual_seed(4)
    truth = torch.randn(80, 3, generator=gen, dtype=torch.float64)
    history = torch.randn(500, 80, 3, generator=gen, dtype=torch.float64)
    with torch.no_grad():
        net.weight.copy_(truth)
        target = net(history)
        net.weight.zero_()
    fit_closed_form(net, [(history, target)], 0.0)
    torch.testing.assert_close(net.weight.detach(), truth, atol=1e-8, rtol=0)
    coefficients, neighbours = filter_coefficients(net)
    assert coefficients.shape == (80, 80, 3) and (neighbours == torch.arange(80).numpy()).all()
    torch.testing.assert_close(torch.einsum("ijt,bjt->bi", torch.as_tensor(coefficients), history), target)


@pytest.mark.cli
@pytest.mark.slow
def test_a_noise_free_fit_made_for_deployment_noise_records_it_and_meets_noisy_telemetry_without_a_warning(
        cli, tmp_path, clean_and_noisy_telemetry):
    """Fitted on noise-free telemetry for 3 nm of deployment noise: the checkpoint says so, its filter is more
    attenuated than the plain fit's, and its replay on 3 nm telemetry raises no noise-shift warning."""
    from eofnn.training.checkpoint import load_predictor

    fits = {}
    for name, extra in (("plain", []), ("deploy", ["--predictor.optimization.noise_at_deployment_nm", "3.0"])):
        code, err = cli("fit", "--telemetry", f"[{tmp_path / 'clean.npz'}]", "--predictor.history_length", "3",
                        "--predictor.data.val_frames", "300", "--out", tmp_path / f"{name}.ckpt", *extra)
        assert code == 0, err
        fits[name] = load_predictor(tmp_path / f"{name}.ckpt")
    info = fits["deploy"].info
    assert info["noise"]["deployment_wfs_noise_nm"] == 3.0 and info["noise"]["training_wfs_noise_nm"] < 1.0
    assert info["conditions"]["wfs_noise_nm"] == 3.0 and "noise_at_deployment" not in fits["plain"].info
    # Noise calls for a filter that sums its taps to less: the DC gain of the deployment fit is smaller.
    dc = {name: float(fit.network.weight.detach().sum(-1).abs().mean()) for name, fit in fits.items()}
    assert dc["deploy"] < dc["plain"]
    code, err = cli("replay", "--checkpoint", tmp_path / "deploy.ckpt", "--telemetry", f"[{tmp_path / 'noisy.npz'}]",
                    "--settle_frames", "100", "--out", tmp_path / "replay")
    assert code == 0, err
    assert not [line for line in err.splitlines() if line.startswith("eofnn: warning:") and "WFS noise" in line], err
    # The plain fit, made for the noise-free telemetry it learnt from, is named with both noise levels.
    code, err = cli("replay", "--checkpoint", tmp_path / "plain.ckpt", "--telemetry", f"[{tmp_path / 'noisy.npz'}]",
                    "--settle_frames", "100", "--out", tmp_path / "replay_plain")
    assert code == 0 and [line for line in err.splitlines() if line.startswith("eofnn: warning:")
                          and "WFS noise" in line], err
