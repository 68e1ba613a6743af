"""Where the anti-aliasing EOF trained in eofnn's twin loses against the same filter trained on OOPAO's truth (issue
30): the pupil's rim, or the interior. OOPAO's 40 x 40 loop of `run.sh oopao_aa`'s m8 point (8 m, I = 8, 20 m/s, DM
applying 2x) recorded and identified as there, plus a fourth recording held out; the filter trained on OOPAO's truth
and the one trained on telemetry alone fitted as there (`fit_eofs`), the twin's as `--eofnn-trained` trains it.

- **Offline**, on the held-out recording: each filter's command of frame n against the truth recorded with it (the
  DM's fit of the true phase, through OOPAO's DM gain), its error variance per actuator split into the 40 actuators the
  twin lacks (held), the rest of the rim (less than two pitches inside the outermost actuator's radius) and the
  interior.
- **In the loop**, on the page's three scored realisations, warmed up with the integrator gain that run scanned:
  the twin's filter, the truth-trained one, and spliced filters (`eofnn.studies.transfer.splice_filters`) that take
  the rim from one and the interior from the other. The splices are diagnostics, not contenders: the twin's filter
  with the truth-trained rim tells how much of its loss is at the rim.

Writes experiments/runs/interop/rim/rim.json; the page reads it beside the m8 run.

    OMP_NUM_THREADS=1 .venv/bin/python experiments/interop/rim_diagnostic.py    # 35 min beside four other jobs on 2 cores
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
from m8_point import RUNS, m8_point

from eofnn.interop.loop import FilterControl, run_closed_loop
from eofnn.outputs import write_text_atomic
from eofnn.studies.antialias import fit_eofs, record_with_truth
from eofnn.studies.transfer import eofnn_trained, rim_actuators, splice_filters
from eofnn.training.identify import identify_plant

RIM_PITCHES = 2.0


def commands(runtime, record) -> np.ndarray:
    """``(frames, K)``: the filter's command at each frame of a recording, read with the commands really applied."""
    runtime.reset()
    wfs, y = record.wfs.numpy(), record.y.numpy()
    return np.stack([runtime.step(wfs[n], y_last=y[n - 1] if n else None) for n in range(len(wfs))])


def main() -> None:
    gain, scored, sim, config = m8_point()
    recorded = record_with_truth(sim, replace(config, train_sequences=config.train_sequences + 1))
    telemetry, held_out = recorded[:-1], recorded[-1]
    plant = identify_plant(telemetry)
    filters, _ = fit_eofs(sim, telemetry, plant, config)
    filters["eof_eofnn"], info = eofnn_trained(54000, 10800, sequences=9)(sim, plant)
    print(f"identified gain {plant.dm_gain:.4f}; twin alpha {info['alpha']:.3g}", flush=True)

    rim = rim_actuators(sim.positions_m, RIM_PITCHES)
    coefficients = filters["eof_eofnn"].coefficients
    held = np.count_nonzero(coefficients.reshape(len(coefficients), -1), axis=1) == 1  # hold their last POL value
    regions = {"held": held, "rim": rim & ~held, "interior": ~rim}
    truth = held_out.s.numpy()
    offline = {}
    for name, runtime in filters.items():
        error = truth + sim.dm_gain * commands(runtime, held_out)
        variance = (error[config.settle_frames:] ** 2).mean(0)
        offline[name] = {region: {"variance_per_actuator_nm2": float(variance[mask].mean()),
                                  "share": float(variance[mask].sum() / variance.sum())}
                         for region, mask in regions.items()}
        print(name, {r: round(v["variance_per_actuator_nm2"]) for r, v in offline[name].items()}, flush=True)

    splices = {"eof_eofnn": filters["eof_eofnn"], "eof_antialias": filters["eof_antialias"],
               "eofnn_interior_truth_rim": splice_filters(filters["eof_eofnn"], filters["eof_antialias"], rim),
               "eofnn_interior_telemetry_rim": splice_filters(filters["eof_eofnn"], filters["eof_measured"], rim),
               "truth_interior_eofnn_rim": splice_filters(filters["eof_antialias"], filters["eof_eofnn"], rim)}
    loop = {}
    for name, runtime in splices.items():
        rms = [run_closed_loop(sim, FilterControl(runtime, gain, config.warmup_frames), config.loop_frames, s)
               .metrics(config.settle_frames).median_rms_nm for s in scored]
        loop[name] = rms
        print(name, ", ".join("diverged" if v is None else f"{v:.2f}" for v in rms), "nm", flush=True)
    out = {"command": "python experiments/interop/rim_diagnostic.py", "scored_seeds": scored, "warmup_gain": gain,
           "rim_pitches": RIM_PITCHES, "actuators": {region: int(mask.sum()) for region, mask in regions.items()},
           "identified": {"dm_gain": plant.dm_gain, "wfs_noise_nm": plant.wfs_noise_nm},
           "offline_held_out": offline, "loop_realisations_median_rms_nm": loop}
    (RUNS / "rim").mkdir(parents=True, exist_ok=True)
    write_text_atomic(RUNS / "rim" / "rim.json", json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
