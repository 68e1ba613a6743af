"""eofnn's closed-loop EOF inside an OOPAO loop: Shack-Hartmann, Fried DM applying 2x its command, 1 kHz, 2 frames.

Everything eofnn learns comes from the telemetry of OOPAO's own integrator loop (with 10 nm of white dither):

1. record telemetry (``y``, ``wfs = R @ slopes``, actuator positions in metres, delay, rate);
2. identify the plant (``eofnn.training.identify``): the DM gain (2 x the Shack-Hartmann's optical gain, which
   is measured beside it by push-pull probes on the closed-loop residual);
3. fit a closed-loop EOF from that telemetry alone (``fit_from_telemetry``), refit once on telemetry it recorded
   itself in OOPAO's loop (closed-loop identification);
4. replay it on a held-out realisation (``eofnn.evaluation.replay``);
5. run it (the exported ``eofnn.runtime.PredictiveFilter``) in OOPAO's loop against OOPAO's best-gain integrator:
   residual OPD (median RMS over the pupil, nm), on ``--realisations`` realisations;
6. run the split controller beside them: the integrator keeps the lowest-order modes of the recorded
   pseudo-open loop, the EOF's command is mixed in on the rest (both tuned on the integrator's scan realisation).

With ``--aliasing`` the same chain runs three times, with a perfect (non-aliasing) sensor, the Shack-Hartmann
noise-free and with photon noise, beside the fitting error, to say how much of the residual the EOF removes and
what it cannot (fitting error, aliasing, noise).

    python examples/oopao_loop.py --small                          # 10 x 10 on 2 m, CI size (about a minute)
    python examples/oopao_loop.py --small --aliasing --out DIR     # plus the decomposition; DIR/metrics.json
    python examples/oopao_loop.py --small --photon-noise --magnitude 10 --wind 10   # photon noise only
    python examples/oopao_loop.py --n-subapertures 40 --diameter 8 --out experiments/runs/interop/oopao

With ``--sensor pyramid`` the same chain runs with OOPAO's modulated pyramid in place of the Shack-Hartmann
(``--modulation`` in lambda/D, 3 by default; :mod:`eofnn.interop.oopao_pyramid`), noise-free or with
``--photon-noise``; the DM gain identified is then 2 x the pyramid's optical gain about the loop's residual. What
is built on the Shack-Hartmann alone (``--aliasing``'s split, the twins of ``--eofnn-trained`` and
``--twin-identified``) is refused with it. ``--anti-aliasing`` runs with it as the contest through OOPAO's pyramid:
every contender's POL histories are the closed loop's own readings (``wfs = R @ slopes maps`` plus the identified
DM gain, 2 x the optical gain about the loop's residual, times the delayed command), recorded in the loop as eofnn's
``open_loop_recorded`` does, never the pyramid's open-loop reading (docs/findings.md); the optical gains are not
compensated (the best gain and the modal gains absorb them):

    python examples/oopao_loop.py --small --sensor pyramid --modulation 3 --out DIR
    python examples/oopao_loop.py --small --sensor pyramid --photon-noise --anti-aliasing --out DIR

With ``--anti-aliasing`` it runs instead the study of :mod:`eofnn.studies.antialias`: the open-loop EOF (5 x 5
neighbourhood) fitted on telemetry alone and the anti-aliasing EOF fitted on the same telemetry with OOPAO's truth
(the DM's fit of the true phase) as its target, each run in OOPAO's loop against the best-gain integrator, scored in
residual variance after fitting and raw contrast; beside them the oracle (the same filter trained on OOPAO's truth
with more taps, a wider neighbourhood and four times the recorded frames: simulator knowledge, a ceiling, not a
contender; ``--no-oracle`` leaves it out), and each predictor's share of its gain (eta):

    python examples/oopao_loop.py --small --anti-aliasing --photon-noise --out DIR

``--twin-identified`` adds ``eof_twin_identified``: the same anti-aliasing EOF trained in a twin that eofnn identifies
from OOPAO's telemetry alone (a recording of its own dithered integrator, its interaction matrix and reconstructor:
:mod:`eofnn.studies.twin_transfer`, the code of ``eofnn twin``), with the share of the gap between the best classical
controller and ``eof_antialias`` (the same filter trained on OOPAO's truth) it closes, in plain variance.
``--eofnn-trained`` (``eof_eofnn``) builds its twin from OOPAO's settings instead (r0, L0, every layer's wind):
simulator knowledge, a labelled reference.
``--reconstructor map`` (or ``map_telemetry``) replaces the loop's truncated least-squares reconstructor by a MAP
one for every contender (:mod:`eofnn.interop.map_reconstructor`): the von Kármán prior and the photon noise from the
simulator (knowledge), or both estimated from a recording of the loop's integrator; its regularisation factor is
chosen on the scan realisation.
``--layers F:V:DIR,...`` sets several frozen-flow layers (Cn2 fraction, m/s, degrees) in place of ``--wind`` and
``--wind-direction``:

    python examples/oopao_loop.py --small --anti-aliasing --photon-noise --twin-identified --layers 0.7:20:30,0.3:10:120
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace

from eofnn.errors import ConfigError, TelemetryError
from eofnn.interop.map_reconstructor import RECONSTRUCTORS, apply_reconstructor
from eofnn.interop.oopao import OopaoLoop, fitting_error, measure_sensor_gain
from eofnn.outputs import write_text_atomic
from eofnn.reporting.interop import antialias_psd_figure
from eofnn.studies.antialias import AntiAliasConfig, antialias_markdown, run_antialias
from eofnn.studies.report import aliasing_budget, example_parser, parse_example, split_text, write_results
from eofnn.studies.study import StudyConfig, run_study
from eofnn.studies.transfer import eofnn_direction, eofnn_trained
from eofnn.studies.twin_transfer import gap_closed, identified_trained


def study(sensor: str, photon_noise: bool, args, config: StudyConfig) -> dict:
    sim = oopao_loop(args, sensor, photon_noise)
    started = time.time()
    chosen = reconstructor(sim, args, config)
    result = run_study(sim, config, dm_gain_true=args.dm_gain).summary()
    if chosen:
        result["reconstructor"] = chosen
    # the pyramid's probes are read noise-free: under photon noise a 5 nm probe's read scatters by several percent
    # of the gain (docs/findings.md, "The pyramid under photon noise in OOPAO's loop")
    gain = measure_sensor_gain(sim, config.record_gain, min(config.record_frames, 1500), config.seed,
                               dither_nm=config.dither_nm, noise_free=sensor == "pyramid")
    result["identified"]["sensor_optical_gain"] = gain
    seen = args.dm_gain * gain["mean"]  # what telemetry can identify: DM gain x the sensor's optical gain
    result["identified"]["dm_gain_times_optical_gain"] = seen
    result["identified"]["error_vs_dm_gain_times_optical_gain"] = result["identified"]["dm_gain"] / seen - 1
    result["seconds"] = round(time.time() - started, 1)
    result["fitting_error"] = fitting_error(sim, config.loop_frames, config.seed + 2)
    label = f"{sensor}{' + photon noise' if photon_noise else ''}"
    print(f"[{label}] DM gain identified {result['identified']['dm_gain']:.4f} +- "
          f"{result['identified']['dm_gain_se']:.4f} (true {args.dm_gain} x optical gain "
          f"{gain['mean']:.4f} +- {gain['se']:.4f} = {seen:.4f}); replay: EOF "
          f"{result['replay']['predictor_median_rms_nm']:.2f} nm vs "
          f"integrator {result['replay']['integrator_median_rms_nm']:.2f} nm; in OOPAO's loop: EOF "
          f"{result['eof']['median_rms_nm']:.2f} nm vs best-gain integrator {result['integrator']['median_rms_nm']:.2f} "
          f"nm (gain {result['integrator']['best_gain']}); split {split_text(result.get('split'))}; fitting error "
          f"{result['fitting_error']['median_rms_nm']:.2f} "
          f"nm ({result['seconds']} s)")
    return result


def main(argv: list[str] | None = None) -> dict:
    parser = example_parser(__doc__.splitlines()[0])
    parser.add_argument("--magnitude", type=float, default=8.0, help="guide star I magnitude (photon noise runs)")
    parser.add_argument("--sensor", choices=("shack_hartmann", "pyramid"), default="shack_hartmann",
                        help="OOPAO's diffractive Shack-Hartmann or its modulated pyramid")
    parser.add_argument("--modulation", type=float, default=3.0,
                        help="with --sensor pyramid: the modulation radius (lambda/D in I band)")
    parser.add_argument("--aliasing", action="store_true", help="also the perfect-sensor and photon-noise runs")
    parser.add_argument("--photon-noise", action="store_true",
                        help="only the Shack-Hartmann run with photon noise (a point of a wind x magnitude map)")
    parser.add_argument("--wind-direction", type=float, default=0.0,
                        help="degrees from the x axis (0: along a row of actuators)")
    parser.add_argument("--anti-aliasing", action="store_true",
                        help="only the anti-aliasing study (eofnn.studies.antialias), with or without --photon-noise")
    parser.add_argument("--eofnn-trained", action="store_true",
                        help="with --anti-aliasing: also the anti-aliasing EOF trained in eofnn's own Shack-Hartmann "
                             "simulation of this system (eofnn.studies.transfer), on 27 x --frames frames in 9 "
                             "realisations (a fifth more to choose its ridge alpha)")
    parser.add_argument("--twin-identified", action="store_true",
                        help="with --anti-aliasing: also the anti-aliasing EOF trained in a twin identified from OOPAO's "
                             "telemetry alone (eofnn.studies.twin_transfer), on 27 x --frames frames in 9 realisations "
                             "of the twin, and the share of the gap to the OOPAO-truth filter it closes")
    parser.add_argument("--twin-record-frames", type=int, default=4000,
                        help="with --twin-identified: frames of OOPAO's dithered integrator recorded for the "
                             "identification (default 4000, the first 200 dropped)")
    parser.add_argument("--layers", type=layers_arg, default=None,
                        help="frozen-flow layers FRACTION:SPEED:DIRECTION,... (Cn2 fractions summing to 1, m/s, "
                             "degrees) in place of --wind and --wind-direction")
    parser.add_argument("--own-noise", action="store_true",
                        help="with --eofnn-trained: eofnn's simulation at its own photon noise for the guide star, "
                             "not at the WFS noise identified from OOPAO's telemetry")
    parser.add_argument("--all-modes", action="store_true",
                        help="with --eofnn-trained: trained on every mode eofnn's sensor reconstructs, not only those "
                             "OOPAO's reconstructor sees")
    parser.add_argument("--twin-pupil", choices=("grid", "oopao", "both"), default="grid",
                        help="with --eofnn-trained: the twin's pupil, its actuator grid's (half a pitch wider than "
                             "OOPAO's, its rim subapertures fully lit, 40 of OOPAO's 1353 actuators missing at 40 x 40) "
                             "or OOPAO's (the same actuators and subapertures, partly lit ones included); both: two "
                             "contenders, eof_eofnn and eof_eofnn_pupil")
    parser.add_argument("--static-gain", action="store_true",
                        help="with --eofnn-trained: each actuator's carried filter scaled to cancel a constant POL "
                             "value exactly")
    parser.add_argument("--radius", type=float, default=2.5,
                        help="with --anti-aliasing: the EOFs' neighbourhood in pitches (2.5: 5 x 5; 0.5: each "
                             "actuator's own history alone)")
    parser.add_argument("--no-oracle", action="store_true",
                        help="with --anti-aliasing: without the oracle (trained on OOPAO's truth, wider and longer than "
                             "the EOFs, on four times the recorded frames): no eta")
    parser.add_argument("--scored-frames", type=int,
                        help="with --anti-aliasing: frames scored on each scored realisation after its settling "
                             "(default: --frames / 2 less the settling, as long as a tuning run's)")
    parser.add_argument("--reconstructor", choices=RECONSTRUCTORS, default="least_squares",
                        help="the loop's reconstructor, every contender's: least_squares (the truncated pseudo-inverse), "
                             "map (MAP with r0, L0 and the photon noise from the simulator: knowledge) or map_telemetry "
                             "(MAP with the turbulence and the noise estimated from a recording of the loop); the MAP's "
                             "regularisation factor is scanned on the scan realisation (eofnn.interop.map_reconstructor)")
    parser.add_argument("--rcond", type=float, default=0.15,
                        help="reconstructor: singular values of the interaction matrix below rcond x the largest are "
                             "dropped; the smooth modes' share of the spectrum shrinks as 1 / n-subapertures, so scale "
                             "it down for larger systems (0.075 at 40 x 40 keeps what 0.15 keeps at 20 x 20)")
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_example(parser, argv)
    if args.sensor == "pyramid":
        for flag, on, what in (("--aliasing", args.aliasing, "its aliasing split is the Shack-Hartmann's"),
                               ("--eofnn-trained", args.eofnn_trained, "its twin is a Shack-Hartmann"),
                               ("--twin-identified", args.twin_identified, "its twin is a Shack-Hartmann")):
            if on:
                parser.error(f"{flag} is invalid with --sensor pyramid: {what}; with the pyramid, run the plain "
                             "study, --photon-noise or the contest (--anti-aliasing)")
    elif args.modulation != 3.0:
        parser.error(f"--modulation {args.modulation:g} is invalid with --sensor shack_hartmann: only the pyramid is "
                     "modulated (give --sensor pyramid)")
    if args.photon_noise and args.aliasing and not args.anti_aliasing:
        parser.error("--photon-noise runs only the photon-noise study; --aliasing runs it beside the others: "
                     "give one of them")
    for flag, on in (("--eofnn-trained", args.eofnn_trained), ("--twin-identified", args.twin_identified)):
        if on and not args.anti_aliasing:
            parser.error(f"{flag} adds to the anti-aliasing study: give --anti-aliasing too")
    if args.twin_record_frames < 1200:
        parser.error(f"--twin-record-frames={args.twin_record_frames} is invalid: at least 1200 (1000 after the "
                     "200 dropped: the fewest a layer is identified from)")
    tweaks = [flag for flag, on in (("--own-noise", args.own_noise), ("--all-modes", args.all_modes),
                                    ("--static-gain", args.static_gain),
                                    ("--twin-pupil", args.twin_pupil != "grid")) if on]
    if tweaks and not args.eofnn_trained:
        parser.error(f"{' and '.join(tweaks)} set the eofnn-trained predictor: give --eofnn-trained too")
    if args.scored_frames is not None and not args.anti_aliasing:
        parser.error("--scored-frames sets the anti-aliasing study's scored runs: give --anti-aliasing too")
    segment = AntiAliasConfig.psd_segment_frames  # the study's PSD segment: the fewest frames it scores
    if args.scored_frames is not None and args.scored_frames < segment:
        parser.error(f"--scored-frames={args.scored_frames} is invalid: at least {segment} (one segment of the "
                     "residual's temporal PSD)")
    if args.no_oracle and not args.anti_aliasing:
        parser.error("--no-oracle leaves the oracle out of the anti-aliasing study: give --anti-aliasing too")
    if args.anti_aliasing and args.aliasing:
        parser.error("--anti-aliasing runs only the anti-aliasing study; --aliasing runs the decomposition: give "
                     "one of them")
    try:
        if args.anti_aliasing:
            return antialias(args, argv)
        config = replace(StudyConfig.from_frames(args.frames, gains=(0.15, 0.2, 0.25, 0.3, 0.35, 0.4)),
                         scored_realisations=args.realisations)
    except (ConfigError, TelemetryError) as err:  # TelemetryError: a twin the loop's telemetry cannot give
        parser.error(str(err))
    try:
        if args.photon_noise:
            runs = {f"{args.sensor}_photon_noise": study(args.sensor, True, args, config)}
        else:
            runs = {args.sensor: study(args.sensor, False, args, config)}
    except ConfigError as err:  # e.g. a modulation the pupil's sampling cannot carry
        parser.error(str(err))
    if args.aliasing:
        runs["perfect"] = study("perfect", False, args, config)
        runs["shack_hartmann_photon_noise"] = study("shack_hartmann", True, args, config)
    metrics = {"runs": runs}
    if args.aliasing:
        metrics["budget"] = aliasing_budget(runs["perfect"], runs["shack_hartmann"],
                                            runs["shack_hartmann_photon_noise"])
        print(json.dumps(metrics["budget"], indent=1))
    if args.out:
        write_results(args.out, "OOPAO", metrics, " ".join(["python examples/oopao_loop.py", *argv]))
    return metrics


def oopao_loop(args, sensor: str, photon_noise: bool) -> OopaoLoop:
    """OOPAO's loop of the command line's system, with ``sensor`` and ``photon_noise`` (a study may run several)."""
    return OopaoLoop(args.n_subapertures, args.diameter, sensor=sensor, modulation_lambda_over_d=args.modulation,
                     photon_noise=photon_noise, magnitude=args.magnitude, dm_gain=args.dm_gain,
                     wind_speed_mps=args.wind, wind_direction_deg=args.wind_direction, rcond=args.rcond,
                     layers=args.layers)


def reconstructor(sim, args, config) -> dict | None:
    """``--reconstructor`` in place of the truncated least-squares one, for every contender of this loop (the MAP's
    factor scanned on the study's scan realisation, ``config.seed + 3``, with its integrator gains); None when the
    loop keeps least squares (its outputs then unchanged) or has no slopes (the perfect sensor)."""
    if args.reconstructor == "least_squares" or sim.sensor == "perfect":
        return None
    return apply_reconstructor(sim, args.reconstructor, scan_seed=config.seed + 3, loop_frames=config.loop_frames,
                               settle_frames=config.settle_frames, gains=config.gains,
                               record_frames=max(args.frames, 1200), record_gain=config.record_gain)


def layers_arg(text: str) -> list[tuple[float, float, float]]:
    """``--layers``: ``FRACTION:SPEED:DIRECTION`` separated by commas."""
    import argparse

    try:
        layers = [tuple(float(v) for v in part.split(":")) for part in text.split(",")]
    except ValueError:
        layers = []
    if not layers or any(len(layer) != 3 for layer in layers):
        raise argparse.ArgumentTypeError(f"{text!r} is invalid: FRACTION:SPEED:DIRECTION for each layer, separated "
                                         "by commas (e.g. 0.7:20:30,0.3:10:120)")
    return layers


def antialias(args, argv: list[str]) -> dict:
    """The anti-aliasing study at one point (``--frames`` per training sequence, 3 sequences)."""
    f = args.frames
    config = AntiAliasConfig(train_frames=f, val_frames=f // 5, loop_frames=f // 2, settle_frames=f // 10,
                             warmup_frames=f // 20, scored_realisations=args.realisations, radius=args.radius,
                             scored_frames=args.scored_frames,
                             oracle=not args.no_oracle)
    for layer in args.layers or [(1.0, args.wind, args.wind_direction)]:
        eofnn_direction(layer[2])  # a direction eofnn cannot map is refused before anything is simulated
    sim = oopao_loop(args, args.sensor, args.photon_noise)
    started = time.time()
    chosen = reconstructor(sim, args, config)
    external = {}
    if args.eofnn_trained:
        # 27 x --frames of the twin in 9 sequences (and a fifth as much held out for the ridge alpha): at 40 x 40, I = 8,
        # 9 x in 3 sequences left 72.8 and 74.1 nm at twin seeds 0 and 1, 27 x in 9 left 72.4 and 72.9.
        pupils = {"grid": {"eof_eofnn": "grid"}, "oopao": {"eof_eofnn": "oopao"},
                  "both": {"eof_eofnn": "grid", "eof_eofnn_pupil": "oopao"}}[args.twin_pupil]
        external = {name: eofnn_trained(27 * f, 27 * f // 5, match_noise=not args.own_noise,
                                        controlled=not args.all_modes, static_gain=args.static_gain, sequences=9,
                                        pupil=pupil) for name, pupil in pupils.items()}
    if args.twin_identified:  # the same twin frames as --eofnn-trained's; seeds: eofnn.studies.twin_transfer
        external["eof_twin_identified"] = identified_trained(args.twin_record_frames, 27 * f, 27 * f // 5, sequences=9,
                                                             seed=config.seed, out=args.out and args.out / "twin")
    metrics = run_antialias(sim, config, external or None,
                            progress=lambda text: print(f"[{time.time() - started:.0f} s] {text}", flush=True))
    if args.twin_identified:
        metrics["gap_closed"] = {"eof_twin_identified": gap_closed(metrics, "eof_twin_identified")}
        if "eof_eofnn" in metrics["contenders"]:
            metrics["gap_closed"]["eof_eofnn"] = gap_closed(metrics, "eof_eofnn")
        for name, gap in metrics["gap_closed"].items():
            shares = [f"{gap[k]['share'] if gap[k]['share'] is not None else gap[k].get('why')} (best classical "
                      f"{where}: {gap[k]['best_classical']})" for k, where in (("on_scan", "on the scan"),
                                                                              ("on_scored", "on the scored"))]
            print(f"{name}: share of the gap to eof_antialias closed, plain variance: {shares[0]}, {shares[1]}; "
                  f"variances {gap['variance_nm2']}")
    if chosen:
        metrics["reconstructor"] = chosen
    metrics["seconds"] = round(time.time() - started, 1)
    metrics["command"] = " ".join(["python examples/oopao_loop.py", *argv])
    text = antialias_markdown(metrics)
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        write_text_atomic(args.out / "metrics.json", json.dumps(metrics, indent=1))
        write_text_atomic(args.out / "results.md", text)
        antialias_psd_figure(metrics, args.out / "psd.png")
    return metrics


if __name__ == "__main__":
    main()
