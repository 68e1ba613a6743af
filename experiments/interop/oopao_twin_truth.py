"""The twin's r0 on OOPAO's noise-free open-loop turbulence, beside the r0 that the same frames' phase screen realises
(issue 46: the twin's r0 came out high on every OOPAO record of identify_unseen.py; oopao_screen_r0.py measures
the screens).

Each case of identify_unseen.py (its layers, r0, L0 25 m and seed; OOPAO's geometric SH, 20 x 20 on 4 m) runs open
loop, noise-free, for ``FRAMES`` frames (zero commands): per frame the measurement ``wfs = R @ slopes`` (nm of
command), the truth in command space (``turbulence_fit_nm``: the least-squares fit of the OPD by the seen DM modes)
and the OPD over the pupil (every 2nd pixel). ``identify_twin`` (``command_unit="peak"``, as ``eofnn twin
--command_unit peak``) runs on (y = 0, wfs); its references and POL are kept, and ``fit_seeing`` is evaluated on
each outer scale of the grid alone and on the truth's covariance (x ``surface_per_command`` squared) too. The
screen's realised r0 (oopao_screen_r0.realised, PTT removed, the same frames) is what the twin should find.

    OMP_NUM_THREADS=1 nice -n 5 .venv/bin/python experiments/interop/oopao_twin_truth.py U2 U5 U9

Writes experiments/interop/oopao_twin_truth/summary.json.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from identify_unseen import CASES, OOPAO_L0_M, _multilayer_loop  # noqa: E402
from oopao_screen_r0 import DIAMETER_M, RESOLUTION, ROOT, WAVELENGTH_NM, realised  # noqa: E402

from eofnn.sim.sensing.mmse import von_karman_covariance_nm2  # noqa: E402

OUT = ROOT / "experiments" / "interop" / "oopao_twin_truth"

FRAMES = 4000
REFERENCE_R0 = 0.1


def open_loop(name: str) -> dict:
    case = CASES[name]
    sim = _multilayer_loop(case)
    sim.reset(case["seed"])
    k = sim.n_actuators
    sub = np.zeros((RESOLUTION, RESOLUTION), bool)
    sub[::2, ::2] = True
    pick = sub[sim.pupil_mask]
    iy, ix = np.nonzero(sim.pupil_mask & sub)
    points = np.column_stack([ix, iy]) * DIAMETER_M / RESOLUTION
    # the OPD at each actuator: the mean of the 2 x 2 pixels around it (clipped at the support's edge)
    corner = np.rint(sim.positions_m / (DIAMETER_M / RESOLUTION) + RESOLUTION / 2).astype(int)
    cols = [np.clip(corner + np.array(d), 0, RESOLUTION - 1) for d in ((-1, -1), (-1, 0), (0, -1), (0, 0))]
    wfs, fit, opd = np.zeros((FRAMES, k)), np.zeros((FRAMES, k)), np.zeros((FRAMES, int(pick.sum())))
    at_actuators = np.zeros((FRAMES, k))
    for n in range(FRAMES):
        wfs[n], _ = sim.advance(np.zeros(k))
        fit[n] = sim.turbulence_fit_nm()
        opd[n] = sim.turbulence_opd_nm()[pick]
        full = np.asarray(sim.atm.OPD) * 1e9
        at_actuators[n] = sum(full[c[:, 1], c[:, 0]] for c in cols) / 4
    screen = realised(opd.T @ opd / FRAMES, points, case["r0"], OOPAO_L0_M)
    return {"sim": sim, "wfs": wfs, "fit": fit, "screen": screen, "at_actuators": at_actuators}


def twin_on(name: str, run: dict) -> dict:
    import torch

    import eofnn.training.twin as twin
    from eofnn.sim.sensing.least_squares import MECHANICAL_COUPLING, surface_per_command
    from eofnn.telemetry.record import Telemetry
    from eofnn.training.twin_seeing import fit_seeing

    sim, kept = run["sim"], {}
    original = twin.seeing_and_noise

    def keep(pol, references, positions, pitch, *args, **kwargs):
        if not kept:
            kept.update(pol=pol, references=references, positions=positions, pitch=pitch)
        return original(pol, references, positions, pitch, *args, **kwargs)

    twin.seeing_and_noise = keep
    try:
        telemetry = Telemetry(y=torch.zeros(FRAMES, sim.n_actuators, dtype=torch.float64),
                              wfs=torch.as_tensor(run["wfs"]), delay_frames=2, frame_rate_hz=1000.0,
                              positions_m=torch.as_tensor(sim.positions_m))
        result = twin.identify_twin(telemetry, interaction_matrix=sim.interaction_matrix,
                                    reconstructor=sim.reconstructor, command_unit="peak")
    finally:
        twin.seeing_and_noise = original
    r0_true = CASES[name]["r0"]
    refs, positions, pitch = kept["references"], kept["positions"], kept["pitch"]
    scale = surface_per_command(MECHANICAL_COUPLING)
    per_l0 = {}
    for label, cov in {"wfs": np.cov(kept["pol"].T), "truth_fit": np.cov(run["fit"].T) * scale ** 2}.items():
        fits = {f"{l0:g}": fit_seeing(cov, {l0: refs[l0]}, positions, pitch)["r0_m"] / r0_true - 1 for l0 in refs}
        per_l0[label] = {"best": fit_seeing(cov, refs, positions, pitch), "r0_rel_per_L0": fits}
    # Each against von Karman theory on the actuators (what fit_seeing finds against an exact reference): the
    # twin's references (eofnn's SH on eofnn's turbulence at r0 0.1), OOPAO's truth and wfs (x scale), the point OPD.
    distance = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    theory = {l0: (von_karman_covariance_nm2(distance, REFERENCE_R0, l0, WAVELENGTH_NM * 1e-9), None, positions)
              for l0 in (*refs, OOPAO_L0_M)}
    against = {f"twin_reference_L0_{l0:g}": fit_seeing(refs[l0][0], {l0: theory[l0]}, positions, pitch)["r0_m"]
               / REFERENCE_R0 - 1 for l0 in refs}
    for label, x in {"oopao_truth_fit": run["fit"] * scale, "oopao_wfs": run["wfs"] * scale,
                     "oopao_opd_at_actuators": run["at_actuators"]}.items():
        second = x.T @ x / len(x)
        against[label] = fit_seeing(second, {OOPAO_L0_M: theory[OOPAO_L0_M]}, positions, pitch)["r0_m"] / r0_true - 1
    # The references on the record's actuators, projected on the modes OOPAO's reconstructor outputs (its row space:
    # the seen modes), as the record's wfs are: the twin's fit against them.
    where = refs[next(iter(refs))][2]
    gap = np.linalg.norm(positions[:, None] - where[None], axis=-1)
    idx = gap.argmin(1)
    seen = sim.controlled_modes
    proj = seen @ seen.T
    projected = {l0: (proj @ refs[l0][0][np.ix_(idx, idx)] @ proj, None, positions) for l0 in refs}
    cov = np.cov(kept["pol"].T)
    on_seen = {f"{l0:g}": fit_seeing(cov, {l0: projected[l0]}, positions, pitch)["r0_m"] / r0_true - 1
               for l0 in refs}
    on_seen["best"] = fit_seeing(cov, projected, positions, pitch)
    on_seen["matched_positions_max_gap_m"] = float(gap.min(1).max())
    against.update({f"twin_reference_on_seen_L0_{l0:g}": fit_seeing(projected[l0][0], {l0: theory[l0]}, positions,
                                                                      pitch)["r0_m"] / REFERENCE_R0 - 1
                    for l0 in refs})
    est = result.estimates
    return {"twin_r0_rel": est["r0_m"].value / r0_true - 1, "twin_L0_m": est["outer_scale_m"].value,
            "twin_noise_nm": est["wfs_noise_nm"].value, "layers": [[lay["speed_mps"], lay["direction_deg"]]
                                                                   for lay in result.layers],
            "fit_seeing_no_noise_correction": per_l0, "r0_rel_against_theory": against,
            "references_on_seen_modes": on_seen,
            "twin_projected_its_references": all(np.allclose(refs[l0][0], projected[l0][0]) for l0 in refs),
            "screen_r0_rel_ptt_removed": run["screen"]["ptt_removed"]["r0_rel"],
            "screen_r0_rel_raw": run["screen"]["raw"]["r0_rel"]}


def main(names: list[str]) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "summary.json"
    summary = json.loads(path.read_text()) if path.exists() else {}
    summary["method"] = __doc__.split("\n\n")[1]
    for name in names:
        row = twin_on(name, open_loop(name))
        summary[name] = row
        print(name, json.dumps(row), flush=True)
        path.write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
