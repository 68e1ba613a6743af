"""How the spine's numbers are compared with the committed ones: bit for bit on the machine that wrote them, within
what another CPU's rounding can move elsewhere.

Another CPU (or BLAS, or torch build) takes other kernel paths: sums are added in another order, so a value moves in
its last digits (measured: at most 4.4e-9 of its own size, an SGD-trained MLP's contrast; the rest below 1e-9), and a
value that is zero up to rounding (a standard error of 0 against 8e-19) moves wholly. A re-cut that changes behaviour
moves numbers by far more than that. So a float agrees when

    |now - before| <= RELATIVE * max(|now|, |before|) + FAMILY_FLOOR * scale(family) + ABSOLUTE_FLOOR

where a family is the path with its list indices dropped (``identify/coupling_se/*/*``) and its scale the largest
magnitude any member takes: a rounding-level value is judged against the size of the quantity it belongs to. Integers,
flags, strings and ``None`` must be equal.
"""

from __future__ import annotations

import json
import platform
import re
from pathlib import Path

#: A value's own size: another CPU's rounding moved none by more than 4.4e-9 of it (the SGD-trained MLP).
RELATIVE = 1e-8
#: Of its family's largest magnitude: rounding-level values (couplings' standard errors of 1e-17 beside 7e-3) moved by
#: at most 5.4e-12 of their family's scale.
FAMILY_FLOOR = 1e-10
#: Below this every quantity the spine records is rounding (the smallest meaningful one is an alpha of 1e-14).
ABSOLUTE_FLOOR = 1e-16

MACHINE = Path(__file__).parent / "spine_machine.json"


def flat(tree, prefix: str = "") -> dict:
    """``{"a/b/0/": value}`` for every leaf of a JSON tree."""
    if isinstance(tree, dict):
        return {k: v for key, sub in tree.items() for k, v in flat(sub, f"{prefix}{key}/").items()}
    if isinstance(tree, list):
        return {k: v for i, sub in enumerate(tree) for k, v in flat(sub, f"{prefix}{i}/").items()}
    return {prefix: tree}


def family(path: str) -> str:
    """The path with its list indices dropped: the quantity a value belongs to."""
    return re.sub(r"/\d+(?=/)", "/*", path)


def _is_float(value) -> bool:
    return isinstance(value, float) or (isinstance(value, int) and not isinstance(value, bool))


def moved_numbers(before: dict, now: dict, *, exact: bool) -> dict:
    """``{path: (before, now)}`` for every leaf that moved: any difference when ``exact``, else beyond the
    tolerance of this module's docstring. Both trees must be flat (:func:`flat`) with the same keys."""
    if exact:
        return {k: (before[k], now[k]) for k in before if now[k] != before[k]}
    scale: dict[str, float] = {}
    for tree in (before, now):
        for key, value in tree.items():
            if isinstance(value, float):
                scale[family(key)] = max(scale.get(family(key), 0.0), abs(value))
    moved = {}
    for key, old in before.items():
        new = now[key]
        if isinstance(old, float) and _is_float(new) or isinstance(new, float) and _is_float(old):
            allowed = (RELATIVE * max(abs(old), abs(new)) + FAMILY_FLOOR * scale.get(family(key), 0.0)
                       + ABSOLUTE_FLOOR)
            if not abs(new - old) <= allowed:  # NaN moves
                moved[key] = (old, new)
        elif type(old) is not type(new) or old != new:
            moved[key] = (old, new)
    return moved


def machine() -> dict:
    """What sets the last digits: CPU model, torch and numpy builds, the BLAS libraries in use."""
    import numpy as np
    import scipy.linalg  # noqa: F401  (its own BLAS: loaded by every spine run, so listed whether or not loaded yet)
    import torch
    from threadpoolctl import threadpool_info

    cpu = platform.processor() or platform.machine()
    try:  # the name alone ("AMD EPYC") covers several generations: family, model and stepping tell them apart
        info = dict(line.split(":", 1) for line in Path("/proc/cpuinfo").read_text().split("\n\n")[0].splitlines()
                    if ":" in line)
        info = {k.strip(): v.strip() for k, v in info.items()}
        cpu = " ".join(f"{k}={info[k]}" for k in ("vendor_id", "model name", "cpu family", "model", "stepping")
                       if k in info)
    except OSError:
        pass
    blas = sorted({f"{i.get('internal_api')} {i.get('version')} {i.get('architecture')}" for i in threadpool_info()})
    return {"cpu": cpu, "torch": torch.__version__, "numpy": np.__version__, "blas": blas,
            "torch_cpu_capability": torch.backends.cpu.get_cpu_capability()}


def recorded_machine() -> dict | None:
    """The machine that wrote ``spine.json``, or ``None`` when it was not recorded."""
    return json.loads(MACHINE.read_text()) if MACHINE.exists() else None
