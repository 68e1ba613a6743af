"""The re-cut into one spine moved no number: every command on the tiny scenario against the numbers of before."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from golden.spine import spine_numbers

GOLDEN = Path(__file__).parent / "golden" / "spine.json"


def _flat(tree, prefix=""):
    if isinstance(tree, dict):
        return {k: v for key, sub in tree.items() for k, v in _flat(sub, f"{prefix}{key}/").items()}
    if isinstance(tree, list):
        return {k: v for i, sub in enumerate(tree) for k, v in _flat(sub, f"{prefix}{i}/").items()}
    return {prefix: tree}


@pytest.mark.cli
@pytest.mark.slow
def test_every_command_gives_the_numbers_of_before():
    """Bit for bit on this machine's libraries (the numbers were written by ``tests/golden/spine.py`` on main before
    the re-cut); a difference is listed by its path, e.g. ``compare/scenarios/nominal/lqg/median_rms_nm``."""
    before = _flat(json.loads(GOLDEN.read_text()))
    now = _flat(json.loads(json.dumps(spine_numbers(), sort_keys=True)))
    assert now.keys() == before.keys()
    moved = {k: (before[k], now[k]) for k in before if now[k] != before[k]}
    assert not moved, f"{len(moved)} numbers moved, e.g. {dict(list(moved.items())[:5])}"


if __name__ == "__main__":
    pytest.main([__file__])
