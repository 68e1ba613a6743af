"""The settings a classical controller's scan tries (:attr:`eofnn.evaluation.config.PredictorConfig.setting_grid`)
and a config with one of them put in."""

from __future__ import annotations

import itertools
from dataclasses import replace
from typing import Any


def setting_grid(**values: list) -> list[dict]:
    """Every combination of ``values`` (a list per name), the first name outermost, without repeats."""
    grid = [dict(zip(values, combo, strict=True)) for combo in itertools.product(*values.values())]
    return [setting for i, setting in enumerate(grid) if setting not in grid[:i]]


def with_setting(cfg: Any, setting: dict) -> Any:
    """``cfg`` with the fields of one scanned ``setting`` replaced; a dotted key (``"pfc.alpha"``) replaces a field
    of that section (:attr:`eofnn.evaluation.config.PredictorConfig.setting_grid`)."""
    plain = {key: value for key, value in setting.items() if "." not in key}
    out = replace(cfg, **plain)
    for key, value in setting.items():
        if "." in key:
            section, name = key.split(".", 1)
            out = replace(out, **{section: replace(getattr(out, section), **{name: value})})
    return out


__all__ = ["setting_grid", "with_setting"]
