"""Telemetry in the spaces real loops record: slopes with an interaction matrix or a reconstructor, and modes."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from astropy.io import fits
from layout_telemetry import PITCH_M, fried_positions, record

from eofnn.cli.main import main
from eofnn.data.history import HistorySpec
from eofnn.evaluation.replay import replay
from eofnn.telemetry.record import Telemetry
from eofnn.telemetry.spaces import max_unseen
from eofnn.training.checkpoint import load_predictor
from eofnn.training.from_telemetry import fit_from_telemetry
from eofnn.training.identify import identify_plant


def fried_shack_hartmann(positions_m: np.ndarray, pitch_m: float = PITCH_M) -> np.ndarray:
    """``(2 S, K)`` interaction matrix of a noiseless Shack-Hartmann in Fried geometry: each subaperture whose four
    corners are actuators measures the mean x and y differences of its corners (nm per pitch per nm)."""
    index = {tuple(np.round(p / pitch_m * 2).astype(int)): k for k, p in enumerate(positions_m)}
    rows = []
    for x2, y2 in index:
        corners = [index.get((x2 + 2 * dx, y2 + 2 * dy)) for dy in (0, 1) for dx in (0, 1)]
        if None in corners:
            continue
        a00, a10, a01, a11 = corners  # (dx, dy) = (0,0), (1,0), (0,1), (1,1)
        for weights in ({a10: 0.5, a11: 0.5, a00: -0.5, a01: -0.5}, {a01: 0.5, a11: 0.5, a00: -0.5, a10: -0.5}):
            row = np.zeros(len(positions_m))
            for k, w in weights.items():
                row[k] = w
            rows.append(row)
    return np.array(rows)


@pytest.fixture(scope="module")
def fried():
    pos = fried_positions()
    return pos, record(pos, 3000, noise_nm=1.0), record(pos, 1500, seed=5, noise_nm=1.0)


def test_slopes_with_an_invertible_interaction_matrix_give_the_actuator_space_fit(fried):
    pos, tel, _ = fried
    k = len(pos)
    im = np.random.default_rng(3).standard_normal((2 * k, k))  # full column rank: every actuator mode is seen
    slopes = tel.wfs.numpy() @ im.T
    by_slopes = Telemetry.from_slopes(tel.y, slopes, interaction_matrix=im, delay_frames=2, positions_m=pos)
    assert "pinv(IM)" in by_slopes.measurement and "0 mode(s)" in by_slopes.measurement
    assert torch.allclose(by_slopes.wfs, tel.wfs, atol=1e-9)
    spec = HistorySpec("open_loop", 4, 2)
    plants = identify_plant(tel), identify_plant(by_slopes)
    assert plants[0].dm_gain == pytest.approx(plants[1].dm_gain, rel=1e-9)
    fits = [fit_from_telemetry(t, spec, plant=p).network.weight for t, p in zip((tel, by_slopes), plants, strict=True)]
    assert torch.allclose(fits[0], fits[1], atol=1e-8)
    # A reconstructor is used as given: R = pinv(IM) is the same route.
    by_r = Telemetry.from_slopes(tel.y, slopes, reconstructor=np.linalg.pinv(im), delay_frames=2)
    assert torch.allclose(by_r.wfs, tel.wfs, atol=1e-9) and "given reconstructor" in by_r.measurement


@pytest.mark.slow
@pytest.mark.cli
def test_a_fried_shack_hartmann_loses_piston_and_waffle_only(fried, tmp_path, capsys):
    pos, tel, _ = fried
    im = fried_shack_hartmann(pos)
    assert np.linalg.matrix_rank(im) == len(pos) - 2
    # The worked example of docs/telemetry.md: a FITS file written with astropy alone.
    primary = fits.PrimaryHDU()
    primary.header["DELAY"] = 2
    primary.header["RCOND"] = 1e-3
    path = tmp_path / "sh.fits"
    fits.HDUList([primary, fits.ImageHDU(tel.y.numpy(), name="Y"), fits.ImageHDU(tel.wfs.numpy() @ im.T, name="SLOPES"),
                  fits.ImageHDU(im, name="INTERACTION_MATRIX"), fits.ImageHDU(pos, name="POSITIONS")]).writeto(path)
    assert main(["identify", "--telemetry", str(path), "--out", str(tmp_path / "plant.json")]) == 0
    err = capsys.readouterr().err
    assert "2 mode(s) with singular values below rcond=0.001" in err
    plant = json.loads((tmp_path / "plant.json").read_text())
    assert abs(plant["dm_gain"] / 2 - 1) < 0.02 and abs(plant["misregistration_x"]) < 0.01
    # The interaction matrix in its own file, beside slopes-only telemetry: the same plant.
    np.save(tmp_path / "im.npy", im)
    np.savez(tmp_path / "slopes.npz", y=tel.y.numpy(), slopes=tel.wfs.numpy() @ im.T, positions_m=pos, delay_frames=2)
    assert main(["identify", "--telemetry", str(tmp_path / "slopes.npz"), "--interaction_matrix",
                 str(tmp_path / "im.npy"), "--out", str(tmp_path / "plant2.json")]) == 0
    assert json.loads((tmp_path / "plant2.json").read_text())["dm_gain"] == pytest.approx(plant["dm_gain"], rel=1e-9)


@pytest.mark.slow
@pytest.mark.cli
def test_modal_telemetry_predicts_in_modes_and_replays_on_actuators(fried, tmp_path, capsys):
    pos, tel, held_out = fried
    # 60 smooth modes: the leading eigenvectors of a Gaussian covariance over the actuators.
    d2 = ((pos[:, None] - pos[None]) ** 2).sum(-1)
    basis = np.linalg.eigh(np.exp(-d2 / (2 * 0.4 ** 2)))[1][:, ::-1][:, :60].copy()
    project = np.linalg.pinv(basis)

    def modal(t: Telemetry) -> Telemetry:  # a linear loop projected on the modes is a modal loop of the same plant
        return Telemetry(y=t.y.numpy() @ project.T, wfs=t.wfs.numpy() @ project.T, delay_frames=2, positions_m=pos,
                         modal_basis=basis)

    train, test = modal(tel), modal(held_out)
    plant = identify_plant(train)
    assert abs(plant.dm_gain / 2 - 1) < 0.02 and plant.misregistration_x is None
    assert "the telemetry is modal" in plant.warnings[0]
    spec = HistorySpec("open_loop", 4, 2)
    fit = fit_from_telemetry(train, spec, plant=plant)
    assert fit.network.weight.shape == (60, 4)
    result = replay(fit.network, spec, test, plant=plant, start=100)
    assert len(result.predictor.map_rms_nm) == len(pos)  # errors on the actuators, B @ e
    assert result.predictor.median_rms_nm < 0.5 * result.own_controller.median_rms_nm
    # The command line: identify and a closed-loop fit in modes from an npz file.
    np.savez(tmp_path / "modal.npz", y=train.y.numpy(), wfs=train.wfs.numpy(), modal_basis=basis, positions_m=pos,
             delay_frames=2)
    assert main(["identify", "--telemetry", str(tmp_path / "modal.npz"), "--out", str(tmp_path / "plant.json")]) == 0
    assert main(["fit", "--telemetry", str(tmp_path / "modal.npz"), "--plant", str(tmp_path / "plant.json"),
                 "--predictor.history", "closed_loop", "--out", str(tmp_path / "cl.ckpt")]) == 0
    err = capsys.readouterr().err
    assert "modal, 60 modes of a (100, 60) basis" in err and "identify: misregistration not identified" in err
    assert load_predictor(tmp_path / "cl.ckpt").network.weight.shape[0] == 60


@pytest.mark.slow
@pytest.mark.cli
def test_bad_spaces_are_one_line_and_nothing_written(fried, tmp_path, cli_error):
    pos, tel, _ = fried
    k = len(pos)
    y = tel.y.numpy()[:600]
    im = np.random.default_rng(0).standard_normal((2 * k, k))
    slopes = tel.wfs.numpy()[:600] @ im.T
    singular = im.copy()
    singular[:, : max_unseen(k) + 1] = 0.0  # more actuators unseen than allowed
    basis = np.linalg.qr(np.random.default_rng(1).standard_normal((k, 10)))[0]
    dependent = basis.copy()
    dependent[:, 9] = dependent[:, 8]
    cases = {
        "count": ({"y": y, "slopes": slopes, "interaction_matrix": im[:-1]},
                  "interaction_matrix has shape (199, 100) but the slopes have 200 values"),
        "singular_im": ({"y": y, "slopes": slopes, "interaction_matrix": singular},
                        "interaction_matrix (200, 100) is singular: rank 92"),
        "singular_r": ({"y": y, "slopes": slopes, "reconstructor": np.linalg.pinv(singular)},
                       "reconstructor (100, 200) is singular"),
        "nothing": ({"y": y, "slopes": slopes}, "neither an interaction_matrix"),
        "basis_shape": ({"y": y[:, :10], "wfs": y[:, :10], "modal_basis": basis[:, :9]},
                        "modal_basis has shape (100, 9): expected (actuators >= 10, 10)"),
        "basis_rank": ({"y": y[:, :10], "wfs": y[:, :10], "modal_basis": dependent},
                       "modal_basis (100, 10) is not of full rank: rank 9 < 10"),
    }
    for name, (arrays, message) in cases.items():
        path = tmp_path / f"{name}.npz"
        np.savez(path, delay_frames=2, **arrays)
        out = tmp_path / f"{name}.json"
        assert message in cli_error(["identify", "--telemetry", path, "--out", out], out=out, alone=False), name
