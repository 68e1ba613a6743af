"""The re-cuts moved no number: every command on the tiny scenario against the numbers of before.

``tests/golden/spine.json`` holds them (written by ``python tests/golden/spine.py tests/golden/spine.json``, which also
records the machine that wrote them in ``spine_machine.json``). On that machine the check is bit for bit; on any other
(another CPU, BLAS or torch build adds in another order) it allows what rounding can move and nothing more
(``tests/golden/agreement.py``). The failure message says which check ran.
"""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest
from golden.agreement import flat, machine, moved_numbers, recorded_machine
from golden.spine import spine_numbers

GOLDEN = Path(__file__).parent / "golden" / "spine.json"
#: The same numbers written on another CPU (main c3f53a9, before ``spine.json`` was rewritten on an AMD EPYC): what
#: another machine's rounding really moves.
OTHER_CPU = Path(__file__).parent / "golden" / "spine_other_cpu.json"


@pytest.mark.cli
@pytest.mark.slow
def test_every_command_gives_the_numbers_of_before():
    """A difference is listed by its path, e.g. ``compare/scenarios/nominal/lqg/median_rms_nm``."""
    before = flat(json.loads(GOLDEN.read_text()))
    now = flat(json.loads(json.dumps(spine_numbers(), sort_keys=True)))
    assert now.keys() == before.keys()
    exact = recorded_machine() == machine()
    check = ("bit for bit (this is the machine that wrote spine.json)" if exact else
             "within rounding (relative 1e-8, 1e-10 of each quantity's scale; spine.json was written on another "
             "machine: tests/golden/spine_machine.json)")
    moved = moved_numbers(before, now, exact=exact)
    assert not moved, f"{len(moved)} numbers moved, checked {check}, e.g. {dict(list(moved.items())[:5])}"


def _golden() -> dict:
    return flat(json.loads(GOLDEN.read_text()))


def test_another_cpus_numbers_agree_within_rounding_but_not_bit_for_bit():
    """The committed numbers of two CPUs: thousands differ in their last digits, none beyond the tolerance. The other
    CPU recorded the keys of c3f53a9; keys added since (``verdict``, ``spatial_split_nm``, replay's ``guard``) have no
    other-CPU record, so the comparison is over the keys it has, all of which spine.json still holds."""
    here, there = _golden(), flat(json.loads(OTHER_CPU.read_text()))
    assert there.keys() <= here.keys()
    assert all("/verdict/" in k or "/spatial_split_nm/" in k or k.startswith("replay/guard/")
               for k in here.keys() - there.keys())
    here = {k: here[k] for k in there}
    assert len(moved_numbers(there, here, exact=True)) > 1000
    assert moved_numbers(there, here, exact=False) == {}


def test_rounding_level_perturbations_pass_and_a_moved_number_fails():
    """1e-12 relative on every float and 1e-18 on every zero pass; one number moved by 1e-6 of itself fails, as does a
    changed integer or flag."""
    before = _golden()
    rng = random.Random(0)
    floats = [k for k, v in before.items() if isinstance(v, float)]
    assert any(before[k] == 0.0 for k in floats)
    perturbed = dict(before)
    for k in floats:
        v = before[k]
        perturbed[k] = v * (1 + rng.choice((-1, 1)) * 1e-12) if v else rng.choice((-1, 1)) * 1e-18
    assert moved_numbers(before, perturbed, exact=False) == {}
    assert moved_numbers(before, perturbed, exact=True)  # the exact check sees them

    key = "compare/scenarios/nominal/lqg/median_rms_nm/"
    assert moved_numbers(before, {**perturbed, key: before[key] * (1 + 1e-6)}, exact=False).keys() == {key}
    ints = [k for k, v in before.items() if isinstance(v, int) and not isinstance(v, bool) and v]
    assert moved_numbers(before, {**before, ints[0]: before[ints[0]] + 1}, exact=False).keys() == {ints[0]}
    flags = [k for k, v in before.items() if isinstance(v, bool)]
    assert moved_numbers(before, {**before, flags[0]: not before[flags[0]]}, exact=False).keys() == {flags[0]}
    nan = float("nan")
    assert moved_numbers(before, {**before, key: nan}, exact=False).keys() == {key}


if __name__ == "__main__":
    pytest.main([__file__])
