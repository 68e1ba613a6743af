"""Benchmark: the RLS update per frame against the 2 kHz budget and numpy, and the stability analysis time.

    PYTHONPATH=. .venv/bin/python -m benchmarks.bench_adaptive [--quick] [--device cuda] [--out FILE]

Rows (ratio = baseline / eofnn, higher is better): ``rls/update`` (one batched RLS update of 1264 actuators x 10
taps vs the same algorithm in numpy), ``rls/budget`` (the same time vs the 0.5 ms of a 2 kHz frame), ``rls/step``
(a whole adaptive controller step vs a static predictive step, information) and ``stability/analysis`` (the full
analysis of a 1264-actuator 12-tap closed-loop EOF vs a bisection of its upper gain margin alone).
"""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.common import Row, Skipped, Timing, synchronizer, time_interleaved
from eofnn.analysis import polynomials as poly
from eofnn.analysis.stability import LoopSetup, analyse, controller_polynomials
from eofnn.control.adaptive import RLSController, integrator_filter
from eofnn.control.predictive import PredictiveController
from eofnn.data.history import HistorySpec
from eofnn.models.linear import LinearFilter
from eofnn.sim.loop.runner import LoopInput

#: One frame of a 2 kHz loop leaves 0.5 ms for the controller.
RLS_BUDGET_S = 0.5e-3


class NumpyRLS:
    """Baseline: the same batched RLS update written in numpy (matmul for ``P x``, an outer product for ``P``)."""

    def __init__(self, weights: np.ndarray, covariance: np.ndarray, forgetting: float) -> None:
        self.weights, self.covariance, self.forgetting = weights.copy(), covariance.copy(), forgetting

    def update(self, x: np.ndarray, target: np.ndarray) -> None:
        px = (self.covariance @ x[..., None])[..., 0]
        gain = px / (self.forgetting + (x * px).sum(-1, keepdims=True))
        self.weights += gain * (target - (self.weights * x).sum(-1))[..., None]
        self.covariance -= gain[..., :, None] * px[..., None, :]
        self.covariance /= self.forgetting


def rls_rows(n_actuators: int, n_taps: int, n_frames: int, repeat: int, seed: int, device: str) -> list[Row]:
    """``rls/update``: eofnn vs numpy, and ``rls/budget``: eofnn vs the 0.5 ms of a 2 kHz frame."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n_frames, 1, n_actuators, n_taps, generator=gen, dtype=torch.float64)
    t = torch.randn(n_frames, 1, n_actuators, generator=gen, dtype=torch.float64)
    spec = HistorySpec("open_loop", n_taps, 2)
    rls = RLSController(spec, forgetting=0.999)
    rls.reset(1, n_actuators, 2, torch.float64)
    rls.weights = rls.weights.to(device)
    xd, td = x.to(device), t.to(device)
    rls.update(xd[0], td[0])  # sets the covariance
    baseline = NumpyRLS(rls.weights[0].cpu().numpy(), rls.covariance.cpu().numpy(), 0.999)
    xn, tn = x[:, 0].numpy(), t[:, 0].numpy()

    def run_eofnn():
        for i in range(n_frames):
            rls.update(xd[i], td[i])

    def run_numpy():
        for i in range(n_frames):
            baseline.update(xn[i], tn[i])

    timings = time_interleaved({"eofnn": (run_eofnn, n_frames), "numpy": (run_numpy, n_frames)}, repeat,
                               sync=synchronizer(device))
    info = {"n_actuators": n_actuators, "n_taps": n_taps, "frames_per_repeat": n_frames,
            "bytes_covariance": n_actuators * n_taps * n_taps * 8}
    return [
        Row("adaptive", "rls/update", "s/frame", timings["eofnn"], timings["numpy"], "numpy RLS, same algorithm",
            1.0, "faster than numpy", device, info),
        Row("adaptive", "rls/budget", "s/frame", timings["eofnn"], Timing([RLS_BUDGET_S]),
            "0.5 ms frame of a 2 kHz loop", 1.0, "within the 2 kHz budget", device, info),
    ]


def step_rows(n_actuators: int, n_taps: int, n_frames: int, repeat: int, seed: int) -> list[Row]:
    """``rls/step``: a whole ``RLSController.step`` (histories, learning, fallback guard) against the step of a
    static ``PredictiveController`` with the same filter size (information: what adaptation adds per frame).

    Each controller runs in its own minimal loop (``eps(n) = s(n) + y(n)``, measured two frames later) on a smooth
    random-walk ``s``, so that its telemetry is consistent and the fallback stays off (checked in ``info``).
    """
    spec = HistorySpec("open_loop", n_taps, 2)
    gen = torch.Generator().manual_seed(seed)
    total = n_frames * (repeat + 2)
    turbulence = torch.randn(total, 1, n_actuators, generator=gen, dtype=torch.float64).cumsum(0)
    network = LinearFilter(n_actuators, n_taps)
    with torch.no_grad():
        network.weight.copy_(integrator_filter(spec, 1.0).expand(n_actuators, -1))
    controllers = {"rls": RLSController(spec, forgetting=0.999), "static": PredictiveController(network, spec)}
    state = {}
    for name, controller in controllers.items():
        controller.reset(1, n_actuators, 2, torch.float64)
        state[name] = {"n": 0, "eps": torch.zeros(2, 1, n_actuators, dtype=torch.float64)}

    def run(name):
        controller, loop = controllers[name], state[name]

        def go():
            for _ in range(n_frames):
                n = loop["n"]
                y = controller.step(LoopInput(n, loop["eps"][n % 2], loop["eps"][n % 2]))
                loop["eps"][n % 2] = turbulence[n] + y  # slot n % 2 now holds eps(n), read at frame n + 2
                loop["n"] = n + 1
        return go

    timings = time_interleaved({name: (run(name), n_frames) for name in controllers}, repeat)
    info = {"n_actuators": n_actuators, "n_taps": n_taps, "rls_fallback_frame": controllers["rls"].fallback_frame}
    return [Row("adaptive", "rls/step", "s/frame", timings["rls"], timings["static"],
                "static PredictiveController step", None, "", "cpu", info)]


def bisected_upper_gain(d_poly: torch.Tensor, n_poly: torch.Tensor, setup: LoopSetup, steps: int = 40) -> np.ndarray:
    """Baseline: the upper DM gain margin by bisection of the pole modulus (batched numpy eigenvalues)."""
    q_n = poly.multiply(setup.plant_polynomial(), n_poly).numpy()
    d = poly.pad(d_poly, q_n.shape[-1]).numpy()
    q_n = poly.pad(torch.as_tensor(q_n), d.shape[-1]).numpy()
    n = d.shape[-1] - 1
    companion = np.zeros((len(d), n, n))
    companion[:, 1:, :-1] = np.eye(n - 1)

    def stable(gain: np.ndarray) -> np.ndarray:
        companion[:, 0, :] = -(d[:, 1:] - gain[:, None] * q_n[:, 1:])
        return np.abs(np.linalg.eigvals(companion)).max(-1) < 1

    lo, hi = np.full(len(d), setup.dm_gain), np.full(len(d), 100.0 * setup.dm_gain)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        ok = stable(mid)
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    return 0.5 * (lo + hi)


def stability_rows(n_actuators: int, history_length: int, repeat: int, seed: int, benchmark: str = "adaptive",
                   name: str = "stability/analysis", goal_seconds: float | None = None) -> list[Row]:
    """``stability/analysis``: the whole analysis vs a bisection of the upper gain margin alone; with
    ``goal_seconds``, a second row ``<name>/budget`` against that many seconds (goal: ratio >= 1)."""
    gen = torch.Generator().manual_seed(seed)
    # A closed-loop EOF near an integrator: the weights of a typical fit, and a stable loop.
    weights = 0.01 * torch.randn(n_actuators, 2 * history_length, generator=gen, dtype=torch.float64)
    weights[:, 0] += 1.0
    weights[:, history_length] -= 0.5
    setup = LoopSetup(delay_frames=2)
    d_poly, n_poly = controller_polynomials(weights, "closed_loop", history_length, 1.0, 2)
    results = {}

    def run_eofnn():
        results["eofnn"] = analyse(weights, "closed_loop", history_length, setup)

    def run_bisection():
        results["bisection"] = bisected_upper_gain(d_poly, n_poly, setup)

    timings = time_interleaved({"eofnn": (run_eofnn, 1), "bisection": (run_bisection, 1)}, repeat)
    analytic = results["eofnn"].gain_interval[:, 1].numpy()
    info = {"n_actuators": n_actuators, "n_taps": 2 * history_length, "kind": "closed_loop",
            "upper_gain_max_relative_difference": float(np.abs(results["bisection"] / analytic - 1).max()),
            "computes": "eofnn: poles, DM gain interval, fractional and integer delay margins, 256-point transfer "
                        "functions; baseline: the upper DM gain bound only (40 bisections of batched eigenvalues)"}
    rows = [Row(benchmark, name, "s/analysis", timings["eofnn"], timings["bisection"],
                "bisection of the upper gain margin (numpy eigvals)", None, "", "cpu", info)]
    if goal_seconds is not None:
        rows.append(Row(benchmark, f"{name}/budget", "s/analysis", timings["eofnn"], Timing([goal_seconds]),
                        f"{goal_seconds:g} s budget", 1.0, f">= 1 (analysis < {goal_seconds:g} s)", "cpu", info))
    return rows


def bench_adaptive(n_actuators: int = 1264, n_taps: int = 10, n_frames: int = 200, repeat: int = 5,
                   stability_history: int = 6, stability_repeat: int = 3, seed: int = 0,
                   device: str = "cpu") -> tuple[list[Row], list[Skipped]]:
    """RLS update rows on ``device`` and the stability-analysis row (CPU) at ``n_actuators``."""
    rows = rls_rows(n_actuators, n_taps, n_frames, repeat, seed, device)
    rows += step_rows(n_actuators, n_taps, n_frames, repeat, seed)
    rows += stability_rows(n_actuators, stability_history, stability_repeat, seed)
    return rows, []


def main() -> None:
    import argparse
    import json

    from benchmarks.common import fmt_seconds

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="tiny sizes (a smoke run)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default=None, help="write the rows as JSON here")
    args = parser.parse_args()
    sizes = dict(n_actuators=80, n_frames=20, repeat=2, stability_repeat=1) if args.quick else {}
    rows, _ = bench_adaptive(device=args.device, **sizes)
    for row in rows:
        print(f"{row.name:22s} eofnn {fmt_seconds(row.eofnn.min):>10s}  {row.baseline_label}: "
              f"{fmt_seconds(row.baseline.min):>10s}  ratio {row.ratio:.3g} (median {row.ratio_median:.3g})"
              f"{'' if row.goal_met is None else '  goal met' if row.goal_met else '  goal MISSED'}  {row.info}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump([row.to_dict() for row in rows], fh, indent=1)


if __name__ == "__main__":
    main()
