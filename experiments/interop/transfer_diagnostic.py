"""Why the anti-aliasing EOF trained in eofnn's simulation keeps less in OOPAO's loop than the one trained on OOPAO's
truth (issue 30): both filters side by side on OOPAO's 20 x 20 system (I = 8, 20 m/s, DM applying 2x), and their
responses to static patterns of POL values over the inner actuators (radius < 1.2 m): uniform (the static gain that
cancels a constant must be -1 times the identified gain), tip, tilt and a checkerboard.

    .venv/bin/python experiments/interop/transfer_diagnostic.py     # about a minute on 2 cores
"""

from __future__ import annotations

import numpy as np

from eofnn.data.history import HistorySpec
from eofnn.interop.loop import runtime_filter
from eofnn.interop.oopao import OopaoLoop
from eofnn.studies.antialias import AntiAliasConfig, record_with_truth
from eofnn.studies.study import ALPHA_PATH
from eofnn.studies.transfer import train_in_eofnn, transfer_filter
from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry
from eofnn.training.identify import identify_plant
from eofnn.training.task import OptimizationConfig


def response(runtime, pattern: np.ndarray, gain: float) -> np.ndarray:
    """The command (times the identified gain) of each actuator to a static POL ``pattern`` on every tap."""
    values = np.append(pattern, 0.0)[np.where(runtime.neighbours < 0, len(pattern), runtime.neighbours)]
    return (runtime.coefficients.sum(-1) * values).sum(-1) * gain


def main() -> None:
    sim = OopaoLoop(20, 4.0, photon_noise=True, magnitude=8, dm_gain=2.0, wind_speed_mps=20)
    config = AntiAliasConfig(train_sequences=2, train_frames=1500, val_frames=300, settle_frames=150)
    telemetry = record_with_truth(sim, config)
    plant = identify_plant(telemetry)
    spec = HistorySpec("open_loop", 4, 2)
    network = {"class_path": "eofnn.models.linear.LinearFilter",
               "init_args": {"structure": "neighbourhood", "radius": 2.5}}
    truth = fit_from_telemetry(telemetry, spec, network, plant=plant,
                               data=TelemetryDataConfig(val_frames=300, target="s", target_dm_gain=2.0),
                               optimization=OptimizationConfig(alpha="auto", alpha_path=ALPHA_PATH))
    oopao = runtime_filter(truth.network, spec, plant.dm_gain)
    fitted, scenario = train_in_eofnn(sim, frames=3000, val_frames=600)
    eofnn, moved = transfer_filter(fitted.network, fitted.spec, scenario.grid.positions_m, sim.positions_m,
                                   plant.dm_gain)
    x, y = sim.positions_m.T
    inner = np.hypot(x, y) < 1.2
    print(f"identified gain {plant.dm_gain:.4f}; {moved['matched']} actuators matched, {moved['held']} held")
    for name, pattern in (("uniform", np.ones_like(x)), ("tip", x), ("tilt", y),
                          ("checkerboard", (-1.0) ** (np.round(x / 0.2) + np.round(y / 0.2)))):
        a, b = response(oopao, pattern, plant.dm_gain)[inner], response(eofnn, pattern, plant.dm_gain)[inner]
        print(f"{name}: eofnn-trained / OOPAO-truth-trained response {float(a @ b / (a @ a)):.3f} "
              f"(correlation {float(np.corrcoef(a, b)[0, 1]) if np.std(a) and np.std(b) else 1.0:.3f}); "
              f"mean response OOPAO-trained {a.mean():+.3f}, eofnn-trained {b.mean():+.3f}")


if __name__ == "__main__":
    main()
