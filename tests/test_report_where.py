"""Section 2d's arithmetic (experiments/report_where.py): the map's gains are the best classical controller's over
the best predictor's, in residual variance after the fitting error is removed and in raw contrast; a diverged
contender is never the best; the never-worse check: worse on every realisation is worse; contrast by separation."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"


@pytest.fixture
def where(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(EXPERIMENTS))
    import report_common
    import report_where

    monkeypatch.setattr(report_common, "HERE", tmp_path)
    yield report_where, tmp_path
    sys.modules.pop("report_where", None)


def contender(rms, fitting=100.0, contrast=1e-4, diverged=False, realisations=None):
    return {"median_rms_nm": rms, "diverged": diverged, "realisations_nm": realisations or [rms, rms],
            "error_budget": {"fitting_nm": fitting}, "raw_contrast_3": contrast}


def write_points(root: Path, points: list[dict]) -> None:
    (root / "where" / "sh").mkdir(parents=True)
    (root / "where" / "sh" / "summary.json").write_text(json.dumps({"points": points}))


def point(wind, magnitude, contenders, deployed="composite"):
    return {"point": f"v{wind}_m{magnitude}", "contenders": contenders,
            "values": {"scenario.atmosphere.layers": [{"wind_speed_mps": wind}, {"wind_speed_mps": wind / 2}],
                       "scenario.sensor.detector.magnitude": magnitude},
            "fallback": {"ol_eof_aa_guarded": {"deployed": deployed}}}


def test_gains_are_variance_after_fitting_and_contrast_of_the_best_of_each_kind(where):
    report, root = where
    write_points(root, [point(10.0, 8.0, {
        "integrator": contender(130.0, contrast=4e-4), "lqg": contender(125.0, contrast=3e-4),
        "pfc": contender(90.0, diverged=True),  # diverged: never the best, however low its number
        "ol_eof": contender(120.0, contrast=1.5e-4), "ol_eof_nb": contender(140.0),
        "ol_eof_aa_guarded": contender(129.0)})])
    [row] = report.rows()
    assert (row["best_classical"], row["best_predictor"]) == ("lqg", "ol_eof")
    assert row["variance_gain"] == pytest.approx((125.0**2 - 100.0**2) / (120.0**2 - 100.0**2))
    assert row["contrast_gain"] == pytest.approx(2.0)
    section = " ".join(report.where_section().split())
    assert "| 10 | 8 |" in section and "1.28x" in section and "2.00x" in section
    assert "at or below the best-gain integrator at 1 of 1 points" in section


def test_never_worse_fails_beyond_the_scatter(where):
    report, root = where
    integrator = contender(130.0, realisations=[125.0, 135.0])
    write_points(root, [point(20.0, 10.0, {  # worse on both realisations, by less than their spread: worse
        "integrator": integrator, "ol_eof_aa_guarded": contender(131.0, realisations=[126.0, 136.0])}),
                        point(30.0, 10.0, {  # worse in the median, better on one realisation: within the scatter
        "integrator": integrator, "ol_eof_aa_guarded": contender(131.0, realisations=[124.0, 138.0])})])
    section = " ".join(report.where_section().split())
    assert "at 1 of 2 points" in section


def test_the_map_figure_is_drawn(where, tmp_path):
    report, root = where
    write_points(root, [point(w, m, {"integrator": contender(130.0), "ol_eof": contender(125.0)})
                        for w in (5.0, 10.0) for m in (8.0, 10.0)])
    report.plot(report.rows(), tmp_path / "gain_map.png")
    assert (tmp_path / "gain_map.png").stat().st_size > 10_000


def test_contrast_by_separation_and_its_match_to_the_temporal_term(where):
    """The verdict counts the points where the best predictor wins in contrast at each separation and says whether
    its wins at 3 lambda/D are the points where its budgeted temporal term is below the classical's; without contrast
    at several separations it says nothing."""
    report, root = where

    def c(rms, temporal, contrast):
        out = contender(rms, contrast=contrast["3"])
        out["error_budget"]["temporal_nm"] = temporal
        out["raw_contrast"] = contrast
        return out

    write_points(root, [
        point(30.0, 8.0, {"integrator": c(130.0, 80.0, {"2": 4e-4, "3": 3e-4, "5": 2e-4}),
                          "ol_eof": c(120.0, 60.0, {"2": 2e-4, "3": 2e-4, "5": 3e-4})}),
        point(5.0, 8.0, {"integrator": c(130.0, 20.0, {"2": 4e-4, "3": 2e-4, "5": 2e-4}),
                         "ol_eof": c(120.0, 60.0, {"2": 3e-4, "3": 3e-4, "5": 3e-4})})])
    section = " ".join(report.where_section().split())
    assert "at 2 λ/D at 2, at 3 λ/D at 1, at 5 λ/D at 0 of 2 points, against 2 in variance" in section
    assert "exactly the points where its budgeted temporal term is below" in section
    assert "its halo is" not in section  # no radial profile, no halo
    (root / "where" / "sh" / "summary.json").write_text(json.dumps({"points": [  # a summary with 3 lambda/D only
        point(30.0, 8.0, {"integrator": contender(130.0), "ol_eof": contender(120.0)})]}))
    assert "In raw contrast it beats" not in report.where_section()


def test_the_halo_is_the_area_weighted_contrast_inside_the_profile(where):
    """The halo integrates raw contrast over rings from 0.5 lambda/D, each weighted by its separation (its ring's
    area); its gain below the variance gain at every point says the gain lies outside the profile's circle."""
    report, root = where
    sep = [0.0, 0.25, 0.5, 1.0, 2.0, 4.0]

    def c(rms, profile):
        out = contender(rms, contrast=profile[4])
        out["raw_contrast"] = {"2": profile[4], "3": profile[4], "5": profile[5]}
        out["contrast_profile"] = {"separation_lod": sep, "raw_contrast": profile}
        return out

    classical = c(130.0, [1.0, 9.0, 1e-3, 1e-3, 2e-4, 1e-4])
    predictor = c(120.0, [1.0, 1.0, 1e-3, 1e-3, 2e-4, 2e-4])  # worse at 4 lambda/D; the core (< 0.5) is left out
    assert report.halo(classical) == pytest.approx((0.5e-3 + 1e-3 + 4e-4 + 4e-4, 4.0))
    write_points(root, [point(20.0, 8.0, {"integrator": classical, "ol_eof": predictor})])
    [row] = report.rows()
    assert row["halo_gain"] == pytest.approx(2.3e-3 / 2.7e-3)
    section = " ".join(report.where_section().split())
    assert "from 0.5 to 4 λ/D" in section and "coronagraphic halo is 0.85x-0.85x" in section
    assert "(the spatial split, `experiments/where/check_space.yaml`, not run)" in section


def test_the_spatial_split_check_gives_each_regions_share_and_the_halo_at_two_wavelengths(where):
    """Section 2d's spatial split: the variance gain region by region over PFC and the integrator, and the halo
    ratios at 1.65 and 10 µm beside the split's inside the control circle."""
    report, root = where
    split = {"integrator": (100.0, 40.0, 121.0), "pfc": (90.0, 40.0, 121.0), "ol_eof_aa": (80.0, 40.0, 118.0)}
    scenarios = {k: {"median_rms_nm": 150.0, "spatial_split_nm": dict(zip(
        ("inside_control_circle", "control_square_corners", "beyond_control"), v, strict=True))}
                 for k, v in split.items()}

    def profiles(scale):  # a flat halo per contender, proportional to its variance inside the circle (times scale)
        return {"nominal": {k: {"separation_lod": [0.5, 1.0], "raw_contrast": [scale(v[0] ** 2)] * 2}
                            for k, v in split.items()}}

    for name, scale in (("check_space", lambda v: 100.0 + v * 1e-4), ("check_space_10um", lambda v: v * 1e-4)):
        (root / "where" / name).mkdir(parents=True)
        (root / "where" / name / "summary.json").write_text(json.dumps(
            {"metrics": {"scenarios": {"nominal": scenarios}}, "contrast_profiles": profiles(scale)}))
    text = " ".join(report._check_space_text().split())
    pfc_gain = 90.0**2 + 121.0**2 - 80.0**2 - 118.0**2
    assert f"{pfc_gain:.0f} nm² over the predictive Fourier control: +1700 (" in text
    assert "+0 (0%) in the corners" in text
    assert "against the split's 1.27x" in text and "1.27x at 10 µm" in text  # linear at 10 µm: the split's ratio
    assert "1.00x at 1.65 µm" in text  # the flat offset (the nonlinear light) swamps it


def test_the_spatial_split_over_the_map_takes_the_better_classical_and_checks_the_maps_medians(where):
    report, root = where

    def run(rms, inside, corners, beyond):
        return {"median_rms_nm": rms, "spatial_split_nm": {"inside_control_circle": inside,
                                                           "control_square_corners": corners,
                                                           "beyond_control": beyond}}

    space = point(20.0, 8.0, {"integrator": run(160.0, 100.0, 40.0, 121.0), "pfc": run(155.0, 90.0, 40.0, 121.0),
                              "ol_eof_aa": run(149.0, 80.0, 40.0, 118.0)})
    (root / "where" / "space").mkdir(parents=True)
    (root / "where" / "space" / "summary.json").write_text(json.dumps({"points": [space]}))
    write_points(root, [point(20.0, 8.0, {"pfc": contender(155.5), "integrator": contender(160.0)})])
    text = " ".join(report._space_map_text().split())
    gain = 90.0**2 + 121.0**2 - 80.0**2 - 118.0**2
    assert f"| 20 | 8 | predictive Fourier control | {gain:.0f} | {1700 / gain:.0%} | 0% |" in text
    assert "differ from the map's by at most 0.5 nm" in text and f"inside the circle: {1700 / gain:.0%} to" in text
