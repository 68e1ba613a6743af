"""compare --pareto true: every linear family along its tuning path, RMS beside the stable DM-gain interval."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from eofnn.cli.main import main

pytestmark = [pytest.mark.cli, pytest.mark.slow]

SCENARIO = Path(__file__).parent / "conf" / "tiny_scenario.yaml"


def test_pareto_draws_each_family_along_its_path(tmp_path):
    config = tmp_path / "pareto.yaml"
    config.write_text(f"""
scenario: {SCENARIO}
scenarios: {{nominal: {{wfs_noise_nm: 1.0}}}}
predictors:
  uncorrected: {{controller: uncorrected}}
  integrator: {{controller: integrator, gains: [0.2, 0.5], data: {{frames: 600}}}}
  ol_eof:
    history_length: 3
    data: {{frames: 1500, val_frames: 500, sequence_frames: 1000}}
    optimization: {{alpha_path: [1.0e-12, 1.0e-8, 1.0e-4, 1.0e-2], select: {{dm_gain_interval: [0.95, 1.05]}}}}
evaluation: {{frames: 800, settle_frames: 200, psd_segment_frames: 256}}
""")
    out = tmp_path / "out"
    assert main(["compare", "--config", str(config), "--out", str(out), "--pareto", "true"]) == 0
    data = json.loads((out / "pareto.json").read_text())
    assert (out / "pareto.png").stat().st_size > 0 and "| ol_eof * |" in (out / "pareto.md").read_text()
    families = data["families"]
    assert set(families) == {"integrator", "ol_eof"}  # uncorrected has no loop to analyse
    ol = families["ol_eof"]
    assert [p["value"] for p in ol] == [1e-12, 1e-8, 1e-4, 1e-2]
    chosen = [p for p in ol if p["chosen"]]
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(chosen) == 1 and chosen[0]["value"] == metrics["ridge_alphas"]["nominal"]["ol_eof"]["alpha"]
    # select asked for [0.95, 1.05]: every point says whether its interval contains it, the chosen one does.
    assert data["required_dm_gain_interval"] == [0.95, 1.05] and chosen[0]["meets"]
    for p in ol + families["integrator"]:
        interval = p["dm_gain_interval"]
        assert p["meets"] == (interval is not None and p["median_rms_nm"] is not None
                              and interval[0] <= 0.95 and interval[1] >= 1.05)
    assert "contains it |" in (out / "pareto.md").read_text()
    # More ridge: a wider stable interval, a worse residual (the trade-off the figure shows).
    assert ol[-1]["width"] > ol[0]["width"]
    assert ol[-1]["median_rms_nm"] > min(p["median_rms_nm"] for p in ol)
    # An integrator's interval is [0, critical gain / gain]: the analysis, not a fit.
    for p in families["integrator"]:
        assert p["dm_gain_interval"][0] == 0.0 and abs(p["dm_gain_interval"][1] * p["value"] - 1.0) < 1e-6
