"""An experiment's folder: ``results.md`` and its figures, the analyses' files, ``timeseries.npz`` and
``metrics.json`` (the last stage of ``compare``: :mod:`eofnn.evaluation.stages`)."""

from __future__ import annotations

from pathlib import Path

from eofnn.evaluation.results import ExperimentResult, save_timeseries, write_metrics
from eofnn.evaluation.stages import Analyses
from eofnn.reporting.pareto import plot_pareto
from eofnn.reporting.report import write_report
from eofnn.reporting.robustness import plot_robustness


def write_experiment(folder: Path, result: ExperimentResult, analyses: Analyses, frame_rate_hz: float,
                     reference: dict | None, strehl_wavelength_m: float) -> None:
    """Write ``result`` and ``analyses`` into ``folder``: ``results.md`` and its figures (``reference``: the
    published numbers to quote beside them; ``strehl_wavelength_m``: the Strehl's wavelength, m), then
    ``robustness.json`` / ``.png`` and ``pareto.json`` / ``.md`` / ``.png`` where analysed, ``timeseries.npz`` and
    ``metrics.json``."""
    folder = Path(folder)
    write_report(result, folder, frame_rate_hz, reference, strehl_wavelength_m)
    if analyses.robustness is not None:
        (folder / "robustness.json").write_text(analyses.robustness.to_json())
        plot_robustness(analyses.robustness, folder / "robustness.png")
    if analyses.pareto is not None:
        (folder / "pareto.json").write_text(analyses.pareto.to_json())
        (folder / "pareto.md").write_text(analyses.pareto.markdown())
        plot_pareto(analyses.pareto, folder / "pareto.png")
    save_timeseries(result, folder / "timeseries.npz")
    write_metrics(result, folder / "metrics.json")
