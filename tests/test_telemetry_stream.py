"""Telemetry files read in blocks of frames (eofnn.telemetry.file): the same fits and identifications as the
whole file in memory, memory bounded by the block, and one line for what cannot be read."""

from __future__ import annotations

import tracemalloc
import warnings

import numpy as np
import pytest
import torch

from eofnn.cli.main import main
from eofnn.control import Dithered, Integrator
from eofnn.data.history import HistorySpec
from eofnn.data.targets import TelemetryBatches, load_telemetry
from eofnn.errors import ConfigError, TelemetryError
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Plant, Telemetry, run_loop
from eofnn.sim.scenario import Scenario
from eofnn.telemetry.file import SCAN_FRAMES, StreamedTelemetry
from eofnn.telemetry.readers import RawReader
from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry
from eofnn.training.identify import identify_plant

PLANT = {"dm_gain": 1.5, "misregistration_x": 0.1, "wfs_noise_nm": 2.0}


@pytest.fixture(scope="module")
def recorded() -> Telemetry:
    """Two dithered integrator recordings (a batch) of 1500 frames, 80 actuators, DM gain 1.5, 2 nm of noise."""
    atmosphere = Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, outer_scale_m=20.0, layers=(Layer(1.0, 10.0, 0.0),),
                            screen_frames=4096)
    sc = Scenario(ActuatorGrid(2.0, 10), atmosphere, 1000.0, Plant(delay_frames=2))
    plant = sc.plant.with_errors(**PLANT)
    result = run_loop(sc.turbulence(3, "stream", 2), plant, Dithered(Integrator(0.3), 10.0, seed=4), 1500,
                      noise_seed=5, record=("y", "wfs"))
    telemetry = result.telemetry
    telemetry.positions_m = torch.as_tensor(sc.grid.positions_m)  # positions: misregistration is identified too
    return telemetry


def save(telemetry: Telemetry, path, dtype: str = "float32", compressed: bool = False):
    if not compressed:
        return telemetry.save(path, overwrite=True, dtype=dtype)
    np.savez_compressed(path, y=telemetry.y.numpy().astype(dtype), wfs=telemetry.wfs.numpy().astype(dtype),
                        positions_m=telemetry.positions_m.numpy(), delay_frames=np.array(telemetry.delay_frames))
    return path


def relative(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach(), b.detach()
    return float((a - b).abs().max() / b.abs().max())


@pytest.fixture
def reads(monkeypatch) -> list[int]:
    """The length (frames) of every read of a telemetry file, in order."""
    lengths: list[int] = []
    original = RawReader.read

    def spy(self, batch, start, stop):
        lengths.append(stop - start)
        return original(self, batch, start, stop)

    monkeypatch.setattr(RawReader, "read", spy)
    return lengths


FILES = [(".npz", "float32", False), (".fits", "float32", False), (".npz", "float64", True), (".fits", "float64", False)]


@pytest.mark.slow
@pytest.mark.parametrize(("suffix", "dtype", "compressed"), FILES)
def test_streamed_fit_equals_in_memory_fit(recorded, tmp_path, suffix, dtype, compressed):
    path = save(recorded, tmp_path / f"t{suffix}", dtype, compressed)
    whole = Telemetry.load(path, required=("y", "wfs"))
    streamed = StreamedTelemetry.open(path)
    assert streamed.batched and tuple(streamed.y.shape) == (2, 1500, 80)
    assert streamed.y.stored_dtype == np.dtype(dtype) and streamed.stored_bytes == 2 * 2 * 1500 * 80 * int(dtype[-2:]) // 8
    assert torch.equal(streamed.y[1][397:811], whole.y[1, 397:811])  # a block read is the file's values, exactly
    for kind in ("open_loop", "closed_loop"):
        spec = HistorySpec(kind, 3, 2)
        # Batches of 41 frames: block boundaries fall everywhere, histories reach first_frame frames back over them.
        ours = fit_from_telemetry(streamed, spec, plant=PLANT, data=TelemetryDataConfig(batch_frames=41, val_frames=300))
        reference = fit_from_telemetry(whole, spec, plant=PLANT, data=TelemetryDataConfig(batch_frames=256, val_frames=300))
        assert relative(ours.network.weight, reference.network.weight) < 1e-10
        assert ours.train_loss == pytest.approx(reference.train_loss, rel=1e-10)
        assert ours.val_loss == pytest.approx(reference.val_loss, rel=1e-10)


def test_blocks_shorter_than_the_history_and_fractional_delay(recorded, tmp_path):
    """A batch of one frame still reads its whole history (the window reaches first_frame back): the same fit."""
    one = Telemetry(y=recorded.y[0, :400], wfs=recorded.wfs[0, :400], delay_frames=1.5)
    path = one.save(tmp_path / "frac.fits", dtype="float64")
    spec = HistorySpec("open_loop", 6, 1.5)
    assert spec.first_frame + spec.target_lead > 1
    ours = fit_from_telemetry(StreamedTelemetry.open(path), spec, plant={"dm_gain": 1.5},
                              data=TelemetryDataConfig(batch_frames=1))
    reference = fit_from_telemetry(one, spec, plant={"dm_gain": 1.5}, data=TelemetryDataConfig(batch_frames=400))
    assert relative(ours.network.weight, reference.network.weight) < 1e-10


@pytest.mark.parametrize(("kind", "delay"), [("open_loop", 1.5), ("closed_loop", 2)])
def test_streamed_replay_in_blocks_equals_in_memory(recorded, tmp_path, monkeypatch, reads, kind, delay):
    """A replay reads the file in blocks of frames, each with the history before it (a fractional delay's block also
    predicts the frame before it): the same errors, frame by frame, as the whole recording in memory, and no read
    larger than a block."""
    from eofnn.evaluation import replay as replay_module
    from eofnn.models.linear import LinearFilter

    both = Telemetry(y=recorded.y, wfs=recorded.wfs, delay_frames=delay,  # a batch: two sequences of 1500 frames
                     positions_m=recorded.positions_m)
    path = both.save(tmp_path / "held.fits", dtype="float64")
    spec = HistorySpec(kind, 3, delay)
    network = LinearFilter(80, spec.n_taps, structure="per_actuator")
    with torch.no_grad():
        network.weight.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(1))
    whole = replay_module.replay(network, spec, both, plant=PLANT, settle_frames=20)
    monkeypatch.setattr(replay_module, "REPLAY_BLOCK_ELEMENTS", 97 * 80 * spec.n_taps)  # blocks of 97 frames
    streamed = replay_module.replay(network, spec, StreamedTelemetry.open(path), plant=PLANT, settle_frames=20)
    for ours, reference in ((streamed.predictor, whole.predictor), (streamed.own_controller, whole.own_controller)):
        assert ours.rms_nm == pytest.approx(reference.rms_nm, rel=1e-12)
        assert ours.map_rms_nm == pytest.approx(reference.map_rms_nm, rel=1e-12)
        assert ours.psd_nm2_per_hz == pytest.approx(reference.psd_nm2_per_hz, rel=1e-12)
    assert streamed.n_frames == whole.n_frames == 2 * (1500 - whole.first_frame - spec.target_lead - (delay % 1 > 0))
    window = 97 + spec.first_frame + 1 + spec.target_lead  # a block, its history, the frame before, the lead
    assert max(reads) <= SCAN_FRAMES  # the finiteness scan's blocks, and the replay's windows
    assert sum(r <= window for r in reads) >= 2 * (1500 // 97)


@pytest.mark.slow
def test_streamed_identification_equals_in_memory(recorded, tmp_path):
    path = save(recorded, tmp_path / "t.npz", "float32")
    whole = Telemetry.load(path, required=("y", "wfs"))
    ours = identify_plant(StreamedTelemetry.open(path), batch_frames=97)
    reference = identify_plant(whole)
    assert ours.identified and abs(ours.dm_gain / PLANT["dm_gain"] - 1) < 0.03
    for key in ("dm_gain", "dm_gain_se", "misregistration_x", "misregistration_y", "wfs_noise_nm", "excitation_rms_nm"):
        assert getattr(ours, key) == pytest.approx(getattr(reference, key), rel=1e-10, abs=1e-12), key
    assert relative(torch.tensor(ours.coupling), torch.tensor(reference.coupling)) < 1e-10
    # A file whose wfs is logged one frame late: found and realigned lazily, as in memory.
    late = Telemetry(y=whole.y[0, 1:], wfs=whole.wfs[0, :-1], delay_frames=2, positions_m=whole.positions_m)
    late_path = late.save(tmp_path / "late.fits", dtype="float32")
    ours, reference = identify_plant(StreamedTelemetry.open(late_path), batch_frames=200), identify_plant(late)
    assert ours.lag_frames == reference.lag_frames == 1
    assert ours.dm_gain == pytest.approx(reference.dm_gain, rel=1e-10)


@pytest.mark.slow
def test_slopes_stream_through_the_reconstructor(recorded, tmp_path):
    rng = np.random.default_rng(0)
    im = rng.normal(size=(120, 80))
    y, wfs = recorded.y[0].numpy(), recorded.wfs[0].numpy()
    np.savez(tmp_path / "slopes.npz", y=y, slopes=wfs @ im.T, interaction_matrix=im, delay_frames=np.array(2))
    whole = Telemetry.load(tmp_path / "slopes.npz", required=("y", "wfs"))
    streamed = StreamedTelemetry.open(tmp_path / "slopes.npz")
    assert streamed.measurement == whole.measurement and "pinv(IM)" in streamed.measurement
    assert relative(streamed.wfs[100:300], whole.wfs[100:300]) < 1e-12
    slopes = wfs @ im.T
    slopes[700, 3] = np.inf
    np.savez(tmp_path / "bad.npz", y=y, slopes=slopes, interaction_matrix=im, delay_frames=np.array(2))
    with pytest.raises(TelemetryError, match=r"'slopes' holds 1 non-finite values \(NaN or inf\) in frames 512 "):
        identify_plant(StreamedTelemetry.open(tmp_path / "bad.npz"))
    spec = HistorySpec("open_loop", 2, 2)
    ours = fit_from_telemetry(streamed, spec, plant={"dm_gain": 1.5}, data=TelemetryDataConfig(batch_frames=64))
    reference = fit_from_telemetry(whole, spec, plant={"dm_gain": 1.5}, data=TelemetryDataConfig(batch_frames=512))
    assert relative(ours.network.weight, reference.network.weight) < 1e-10


def test_memory_is_bounded_by_the_block(recorded, tmp_path, reads):
    """Every read is one window (batch plus history), and what numpy allocates at once stays a few windows."""
    long = Telemetry(y=recorded.y.reshape(-1, 80).repeat(4, 1), wfs=recorded.wfs.reshape(-1, 80).repeat(4, 1),
                     delay_frames=2)  # 12000 frames: 7.7 MB in float32
    path = long.save(tmp_path / "long.npz", dtype="float32")
    streamed = StreamedTelemetry.open(path)
    spec = HistorySpec("open_loop", 4, 2)
    tracemalloc.start()
    try:
        fit_from_telemetry(streamed, spec, plant={"dm_gain": 1.5}, data=TelemetryDataConfig(batch_frames=200))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    window = 200 + spec.first_frame
    assert reads and max(reads) <= max(window, SCAN_FRAMES)  # fit windows; the finiteness scan reads its blocks
    assert sum(r for r in reads if r <= window) >= 12000  # ... and the fit did read every frame
    assert peak < streamed.stored_bytes / 4, (peak, streamed.stored_bytes)


@pytest.mark.cli
def test_bad_files_one_line(recorded, tmp_path, capsys):
    path = save(recorded, tmp_path / "t.fits", "float32")
    data = path.read_bytes()
    (tmp_path / "cut.fits").write_bytes(data[: len(data) // 2])
    with pytest.raises(TelemetryError, match="truncated"):
        StreamedTelemetry.open(tmp_path / "cut.fits")
    npz = save(recorded, tmp_path / "t.npz", "float32")
    (tmp_path / "cut.npz").write_bytes(npz.read_bytes()[:-200])
    with pytest.raises(TelemetryError, match="not readable"):
        StreamedTelemetry.open(tmp_path / "cut.npz")
    bad = recorded.wfs.clone().numpy()
    bad[1, 1203, 7] = np.nan
    np.savez(tmp_path / "nan.npz", y=recorded.y.numpy(), wfs=bad, delay_frames=np.array(2))
    with pytest.raises(TelemetryError, match=r"'wfs' holds 1 non-finite values \(NaN or inf\) in frames 1024 \.\. 1279"):
        identify_plant(StreamedTelemetry.open(tmp_path / "nan.npz"))
    with pytest.raises(TelemetryError, match="batch_frames=0 is invalid"):
        fit_from_telemetry(StreamedTelemetry.open(npz), HistorySpec("open_loop", 2, 2), data=TelemetryDataConfig(batch_frames=0))
    with pytest.raises(ConfigError, match="batch_frames=0 is invalid"):
        identify_plant(StreamedTelemetry.open(npz), batch_frames=0)
    # Through the command line: one line, nothing written.
    code = main(["fit", "--telemetry", str(tmp_path / "cut.fits"), "--plant", "nominal", "--out",
                 str(tmp_path / "x.ckpt")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and err[0].startswith("eofnn: error:") and "truncated" in err[0]
    assert not (tmp_path / "x.ckpt").exists()
    code = main(["identify", "--telemetry", str(npz), "--batch_frames", "0", "--out", str(tmp_path / "p.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "batch_frames" in err[0] and not (tmp_path / "p.json").exists()


def test_fortran_order_is_read_whole(recorded, tmp_path):
    """Frames not contiguous on disk: the CLI's loader reads the file whole instead (as before streaming)."""
    y, wfs = recorded.y[0].numpy(), recorded.wfs[0].numpy()
    np.savez(tmp_path / "f.npz", y=np.asfortranarray(y), wfs=np.asfortranarray(wfs), delay_frames=np.array(2))
    with pytest.raises(TelemetryError, match="Fortran order"):
        StreamedTelemetry.open(tmp_path / "f.npz")
    (loaded,) = load_telemetry(tmp_path / "f.npz", streamed=True)
    assert isinstance(loaded, Telemetry) and torch.equal(loaded.y, torch.as_tensor(y))


def test_batches_cover_every_frame_once(recorded, tmp_path):
    """Streamed batches hold exactly the in-memory histories and targets, in order, across block boundaries."""
    path = save(recorded, tmp_path / "t.fits", "float64")
    spec = HistorySpec("closed_loop", 5, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ours = list(TelemetryBatches(StreamedTelemetry.open(path), spec, lambda y: y, 1.0, batch_frames=13))
        reference = list(TelemetryBatches(Telemetry.load(path, required=("y", "wfs")), spec, lambda y: y, 1.0,
                                          batch_frames=1500))
    history = torch.cat([h for h, _ in ours])
    assert torch.equal(history, torch.cat([h for h, _ in reference]))
    assert torch.equal(torch.cat([t for _, t in ours]), torch.cat([t for _, t in reference]))
    assert history.shape[0] == 2 * (1500 - spec.first_frame)


def test_memory_refused_up_front(recorded, tmp_path, monkeypatch):
    """What the fit and identification will hold is checked against the memory available before any pass."""
    import eofnn.resources

    path = save(recorded, tmp_path / "t.npz", "float32")
    monkeypatch.setattr(eofnn.resources, "available_memory_bytes", lambda: 2**20)
    with pytest.raises(ConfigError, match=r"fitting from telemetry \(80 actuators, 3 taps, batches of 4096 frames\) "
                                          r"needs about .* GiB of memory"):
        fit_from_telemetry(StreamedTelemetry.open(path), HistorySpec("open_loop", 3, 2),
                           data=TelemetryDataConfig(batch_frames=4096))
    with pytest.raises(ConfigError, match=r"identification \(80 actuators, batches of 4096 frames\) needs about"):
        identify_plant(StreamedTelemetry.open(path), batch_frames=4096)
    with pytest.raises(ConfigError, match="reading telemetry file .* whole"):
        load_telemetry(path)


def test_compressed_members_read_any_window(tmp_path):
    """Forward windows continue the decompression; a window behind it reopens the member: the values are exact."""
    rng = np.random.default_rng(1)
    y = rng.normal(size=(3, 500, 7)).astype(np.float32)
    np.savez_compressed(tmp_path / "c.npz", y=y, wfs=-y, delay_frames=np.array(2))
    streamed = StreamedTelemetry.open(tmp_path / "c.npz")
    for batch, start, stop in [(0, 0, 100), (0, 90, 250), (0, 250, 500), (2, 10, 20), (1, 495, 500), (0, 3, 9),
                               (2, 0, 500)]:
        assert np.array_equal(streamed.y[batch][start:stop].numpy(), y[batch, start:stop])
        assert np.array_equal(streamed.wfs[batch][start:stop].numpy(), -y[batch, start:stop])
