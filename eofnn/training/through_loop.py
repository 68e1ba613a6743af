"""Training through the closed loop (``optimization.fit_method: closed_loop``): a linear predictor, started from its
closed-form fit, descends on its own closed-loop residual.

The closed-form fit learns to predict the turbulence from histories recorded in a loop it does not hold (open loop:
pseudo-open-loop values that are exact only in the nominal plant; closed loop: an integrator plus dither). Once it
holds the loop itself, what it sees and what its errors cost change. Here the loss is what the loop delivers: the
mean squared residual ``eps(n) = s(n) + DM(y(n))`` of the predictor closing the loop
(:func:`~eofnn.training.rollout.rollout`, the step :func:`~eofnn.sim.loop.runner.run_loop` runs), backpropagated
through windows of ``optimization.loop_window`` frames, each after ``optimization.loop_warmup`` frames of the loop run
without gradients (truncated backpropagation). The loop is the scenario's, sensor included: in a Shack-Hartmann
scenario the measurement is the sensor's (``R S phi``, its photon and read noise reconstructed, the fill of the modes
the reconstructor cuts; through ``sensor.reconstructor: mmse``, ``R_mmse`` applied to the slopes and their noise as
``run_loop`` applies it) and the loss is the residual over the pupil, piston removed, where the loop is scored.

Data budget: the same as the closed-form fit's. The windows are cut from the same training sequences (the same
turbulence frames, ``data.frames`` of them, the same WFS-noise draws and, under ``data.plant_range``, the same range;
:class:`~eofnn.training.rollout.LoopWindows`), and the epoch kept is chosen on the same ``data.val_frames`` validation
frames, the closed-form start included: the result's validation residual is never above the start's.

The trained network is still the same linear filter (per actuator, shared or neighbourhood), so its checkpoint is
read, run, exported and analysed (stability margins, ``eofnn stability``, ``compare``) like any other.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

import lightning as L
from torch.utils.data import DataLoader

from eofnn.data.config import DataConfig
from eofnn.data.stream import LoopDataModule
from eofnn.errors import require
from eofnn.training.config import OptimizationConfig
from eofnn.training.ridge import ClosedFormFit
from eofnn.training.rollout import LoopWindows, loop_residual
from eofnn.training.search import KeepBest


@dataclass
class LoopData:
    """The windows training through the loop learns from (``train``) and chooses its epoch on (``validation``)."""

    train: LoopWindows
    validation: LoopWindows


def loop_data(datamodule: LoopDataModule, data: DataConfig, optimization: OptimizationConfig) -> LoopData:
    """The training and validation streams of ``datamodule`` (those of the closed-form fit) as windows of the loop;
    all the windows in one batch for L-BFGS, one batch per sequence otherwise."""
    require(data.target == "measured", f"data.target={data.target!r} is invalid with optimization.fit_method: "
                                       "closed_loop: training through the loop scores the measured s it closes on; "
                                       "use fit_method: closed_form or sgd")
    full = optimization.gradient_optimizer == "lbfgs"
    window, warmup = optimization.loop_window, optimization.loop_warmup
    return LoopData(LoopWindows(datamodule.dataset("train", data.frames), window, warmup, full),
                    LoopWindows(datamodule.dataset("validation", data.val_frames), window, warmup, full))


def train_through_loop(task, loop: LoopData | None, start: ClosedFormFit,
                       make_trainer: Callable[[list], L.Trainer]) -> tuple[L.Trainer, dict]:
    """Train ``task``'s network (fitted in closed form: ``start``) through the loop on ``loop``'s windows, for
    ``optimization.epochs`` epochs of Lightning's ``fit``, and keep the epoch of least validation residual (the start
    included). Returns the trainer (which holds ``task``, to save it) and the metrics (residuals in nm²); the
    provenance (``task.hparams["info"]["through_loop"]``) gets the start's and the result's residuals, and where they
    are taken (``residual_over``: ``pupil`` through a Shack-Hartmann, else ``actuators``)."""
    require(loop is not None, "optimization.fit_method: closed_loop trains through the simulated loop: it needs a "
                              "scenario and simulator truth (data.truth: true), not telemetry alone")
    network, spec, optimization = task.network, task.spec, task.optimization
    start_train = loop_residual(network, spec, loop.train)
    keep = KeepBest(optimization.epochs + 1)  # no early stop: every epoch runs, the best one is kept
    keep.best, keep.state = loop_residual(network, spec, loop.validation), copy.deepcopy(network.state_dict())
    start_val = keep.best
    trainer = make_trainer([keep])
    trainer.fit(task, train_dataloaders=DataLoader(loop.train, batch_size=None),
                val_dataloaders=DataLoader(loop.validation, batch_size=None), weights_only=True)
    network.load_state_dict(keep.state)
    train_loss = start_train if keep.best_epoch == 0 else loop_residual(network, spec, loop.train)
    summary = {
        "start": {"fit_method": "closed_form", "alpha": start.alpha, "train_residual_nm2": start_train,
                  "val_residual_nm2": start_val, "one_step_train_loss_nm2": start.train_loss},
        "train_residual_nm2": train_loss, "val_residual_nm2": keep.best, "best_epoch": keep.best_epoch,
        "epochs": keep.epochs, "optimizer": optimization.gradient_optimizer, "lr": optimization.learning_rate,
        "window_frames": loop.train.window, "warmup_frames": loop.train.warmup,
        "train_windows": loop.train.n_windows,
        # Where the residuals are taken: over the pupil through a Shack-Hartmann, else at the actuators.
        "residual_over": "pupil" if loop.train.telemetry.scenario.sensor.is_shack_hartmann else "actuators",
    }
    task.hparams["info"] = {**task.hparams["info"], "alpha": start.alpha, "through_loop": summary}
    return trainer, {"train_loss": train_loss, "val_loss": keep.best, "alpha": start.alpha,
                     "start_val_loss": start_val}


def loop_work(optimization: OptimizationConfig, data: DataConfig, n_actuators: int) -> float:
    """Actuator-frames of loop simulation that training through the loop costs at most, for an experiment's time
    estimate (0 for the other fit methods): per epoch up to 20 evaluations of the training windows (L-BFGS; 1 for
    the other optimisers), each a forward and a backward pass (about three rollouts), and one of the validation
    windows, every window with its warm-up."""
    if optimization.fit_method != "closed_loop":
        return 0.0
    evaluations = 20 if optimization.gradient_optimizer == "lbfgs" else 1
    warmups = 1 + optimization.loop_warmup / optimization.loop_window
    return (optimization.epochs * (3 * evaluations * data.frames + data.val_frames) * warmups * data.realisations
            * (data.refit_rounds + 1) * n_actuators)


__all__ = ["LoopData", "loop_data", "loop_work", "train_through_loop"]
