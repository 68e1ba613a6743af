"""A training run through the command line prints eofnn's own progress lines and real warnings, nothing else:
no Lightning banners ("GPU available", "TPU available"), tips (LitLogger), checkpoint notices (``weights_only``),
warnings about eofnn's own tensors (``requires_grad``) or Lightning's internals (``LeafSpec``, DataLoader workers).
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path

import pytest

pytestmark = pytest.mark.cli

TINY = Path(__file__).parent / "conf" / "tiny_compare.yaml"
#: What a quiet run never shows: Lightning's banners and tips, its checkpoint notice, torch's warning about a
#: scalar taken from a tensor that requires grad, Lightning's deprecated pytree call, its DataLoader-workers hint.
NOISE = ("GPU available", "TPU available", "litlogger", "Tip", "weights_only", "requires_grad", "LeafSpec",
         "does not have many workers")
#: One linear predictor fitted in closed form, saved as a checkpoint and analysed for stability (the Lightning
#: trainer, the checkpoint writer and the analysis of a fitted Parameter), on short streams.
ONE_PREDICTOR = {"ol_eof": {"history": "open_loop", "history_length": 2, "optimization": {"alpha": 1.0e-9},
                            "data": {"frames": 600, "val_frames": 200, "sequence_frames": 600}}}


@pytest.mark.slow  # a compare with its figures: 4.5 s measured on 2 cores under a load of 4
def test_a_training_run_prints_only_eofnns_own_lines(cli, capsys, caplog, tmp_path):
    caplog.set_level(logging.INFO)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")  # pyproject's filters for the suite are not what a user runs with
        code, err = cli("compare", "--config", TINY, "--scenarios", '{"nominal": {}}', "--predictors",
                        json.dumps(ONE_PREDICTOR), "--evaluation.frames", "300", "--evaluation.settle_frames", "50",
                        "--evaluation.psd_segment_frames", "64", "--out", tmp_path / "run")
    out = capsys.readouterr().out
    assert code == 0, err
    shown = {
        "stderr": err,
        "stdout": out,
        "warnings": "\n".join(f"{w.category.__name__}: {w.message}" for w in caught),
        "log records": "\n".join(f"{r.name}: {r.getMessage()}" for r in caplog.records),
    }
    for where, text in shown.items():
        noise = [line for line in text.splitlines() if any(word in line for word in NOISE)]
        assert not noise, f"{where} holds {noise}"
    assert "training ol_eof in scenario nominal" in err and "ol_eof: median RMS" in err  # eofnn's own lines stay


def test_lightning_is_quiet_only_while_eofnn_trains():
    from eofnn.training.fit import LIGHTNING_INFO_LOGGERS, quiet_lightning

    loggers = [logging.getLogger(name) for name in LIGHTNING_INFO_LOGGERS]
    before = [logger.level for logger in loggers]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with quiet_lightning():
            assert all(logger.getEffectiveLevel() >= logging.WARNING for logger in loggers)
            warnings.warn_explicit("`isinstance(treespec, LeafSpec)` is deprecated, use ...", FutureWarning,
                                   "_pytree.py", 21, module="lightning.pytorch.utilities._pytree")
            warnings.warn("a real warning", UserWarning, stacklevel=1)
            warnings.warn_explicit("`isinstance(treespec, LeafSpec)` is deprecated, use ...", FutureWarning,
                                   "mine.py", 1, module="mine")  # not Lightning's: kept
    assert [str(w.message) for w in caught] == ["a real warning", "`isinstance(treespec, LeafSpec)` is deprecated, use ..."]
    assert [logger.level for logger in loggers] == before
