"""Telemetry written by hand (numpy + astropy only, no eofnn) in the layout of docs/telemetry.md.

The centrepiece: a loop simulated in plain numpy by "another simulator" (moving Fourier modes, an integrator with
dither, a DM that applies 1.7x its command, WFS noise) is written as FITS and as npz; eofnn loads it, identifies
the plant, fits predictors from it alone, replays them on the held-out tail and exports one, and the numpy runtime
closes the numpy loop with the exported file.
"""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits

from eofnn.data.history import HistorySpec
from eofnn.errors import TelemetryError
from eofnn.evaluation.replay import replay
from eofnn.runtime import PredictiveFilter
from eofnn.telemetry.record import TELEMETRY_REQUIRED, Telemetry
from eofnn.training.export import export_filter
from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry
from eofnn.training.identify import identify_plant

DM_GAIN, NOISE_NM, DELAY, RATE_HZ = 1.7, 3.0, 2, 1000.0


class NumpyAO:
    """A foreign simulator: 10 x 10 actuators on a 2 m pupil, frozen flow of random Fourier modes at 20 m/s."""

    def __init__(self, seed: int = 0) -> None:
        centres = (np.arange(10) + 0.5) * 0.2 - 1.0
        yy, xx = np.meshgrid(centres, centres, indexing="ij")  # row-major: y, then x
        inside = np.hypot(xx, yy) <= 1.0 + 1e-9
        self.positions_m = np.stack([xx[inside], yy[inside]], 1)
        rng = np.random.default_rng(seed)
        k = 2 * np.pi * rng.uniform(0.05, 2.0, 300)  # rad/m, up to one cycle per 2.5 pitches
        angle = rng.uniform(0, 2 * np.pi, 300)
        self.wavevectors = np.stack([k * np.cos(angle), k * np.sin(angle)], 1)
        self.amplitudes = 2000.0 * (k / k.min()) ** (-11 / 6) * rng.standard_normal(300)
        self.phases = rng.uniform(0, 2 * np.pi, 300)
        q, _ = np.linalg.qr(np.stack([np.ones(len(self.positions_m)), *self.positions_m.T], 1))
        self.remove_ptt = np.eye(len(q)) - q @ q.T
        self.rng = np.random.default_rng(seed + 1)

    def turbulence(self, start: int, n_frames: int) -> np.ndarray:
        t = (start + np.arange(n_frames))[:, None, None] / RATE_HZ
        shifted = self.positions_m[None] - np.array([20.0, 0.0]) * t  # (frames, K, 2)
        opd = (self.amplitudes * np.cos(shifted @ self.wavevectors.T + self.phases)).sum(-1)
        return opd @ self.remove_ptt.T

    def loop(self, turbulence: np.ndarray, step) -> dict[str, np.ndarray]:
        """wfs(n) measures eps(n) = s(n) + 1.7 y(n); the controller gets it at frame n + 2."""
        n_frames, k = turbulence.shape
        pending = [np.zeros(k)] * DELAY
        out = {name: np.zeros((n_frames, k)) for name in ("y", "wfs", "eps")}
        for n in range(n_frames):
            y = step(pending.pop(0))
            eps = turbulence[n] + DM_GAIN * y
            wfs = eps + NOISE_NM * self.rng.standard_normal(k)
            pending.append(wfs)
            out["y"][n], out["wfs"][n], out["eps"][n] = y, wfs, eps
        return out


def integrator(k: int, gain: float, dither_nm: float, rng: np.random.Generator):
    state = np.zeros(k)

    def step(measurement):
        state[:] = state - gain * measurement
        return state + dither_nm * rng.standard_normal(k)
    return step


def write_by_hand(path, y, wfs, positions_m) -> None:
    """What a user does with their own data: numpy and astropy, nothing else."""
    if path.suffix == ".fits":
        primary = fits.PrimaryHDU()
        primary.header["DELAY"] = DELAY
        primary.header["FRATE"] = RATE_HZ
        fits.HDUList([primary, fits.ImageHDU(y, name="Y"), fits.ImageHDU(wfs, name="WFS"),
                      fits.ImageHDU(positions_m, name="POSITIONS")]).writeto(path)
    else:
        np.savez(path, y=y, wfs=wfs, positions_m=positions_m, delay_frames=DELAY, frame_rate_hz=RATE_HZ)


@pytest.fixture(scope="module")
def recording():
    ao = NumpyAO()
    k = len(ao.positions_m)
    record = ao.loop(ao.turbulence(0, 5000), integrator(k, 0.3, 10.0, np.random.default_rng(5)))
    return ao, record


@pytest.mark.slow
@pytest.mark.parametrize("suffix", [".fits", ".npz"])
def test_hand_written_file_identifies_trains_replays_and_exports(recording, tmp_path, suffix):
    ao, record = recording
    path = tmp_path / f"telemetry{suffix}"
    write_by_hand(path, record["y"], record["wfs"], ao.positions_m)
    telemetry = Telemetry.load(path, required=TELEMETRY_REQUIRED)
    assert telemetry.delay_frames == DELAY and telemetry.frame_rate_hz == RATE_HZ and telemetry.s is None

    plant = identify_plant(telemetry)
    assert plant.identified and plant.lag_frames == 0
    assert abs(plant.dm_gain / DM_GAIN - 1) < 0.02
    assert abs(plant.misregistration_x) < 0.02 and abs(plant.misregistration_y) < 0.02
    assert plant.wfs_noise_nm == pytest.approx(NOISE_NM, rel=0.2)
    plant.to_json(tmp_path / "plant.json")

    errors = {}
    for kind in ("open_loop", "closed_loop"):
        spec = HistorySpec(kind, 4, DELAY)
        fitted = fit_from_telemetry(telemetry, spec, plant=plant, data=TelemetryDataConfig(stop=4000))
        result = replay(fitted.network, spec, telemetry, plant=plant, start=4000)
        result.to_json(tmp_path / f"replay_{kind}.json")
        errors[kind] = result.predictor.median_rms_noise_corrected_nm
        # Predicting the turbulence beats the recording integrator on the same held-out frames.
        assert result.predictor.median_rms_nm < 0.8 * result.own_controller.median_rms_nm, kind

    spec = HistorySpec("open_loop", 4, DELAY)
    fitted = fit_from_telemetry(telemetry, spec, plant=plant, data=TelemetryDataConfig(stop=4000))
    exported = export_filter(fitted.network, spec, tmp_path / "filter.fits", dm_gain_model=fitted.predictor.dm_gain_model,
                             positions_m=telemetry.positions_m)
    runtime = PredictiveFilter.from_file(exported)
    fresh = ao.turbulence(6000, 1500)  # turbulence no recording has seen
    k = len(ao.positions_m)
    by_filter = ao.loop(fresh, runtime.step)["eps"][200:]
    by_integrator = ao.loop(fresh, integrator(k, 0.5 / DM_GAIN, 0.0, np.random.default_rng(0)))["eps"][200:]
    rms_filter = np.median(np.sqrt((by_filter ** 2).mean(1)))
    rms_integrator = np.median(np.sqrt((by_integrator ** 2).mean(1)))
    assert rms_filter < 0.7 * rms_integrator
    # The runtime in the loop does what the replay predicted (same filter, same noise level), within 20%.
    assert rms_filter == pytest.approx(errors["open_loop"], rel=0.2)


def _fits(path, delay=DELAY, **arrays):
    primary = fits.PrimaryHDU()
    if delay is not None:
        primary.header["DELAY"] = delay
    fits.HDUList([primary] + [fits.ImageHDU(v, name=k.upper()) for k, v in arrays.items()]).writeto(path)
    return path


def test_bad_hand_written_files(tmp_path):
    good = np.zeros((50, 6))
    cases = {
        "missing wfs": (_fits(tmp_path / "a.fits", y=good), "lacks array.*wfs"),
        "shapes": (_fits(tmp_path / "b.fits", y=good, wfs=np.zeros((50, 7))), "'wfs' has shape"),
        "nan": (_fits(tmp_path / "c.fits", y=good, wfs=np.where(np.eye(50, 6) > 0, np.nan, 0.0)), "'wfs' holds 6 non"),
        "no delay": (_fits(tmp_path / "d.fits", None, y=good, wfs=good), "lacks the loop delay"),
        "delay below a frame": (_fits(tmp_path / "e.fits", 0.5, y=good, wfs=good), "delay_frames=0.5 is invalid"),
        "zero delay": (_fits(tmp_path / "f.fits", 0, y=good, wfs=good), "delay_frames=0 is invalid"),
        "positions": (_fits(tmp_path / "g.fits", y=good, wfs=good, positions=np.zeros((5, 2))), "positions_m has shape"),
    }
    np.savez(tmp_path / "complex.npz", y=good + 1j, wfs=good, delay_frames=2)
    np.savez(tmp_path / "text.npz", y=np.full((50, 6), "x"), wfs=good, delay_frames=2)
    np.savez(tmp_path / "delay_text.npz", y=good, wfs=good, delay_frames="two")
    cases |= {"complex": (tmp_path / "complex.npz", "dtype complex128"), "text": (tmp_path / "text.npz", "dtype <U1"),
              "delay text": (tmp_path / "delay_text.npz", "delay_frames='two' is invalid")}
    whole = _fits(tmp_path / "whole.fits", y=np.ones((400, 30)), wfs=np.ones((400, 30))).read_bytes()
    (tmp_path / "truncated.fits").write_bytes(whole[: len(whole) * 2 // 3])
    (tmp_path / "garbage.fits").write_bytes(bytes(range(256)) * 20)
    np.savez(tmp_path / "whole.npz", y=good, wfs=good, delay_frames=2)
    (tmp_path / "truncated.npz").write_bytes((tmp_path / "whole.npz").read_bytes()[:300])
    cases |= {"truncated fits": (tmp_path / "truncated.fits", "truncated or corrupt|not readable as fits"),
              "garbage fits": (tmp_path / "garbage.fits", "not readable as fits"),
              "truncated npz": (tmp_path / "truncated.npz", "not readable as npz")}
    for name, (path, message) in cases.items():
        with pytest.raises(TelemetryError, match=message) as caught:
            Telemetry.load(path, required=TELEMETRY_REQUIRED)
        assert "\n" not in str(caught.value), name
    assert Telemetry.load(tmp_path / "whole.npz", required=TELEMETRY_REQUIRED).delay_frames == 2


@pytest.mark.parametrize("suffix", [".fits", ".npz"])
def test_eofnn_files_carry_positions_and_frame_rate(tmp_path, suffix):
    ao = NumpyAO()
    y = np.random.default_rng(0).standard_normal((20, len(ao.positions_m)))
    tel = Telemetry(y=y, wfs=2 * y, delay_frames=3, frame_rate_hz=500.0, positions_m=ao.positions_m)
    back = Telemetry.load(tel.save(tmp_path / f"t{suffix}"), required=TELEMETRY_REQUIRED)
    assert back.delay_frames == 3 and back.frame_rate_hz == 500.0
    assert np.array_equal(back.positions_m.numpy(), ao.positions_m) and np.array_equal(back.wfs.numpy(), 2 * y)
