"""eofnn's pyramid (eofnn/sim/sensing/pyramid.py) against OOPAO's (``OOPAO.Pyramid``) on the same system.

With ``--loop`` it compares instead the two closed loops on one system built alike (the interaction matrices per KL
mode, the best-gain integrators, the optical gains on their residuals: experiments/pyramid/vs_oopao_loop.py)::

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python experiments/pyramid/vs_oopao.py --loop \
        --out experiments/pyramid/vs_oopao/summary.json --md experiments/pyramid/vs_oopao.md

Without it, the same phase maps through both sensors:

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python experiments/pyramid/vs_oopao.py --n-subapertures 20 \
        --residual-nm 50 100 200 --out experiments/runs/pyramid/vs_oopao.json --summary experiments/pyramid/summary.json

The same pupil (OOPAO's ``tel.pupil``), the same phase maps (OOPAO's Zernike modes and atmosphere), the same
geometry (pupil pixels, separation, PSF centred on four pixels, ``n_pix_edge = n_pix_separation / 2``), wavelength
(I band), modulation points and slopes maps go through both; eofnn's modulation radius is OOPAO's times
``n / (n - 1)`` (OOPAO's tip-tilt spans ``2 pi r`` over ``n - 1`` pupil samples: its PSF runs on that radius).
Measured:

- the interaction matrix's response per Zernike mode (tip onward): the norm of the push-pull response of each
  mode, eofnn's over OOPAO's, and the correlation of the two responses pixel by pixel;
- the optical gains of the same modes about closed-loop-like residuals (OOPAO's atmosphere, its first
  ``--corrected`` Zernike modes removed as a DM would, scaled to ``--residual-nm`` RMS): eofnn's over OOPAO's.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from eofnn.sim.sensing.detector import PHOTOMETRY  # noqa: E402
from eofnn.sim.sensing.pyramid import PyramidOptics, PyramidSignals  # noqa: E402


def _quiet():
    return contextlib.redirect_stdout(io.StringIO())


def build_oopao(n_subapertures: int, samples_per_pixel: int, diameter_m: float, modulation: float,
                light_ratio: float, separation: int):
    """OOPAO's telescope, I-band source and pyramid."""
    with _quiet():
        from OOPAO.Pyramid import Pyramid
        from OOPAO.Source import Source
        from OOPAO.Telescope import Telescope

        tel = Telescope(resolution=n_subapertures * samples_per_pixel, diameter=diameter_m, samplingTime=1e-3,
                        centralObstruction=0.0)
        ngs = Source(optBand="I", magnitude=8)
        ngs * tel
        wfs = Pyramid(nSubap=n_subapertures, telescope=tel, modulation=modulation, lightRatio=light_ratio,
                      n_pix_separation=separation, psfCentering=True, postProcessing="slopesMaps")
    return tel, ngs, wfs


def oopao_signals(wfs, phase_rad: np.ndarray) -> np.ndarray:
    """OOPAO's slopes ``(M, nSignal)`` of ``(M, n, n)`` phase maps (rad)."""
    with _quiet():
        wfs.wfs_measure(phase_in=np.ascontiguousarray(np.moveaxis(phase_rad, 0, -1)))
    return np.array(wfs.signal).T


def main(argv=None) -> dict:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--loop" in argv:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from vs_oopao_loop import loop_main

        return loop_main([a for a in argv if a != "--loop"])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-subapertures", type=int, default=16)
    parser.add_argument("--samples-per-pixel", type=int, default=2)
    parser.add_argument("--diameter", type=float, default=8.0)
    parser.add_argument("--modulation", type=float, default=3.0)
    parser.add_argument("--light-ratio", type=float, default=0.1)
    parser.add_argument("--separation", type=int, default=2)
    parser.add_argument("--modes", type=int, default=100, help="Zernike modes from tip on")
    parser.add_argument("--amplitude-nm", type=float, default=1.0, help="push-pull amplitude (nm RMS of a mode)")
    parser.add_argument("--r0", type=float, default=0.15, help="r0 at 500 nm (m)")
    parser.add_argument("--corrected", type=int, default=100, help="Zernike modes the residual has removed")
    parser.add_argument("--residual-nm", type=float, nargs="+", default=[50.0, 100.0], help="residual RMS (nm)")
    parser.add_argument("--residuals", type=int, default=2, help="residual realisations per RMS")
    parser.add_argument("--shift-frames", type=int, default=400, help="atmosphere updates between residuals")
    parser.add_argument("--exact-radius", action="store_true",
                        help="eofnn modulates on the radius asked for (by default on OOPAO's, times n / (n - 1))")
    parser.add_argument("--own-valid", action="store_true",
                        help="eofnn chooses its own valid pixels (by default it takes OOPAO's validI4Q)")
    parser.add_argument("--out", type=Path, default=None, help="every number (JSON)")
    parser.add_argument("--summary", type=Path, default=None, help="the agreement in a few numbers (JSON)")
    args = parser.parse_args(argv)

    t0 = time.time()
    tel, ngs, wfs = build_oopao(args.n_subapertures, args.samples_per_pixel, args.diameter, args.modulation,
                                args.light_ratio, args.separation)
    n = tel.resolution
    wavelength_nm = PHOTOMETRY["I"][0] * 1e9
    assert abs(ngs.wavelength * 1e9 - wavelength_nm) < 1e-6, (ngs.wavelength, wavelength_nm)
    radius = args.modulation if args.exact_radius else args.modulation * n / (n - 1)
    optics = PyramidOptics(tel.pupil, args.n_subapertures, args.samples_per_pixel, args.separation, radius,
                           wfs.nTheta, wavelength_nm)
    signals = PyramidSignals(optics, "slopes_maps", args.light_ratio, 50.0,
                             valid=None if args.own_valid else np.asarray(wfs.validI4Q, dtype=bool))
    pupil = tel.pupil.astype(bool)
    build_s = time.time() - t0

    with _quiet():
        from OOPAO.Zernike import Zernike

        zern = Zernike(tel, args.modes)
        zern.computeZernike(tel)
    modes_nm = np.moveaxis(zern.modesFullRes, -1, 0)  # (M, n, n), 1 nm RMS per unit
    a = args.amplitude_nm

    def responses(around_nm: np.ndarray | None):
        base = np.zeros((n, n)) if around_nm is None else around_nm
        push = np.concatenate([base + a * modes_nm, base - a * modes_nm])
        t = time.time()
        ours = signals.process(optics.frames(torch.as_tensor(push[:, pupil])))
        ours = ((ours[:len(modes_nm)] - ours[len(modes_nm):]) / (2 * a)).numpy()
        t_ours = time.time() - t
        t = time.time()
        theirs = oopao_signals(wfs, push * 2 * np.pi / wavelength_nm)
        theirs = (theirs[:len(modes_nm)] - theirs[len(modes_nm):]) / (2 * a)
        return ours, theirs, t_ours, time.time() - t

    d_ours, d_theirs, t_ours, t_theirs = responses(None)
    same_pixels = d_ours.shape == d_theirs.shape
    ratio = np.linalg.norm(d_ours, axis=1) / np.linalg.norm(d_theirs, axis=1)
    corr = ([float(np.dot(u, v) / np.linalg.norm(u) / np.linalg.norm(v)) for u, v in zip(d_ours, d_theirs, strict=True)]
            if same_pixels else None)

    # Closed-loop-like residuals: OOPAO's atmosphere, the first `corrected` Zernike modes fitted out, scaled.
    with _quiet():
        from OOPAO.Atmosphere import Atmosphere

        atm = Atmosphere(telescope=tel, r0=args.r0, L0=25, windSpeed=[10], fractionalR0=[1], windDirection=[0],
                         altitude=[0])
        ngs * tel
        atm.initializeAtmosphere(tel)
        fit = Zernike(tel, args.corrected)
        fit.computeZernike(tel)
    basis = fit.modesFullRes[pupil]  # (n_pupil, corrected)
    gains = []
    for rms in args.residual_nm:
        for _ in range(args.residuals):
            with _quiet():  # a new stretch of the frozen-flow screen
                for _ in range(args.shift_frames):
                    atm.update()
                ngs ** atm  # the source through the atmosphere: atm.OPD is its stretch of screen
            opd = atm.OPD * 1e9
            inside = opd[pupil] - opd[pupil].mean()
            inside = inside - basis @ np.linalg.lstsq(basis, inside, rcond=None)[0]
            residual = np.zeros((n, n))
            residual[pupil] = inside * rms / inside.std()
            r_ours, r_theirs, _, _ = responses(residual)
            g_ours = (r_ours * d_ours).sum(1) / (d_ours * d_ours).sum(1)
            g_theirs = (r_theirs * d_theirs).sum(1) / (d_theirs * d_theirs).sum(1)
            gains.append({"rms_nm": rms, "eofnn": g_ours.tolist(), "oopao": g_theirs.tolist()})

    out = {"system": {"n_subapertures": args.n_subapertures, "pupil_points": n, "diameter_m": args.diameter,
                      "modulation_lambda_over_d": args.modulation, "modulation_points": int(wfs.nTheta),
                      "separation_pixels": args.separation, "light_ratio": args.light_ratio, "band": "I",
                      "eofnn_modulation_lambda_over_d": radius,
                      "valid_pixels": {"eofnn": signals.n_valid, "oopao": int(wfs.validI4Q.sum()),
                                       "shared": not args.own_valid}},
           "modes": args.modes, "amplitude_nm": a,
           "response_ratio": ratio.tolist(), "response_correlation": corr,
           "response_ratio_max_deviation": float(np.abs(ratio - 1).max()),
           "response_ratio_median": float(np.median(ratio)),
           "optical_gains": gains,
           "timing_s": {"build": build_s, "eofnn_frames": t_ours, "oopao_frames": t_theirs,
                        "frames": 2 * args.modes}}
    for g in gains:
        ratio_g = np.asarray(g["eofnn"]) / np.asarray(g["oopao"])
        g["ratio_max_deviation"] = float(np.abs(ratio_g - 1).max())
        g["ratio_median"] = float(np.median(ratio_g))
    print(f"{args.n_subapertures} x {args.n_subapertures} pixels, {n} pupil points, modulation {args.modulation:g} "
          f"lambda/D ({wfs.nTheta} points), valid pixels eofnn {signals.n_valid} / OOPAO {int(wfs.validI4Q.sum())}")
    print(f"interaction matrix, {args.modes} Zernike modes: |D_eofnn| / |D_oopao| median {np.median(ratio):.4f}, "
          f"range {ratio.min():.4f}-{ratio.max():.4f} (max deviation {np.abs(ratio - 1).max():.2%})"
          + (f"; correlation min {min(corr):.5f}" if corr else ""))
    for g in gains:
        e, o = np.asarray(g["eofnn"]), np.asarray(g["oopao"])
        print(f"optical gains about {g['rms_nm']:g} nm RMS: eofnn {e.mean():.3f} (range {e.min():.3f}-{e.max():.3f}), "
              f"OOPAO {o.mean():.3f}; ratio median {g['ratio_median']:.4f}, max deviation {g['ratio_max_deviation']:.2%}")
    print(f"timing: {2 * args.modes} frames eofnn {t_ours:.2f} s, OOPAO {t_theirs:.2f} s")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1) + "\n")
    if args.summary is not None:
        args.summary.parent.mkdir(parents=True, exist_ok=True)
        args.summary.write_text(json.dumps(summary(out, argv), indent=1) + "\n")
    return out


def summary(out: dict, argv) -> dict:
    """The agreement in a few numbers, rounded, with the command's arguments."""
    def r(x):
        return float(f"{x:.4g}")

    gains = {}
    for g in out["optical_gains"]:
        e, o = np.asarray(g["eofnn"]), np.asarray(g["oopao"])
        row = gains.setdefault(f"{g['rms_nm']:g}", {"eofnn_mean": [], "oopao_mean": [], "ratio_max_deviation": []})
        row["eofnn_mean"].append(r(e.mean()))
        row["oopao_mean"].append(r(o.mean()))
        row["ratio_max_deviation"].append(r(g["ratio_max_deviation"]))
    corr = out["response_correlation"]
    return {"arguments": list(sys.argv[1:] if argv is None else argv), "system": out["system"], "modes": out["modes"],
            "response_ratio_median": r(out["response_ratio_median"]),
            "response_ratio_max_deviation": r(out["response_ratio_max_deviation"]),
            "response_correlation_range": None if corr is None else [r(min(corr)), r(max(corr))],
            "optical_gains_by_residual_rms_nm": gains}


if __name__ == "__main__":
    main()
