"""Anti-aliasing prediction learned from a simulator's truth, run in OOPAO's loop (eofnn/studies/antialias.py).

One small study (10 x 10 Shack-Hartmann on 2 m, photon noise at I = 8, 20 m/s, DM applying 2x) is run once for the
module; the telemetry targets it rests on are checked on their own, without OOPAO.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eofnn.data.history import HistorySpec, blended_target
from eofnn.data.targets import TelemetryBatches
from eofnn.errors import ConfigError, TelemetryError
from eofnn.studies.antialias import AntiAliasConfig, antialias_markdown, run_antialias
from eofnn.telemetry.record import Telemetry

CONFIG = AntiAliasConfig(train_sequences=2, train_frames=700, val_frames=140, loop_frames=400, settle_frames=70,
                         warmup_frames=35, gains=(0.25, 0.3, 0.35), scored_realisations=2)


def _telemetry(with_s: bool) -> Telemetry:
    g = torch.Generator().manual_seed(0)
    y, wfs, s = (torch.randn(60, 5, generator=g, dtype=torch.float64) for _ in range(3))
    return Telemetry(s=s if with_s else None, y=y, wfs=wfs, delay_frames=2)


def test_truth_targets_cancel_the_recorded_s_through_the_simulators_dm_gain():
    tel, spec = _telemetry(True), HistorySpec("open_loop", 3, 2)
    measured = list(TelemetryBatches(tel, spec, lambda y: 1.5 * y, 1.5, batch_frames=20))
    truth = list(TelemetryBatches(tel, spec, lambda y: 1.5 * y, 1.5, batch_frames=20, target="s", target_dm_gain=2.0))
    assert len(truth) == len(measured) == 3
    for (h_m, t_m), (h_t, t_t) in zip(measured, truth, strict=True):
        assert torch.equal(h_m, h_t)  # the same measured POL histories
        assert not torch.allclose(t_m, t_t)
    expected = -blended_target(tel.s, spec) / 2.0
    assert torch.allclose(torch.cat([t for _, t in truth]), expected)


def test_truth_targets_are_refused_in_one_line_without_s_or_with_an_unknown_target():
    spec = HistorySpec("open_loop", 3, 2)
    with pytest.raises(TelemetryError, match="lacks"):
        TelemetryBatches(_telemetry(False), spec, lambda y: y, 1.0, target="s")
    with pytest.raises(TelemetryError, match="target='truth' is invalid"):
        TelemetryBatches(_telemetry(True), spec, lambda y: y, 1.0, target="truth")


def test_a_config_that_leaves_nothing_to_train_is_refused():
    with pytest.raises(ConfigError, match="leave nothing"):
        AntiAliasConfig(train_frames=300, val_frames=200, settle_frames=100)
    with pytest.raises(ConfigError, match=r"^psd_segment_frames=512 is longer than the 300 settled frames"):
        AntiAliasConfig(loop_frames=400, settle_frames=100, psd_segment_frames=512)


def _psd_metrics() -> dict:
    """Two contenders' PSDs of 1 kHz runs (segment 8): flat at 2 and 1 nm²/Hz, frozen flow at 200 Hz."""
    freq = np.fft.rfftfreq(8, 1e-3).tolist()
    run = {"realisations_median_rms_nm": [1.0], "mean_of_realisations_nm": 1.0, "mean_contrast": {}}
    return {"psd_frequency_hz": freq, "frozen_flow_hz": 200.0, "simulator": {"simulator": "oopao", "n_subapertures": 4},
            "contenders": {"integrator": {**run, "measured_psd_nm2_per_hz": [2.0] * 5},
                           "eof_measured": {**run, "measured_psd_nm2_per_hz": [1.0] * 5},
                           "guarded": {**run, "measured_psd_nm2_per_hz": []}}}


def test_the_psd_bands_split_the_measured_residual_at_the_frozen_flow_frequency(tmp_path):
    from eofnn.reporting.interop import antialias_psd_figure
    from eofnn.studies.report import psd_bands, psd_bands_markdown

    metrics = _psd_metrics()
    assert psd_bands(metrics, "integrator") == (2.0 * 2 * 125, 2.0 * 3 * 125)  # 0, 125 Hz below; 250, 375, 500 above
    assert psd_bands(metrics, "eof_measured") == (250.0, 375.0)
    assert psd_bands(metrics, "guarded") is None
    text = "\n".join(psd_bands_markdown(metrics))
    assert "| integrator | 500 | 750 |" in text and "| guarded | diverged |" in text and "200 Hz" in text
    path = antialias_psd_figure(metrics, tmp_path / "psd.png")
    assert path.read_bytes()[:4] == b"\x89PNG"
    metrics["contenders"] = {"guarded": metrics["contenders"]["guarded"]}
    assert antialias_psd_figure(metrics, tmp_path / "none.png") is None and not (tmp_path / "none.png").exists()


@pytest.fixture(scope="module")
def study():
    pytest.importorskip("OOPAO")
    from eofnn.interop.oopao import OopaoLoop

    sim = OopaoLoop(10, 2.0, photon_noise=True, magnitude=8.0, dm_gain=2.0, wind_speed_mps=20.0)
    return run_antialias(sim, CONFIG)


@pytest.mark.slow
def test_the_fit_of_the_true_phase_leaves_the_fitting_error_of_theory():
    pytest.importorskip("OOPAO")
    from eofnn.interop.oopao import OopaoLoop, fitting_error

    sim = OopaoLoop(10, 2.0)
    sim.reset(5)
    sim.step_turbulence()
    opd = sim.turbulence_opd_nm()
    opd = opd - opd.mean()
    modes = sim._fit_operator()[0]
    left = np.sqrt(np.mean((opd - modes @ sim.turbulence_fit_nm()) ** 2))
    assert left == pytest.approx(fitting_error(sim, 1, 5)["median_rms_nm"], rel=1e-9)
    # Fitting error of a DM of pitch d (Hudgins 1977, Gaussian influence functions): 0.28 (d / r0)^(5/3) rad^2, with
    # r0 = 0.15 m at 500 nm and d = 0.2 m: 53 nm; one frame of a 2 m pupil scatters around it.
    theory = np.sqrt(0.28 * (0.2 / 0.15) ** (5 / 3)) * 500 / (2 * np.pi)
    assert 0.6 < left / theory < 1.2


@pytest.mark.slow
def test_both_eofs_beat_the_best_gain_integrator_and_the_guard_deploys_the_antialiasing_one(study):
    gains = study["gains"]
    for name in ("eof_measured", "eof_antialias"):
        assert gains[name]["variance_after_fitting"] > 1.4, name  # 20 m/s on 0.2 m subapertures: lag dominates
        assert all(d > 0 for d in gains[name]["paired_difference_nm"]), name
        assert gains[name]["contrast"]["3"] > 1.4, name
    assert study["guard"]["deployed"] == "eof_antialias"
    assert study["contenders"]["guarded"]["realisations_median_rms_nm"] == \
        study["contenders"]["eof_antialias"]["realisations_median_rms_nm"]
    assert study["fits"]["eof_antialias"]["target"] == "s" and study["fits"]["eof_measured"]["target"] == "measured"


@pytest.mark.slow
def test_the_lqg_is_built_from_the_same_telemetry_and_the_best_classical_is_chosen_on_the_scan(study):
    scan = study["lqg_scan"]["scan"]
    lqg_scan = study["lqg_scan"]
    chosen = f"ar_order={lqg_scan['ar_order']}, noise_scale={lqg_scan['noise_scale']:g}" + (
        "" if lqg_scan["noise_covariance"] == "identified" else f", noise={lqg_scan['noise_covariance']}")
    assert chosen == min((k for k, v in scan.items() if v is not None), key=scan.get)
    assert any(key.startswith("ar_order=0,") for key in scan)  # the random walk (POL integrator) is a candidate
    lqg = study["contenders"]["lqg"]["realisations_median_rms_nm"]
    integrator = study["contenders"]["integrator"]["realisations_median_rms_nm"]
    assert all(0.8 < a / b < 1.2 for a, b in zip(lqg, integrator, strict=True))  # an AR model per mode: near the integrator here
    on_scan = {"integrator": study["guard"]["scan_integrator_nm"], "modal": study["modal_scan"]["median_rms_nm"],
               "lqg": scan[chosen], "pfc": study["pfc_scan"]["median_rms_nm"]}
    assert study["best_classical"] == min(on_scan, key=on_scan.get)
    # With its memory alpha tuned, predictive Fourier control is the best classical controller of this frozen flow
    # (it was last of the three at the default alpha 0.9999); the anti-aliasing EOF still beats it (1.37x here).
    assert study["best_classical"] == "pfc"
    assert study["gains_over_best_classical"]["eof_antialias"]["variance_after_fitting"] > 1.2


@pytest.mark.slow
def test_predictive_fourier_control_is_built_from_the_same_telemetry_with_its_wind_identified(study):
    """PFC's winds come from OOPAO's telemetry alone: the strongest layer moves along the actuator rows (OOPAO's 0
    degrees: the lattice's rows) at about the simulated 20 m/s (23.4 m/s identified here, from 2 x 630 frames on an
    11-across lattice; 24.1 from 3 x 900); its aliases are chosen on the scan, and it is scored on the same
    realisations as the others. Its memory alpha is scanned without aliases, then one ring is tried at the best alpha,
    and the lowest of the six wins."""
    from eofnn.control.config import alpha_past_edge
    from eofnn.studies.antialias import PFC_ALPHAS

    pfc = study["pfc_scan"]
    scan = pfc["scan"]
    assert list(scan)[:len(PFC_ALPHAS)] == [f"aliases=0, alpha={a}" for a in PFC_ALPHAS]
    no_ring = {float(k.split("alpha=")[1]): v for k, v in scan.items() if k.startswith("aliases=0")}
    assert pfc["alpha"] == min(no_ring, key=no_ring.get)
    # On past the grid's edge exactly while the best was at it: the scan ends with nothing more to try.
    extra = len(no_ring) - len(PFC_ALPHAS)
    assert alpha_past_edge(no_ring, extra) is None
    assert all(alpha_past_edge(dict(list(no_ring.items())[:i]), i - len(PFC_ALPHAS)) == alpha
               for i, alpha in enumerate(list(no_ring)[len(PFC_ALPHAS):], start=len(PFC_ALPHAS)))
    ring = f"aliases=1, alpha={pfc['alpha']:g}"
    assert list(scan)[len(no_ring)] == ring
    assert pfc["median_rms_nm"] == min(v for v in scan.values() if v is not None)
    assert pfc["aliases"] == (1 if scan[ring] < no_ring[pfc["alpha"]] else 0)
    # Then the noise coloured by OOPAO's reconstructor at the chosen alpha and aliases, kept where it does better.
    coloured = f"aliases={pfc['aliases']}, alpha={pfc['alpha']:g}, noise=reconstructor"
    assert list(scan)[-1] == coloured
    assert pfc["noise_covariance"] == ("reconstructor" if scan[coloured] == pfc["median_rms_nm"] else "white")
    strongest = pfc["identified"]["layers"][0]
    assert strongest["speed_mps"] == pytest.approx(20.0, rel=0.25)
    assert abs(strongest["vx_mps"]) < 0.25 * strongest["speed_mps"]  # along the lattice's rows (its y)
    assert pfc["identified"]["noise_rms_nm"] > 0
    assert len(study["contenders"]["pfc"]["realisations_median_rms_nm"]) == CONFIG.scored_realisations


@pytest.mark.slow
def test_the_modal_integrator_with_optimised_gains_is_built_from_the_same_telemetry(study):
    """Gendron & Léna's gain per KL mode from the recorded telemetry's PSDs, the cap on its gains chosen on the scan
    realisation; scored on the same realisations, it does no worse than the best single gain beyond their scatter."""
    from eofnn.control.modal import GAIN_MARGIN_CANDIDATES

    modal = study["modal_scan"]
    scan = {float(k): v for k, v in modal["scan"].items()}
    assert list(scan) == list(GAIN_MARGIN_CANDIDATES)
    assert modal["gain_margin"] == min(scan, key=scan.get) and modal["median_rms_nm"] == scan[modal["gain_margin"]]
    quantiles = modal["info"]["gains_quantiles_0_10_50_90_100"]
    assert 0 < quantiles[0] < quantiles[-1] < modal["info"]["critical_gain"]  # not one gain for every mode
    mine = study["contenders"]["modal"]["realisations_median_rms_nm"]
    integrator = study["contenders"]["integrator"]["realisations_median_rms_nm"]
    assert len(mine) == CONFIG.scored_realisations
    assert np.mean(mine) < 1.05 * np.mean(integrator)
    assert "modal" not in study["gains"]  # a classical controller: a baseline, not a predictor to rate


@pytest.mark.slow
def test_the_results_table_names_every_contender(study):
    text = antialias_markdown(study)
    assert "Modal integrator (optimised gains): gain margin" in text
    for name in ("integrator", "modal", "lqg", "pfc", "eof_measured", "eof_antialias", "guarded"):
        assert f"| {name} |" in text
        psd = study["contenders"][name]["measured_psd_nm2_per_hz"]
        assert len(psd) == len(study["psd_frequency_hz"]) == CONFIG.psd_segment_frames // 2 + 1
        assert all(p > 0 for p in psd)
    assert "Temporal PSD of the measured residual" in text
    assert "raw contrast at 3 λ/D" in text and "variance gain after fitting" in text


def test_a_diverged_recording_is_one_line_naming_the_gain_frame_and_simulator():
    from types import SimpleNamespace

    from eofnn.interop.loop import LoopRecord, require_recorded

    empty = np.zeros((0, 3))
    record = LoopRecord(empty, empty, np.zeros(0), np.zeros((3, 2)), 2, 1000.0, diverged_frame=17)
    with pytest.raises(ConfigError, match=r"^the recording integrator \(gain 0.4\) diverged at frame 17 in oopao's "
                                          r"loop: lower record_gain or dither_nm$"):
        require_recorded(record, 0.4, SimpleNamespace(name="oopao"))
    held = LoopRecord(empty, empty, np.zeros(0), np.zeros((3, 2)), 2, 1000.0)
    assert require_recorded(held, 0.4, SimpleNamespace(name="oopao")) is held


def _run(medians, contrast):
    return {"realisations_median_rms_nm": medians, "mean_of_realisations_nm": sum(medians) / len(medians),
            "mean_contrast": {"3": contrast}}


def test_eta_is_each_predictors_share_of_the_oracles_variance_gain_and_the_oracle_is_not_rated():
    from eofnn.studies.antialias import etas

    results = {"integrator": _run([100.0, 104.0], 6e-4), "pfc": _run([90.0, 92.0], 5e-4),
               "eof_measured": _run([70.0, 72.0], 2e-4), "oracle": _run([60.0, 61.0], 1e-4),
               "guarded": _run([95.0, 96.0], 4e-4)}
    out = etas(results, "pfc")
    assert set(out) == {"eof_measured", "guarded"}  # neither a classical controller nor the oracle is rated
    best, mine, ceiling = 90 ** 2 + 92 ** 2, 70 ** 2 + 72 ** 2, 60 ** 2 + 61 ** 2
    assert out["eof_measured"]["eta"] == pytest.approx((best - mine) / (best - ceiling))
    assert out["eof_measured"]["per_realisation"] == pytest.approx(
        [(90 ** 2 - 70 ** 2) / (90 ** 2 - 60 ** 2), (92 ** 2 - 72 ** 2) / (92 ** 2 - 61 ** 2)])
    assert out["guarded"]["eta"] < 0 and out["eof_measured"]["against"] == "pfc"  # worse than the baseline: below 0
    results["oracle"] = _run([95.0, 96.0], 1e-4)  # an oracle worse than the baseline gains nothing: eta undefined
    assert etas(results, "pfc")["eof_measured"]["eta"] is None
    del results["oracle"]
    assert etas(results, "pfc") == {"eof_measured": None, "guarded": None}


def test_the_oracle_reaches_further_than_the_eofs_as_eofnns_own_oracle_does():
    from eofnn.evaluation.contenders import ORACLE_EXTRA_RADIUS, ORACLE_EXTRA_TAPS, ORACLE_FRAMES_FACTOR
    from eofnn.studies.antialias import oracle_reach

    config = AntiAliasConfig(train_frames=2000, val_frames=400, loop_frames=1000, settle_frames=200)
    reach = oracle_reach(config)
    assert reach == {"history_length": config.history_length + ORACLE_EXTRA_TAPS,
                     "radius": config.radius + ORACLE_EXTRA_RADIUS,
                     "sequences": ORACLE_FRAMES_FACTOR * config.train_sequences, "val_frames": 400}
    assert oracle_reach(CONFIG)["sequences"] * CONFIG.train_frames >= 8000  # never fewer frames than eofnn's oracle
    with pytest.raises(ConfigError, match="oracle"):
        AntiAliasConfig(oracle="yes")


@pytest.mark.slow
def test_the_oracle_is_scored_beside_the_others_and_no_predictor_beats_it_beyond_the_scatter(study):
    """The oracle (trained on OOPAO's truth, wider and longer): its row, its fit labelled as simulator knowledge, each
    predictor's eta, and no predictor below it beyond the scatter of their paired differences."""
    assert study["roles"]["oracle"] == "oracle" and study["guard"]["deployed"] != "oracle"
    fit = study["fits"]["oracle"]
    assert "simulator knowledge" in fit["knowledge"] and fit["target"] == "s"
    assert fit["radius"] > CONFIG.radius and fit["history_length"] > CONFIG.history_length
    oracle = study["contenders"]["oracle"]["realisations_median_rms_nm"]
    for name in ("eof_measured", "eof_antialias", "guarded"):
        mine = study["contenders"][name]["realisations_median_rms_nm"]
        d = np.subtract(mine, oracle)  # above 0: the oracle is lower
        assert d.mean() + 2 * d.std(ddof=1) >= 0, name
        entry = study["eta"][name]
        assert entry["against"] == study["best_classical"] and len(entry["per_realisation"]) == len(oracle)
        assert entry["eta"] <= 1 + 2 * np.std(entry["per_realisation"], ddof=1), name
    assert "oracle" in study["gains_over_best_classical"] and "oracle" not in study["eta"]
    text = antialias_markdown(study)
    assert "| oracle |" in text and "η (per realisation)" in text and "1 (the ceiling)" in text


def test_scored_frames_lengthen_the_scored_runs_only_and_bad_values_are_refused(monkeypatch):
    import types

    import eofnn.studies.antialias as aa

    config = AntiAliasConfig(loop_frames=1000, settle_frames=200, scored_frames=2000)
    assert config.scored_run_frames == 2200 and AntiAliasConfig().scored_run_frames == 1000
    for bad in (0, 2.5, True):
        with pytest.raises(ConfigError, match=rf"^scored_frames={bad!r} is invalid"):
            AntiAliasConfig(scored_frames=bad)
    lengths = []

    class Record:
        shift, diverged_frame = None, None
        wfs = np.zeros((2200, 3))

        def metrics(self, settle):
            return types.SimpleNamespace(median_rms_nm=10.0)

    def fake_loop(sim, control, frames, seed, observers=()):
        lengths.append(frames)
        return Record()

    class Contrast:
        def __init__(self, *args):
            self.contrast = types.SimpleNamespace(at=lambda seps: dict.fromkeys(seps, 1e-4))

    monkeypatch.setattr(aa, "run_closed_loop", fake_loop)
    monkeypatch.setattr(aa, "PupilContrast", Contrast)
    out = aa.score(types.SimpleNamespace(frame_rate_hz=1000.0), lambda name: None, "integrator", [2, 20], config)
    assert lengths == [2200, 2200] and out["realisations_median_rms_nm"] == [10.0, 10.0]
