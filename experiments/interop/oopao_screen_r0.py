"""The r0 that OOPAO's and eofnn's phase screens realise, against von Karman theory (issue 46: the twin's r0 came out
high on every OOPAO record of experiments/interop/identify_unseen.py).

OOPAO's ``Atmosphere`` alone (no sensor, no loop), built as identify_unseen.py's ``_multilayer_loop`` builds it (4 m,
80 pixels across, 1 kHz, L0 25 m, r0 at 500 nm) and seeded as its loop is (``generateNewPhaseScreen(seed)``, then
``update()`` each frame): the OPD over the pupil (every ``STEP``-th pixel) of each frame. The phase structure function
``D(r)`` over the pixel pairs (bins of 0.2 m from 0.3 m to 2 m, the twin's bins: 1.5 pitches to half the pupil) of
the record's second moments, without and with piston/tip/tilt removed per frame, against the same bins of the exact
von Karman covariance (``K_5/6``) on the same points at the nominal r0 and L0. The realised r0 is
``r0 exp(-0.6 mean(log(D / D_theory)))`` over the bins (the twin's fit, ``fit_seeing``). The same for eofnn's exact
frozen flow (point kernel, PTT kept) on a 21 x 21 lattice of 4.2 m, a screen whose statistics are known, to check the
method; and for OOPAO's freshly generated screens alone (frame 0 of many seeds: the FFT screen with subharmonics,
before any extrusion), to tell the generation from the extrusion.

    OMP_NUM_THREADS=1 nice -n 5 .venv/bin/python experiments/interop/oopao_screen_r0.py          # all parts
    OMP_NUM_THREADS=1 nice -n 5 .venv/bin/python experiments/interop/oopao_screen_r0.py U5 O1    # some cases

Writes experiments/interop/oopao_screen_r0/summary.json (kept parts of an earlier run stay).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from identify_unseen import CASES, OOPAO_L0_M  # noqa: E402

from eofnn.sim.sensing.mmse import von_karman_covariance_nm2  # noqa: E402
from eofnn.training.twin_seeing import ptt_projector  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "experiments" / "interop" / "oopao_screen_r0"
WAVELENGTH_NM = 500.0
RESOLUTION, DIAMETER_M = 80, 4.0
STEP = 2  # every STEP-th pupil pixel (10 cm): 1256 points
BINS_M = np.arange(0.3, 2.0 + 0.1, 0.2)
#: examples/twin_accuracy.py's OOPAO development cases (one ground layer: speed, OOPAO direction, Cn2, altitude).
DEV_CASES = {"O1": {"r0": 0.12, "layers": [(12.0, 0.0, 1.0, 0.0)], "seed": 21},
             "O2": {"r0": 0.16, "layers": [(18.0, 30.0, 1.0, 0.0)], "seed": 22},
             "O3": {"r0": 0.10, "layers": [(8.0, 45.0, 1.0, 0.0)], "seed": 23}}


def binned(second: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Mean over pairs of ``second[i,i] + second[j,j] - 2 second[i,j]`` in each bin of :data:`BINS_M`."""
    d = np.diag(second)
    pairs = d[:, None] + d[None] - 2 * second
    which = np.digitize(np.linalg.norm(points[:, None] - points[None], axis=-1), BINS_M)
    return np.array([pairs[which == b].mean() for b in range(1, len(BINS_M))])


def realised(moment: np.ndarray, points: np.ndarray, r0: float, l0: float) -> dict:
    """The realised r0 (and the per-bin ratios D / D_theory) without and with piston/tip/tilt removed."""
    theory = von_karman_covariance_nm2(np.linalg.norm(points[:, None] - points[None], axis=-1), r0, l0,
                                       WAVELENGTH_NM * 1e-9)
    p = ptt_projector(points)
    out = {}
    for name, (m, t) in {"raw": (moment, theory), "ptt_removed": (p @ moment @ p, p @ theory @ p)}.items():
        ratio = binned(m, points) / binned(t, points)
        out[name] = {"r0_m": r0 * math.exp(-0.6 * float(np.log(ratio).mean())),
                     "r0_rel": math.exp(-0.6 * float(np.log(ratio).mean())) - 1,
                     "D_over_theory": [round(float(x), 4) for x in ratio]}
    return out


def _oopao(r0: float, layers: list, seed: int):
    from eofnn.interop.oopao import _import_oopao, quiet

    Atmosphere, *_, Source, Telescope = _import_oopao()
    speeds, directions, fractions, altitudes = (list(map(float, c)) for c in zip(*layers, strict=True))
    with quiet():
        tel = Telescope(resolution=RESOLUTION, diameter=DIAMETER_M, samplingTime=1e-3, centralObstruction=0.0)
        ngs = Source(optBand="I", magnitude=8.0)
        ngs * tel
        atm = Atmosphere(telescope=tel, r0=r0, L0=OOPAO_L0_M, windSpeed=speeds, fractionalR0=fractions,
                         windDirection=directions, altitude=altitudes)
        atm.initializeAtmosphere(tel)
        tel + atm
        atm.generateNewPhaseScreen(seed=int(seed))
    pupil = np.asarray(tel.pupil) > 0
    sub = np.zeros_like(pupil)
    sub[::STEP, ::STEP] = True
    mask = pupil & sub
    iy, ix = np.nonzero(mask)
    points = np.column_stack([ix, iy]) * DIAMETER_M / RESOLUTION
    return atm, mask, points


def oopao_record(r0: float, layers: list, seed: int, frames: int) -> dict:
    """The realised r0 of ``frames`` of OOPAO's frozen flow (``update()`` before each frame's OPD)."""
    atm, mask, points = _oopao(r0, layers, seed)
    x = np.empty((frames, mask.sum()))
    for n in range(frames):
        atm.update()
        x[n] = np.asarray(atm.OPD)[mask] * 1e9
    return {"frames": frames, **realised(x.T @ x / frames, points, r0, OOPAO_L0_M)}


def oopao_extrusion(r0: float, speeds: tuple, seeds: range, frames: int, blocks: int) -> dict:
    """The realised r0 (PTT removed) of OOPAO's frozen flow per wind speed, averaged over seeds, and per block of
    ``frames // blocks`` frames in order (does the extruded screen drift away from von Karman as it grows?)."""
    out = {}
    for v in speeds:
        per_block = []
        for s in seeds:
            atm, mask, points = _oopao(r0, [(v, 0.0, 1.0, 0.0)], s)
            x = np.empty((frames, mask.sum()))
            for n in range(frames):
                atm.update()
                x[n] = np.asarray(atm.OPD)[mask] * 1e9
            size = frames // blocks
            per_block.append([realised(b.T @ b / size, points, r0, OOPAO_L0_M)["ptt_removed"]["r0_rel"]
                              for b in (x[i * size:(i + 1) * size] for i in range(blocks))])
        per_block = np.asarray(per_block)
        out[f"{v:g} m/s"] = {"seeds": len(seeds), "frames": frames, "r0_rel_mean": float(per_block.mean()),
                             "r0_rel_per_block_mean_over_seeds": [round(float(b), 4) for b in per_block.mean(0)],
                             "r0_rel_per_seed": [round(float(b), 4) for b in per_block.mean(1)]}
    return out


def oopao_fresh(r0: float, seeds: range) -> dict:
    """The realised r0 of OOPAO's freshly generated screens (frame 0 of each seed, one layer, no extrusion)."""
    atm, mask, points = _oopao(r0, [(10.0, 0.0, 1.0, 0.0)], seeds[0])
    x = np.empty((len(seeds), mask.sum()))
    for i, s in enumerate(seeds):
        atm.generateNewPhaseScreen(seed=int(s))
        x[i] = np.asarray(atm.OPD)[mask] * 1e9
    return {"screens": len(seeds), **realised(x.T @ x / len(seeds), points, r0, OOPAO_L0_M)}


def eofnn_record(r0: float, speed: float, frames: int, realisations: int = 2) -> dict:
    """The realised r0 of eofnn's exact frozen flow (point kernel, PTT kept) on a 21 x 21 lattice of 4.2 m."""
    from eofnn.sim.scenario import Scenario

    scenario = Scenario.from_dict({"grid": {"diameter_m": 4.2, "n_across": 21, "obstruction": 0.0},
                                   "atmosphere": {"r0_m": r0, "r0_wavelength_m": WAVELENGTH_NM * 1e-9,
                                                  "outer_scale_m": OOPAO_L0_M, "remove_ptt": False,
                                                  "screen_frames": frames,
                                                  "layers": [{"wind_speed_mps": speed, "wind_direction_deg": 30.0}]}})
    s = scenario.turbulence(1, "r0_check", realisations).frames(0, frames).numpy()
    points = np.asarray(scenario.grid.positions_m)
    moment = sum(r.T @ r for r in s) / (frames * realisations)
    return {"frames": frames, "realisations": realisations, **realised(moment, points, r0, OOPAO_L0_M)}


def main(args: list[str]) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "summary.json"
    summary = json.loads(path.read_text()) if path.exists() else {}
    summary["method"] = __doc__.split("\n\n")[1]
    summary["bins_m"] = [round(float(b), 2) for b in BINS_M]
    summary.setdefault("cases", {})
    every = {**CASES, **DEV_CASES}
    names = [a for a in args if a in every] or (list(every) if not args else [])
    for name in names:
        case = every[name]
        row = oopao_record(case["r0"], case["layers"], case["seed"], 4000)
        summary["cases"][name] = {"r0_nominal_m": case["r0"], "seed": case["seed"], **row}
        print(name, json.dumps({k: row[k]["r0_rel"] for k in ("raw", "ptt_removed")}), flush=True)
        path.write_text(json.dumps(summary, indent=1) + "\n")
    if "fresh" in args or not args:
        summary["fresh_screens"] = oopao_fresh(0.15, range(1, 301))
        print("fresh", json.dumps({k: summary["fresh_screens"][k]["r0_rel"] for k in ("raw", "ptt_removed")}))
    if "extrusion" in args or not args:
        summary["extrusion"] = oopao_extrusion(0.15, (5.0, 15.0, 30.0), range(1, 5), 8000, 4)
        print("extrusion", json.dumps({k: v["r0_rel_mean"] for k, v in summary["extrusion"].items()}))
    if "eofnn" in args or not args:
        summary["eofnn"] = {f"{v:g} m/s": eofnn_record(0.15, v, 4000, 4) for v in (5.0, 20.0)}
        print("eofnn", json.dumps({k: {q: v[q]["r0_rel"] for q in ("raw", "ptt_removed")}
                                   for k, v in summary["eofnn"].items()}))
    path.write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
