"""Run an exported eofnn linear filter inside any real-time loop: numpy and astropy only.

This file imports no other eofnn module and no torch: copy it next to a real-time computer's code. A filter file
(``docs/export.md``; written by :func:`eofnn.training.export.export_filter`) holds coefficients per actuator and tap,
the TAPS table saying which signal and lag each tap reads, the loop delay and, for open-loop filters, the DM gain
used for the pseudo-open-loop reconstruction. Per frame::

    filt = PredictiveFilter.from_file("filter.fits")
    filt.reset()
    for each frame n:
        y = filt.step(wfs)          # wfs: the measurement that arrives at frame n, i.e. of eps(n - delay), nm
        apply y to the DM           # command for frame n, nm

``step`` keeps its own buffers of past commands and measurements and commands zero until every tap holds a real
sample (``first_frame`` steps), exactly as eofnn's ``PredictiveController``. When the loop modifies the command
(clipping, an added dither), pass what was really applied at the previous frame as ``y_last``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

SIGNALS = ("y", "wfs", "pol")
FORMAT_VERSION = 1


class FilterFileError(ValueError):
    """A filter file is missing, unreadable or inconsistent; the message says what and where."""


#: Longest lag a filter may read, in frames (buffers hold this many frames per actuator).
MAX_LAG = 10_000


class PredictiveFilter:
    """A linear predictive filter with its own history buffers.

    Parameters
    ----------
    coefficients : ndarray
        ``(K, taps)``, or ``(K, M, taps)`` with ``neighbours`` for a neighbourhood filter (nm of command per nm).
    taps : sequence of (str, int)
        What each tap reads: ``("y", lag)`` the command ``y(n - lag)``, ``("wfs", lag)`` the measurement of
        ``eps(n - lag)``, ``("pol", lag)`` its pseudo-open-loop value ``wfs - dm_gain_model * y(n - lag)``.
    delay_frames : int
        Loop delay ``d``: the measurement arriving at frame ``n`` is of ``eps(n - d)``.
    dm_gain_model : float
        DM gain assumed by the pseudo-open-loop reconstruction.
    neighbours : ndarray, optional
        ``(K, M)`` actuator indices whose histories each actuator reads; ``-1`` reads zeros (beyond the pupil).
    """

    def __init__(self, coefficients: np.ndarray, taps, delay_frames: int, dm_gain_model: float = 1.0,
                 neighbours: np.ndarray | None = None) -> None:
        self.coefficients = np.asarray(coefficients, dtype=np.float64)
        self.taps = [(str(signal), int(lag)) for signal, lag in taps]
        if not float(delay_frames).is_integer() or delay_frames < 1:  # a fractional delay is not truncated silently
            raise FilterFileError(f"delay_frames={delay_frames!r} is invalid: it must be an integer >= 1")
        self.delay_frames, self.dm_gain_model = int(delay_frames), float(dm_gain_model)
        if not (np.isfinite(self.dm_gain_model) and 0 < self.dm_gain_model <= 100):
            raise FilterFileError(f"dm_gain_model={dm_gain_model!r} is invalid: it must be a number in (0, 100]")
        if not np.isfinite(self.coefficients).all():
            bad = int((~np.isfinite(self.coefficients)).sum())
            raise FilterFileError(f"coefficients hold {bad} non-finite value(s) (NaN or inf) of "
                                  f"{self.coefficients.size}: the filter would command NaN")
        if self.delay_frames > MAX_LAG:
            raise FilterFileError(f"delay_frames={self.delay_frames} is invalid: at most {MAX_LAG} frames")
        for signal, lag in self.taps:
            if lag > MAX_LAG:  # buffers are sized by the largest lag: count before allocating
                raise FilterFileError(f"tap ({signal!r}, lag {lag}) is invalid: lags are at most {MAX_LAG} frames")
            if signal not in SIGNALS:
                raise FilterFileError(f"tap signal {signal!r} is invalid: allowed are {', '.join(SIGNALS)}")
            if lag < (1 if signal == "y" else self.delay_frames):
                raise FilterFileError(f"tap ({signal!r}, lag {lag}) is not available: y needs lag >= 1, wfs and pol "
                                      f"lag >= delay_frames={self.delay_frames}")
        self.n_actuators = self.coefficients.shape[0]
        if self.coefficients.shape[-1] != len(self.taps):
            raise FilterFileError(f"coefficients have {self.coefficients.shape[-1]} taps, the TAPS table "
                                  f"{len(self.taps)}")
        self.neighbours = None
        if self.coefficients.ndim == 3:
            if neighbours is None or np.shape(neighbours) != self.coefficients.shape[:2]:
                raise FilterFileError(f"a neighbourhood filter {self.coefficients.shape} needs a NEIGHBOURS index of "
                                      f"shape {self.coefficients.shape[:2]}")
            index = np.asarray(neighbours, dtype=np.int64)
            if index.size and (index.max() >= self.n_actuators or index.min() < -1):
                raise FilterFileError(f"NEIGHBOURS holds actuator indices from {int(index.min())} to "
                                      f"{int(index.max())}: they must be in 0 .. {self.n_actuators - 1} (or -1 for none)")
            self.neighbours = np.where(index < 0, self.n_actuators, index)  # the pad row reads zeros
        elif self.coefficients.ndim != 2:
            raise FilterFileError(f"coefficients have shape {self.coefficients.shape}: expected (K, taps) or "
                                  "(K, M, taps)")
        # Taps index into buffers by lag: commands from lag 1, measurements and POL values from lag d.
        self._y_depth = max([lag for s, lag in self.taps if s == "y"] + [self.delay_frames])
        self._m_depth = max([lag - self.delay_frames + 1 for s, lag in self.taps if s != "y"] + [1])
        self.first_frame = max(lag for _, lag in self.taps)
        self.reset()

    @classmethod
    def from_file(cls, path: str | Path) -> PredictiveFilter:
        """Read a filter FITS file in the layout of ``docs/export.md``."""
        from astropy.io import fits

        path = Path(path)
        if not path.exists():
            raise FilterFileError(f"filter file {str(path)!r} does not exist")
        try:
            with fits.open(path, memmap=False) as hdul:
                header = hdul[0].header
                if header.get("EOFNNFLT") != FORMAT_VERSION:
                    raise FilterFileError(f"filter file {str(path)!r} is not an eofnn filter (EOFNNFLT "
                                          f"{header.get('EOFNNFLT')!r}, expected {FORMAT_VERSION})")
                coefficients = np.array(hdul[0].data, dtype=np.float64)
                table = hdul["TAPS"].data
                taps = [(str(s).strip(), int(lag)) for s, lag in zip(table["SIGNAL"], table["LAG"], strict=True)]
                neighbours = np.array(hdul["NEIGHBOURS"].data) if "NEIGHBOURS" in hdul else None
                return cls(coefficients, taps, header["DELAY"], float(header.get("DMGAIN", 1.0)), neighbours)
        except FilterFileError:
            raise
        except (OSError, KeyError, ValueError, TypeError) as err:
            raise FilterFileError(f"filter file {str(path)!r} is not readable ({type(err).__name__}: "
                                  f"{str(err).splitlines()[0] if str(err) else ''})") from None

    def reset(self) -> None:
        """Forget the past: zero buffers, and zero commands again for the next ``first_frame`` steps."""
        k = self.n_actuators
        self._y = np.zeros((k, self._y_depth))  # column j: y(n - 1 - j)
        self._wfs = np.zeros((k, self._m_depth))  # column j: measurement of eps(n - d - j)
        self._pol = np.zeros((k, self._m_depth))
        self._history = np.zeros((k, len(self.taps)))
        self._frames_seen = 0

    def step(self, wfs: np.ndarray, y_last: np.ndarray | None = None) -> np.ndarray:
        """Next command ``y(n)`` (nm, ``(K,)``) from the measurement arriving now (of ``eps(n - d)``, nm, ``(K,)``).

        ``y_last``: the command really applied at frame ``n - 1``, if it differs from this filter's last output.
        """
        wfs = np.asarray(wfs, dtype=np.float64)
        if wfs.shape != (self.n_actuators,):
            raise ValueError(f"wfs has shape {wfs.shape}: expected ({self.n_actuators},)")
        if y_last is not None:
            self._y[:, 0] = y_last
        d = self.delay_frames
        self._wfs[:, 1:], self._pol[:, 1:] = self._wfs[:, :-1], self._pol[:, :-1]
        self._wfs[:, 0] = wfs
        self._pol[:, 0] = wfs - self.dm_gain_model * self._y[:, d - 1]  # POL value of frame n - d
        for column, (signal, lag) in enumerate(self.taps):
            source = self._y[:, lag - 1] if signal == "y" else (self._wfs if signal == "wfs" else self._pol)[:, lag - d]
            self._history[:, column] = source
        if self._frames_seen < self.first_frame:
            y = np.zeros(self.n_actuators)
        elif self.neighbours is None:
            y = (self._history * self.coefficients).sum(-1)
        else:
            padded = np.concatenate([self._history, np.zeros((1, len(self.taps)))], 0)
            y = (padded[self.neighbours].reshape(self.n_actuators, -1) * self.coefficients.reshape(
                self.n_actuators, -1)).sum(-1)
        self._frames_seen += 1
        self._y[:, 1:] = self._y[:, :-1]
        self._y[:, 0] = y
        return y
