"""Build predictor networks from ``class_path`` / ``init_args`` configs, so any ``nn.Module`` plugs in."""

from __future__ import annotations

import importlib
import inspect
from typing import Any

from torch import nn

from eofnn.errors import ConfigError

#: Short names for eofnn's own networks.
ALIASES = {
    "LinearFilter": "eofnn.models.linear.LinearFilter",
    "OpenLoopEOF": "eofnn.models.linear.OpenLoopEOF",
    "ClosedLoopEOF": "eofnn.models.linear.ClosedLoopEOF",
    "MLP": "eofnn.models.mlp.MLP",
}


def import_class(class_path: str) -> type:
    """Import ``package.module.Class`` (or an alias such as ``MLP``)."""
    class_path = ALIASES.get(class_path, class_path)
    module_name, _, name = class_path.rpartition(".")
    if not module_name:
        raise ConfigError(f"class_path={class_path!r} is invalid: give package.module.Class or one of "
                          f"{', '.join(ALIASES)}")
    try:
        cls = getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError):
        raise ConfigError(f"class_path={class_path!r} cannot be imported") from None
    if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
        raise ConfigError(f"class_path={class_path!r} is not a torch.nn.Module")
    return cls


def build_network(config: dict[str, Any], n_actuators: int, n_taps: int, grid: dict,
                  history_kind: str = "open_loop", delay_frames: int = 2) -> nn.Module:
    """Instantiate ``config = {"class_path": ..., "init_args": {...}}``.

    ``n_actuators``, ``n_taps``, ``grid``, ``history_kind`` and ``delay_frames`` are passed to the constructor when
    it takes them and the config does not set them, so a user's module only declares what it needs.
    """
    if not isinstance(config, dict) or "class_path" not in config:
        raise ConfigError(f"network config {config!r} is invalid: it needs a class_path")
    cls = import_class(config["class_path"])
    init_args = dict(config.get("init_args") or {})
    params = inspect.signature(cls).parameters
    derived = (("n_actuators", n_actuators), ("n_taps", n_taps), ("grid", grid), ("history_kind", history_kind),
               ("delay_frames", delay_frames))
    for name, value in derived:
        if name in params and name not in init_args:
            init_args[name] = value
    try:
        return cls(**init_args)
    except TypeError as err:
        raise ConfigError(f"cannot build {config['class_path']}: {err}") from None
