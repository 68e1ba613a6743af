"""Build predictor networks from ``class_path`` / ``init_args`` configs, so any ``nn.Module`` plugs in.

A network named in a user's own config is imported as asked. A network named by a *file* (a checkpoint someone
sent) is only imported when its class path is eofnn's own or one the user trusts explicitly: importing a module
runs its code, so the check is made on the string, before any import.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Collection
from typing import Any

from eofnn.errors import CheckpointError, ConfigError
from eofnn.lazy import lazy_module

torch = lazy_module("torch")
nn = lazy_module("torch.nn")

#: eofnn's own networks, by short name.
ALIASES = {
    "LinearFilter": "eofnn.models.linear.LinearFilter",
    "OpenLoopEOF": "eofnn.models.linear.OpenLoopEOF",
    "ClosedLoopEOF": "eofnn.models.linear.ClosedLoopEOF",
    "MLP": "eofnn.models.mlp.MLP",
}
OWN_NETWORKS = frozenset(ALIASES.values())


def resolve_class_path(class_path: Any) -> str:
    """The full ``package.module.Class`` of ``class_path`` (an alias such as ``MLP`` is expanded)."""
    if not isinstance(class_path, str):
        raise ConfigError(f"class_path={class_path!r} is invalid: give package.module.Class or one of "
                          f"{', '.join(ALIASES)}")
    class_path = ALIASES.get(class_path, class_path)
    module_name, _, name = class_path.rpartition(".")
    if not module_name or not name.isidentifier():
        raise ConfigError(f"class_path={class_path!r} is invalid: give package.module.Class or one of "
                          f"{', '.join(ALIASES)}")
    return class_path


def check_trusted(class_path: str, trusted: Collection[str], where: str = "checkpoint") -> str:
    """Refuse, without importing anything, a class path that is neither eofnn's own nor in ``trusted``."""
    full = resolve_class_path(class_path)
    if full not in OWN_NETWORKS and full not in {resolve_class_path(t) for t in trusted}:
        raise CheckpointError(f"{where} names network class_path={full!r}, which is not one of eofnn's networks: "
                              "if you trust it, name it in the config's network.class_path or in --trusted_networks")
    return full


def import_class(class_path: str) -> type:
    """Import ``package.module.Class`` (or an alias such as ``MLP``) named by the user."""
    class_path = resolve_class_path(class_path)
    module_name, _, name = class_path.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError):
        raise ConfigError(f"class_path={class_path!r} cannot be imported: is its module on the Python path "
                          "(the folder of the config is added to it)?") from None
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
        raise ConfigError(f"network={config!r} is invalid: it needs a class_path (and optional init_args)")
    cls = import_class(config["class_path"])
    init_args = config.get("init_args") or {}
    if not isinstance(init_args, dict):
        raise ConfigError(f"network.init_args={init_args!r} is invalid: it must be a mapping")
    init_args = dict(init_args)
    params = inspect.signature(cls).parameters
    derived = (("n_actuators", n_actuators), ("n_taps", n_taps), ("grid", grid), ("history_kind", history_kind),
               ("delay_frames", delay_frames))
    for name, value in derived:
        if name in params and name not in init_args:
            init_args[name] = value
    try:
        network = cls(**init_args)
    except TypeError as err:
        raise ConfigError(f"cannot build {config['class_path']}: {err}") from None
    check_network(network, n_actuators, n_taps, config["class_path"])
    return network


def check_network(network: nn.Module, n_actuators: int, n_taps: int, name: str) -> None:
    """One-line :class:`ConfigError` unless ``network`` maps a ``(2, n_actuators, n_taps)`` history to
    ``(2, n_actuators)`` commands (a probe on zeros, without gradients)."""
    shape = (2, n_actuators, n_taps)
    try:
        with torch.no_grad():
            out = network(torch.zeros(shape, dtype=input_dtype(network)))
    except Exception as err:  # a user's forward: any error is theirs, said in one line
        text = str(err).strip().splitlines()
        raise ConfigError(f"network {name}: forward raised {type(err).__name__}"
                          f"{': ' + text[0] if text else ''} on a history of shape {shape}") from None
    if not isinstance(out, torch.Tensor):
        raise ConfigError(f"network {name} returned {type(out).__name__}, not a tensor, for a history of shape {shape}")
    if tuple(out.shape) != shape[:2]:
        raise ConfigError(f"network {name} returned shape {tuple(out.shape)} for a history of shape {shape}: it must "
                          f"return (batch, actuators) = {shape[:2]}")


def input_dtype(network: nn.Module) -> torch.dtype:
    """The dtype a network takes its histories in: its ``input_dtype`` if it declares one, else its first parameter's.

    Histories are float64 nm; a float32 network (the torch default) gets them converted, so a user's module runs
    in its own precision.
    """
    declared = getattr(network, "input_dtype", None)
    if declared is not None:
        return declared
    first = next(network.parameters(), None)
    return torch.float64 if first is None else first.dtype
