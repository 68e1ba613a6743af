"""Named, reproducible random streams: every draw in eofnn comes from ``(seed, stream name, sub-keys)``.

Streams with different names never share draws, so the training, validation and test turbulence, the WFS
noise and the dither are independent, and each is the same whatever else a run does.
"""

from __future__ import annotations

import zlib

import numpy as np

from eofnn.lazy import lazy_module
from eofnn.validation import Interval, check_value

torch = lazy_module("torch")


def stream_seed(seed: int, stream: str, *key: int) -> np.random.SeedSequence:
    """Seed sequence of stream ``stream`` (``"train"``, ``"test"``, ``"wfs-noise"``, ...) and sub-keys ``key``."""
    check_value("seed", seed, Interval(0, 2**63 - 1, integer=True))
    return np.random.SeedSequence(int(seed), spawn_key=(zlib.crc32(stream.encode()), *key))


def sub_seed(seed: np.random.SeedSequence, *key: int) -> np.random.SeedSequence:
    """The sub-stream ``key`` of ``seed`` (independent of it and of other keys, whatever else was drawn)."""
    return np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, *key))


def int_seed(seed: int, stream: str, *key: int) -> int:
    """One 32-bit integer seed drawn from :func:`stream_seed` (for APIs that take an ``int``)."""
    return int(stream_seed(seed, stream, *key).generate_state(1)[0])


def torch_generator(seed: int, stream: str, *key: int) -> torch.Generator:
    """A CPU ``torch.Generator`` seeded from :func:`stream_seed`."""
    return torch.Generator().manual_seed(int_seed(seed, stream, *key))
