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


#: Actuator-frames per second a controller is simulated at, conservatively (2-core machine, 1264 actuators).
ACTUATOR_FRAMES_PER_S = 2e6
#: Longest run accepted without ``--allow_long true``, in seconds.
MAX_SECONDS = 24 * 3600


def peak_resident_bytes() -> int | None:
    """The process's peak resident memory so far (bytes; Linux's ``ru_maxrss`` is in KiB), ``None`` where the
    platform does not say."""
    try:
        import resource  # noqa: PLC0415 (POSIX only)
    except ImportError:
        return None
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def require_time(actuator_frames: float, what: str, allow_long: bool = False) -> None:
    """One-line :class:`ConfigError` when ``what`` would take more than a day at a conservative simulation rate."""
    seconds = actuator_frames / ACTUATOR_FRAMES_PER_S
    if seconds > MAX_SECONDS and not allow_long:
        raise ConfigError(f"{what} would take about {seconds / 3600:.3g} h (estimated at {ACTUATOR_FRAMES_PER_S:.0e} "
                          f"actuator-frames per second), more than the {MAX_SECONDS // 3600} h limit: make it smaller, "
                          "or pass --allow_long true to run it anyway")


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB"


def require_memory(n_bytes: float, what: str) -> None:
    """One-line :class:`ConfigError` when ``what`` would need more than the memory this machine has available."""
    budget = MEMORY_FRACTION * available_memory_bytes()
    if n_bytes > budget:
        raise ConfigError(f"{what} needs about {_gib(n_bytes)} of memory, more than the {_gib(budget)} available: "
                          "use fewer frames, realisations or actuators")
