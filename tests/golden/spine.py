"""The numbers the "one spine" re-cut must not move: every command on the tiny scenario, fixed seeds.

``python tests/golden/spine.py tests/golden/spine.json`` writes them (on purpose only: after a change that is meant to
move numbers, said in its commit) and records the machine in ``spine_machine.json``; ``tests/test_spine_numbers.py``
compares a fresh run with the committed ``tests/golden/spine.json``. Every controller kind, both fit methods (closed
form and SGD), a gain scan, ``alpha: auto``, training from telemetry alone, a robustness map, the DM-gain margins, and
the telemetry commands (simulate, identify, fit --telemetry, replay, export, stability), so a moved rule shows as a
moved number.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

CONF = Path(__file__).parent.parent / "conf"
TINY = CONF / "tiny_compare.yaml"
TINY_EVAL = CONF / "tiny_evaluate.yaml"
SCENARIO = CONF / "tiny_scenario.yaml"

PREDICTORS = {
    "integrator": {"controller": "integrator", "gains": [0.2, 0.4, 0.6], "refine_rounds": 1,
                   "data": {"frames": 600}},
    "extrapolator": {"controller": "extrapolator", "order": 1},
    "modal": {"controller": "modal_integrator", "modes": 10, "data": {"frames": 1200, "dither_nm": 5.0}},
    "lqg": {"controller": "lqg", "modes": 10, "data": {"frames": 1200, "dither_nm": 5.0}},
    "ol_auto": {"history": "open_loop", "history_length": 3, "optimization": {"alpha": "auto"},
                "data": {"frames": 1500, "val_frames": 300, "sequence_frames": 750}},
    "ol_sgd": {"history": "open_loop", "history_length": 3,
               "optimization": {"fit_method": "sgd", "epochs": 2, "alpha": 1.0e-6},
               "data": {"frames": 1200, "val_frames": 300, "sequence_frames": 300}},
    "mlp": {"history": "open_loop", "history_length": 3,
            "network": {"class_path": "eofnn.models.mlp.MLP", "init_args": {"hidden": [16]}},
            "optimization": {"fit_method": "sgd", "epochs": 2},
            "data": {"frames": 1200, "val_frames": 300, "sequence_frames": 300}},
    "cl_tel": {"history": "closed_loop", "history_length": 4, "optimization": {"alpha": 1.0e-6},
               "data": {"frames": 1500, "val_frames": 300, "dither_nm": 10.0, "integrator_gain": 0.25,
                        "truth": False}},
}


def _main(*args) -> None:
    from eofnn.cli.main import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    if code != 0:
        raise RuntimeError(f"eofnn {args[0]} failed ({code}): {err.getvalue()[-2000:]}")


def _numbers(tree):
    """Only the numbers and flags of a JSON tree (no paths, no times)."""
    if isinstance(tree, dict):
        return {k: _numbers(v) for k, v in tree.items()
                if not (k.endswith("_s") or any(s in k for s in ("seconds", "path", "checkpoint", "peak_memory")))}
    if isinstance(tree, list):
        return [_numbers(v) for v in tree]
    if isinstance(tree, str) and "/" in tree:
        return Path(tree).name  # a file written in a temporary folder
    return tree if isinstance(tree, (int, float, bool)) or tree is None else str(tree)


def spine_numbers() -> dict:
    """The numbers, on one thread (torch and BLAS): sums over threads are added in another order otherwise."""
    import torch
    from threadpoolctl import threadpool_limits

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with threadpool_limits(1):
            return _spine_numbers()
    finally:
        torch.set_num_threads(threads)


def _spine_numbers() -> dict:
    out: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        _main("compare", "--config", TINY, "--scenarios", '{"nominal": {}}', "--predictors", json.dumps(PREDICTORS),
              "--robustness", '{"dm_gain": [0.8, 1.5]}', "--evaluation.frames", "900", "--out", t / "cmp")
        out["compare"] = _numbers(json.loads((t / "cmp" / "metrics.json").read_text()))
        out["robustness"] = _numbers(json.loads((t / "cmp" / "robustness.json").read_text()))
        for name, seed in (("run.fits", 1), ("held.npz", 2)):
            _main("simulate", "--scenario", SCENARIO, "--scenario.plant.dm_gain", "2.0",
                  "--scenario.plant.wfs_noise_nm", "2.0", "--predictor.controller", "dithered_integrator",
                  "--predictor.gain", "0.3", "--predictor.data.dither_nm", "10.0", "--frames", "2000",
                  "--seed", seed, "--out", t / name)
        _main("identify", "--telemetry", t / "run.fits", "--out", t / "plant.json")
        out["identify"] = _numbers(json.loads((t / "plant.json").read_text()))
        _main("fit", "--telemetry", f"[{t / 'run.fits'}]", "--plant", t / "plant.json", "--predictor.history",
              "closed_loop", "--predictor.history_length", "4", "--predictor.data.val_frames", "400",
              "--out", t / "cl.ckpt")
        _main("fit", "--scenario", SCENARIO, "--predictor.history_length", "3", "--predictor.data.frames", "1200",
              "--predictor.data.val_frames", "300", "--predictor.optimization.fit_method", "sgd",
              "--predictor.optimization.epochs", "2", "--out", t / "sgd.ckpt")
        _main("replay", "--checkpoint", t / "cl.ckpt", "--telemetry", f"[{t / 'held.npz'}]", "--plant",
              t / "plant.json", "--settle_frames", "100", "--out", t / "replay")
        out["replay"] = _numbers(json.loads((t / "replay" / "replay.json").read_text()))
        _main("export", "--checkpoint", t / "cl.ckpt", "--out", t / "filter.fits")
        from eofnn.runtime import PredictiveFilter

        runtime = PredictiveFilter.from_file(t / "filter.fits")
        out["export"] = {"dm_gain_model": float(runtime.dm_gain_model),
                         "weights_sum": float(np.sum(np.asarray(runtime.coefficients, dtype=np.float64))),
                         "weights_abs_sum": float(np.sum(np.abs(np.asarray(runtime.coefficients, dtype=np.float64))))}
        for name in ("cl.ckpt", "sgd.ckpt"):
            _main("evaluate", "--config", TINY_EVAL, "--scenarios", '{"nominal": {}}', "--checkpoints",
                  json.dumps({"it": str(t / name)}), "--baselines", "[integrator]", "--evaluation.frames", "700",
                  "--out", t / f"ev_{name}")
            out[f"evaluate_{name}"] = _numbers(json.loads((t / f"ev_{name}" / "metrics.json").read_text()))
        _main("stability", "--checkpoint", t / "sgd.ckpt", "--scenario", SCENARIO, "--out", t / "stab")
        out["stability"] = _numbers(json.loads((t / "stab" / "stability.json").read_text()))
    return out


if __name__ == "__main__":
    # Also records the machine that wrote them (tests/golden/agreement.py): there the check is bit for bit.
    sys.path.insert(0, str(Path(__file__).parent.parent))
    from golden.agreement import MACHINE, machine

    Path(sys.argv[1]).write_text(json.dumps(spine_numbers(), indent=1, sort_keys=True) + "\n")
    MACHINE.write_text(json.dumps(machine(), indent=1) + "\n")
