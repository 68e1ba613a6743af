"""What every section of experiments/README.md shares: reading the summaries (experiments/*/summary.json) and
writing their numbers."""

from __future__ import annotations

import json
import math
from pathlib import Path

HERE = Path(__file__).parent
STUDY = {  # Fowler, van Kooten & Jensen-Clem 2023, median RMS residual (nm)
    ("nominal", "uncorrected"): "1534",
    ("nominal", "pseudo_integrator"): "24.3",
    ("nominal", "cl_eof"): "9.49",
    ("nominal", "ol_eof"): "1.03",
    ("dm_gain_2", "cl_eof"): "16.66",
    ("dm_gain_2", "ol_eof"): ">10x worse than nominal",
}
NAMES = {"uncorrected": "uncorrected", "pseudo_integrator": "pseudo-integrator (oracle)", "integrator": "integrator",
         "ol_eof": "open-loop EOF", "cl_eof": "closed-loop EOF", "mlp": "MLP (open loop)",
         "ol_eof_nb": "open-loop EOF, neighbourhood", "mlp_nb": "MLP, neighbourhood", "extrapolator": "POL extrapolation",
         "modal_integrator": "modal integrator", "lqg": "LQG (AR per mode)", "pfc": "predictive Fourier control"}


def load(name: str, part: str = "metrics") -> dict | None:
    """One part of experiments/<name>/summary.json (written by summarise.py from experiments/runs/<name>/)."""
    file = HERE / name / "summary.json"
    return json.loads(file.read_text()).get(part) if file.is_file() else None


def cell(m: dict | None, digits: int = 3) -> str:
    if m is None:
        return "n/a"
    if m["diverged"]:
        return f"diverged (frame {m['diverged_frame']})"
    value = m["median_rms_nm"]
    return f"{value:.0f}" if value >= 1000 else f"{value:.{digits}g}"


def variance_less_fitting(m: dict) -> float:
    """A contender's residual variance over the pupil after its error budget's fitting error is removed (nm², at
    least 0): what a controller can act on."""
    fitting = (m.get("error_budget") or {}).get("fitting_nm") or 0.0
    return max(m["median_rms_nm"] ** 2 - fitting ** 2, 0.0)


def rms(m: dict | None) -> float:
    return math.nan if m is None or m["diverged"] else m["median_rms_nm"]


def sweep_rows(name: str) -> list[dict[str, str]]:
    """The finished points of a sweep (its sweep.csv's rows, as strings), from its summary."""
    return load(f"sweeps/{name}", "rows") or []


def point_margin(sweep: str, row: dict[str, str]) -> str:
    """The analytic DM-gain interval of a sweep point's predictor (from the point's own metrics.json)."""
    stability = (load(f"sweeps/{sweep}", "stability") or {}).get(row["point"])
    if stability is None:
        return ""
    return margin(stability.get(row["scenario"], {}).get(row["predictor"]))


def number(text: str) -> float:
    return float(text) if text not in ("", None) else math.nan


def fmt(value: float, digits: int = 3) -> str:
    return "diverged" if math.isnan(value) else f"{value:.{digits}g}"


def margin(stability: dict | None) -> str:
    if not stability:
        return ""
    if not stability["stable"]:
        return "unstable"
    low, high = stability["dm_gain_interval"]
    return f"{max(low or 0.0, 0.0):.3g}–{high:.3g}" if high is not None else f"> {max(low or 0.0, 0.0):.3g}"


# ---------------------------------------------------------------------------------------------------------------
