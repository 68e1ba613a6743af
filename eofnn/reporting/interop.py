"""``psd.png`` of the anti-aliasing study in another simulator's loop (:func:`eofnn.studies.antialias.run_antialias`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt

from eofnn.outputs import staged_file


def antialias_psd_figure(metrics: dict, path: str | Path) -> Path | None:
    """``psd.png`` of the anti-aliasing study (:func:`eofnn.studies.antialias.run_antialias`'s metrics): each
    contender's temporal PSD of the measured residual, the frozen-flow frequency marked; None (nothing drawn) where
    no contender has one. Written through a temporary file."""
    curves = {name: run.get("measured_psd_nm2_per_hz") for name, run in metrics["contenders"].items()
              if name != "guarded"}
    curves = {name: power for name, power in curves.items() if power}
    if not curves:
        return None
    freq = metrics["psd_frequency_hz"][1:]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, power in curves.items():
        ax.loglog(freq, power[1:], "--" if name in ("integrator", "lqg", "pfc") else "-", lw=1.2, label=name)
    ax.axvline(metrics["frozen_flow_hz"], color="0.5", lw=0.8, ls=":")
    ax.text(metrics["frozen_flow_hz"], ax.get_ylim()[0], " v / (2 pitch)", color="0.4", fontsize=8, va="bottom")
    sim = metrics["simulator"]
    ax.set(xlabel="frequency (Hz)", ylabel="PSD (nm²/Hz, loop's command units)",
           title=f"measured residual, {sim.get('simulator', '')} {sim.get('n_subapertures', '')} x "
                 f"{sim.get('n_subapertures', '')}, mean of actuators and realisations")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    with staged_file(path, overwrite=True) as partial:
        fig.savefig(partial, dpi=110)
    plt.close(fig)
    return path
