"""A Shack-Hartmann subaperture's detector: photons from the guide star, and the centroid noise they and the read
noise leave on a slope (Rousset's formulas), in the sensor's slope unit (nm of OPD difference across the
subaperture: :mod:`eofnn.sim.sensing.shack_hartmann`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from eofnn.validation import COUNT, FINITE, Constraint, Interval, OneOf, check_value, validated

#: Photometry ``band: (wavelength m, bandwidth m, zero point photons / m² / s)``: OOPAO's table
#: (``OOPAO/Source.py``, ``Source.photometry``, "New entries with corrected zero point flux values": the zero points
#: there are ``value / 368``).
PHOTOMETRY: dict[str, tuple[float, float, float]] = {
    name: (wavelength, bandwidth, zero / 368)
    for name, (wavelength, bandwidth, zero) in {
        "U": (0.360e-6, 0.070e-6, 1.96e12), "B": (0.440e-6, 0.100e-6, 5.38e12),
        "V0": (0.500e-6, 0.090e-6, 3.64e12), "V": (0.550e-6, 0.090e-6, 3.31e12),
        "R": (0.640e-6, 0.150e-6, 4.01e12), "R2": (0.650e-6, 0.300e-6, 7.9e12),
        "R3": (0.600e-6, 0.300e-6, 8.56e12), "R4": (0.670e-6, 0.300e-6, 7.66e12),
        "I": (0.790e-6, 0.150e-6, 2.69e12), "I1": (0.700e-6, 0.033e-6, 0.67e12),
        "I2": (0.750e-6, 0.033e-6, 0.62e12), "I3": (0.800e-6, 0.033e-6, 0.58e12),
        "I4": (0.700e-6, 0.100e-6, 2.02e12), "I5": (0.850e-6, 0.100e-6, 1.67e12),
        "I6": (1.000e-6, 0.100e-6, 1.42e12), "I7": (0.850e-6, 0.300e-6, 5.00e12),
        "I8": (0.750e-6, 0.100e-6, 1.89e12), "I9": (0.850e-6, 0.300e-6, 5.00e12),
        "I10": (0.900e-6, 0.300e-6, 4.72e12), "J": (1.215e-6, 0.260e-6, 1.90e12),
        "J2": (1.550e-6, 0.260e-6, 1.49e12), "H": (1.654e-6, 0.290e-6, 1.05e12),
        "Kp": (2.1245e-6, 0.351e-6, 0.62e12), "Ks": (2.157e-6, 0.320e-6, 0.55e12),
        "K": (2.179e-6, 0.410e-6, 0.70e12), "K0": (2.000e-6, 0.410e-6, 0.76e12),
        "K1": (2.400e-6, 0.410e-6, 0.64e12),
    }.items()
}
#: Spots the photon-noise formula may assume: ``gaussian`` (coefficient pi² / (2 ln 2), exact for the centre of
#: gravity of a Gaussian spot of FWHM ``N_T`` pixels: Thomas et al. 2006) or ``rousset`` (pi² / 2, Rousset 1999).
SPOTS = ("gaussian", "rousset")


@dataclass(frozen=True)
@validated
class Detector:
    """Photon and read noise of a Shack-Hartmann's subaperture detector, by Rousset's formulas.

    Parameters
    ----------
    band : str
        Photometric band of the guide star and the sensing (a key of :data:`PHOTOMETRY`, OOPAO's table).
    magnitude : float
        Guide-star magnitude in ``band``.
    throughput : float
        Fraction of the photons reaching the detector, in (0, 1].
    pixels_across : int
        ``N_s``: pixels across the subaperture's centroiding window.
    pixels_per_lambda_over_d : float
        ``N_D``: pixels per ``lambda / d_s`` (2 at Nyquist sampling).
    spot_fwhm_lambda_over_d : float
        ``N_T / N_D``: the spot's FWHM in units of ``lambda / d_s`` (1 for a diffraction-limited spot; about
        ``d_s / r0`` when seeing-limited).
    read_noise_e : float
        ``sigma_e``: read noise per pixel and frame (electrons RMS).
    spot : {"gaussian", "rousset"}
        The photon-noise coefficient: ``gaussian`` (pi² / (2 ln 2), the exact centre-of-gravity variance of a Gaussian
        spot of FWHM ``N_T``; Thomas et al. 2006, MNRAS 371, 323) or ``rousset`` (pi² / 2, Rousset 1999 in Roddier's
        *Adaptive Optics in Astronomy*, which is 0.69 times the Gaussian's).
    """

    band: str = "R"
    magnitude: float = 8.0
    throughput: float = 0.5
    pixels_across: int = 8
    pixels_per_lambda_over_d: float = 2.0
    spot_fwhm_lambda_over_d: float = 1.0
    read_noise_e: float = 0.0
    spot: str = "gaussian"

    _constraints: ClassVar[dict[str, Constraint]] = {
        "band": OneOf(tuple(PHOTOMETRY)),
        "magnitude": FINITE,
        "throughput": Interval(0, 1, closed="right", unit="fraction of the photons"),
        "pixels_across": COUNT,
        "pixels_per_lambda_over_d": Interval(0, None, closed="neither", unit="pixels per lambda/d"),
        "spot_fwhm_lambda_over_d": Interval(0, None, closed="neither", unit="lambda/d"),
        "read_noise_e": Interval(0, None, unit="electrons RMS per pixel"),
        "spot": OneOf(SPOTS),
    }

    @property
    def wavelength_m(self) -> float:
        """The band's central wavelength (m): the sensing wavelength."""
        return PHOTOMETRY[self.band][0]

    def photons_per_subaperture(self, subaperture_m: float, frame_period_s: float) -> float:
        """``N_ph = F0 10^(-0.4 mag) T d_s² dt``: photons per subaperture and frame (``F0`` the band's zero point,
        photons / m² / s, OOPAO's ``Source.photometry``; ``T`` the throughput; ``d_s`` the side in m; ``dt`` in s)."""
        check_value("subaperture_m", subaperture_m, Interval(0, None, closed="neither", unit="m"))
        check_value("frame_period_s", frame_period_s, Interval(0, None, closed="neither", unit="s"))
        return PHOTOMETRY[self.band][2] * 10 ** (-0.4 * self.magnitude) * self.throughput * subaperture_m ** 2 \
            * frame_period_s

    def phase_variance_rad2(self, n_photons: float) -> tuple[float, float]:
        """``(photon, read)``: variances of the phase difference across the subaperture (rad², sensing wavelength).

        Photon: ``c / N_ph (N_T / N_D)²`` with ``c = pi² / (2 ln 2)`` (``spot="gaussian"``) or ``pi² / 2``
        (``"rousset"``); read: ``(pi² / 3) (sigma_e² / N_ph²) (N_s² / N_D)²`` (Rousset 1999; exact for the centre
        of gravity over ``N_s x N_s`` pixels to ``1 - 1 / N_s²``). A centroid of ``x`` pixels is a phase difference
        ``2 pi x / N_D``.
        """
        check_value("n_photons", n_photons, Interval(0, None, closed="neither", unit="photons"))
        c = math.pi ** 2 / 2 / (math.log(2) if self.spot == "gaussian" else 1.0)
        photon = c / n_photons * self.spot_fwhm_lambda_over_d ** 2
        read = (math.pi ** 2 / 3) * (self.read_noise_e / n_photons) ** 2 * (
            self.pixels_across ** 2 / self.pixels_per_lambda_over_d) ** 2
        return photon, read

    def slope_noise_variance_nm2(self, subaperture_m: float, frame_period_s: float) -> float:
        """White noise variance of one slope in the sensor's unit (nm of OPD difference across the subaperture, nm²):
        ``(photon + read) (lambda / 2 pi)²`` with lambda in nm."""
        photon, read = self.phase_variance_rad2(self.photons_per_subaperture(subaperture_m, frame_period_s))
        return (photon + read) * (self.wavelength_m * 1e9 / (2 * math.pi)) ** 2
