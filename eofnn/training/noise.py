"""Noise-aware closed-form fits: the normal equations of the noise a filter will meet, and a ridge set by the noise.

An open-loop (pseudo-open-loop) predictor reads ``h = [s_hat(n-d), ...]`` with ``s_hat = s + v`` and learns the
target ``-s_hat(n) / g``; the white WFS noise ``v`` (``sigma`` nm RMS per actuator and frame) is independent of every
history that predicts frame ``n``. Least squares then converges to

    ``F = -E[s(n) h^T] (C_hh)^-1 / g,   C_hh = C_ss + sigma² I``,

the Wiener (minimum mean-square) predictor of the *true* ``s(n)`` from histories *as noisy as the training data's*:
the errors-in-variables attenuation of plain least squares is exactly the shrinkage that noise calls for, and the
target's noise only adds a constant to the error. What follows from that (``optimization.noise_model`` and
``optimization.noise_at_deployment_nm``, :class:`~eofnn.training.config.OptimizationConfig`):

- ``none`` (the default): the data as recorded. Right whenever the filter meets the training data's noise.
- ``noise_at_deployment_nm: sigma_d``: the normal equations ``D D^T`` (``n`` samples per group) become
  ``D D^T + n (sigma_d² - sigma_t²) I`` (training and validation alike), the Gram of histories carrying ``sigma_d``
  of noise: the exact Wiener fix of a filter fitted on telemetry of one noise level (``sigma_t``, identified from it
  or the scenario's) and deployed at another, the case of a predictor fitted on noise-free telemetry.
- ``errors_in_variables``: ``sigma_d = 0``, the classical correction (``D D^T - n sigma_t² I``, then projected onto the
  positive semi-definite matrices, since a finite sample's noise covariance is not exactly ``n sigma_t² I``): the
  predictor for noise-free histories. The theory says it is *worse* on the noisy histories the loop feeds it; it is
  here to be measured against.
- ``per_mode_snr``: the ridge alpha in units of the noise power ``n sigma_d²`` instead of each group's signal power
  (the mean diagonal of its Gram). A relative alpha shrinks every group by the same fraction of its own power; the
  noise is the same in every mode of an orthonormal basis (``structure: modal``) and every actuator, so this ridge
  shrinks each mode by ``alpha / SNR``: strong low-order modes barely, weak high-order ones a lot. With ``alpha``
  near 1 it is the Wiener filter for ``1 + alpha`` times the noise; ``alpha: auto`` tunes it on validation data.

The noise is taken as white and equal on every feature that carries signal (a neighbourhood's slots beyond the
pupil carry none): exact for eofnn's zonal sensor; for a Shack-Hartmann the reconstructed noise is correlated
between actuators (``sigma² R R^T``) and the identified level is its mean per actuator. Closed-loop histories are
refused: there the loop feeds the noise back into ``y``, so it is not independent of the history.

How the noise models compare in a closed loop (``experiments/noise_aware/``): ``docs/findings.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

from eofnn.errors import ConfigError
from eofnn.lazy import lazy_module

torch = lazy_module("torch")

#: The alphas ``alpha: auto`` searches with ``per_mode_snr`` when ``alpha_path`` is unset: 1e-4 to 1e2 noise powers,
#: two per decade.
NOISE_ALPHA_PATH = tuple(float(f"{10 ** (e / 2):.3g}") for e in range(-8, 5))


@dataclass(frozen=True)
class NoiseTerm:
    """The noise a closed-form fit models: the training data's (``training_nm``) and the one its filter will meet
    (``deployment_nm``), nm RMS per feature and sample; ``snr_ridge``: alpha in units of ``n deployment_nm²``."""

    model: str
    training_nm: float
    deployment_nm: float
    snr_ridge: bool = False

    @property
    def variance_change_nm2(self) -> float:
        """``deployment_nm² - training_nm²``: what each noisy feature's variance changes by."""
        return self.deployment_nm ** 2 - self.training_nm ** 2

    def adjust(self, equations):
        """``equations`` (:class:`~eofnn.training.ridge.NormalEquations`) as if their histories carried
        ``deployment_nm`` of white noise: ``D D^T + n (sigma_d² - sigma_t²) I`` on the features that carry signal,
        projected onto the positive semi-definite matrices when noise was taken away; alpha's unit the noise power
        when ``snr_ridge``. The cross products and the targets are unchanged (their noise is independent)."""
        gram = equations.gram
        carries = (gram.diagonal(dim1=1, dim2=2) != 0).to(gram.dtype)  # structural zeros carry no noise either
        change = self.variance_change_nm2
        if change:
            gram = gram + equations.n_samples * change * torch.diag_embed(carries)
        if change < 0:
            values, vectors = torch.linalg.eigh(gram)
            gram = (vectors * values.clamp(min=0).unsqueeze(-2)) @ vectors.transpose(1, 2)
            gram = gram * carries.unsqueeze(-1) * carries.unsqueeze(-2)  # structural zeros stay exactly zero
        unit = None
        if self.snr_ridge:
            unit = torch.full((gram.shape[0],), equations.n_samples * self.deployment_nm ** 2, dtype=gram.dtype)
        return equations.with_gram(gram, unit)

    def recorded(self, info: dict) -> dict:
        """A fit's provenance ``info`` with what it modelled (``info["noise"]``) and, in ``info["conditions"]``, the
        noise its filter is made for (the level a shift warning compares the telemetry's with)."""
        conditions = dict(info.get("conditions") or {})
        conditions["source"] = (f"{conditions.get('source', 'unknown')}; fitted for {self.deployment_nm:.3g} nm of "
                                f"noise (optimization.noise_model {self.model})")
        return {**info, "noise": self.summary(), "conditions": {**conditions, "wfs_noise_nm": self.deployment_nm}}

    def summary(self) -> dict:
        """JSON-ready: what the fit modelled (a checkpoint keeps it in ``info["noise"]``)."""
        return {"model": self.model, "training_wfs_noise_nm": self.training_nm,
                "deployment_wfs_noise_nm": self.deployment_nm,
                "alpha_unit": "noise power (samples x sigma_deploy^2)" if self.snr_ridge else "signal power"}


def alpha_path(optimization, noise: NoiseTerm | None) -> list[float] | None:
    """The alphas ``alpha: auto`` searches: ``optimization.alpha_path``, or unset :data:`NOISE_ALPHA_PATH` for a
    ridge in noise powers (and the default path otherwise)."""
    if optimization.alpha_path is None and noise is not None and noise.snr_ridge:
        return list(NOISE_ALPHA_PATH)
    return optimization.alpha_path


def noise_term(optimization, conditions: dict | None, history_kind: str) -> NoiseTerm | None:
    """The noise an :class:`~eofnn.training.config.OptimizationConfig` asks its closed-form fit to model, given the
    training data's recorded ``conditions`` (``wfs_noise_nm``: identified, or the scenario's); ``None`` for a fit that
    models none (the default: the data as recorded). One line when it cannot be modelled."""
    if not optimization.noise_aware:
        return None
    asked = f"optimization.noise_model={optimization.noise_model!r}, noise_at_deployment_nm=" \
            f"{optimization.noise_at_deployment_nm!r}"
    if history_kind != "open_loop":
        raise ConfigError(f"{asked} model white noise on pseudo-open-loop histories; a {history_kind} history feeds "
                          "the noise back through the loop's commands (use history: open_loop)")
    training = (conditions or {}).get("wfs_noise_nm")
    if training is None:
        raise ConfigError(f"{asked} needs the training data's WFS noise, which is unknown here (a nominal or given "
                          "plant without wfs_noise_nm): identify the plant from the telemetry (plant: identify)")
    training = float(training)
    if optimization.noise_model == "errors_in_variables":
        deployment = 0.0
    else:
        deployment = training if optimization.noise_at_deployment_nm is None else \
            float(optimization.noise_at_deployment_nm)
    snr = optimization.noise_model == "per_mode_snr"
    if snr and deployment <= 0:
        raise ConfigError(f"{asked}: per_mode_snr sets the ridge from the noise floor, and the noise the filter meets "
                          "is 0 nm: give noise_at_deployment_nm > 0, or noise_model: none")
    return NoiseTerm(optimization.noise_model, training, deployment, snr)
