"""Messages that say what a number is: noise-corrected errors that cannot be estimated, linear analyses, Strehl."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from eofnn.evaluation.metrics import WelchPSD
from eofnn.evaluation.replay import _ErrorAccumulator
from eofnn.evaluation.results import ExperimentResult, describe_run
from eofnn.reporting.report import markdown_table


def stats(sigma_nm: float, noise_nm: float):
    error = torch.randn(400, 50, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * sigma_nm
    accumulated = _ErrorAccumulator(WelchPSD(64, 1000.0))
    accumulated.add(error)
    return accumulated.stats(noise_nm)


def test_a_noise_corrected_error_within_the_noise_is_not_reported_as_zero():
    within = stats(2.0, 2.5)  # the error is all noise: removing 2.5 nm of it leaves nothing to measure
    assert within.median_rms_noise_corrected_nm is None and "cannot be estimated" in within.noise_correction
    above = stats(3.0, 2.0)
    assert abs(above.median_rms_noise_corrected_nm - 5 ** 0.5) < 0.1 and "removed in quadrature" in above.noise_correction
    unknown = stats(3.0, 0.0)
    assert unknown.median_rms_noise_corrected_nm == unknown.median_rms_nm and "no WFS noise" in unknown.noise_correction


def test_the_stability_of_a_progress_line_says_it_is_linear():
    diverged = SimpleNamespace(diverged=True, diverged_frame=120, median_rms_nm=None)
    line = describe_run(diverged, {"stable": True, "dm_gain_interval": [0.4, 1.6]})
    assert "diverged at frame 120" in line and "linear analysis: stable" in line


def test_strehl_is_labelled_with_its_wavelength():
    m = SimpleNamespace(diverged=False, median_rms_nm=10.0, p95_rms_nm=12.0, strehl=0.99)
    table = markdown_table(ExperimentResult({"nominal": {"integrator": m}}), strehl_wavelength_m=1.65e-6)
    assert "nominal Strehl at 1.65 um" in table
