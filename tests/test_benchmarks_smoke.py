"""Smoke test of ``benchmarks/``: every benchmark runs once at tiny size (``--quick``) through the real command.

No wall-clock assertions: only that each benchmark produced its rows with finite, positive ratios, that the
scaling series have finite exponents, and that CUDA rows are skipped cleanly when there is no GPU.
"""

from __future__ import annotations

import copy
import json
import math
import sys
from pathlib import Path

import pytest
import torch

pytestmark = [pytest.mark.cli, pytest.mark.slow]

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # plain `pytest` (not `python -m pytest`) does not put the repository on the path
    sys.path.insert(0, str(ROOT))

from benchmarks import run  # noqa: E402

EXPECTED_ROWS = {
    "turbulence": ("frame/", "setup/"),
    "exact": ("frame/", "setup/", "anywind-frame/", "anywind-setup/", "anywind-stream/"),
    "loop": ("run_loop/bound/", "run_loop/realtime/", "run_loop_pregenerated/numpy/", "step/bound/", "step/numpy/",
             "step/budget/"),
    "fit": ("fit/",),
    "stability": ("analysis/", "coupled/"),
    "end_to_end": ("total", "fit", "evaluate"),
    "stream": ("memory/", "fit_time/"),
    "startup": ("startup/help", "startup/unknown_key", "startup/out_of_range"),
    "flagship": ("flagship/compare",),
    "pyramid": ("pyramid/compare",),
}
EXPECTED_SERIES = (
    "turbulence_vs_actuators", "turbulence_vs_frames", "turbulence_vs_call_frames", "step_vs_actuators",
    "step_vs_history",
    "run_loop_vs_actuators", "run_loop_vs_history", "fit_vs_actuators", "fit_vs_history", "fit_vs_frames",
    "compare_vs_actuators",
)


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """Run ``python -m benchmarks.run --quick --out <tmp>`` in-process once; return (exit code, JSON, stdout)."""
    out = tmp_path_factory.mktemp("bench") / "results.json"
    code = run.main(["--quick", "--out", str(out)])
    return code, json.loads(out.read_text())


def test_command_succeeds_and_writes_the_expected_keys(quick):
    code, results = quick
    assert code == 0
    assert set(results) >= {"meta", "rows", "scaling", "skipped", "errors", "seconds"}
    assert results["errors"] == []
    assert results["meta"]["quick"] is True
    for key in ("date_utc", "cpu_count", "torch", "torch_threads", "cuda_available"):
        assert key in results["meta"]


def test_every_benchmark_has_its_rows(quick):
    _, results = quick
    for benchmark, prefixes in EXPECTED_ROWS.items():
        names = [r["name"] for r in results["rows"] if r["benchmark"] == benchmark and r["device"] == "cpu"]
        for prefix in prefixes:
            assert any(n == prefix or n.startswith(prefix) for n in names), (benchmark, prefix, names)
    assert sorted(s["name"] for s in results["scaling"]) == sorted(EXPECTED_SERIES)


def test_ratios_are_finite_and_positive(quick):
    _, results = quick
    assert results["rows"]
    for row in results["rows"]:
        for key in ("ratio", "ratio_median"):
            assert math.isfinite(row[key]) and row[key] > 0, (row["name"], key, row[key])
        for key in ("eofnn_s", "baseline_s"):
            assert row[key]["min"] > 0 and row[key]["median"] >= row[key]["min"]
        assert set(row) >= {"benchmark", "name", "device", "unit", "baseline", "goal", "goal_met", "info"}
        assert row["goal_met"] in (True, False, None)
        assert (row["goal_met"] is None) == (row["goal_ratio"] is None)


def test_scaling_series_have_finite_exponents(quick):
    _, results = quick
    for series in results["scaling"]:
        assert len(series["x"]) == len(series["seconds"]) == len(series["ratios"]) >= 3
        assert math.isfinite(series["exponent"])
        assert all(math.isfinite(g) and g > 0 for g in series["ratios"])
        assert series["ratios"][0] == pytest.approx(1.0)


def test_baselines_do_the_same_work(quick):
    """The numpy loop reproduces run_loop on the same frames; the streamed fit reproduces the bare solve."""
    _, results = quick
    loop = next(r for r in results["rows"] if r["name"].startswith("run_loop_pregenerated/numpy/"))
    assert loop["info"]["numpy_max_relative_rms_difference"] < 1e-8
    for fit in (r for r in results["rows"] if r["benchmark"] == "fit"):
        assert fit["info"]["max_relative_weight_difference"] < 1e-6
    streamed = next(r for r in results["rows"] if r["name"].startswith("fit_time/"))  # streamed fit = in-memory fit
    assert streamed["info"]["max_relative_weight_difference"] < 1e-10


def test_cuda_rows_are_skipped_cleanly_without_a_gpu(quick):
    _, results = quick
    skipped = {(s["benchmark"], s["device"]) for s in results["skipped"]}
    if torch.cuda.is_available():
        assert any(r["device"] == "cuda" for r in results["rows"]) or skipped
    else:
        assert {("loop", "cuda"), ("fit", "cuda")} <= skipped
        assert all(r["device"] == "cpu" for r in results["rows"])
        assert "Skipped:" in run.format_table(results)


def test_table_lists_every_row_and_the_checker_flags_bad_ratios(quick):
    _, results = quick
    table = run.format_table(results)
    for row in results["rows"]:
        assert row["name"] in table
    assert run.check_results(results) == []
    broken = copy.deepcopy(results)
    broken["rows"][0]["ratio"] = float("nan")
    broken["scaling"][0]["exponent"] = float("inf")
    assert len(run.check_results(broken)) == 2


def test_the_cpu_time_anywind_benchmark_runs_and_its_floor_is_part_of_the_run(capsys):
    from benchmarks import anywind_cpu

    torch.set_num_threads(1)
    hcipy_s, eofnn_s, (draws, transforms) = anywind_cpu.measure(10, 1024, repeats=2)
    assert all(math.isfinite(t) and t > 0 for t in (hcipy_s, eofnn_s, draws, transforms))
    # The floor is two of the run's own steps: together below the whole run (up to timer noise).
    assert draws + transforms < 1.5 * eofnn_s
