"""Close an AO loop written with HCIPy alone, with a filter that eofnn trained from that loop's telemetry.

The loop (:func:`run_loop`) is HCIPy and numpy only: an ``InfiniteAtmosphericLayer`` sampled on the actuator grid,
piston/tip/tilt removed, a DM that applies ``dm_gain`` times its command, white WFS noise, and a measurement that
reaches the controller ``delay`` frames late. eofnn never simulates anything here; it plays the on-sky role:

1. record telemetry in the HCIPy loop with an integrator plus white dither, and write it with numpy + astropy in
   the documented layout (``docs/telemetry.md``: Y, WFS, POSITIONS, header DELAY and FRATE);
2. eofnn identifies the plant from that file, fits an open-loop EOF from it alone and exports it
   (``docs/export.md``);
3. the exported file runs in the HCIPy loop through :class:`eofnn.runtime.PredictiveFilter` (numpy + astropy).

    python examples/hcipy_loop.py                          # 10 actuators across a 2 m pupil, DM gain 1.5
    python examples/hcipy_loop.py --filter filter.fits     # step 3 only, with a filter exported before

It prints the median residual RMS of the integrator and of the exported filter (measured: 28.2 nm and 9.2 nm at
the defaults). The identified "WFS noise" (about 7 nm against the 2 nm simulated) also holds the part of HCIPy's
layer on an actuator-pitch grid that is not smooth from frame to frame (new columns extruded at the rim): white
noise and such turbulence cannot be told apart from telemetry (``eofnn/training/identify.py``).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import hcipy
import numpy as np
from astropy.io import fits

from eofnn.runtime import PredictiveFilter


class HcipyAO:
    """Turbulence and plant of an HCIPy loop on an ``n_across`` x ``n_across`` actuator grid (circular pupil)."""

    def __init__(self, n_across: int = 10, diameter_m: float = 2.0, r0_m: float = 0.1, wind_mps: float = 10.0,
                 frame_rate_hz: float = 1000.0, dm_gain: float = 1.5, wfs_noise_nm: float = 2.0, delay: int = 2,
                 seed: int = 0) -> None:
        self.grid = hcipy.make_pupil_grid(n_across, diameter_m)  # pixel centres = actuator centres
        x, y = np.asarray(self.grid.x), np.asarray(self.grid.y)
        self.active = np.hypot(x, y) <= diameter_m / 2 + 1e-9 * diameter_m
        self.positions_m = np.stack([x[self.active], y[self.active]], 1)  # row-major: y, then x
        modes = np.stack([np.ones(self.active.sum()), *self.positions_m.T], 1)
        q, _ = np.linalg.qr(modes)
        self.remove_ptt = np.eye(len(q)) - q @ q.T
        self.wavelength_m, self.dt = 500e-9, 1.0 / frame_rate_hz
        self.layer = hcipy.InfiniteAtmosphericLayer(self.grid, hcipy.Cn_squared_from_fried_parameter(r0_m, 500e-9),
                                                    20.0, [wind_mps, 0.0], use_interpolation=True,
                                                    seed=np.random.default_rng(seed))
        self.dm_gain, self.wfs_noise_nm, self.delay = dm_gain, wfs_noise_nm, delay
        self.noise = np.random.default_rng(seed + 1)
        self.frame_rate_hz = frame_rate_hz

    def turbulence_nm(self, start: int, n_frames: int) -> np.ndarray:
        """``(n_frames, K)`` OPD (nm, PTT removed) from frame ``start`` on; HCIPy layers only move forward in time."""
        frames = []
        for frame in range(start, start + n_frames):
            self.layer.t = frame * self.dt
            phase = np.asarray(self.layer.phase_for(self.wavelength_m))[self.active]
            frames.append(self.remove_ptt @ (phase * self.wavelength_m / (2 * np.pi) * 1e9))
        return np.array(frames)


def run_loop(ao: HcipyAO, step, turbulence_nm: np.ndarray) -> dict[str, np.ndarray]:
    """Close the loop: ``step(measurement) -> command``; the measurement of frame n reaches it at n + delay."""
    n_frames, k = turbulence_nm.shape
    pending = [np.zeros(k) for _ in range(ao.delay)]  # measurements in flight, oldest first
    out = {name: np.zeros((n_frames, k)) for name in ("y", "wfs", "eps")}
    for n in range(n_frames):
        y = step(pending.pop(0))
        eps = turbulence_nm[n] + ao.dm_gain * y
        wfs = eps + ao.wfs_noise_nm * ao.noise.standard_normal(k)
        pending.append(wfs)
        out["y"][n], out["wfs"][n], out["eps"][n] = y, wfs, eps
    return out


def integrator(k: int, gain: float, dither_nm: float = 0.0, seed: int = 2):
    """``y(n) = y(n-1) - gain * m(n)`` plus white dither (not fed back into the integrator state)."""
    state, rng = np.zeros(k), np.random.default_rng(seed)

    def step(measurement: np.ndarray) -> np.ndarray:
        state[:] = state - gain * measurement
        return state + dither_nm * rng.standard_normal(k)
    return step


def write_telemetry(path: Path, record: dict[str, np.ndarray], ao: HcipyAO) -> Path:
    """The documented telemetry layout, with astropy alone."""
    primary = fits.PrimaryHDU()
    primary.header["DELAY"] = (ao.delay, "loop delay in frames")
    primary.header["FRATE"] = (ao.frame_rate_hz, "frame rate in Hz")
    hdus = [primary, fits.ImageHDU(record["y"], name="Y"), fits.ImageHDU(record["wfs"], name="WFS"),
            fits.ImageHDU(ao.positions_m, name="POSITIONS")]
    fits.HDUList(hdus).writeto(path, overwrite=True)
    return path


def train_filter(telemetry_path: Path, filter_path: Path, history_length: int = 4) -> Path:
    """eofnn's part (what ``eofnn identify``, ``fit --telemetry`` and ``export`` do): file in, filter file out."""
    from eofnn.data.history import HistorySpec
    from eofnn.telemetry.record import TELEMETRY_REQUIRED, Telemetry
    from eofnn.training.export import export_filter
    from eofnn.training.from_telemetry import fit_from_telemetry
    from eofnn.training.identify import identify_plant

    telemetry = Telemetry.load(telemetry_path, required=TELEMETRY_REQUIRED)
    plant = identify_plant(telemetry)
    print(f"identified DM gain {plant.dm_gain:.4f} +- {plant.dm_gain_se:.4f}, WFS noise {plant.wfs_noise_nm:.2f} nm, "
          f"lag {plant.lag_frames} frames")
    spec = HistorySpec("open_loop", history_length, telemetry.delay_frames)
    fitted = fit_from_telemetry(telemetry, spec, plant=plant)
    return export_filter(fitted.network, spec, filter_path, dm_gain_model=fitted.predictor.dm_gain_model,
                         positions_m=telemetry.positions_m, overwrite=True)


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-across", type=int, default=10)
    parser.add_argument("--train-frames", type=int, default=4000)
    parser.add_argument("--frames", type=int, default=3000, help="frames of each evaluation loop")
    parser.add_argument("--dm-gain", type=float, default=1.5)
    parser.add_argument("--filter", type=Path, help="an exported filter to run instead of training one")
    parser.add_argument("--out", type=Path, help="folder for telemetry.fits and filter.fits (default: temporary)")
    args = parser.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="hcipy_loop_"))
    out.mkdir(parents=True, exist_ok=True)
    ao = HcipyAO(args.n_across, dm_gain=args.dm_gain)
    k = int(ao.active.sum())
    filter_path = args.filter
    if filter_path is None:
        record = run_loop(ao, integrator(k, 0.3, dither_nm=10.0), ao.turbulence_nm(0, args.train_frames))
        filter_path = train_filter(write_telemetry(out / "telemetry.fits", record, ao), out / "filter.fits")
    # Evaluate on turbulence the filter has not seen, the same frames for both controllers.
    turbulence = ao.turbulence_nm(args.train_frames + 1000, args.frames)
    runtime = PredictiveFilter.from_file(filter_path)
    settle, results = 200, {}
    for name, step in (("integrator", integrator(k, 0.5 / ao.dm_gain)), ("exported filter", runtime.step)):
        eps = run_loop(ao, step, turbulence)["eps"]
        results[name] = float(np.median(np.sqrt((eps[settle:] ** 2).mean(1))))
        print(f"{name:>16}: median residual RMS {results[name]:.2f} nm")
    return results


if __name__ == "__main__":
    main()
