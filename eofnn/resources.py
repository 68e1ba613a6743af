"""Sizes that cannot fit are refused up front: memory estimates against what this machine has available."""

from __future__ import annotations

import os

from eofnn.errors import ConfigError

#: Fraction of the available memory one run may plan to use.
MEMORY_FRACTION = 0.8


def available_memory_bytes() -> int:
    """Memory available to a new allocation (``MemAvailable`` on Linux, else physical memory)."""
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB"


def require_memory(n_bytes: float, what: str) -> None:
    """One-line :class:`ConfigError` when ``what`` would need more than the memory this machine has available."""
    budget = MEMORY_FRACTION * available_memory_bytes()
    if n_bytes > budget:
        raise ConfigError(f"{what} needs about {_gib(n_bytes)} of memory, more than the {_gib(budget)} available: "
                          "use fewer frames, realisations or actuators")
