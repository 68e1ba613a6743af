"""A pyramid's optical gains measured on a closed loop's residual, for ``metrics.json``.

The pyramid is linear only about a flat wavefront; about the residual a loop leaves, its response to each mode is
smaller (:mod:`eofnn.sim.sensing.optical_gains`). :class:`OpticalGainProbe` keeps the residual over the pupil at a
few settled frames of a run (through :func:`~eofnn.sim.loop.runner.run_loop`'s ``on_chunk``) and measures, about
each, the optical gains of the first Karhunen-Loève command modes
(:func:`~eofnn.sim.sensing.optical_gains.modal_optical_gains`): the mean over those residuals per mode, and the means
over the low and the high orders.
"""

from __future__ import annotations

from eofnn.lazy import lazy_module

torch = lazy_module("torch")

#: Modes measured (at most the actuators less piston) and settled frames whose residual is probed.
N_MODES, N_FRAMES = 50, 6


class OpticalGainProbe:
    """Collects a pyramid scenario's residual over the pupil at ``n_frames`` frames spread over the settled part of
    a run (``on_chunk``), then :meth:`result` measures the optical gains about them.

    Parameters
    ----------
    scenario : Scenario
        A pyramid scenario (its sensor is the one calibrated for the loop).
    settle_frames, frames : int
        The run's settling frames and its length.
    n_modes, n_frames : int
        Karhunen-Loève modes measured; frames probed (each gives one residual per realisation).
    """

    def __init__(self, scenario, settle_frames: int, frames: int, n_modes: int = N_MODES,
                 n_frames: int = N_FRAMES) -> None:
        from eofnn.sim.loop.pyramid import pyramid_operators

        self.sensor = pyramid_operators(scenario.grid, scenario.sensor.pyramid()).sensor
        self.n_modes = min(n_modes, scenario.grid.n_actuators - 1)
        span = max(frames - settle_frames, 1)
        self.frames = sorted({settle_frames + (span * (2 * k + 1)) // (2 * n_frames) for k in range(n_frames)})
        self.residuals: list[torch.Tensor] = []

    def __call__(self, first: int, arrays: dict) -> None:
        stop = first + arrays["s"].shape[1]
        for frame in self.frames:
            if first <= frame < stop:
                self.residuals.append(arrays["pupil_residual"](frame))

    def result(self) -> dict | None:
        """``{"n_modes", "residuals", "residual_rms_nm", "gains", "low_orders", "low_order_mean", "high_orders",
        "high_order_mean"}`` (orders 1-based, inclusive), or ``None`` when no frame was probed (a diverged run)."""
        if not self.residuals:
            return None
        from eofnn.sim.sensing.optical_gains import modal_optical_gains

        residuals = torch.cat(self.residuals)
        gains, _ = modal_optical_gains(self.sensor, residuals, self.n_modes)
        gains = [float(g) for g in gains]
        n = len(gains)
        low, high = max(1, n // 5), n // 2
        centred = residuals - residuals.mean(-1, keepdim=True)
        return {"n_modes": n, "residuals": len(residuals),
                "residual_rms_nm": float(centred.pow(2).mean(-1).sqrt().mean()),
                "gains": gains,
                "low_orders": [1, low], "low_order_mean": sum(gains[:low]) / low,
                "high_orders": [high + 1, n], "high_order_mean": sum(gains[high:]) / (n - high)}
