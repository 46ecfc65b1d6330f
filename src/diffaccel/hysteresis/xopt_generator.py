"""Hysteresis-aware Bayesian optimisation as an Xopt generator.

:class:`HysteresisBayesianGenerator` is Xopt's ``UpperConfidenceBoundGenerator``
whose model is a :class:`~diffaccel.hysteresis.HysteresisGP`, built by
:class:`HysteresisModelConstructor`: the variables named in
``hysteretic_inputs`` are magnet currents whose effect goes through a Preisach
model of the applied history (a triangular mesh with a uniform prior density
over the variable's VOCS bounds, refitted with the GP at every step); the other
variables are plain GP inputs.

Importing this module registers the generator in Xopt under the name
``hysteresis_bayesian`` (Xopt 3.2 finds generators by name in
``xopt.generators.generators``; it reads no package entry points), so that a
YAML with ``generator: {name: hysteresis_bayesian, ...}`` runs under ``Xopt``
once ``import diffaccel.hysteresis.xopt_generator`` has run.

Assumptions and limits:
    * The rows of Xopt's data are the settings *in the order they were applied*
      (Xopt's synchronous loop; an asynchronous evaluator that reorders
      evaluations breaks the history).
    * The state before the first row is the Preisach model's
      ``initial_state`` (``"negative"`` saturation by default).
    * One objective, no constraints. Rows whose objective is missing (failed
      evaluations) are left out of the history.
    * The model is rebuilt and refitted from the prior on the whole history at
      every step (no warm start).

Needs ``pip install diffaccel[xopt]``; ``import diffaccel.hysteresis`` does not
import Xopt.
"""

from __future__ import annotations

from typing import Any

import torch

from diffaccel.hysteresis.hgp import HysteresisGP, fit_hysteresis_gp
from diffaccel.hysteresis.mesh import PreisachMesh
from diffaccel.hysteresis.preisach import INITIAL_STATES, PreisachModel

# importing Xopt sets torch's default dtype to float64 for the whole process;
# the rest of diffaccel (and the user's code) keeps its own default
_DEFAULT_DTYPE = torch.get_default_dtype()
try:
    from pydantic import Field, SerializeAsAny, field_validator, model_validator
    from xopt.generators import generators as _xopt_generators
    from xopt.generators.bayesian.base_model import ModelConstructor
    from xopt.generators.bayesian.upper_confidence_bound import (
        UpperConfidenceBoundGenerator,
    )
except ImportError as err:  # pragma: no cover - exercised without the extra
    raise ImportError(
        "the Xopt generator needs Xopt: pip install diffaccel[xopt]"
    ) from err
finally:
    torch.set_default_dtype(_DEFAULT_DTYPE)


__all__ = ["HysteresisBayesianGenerator", "HysteresisModelConstructor"]

GENERATOR_NAME = "hysteresis_bayesian"


class HysteresisModelConstructor(ModelConstructor):
    """Xopt model constructor that builds and fits a :class:`HysteresisGP`.

    Each hysteretic input gets a :class:`PreisachModel` on a triangular mesh of
    ``mesh_n`` rows (``mesh_n * (mesh_n + 1) / 2`` hysterons) with a uniform
    density over the variable's bounds (Xopt's model input bounds, in the
    variable's units, e.g. current [A]); densities and GP hyperparameters are
    fitted jointly by :func:`fit_hysteresis_gp`.

    Attributes:
        hysteretic_inputs: Names of the hysteretic VOCS variables (set from the
            generator's ``hysteretic_inputs``).
        mesh_n: Rows of each Preisach mesh.
        initial_state: Magnetic state before the first data row (one of
            ``INITIAL_STATES`` except ``"learned"``).
        fit_density: Refit the densities with the GP (True) or keep the
            uniform prior fixed.
        density_prior_scale: Prior width of the raw densities about the uniform
            prior (see ``HysteresisGP``); ``None`` for no prior.
        fit_restarts: Restarts of each fit.
        fit_max_iter: L-BFGS-B iterations per restart.
        seed: Seed of the fit restarts (plus the number of data rows).
    """

    name: str = Field("hysteresis", frozen=True)
    hysteretic_inputs: list[str] = Field(default_factory=list)
    mesh_n: int = Field(12, ge=1, description="rows of each Preisach mesh")
    initial_state: str = Field("negative", description="state before the data")
    fit_density: bool = True
    density_prior_scale: float | None = Field(1.0, gt=0)
    fit_restarts: int = Field(1, ge=1)
    fit_max_iter: int = Field(100, ge=1)
    seed: int = 0

    @field_validator("initial_state")
    @classmethod
    def _check_initial_state(cls, value: str) -> str:
        allowed = [s for s in INITIAL_STATES if s != "learned"]
        if value not in allowed:
            raise ValueError(f"initial_state must be one of {allowed}; got {value!r}.")
        return value

    def build_model(
        self,
        input_names: list[str],
        outcome_names: list[str],
        data: Any,
        input_bounds: dict[str, list[float]] | None = None,
        dtype: torch.dtype = torch.double,
        device: torch.device | str = "cpu",
    ) -> HysteresisGP:
        """Build and fit the H-GP on the data rows, in their order.

        Args:
            input_names: Model input (VOCS variable) names, the ``d`` columns.
            outcome_names: Output names; exactly one (the objective).
            data: Xopt's pandas DataFrame, rows in the order applied.
            input_bounds: ``{name: [lower, upper]}`` of every input; the data
                range if omitted.
            dtype: Floating dtype of the model.
            device: Device of the model.

        Returns:
            The fitted :class:`HysteresisGP` (``posterior(X)`` over ``(*b, q, d)``
            means: apply the q settings after the data history, in order).

        Raises:
            ValueError: for several outputs, an unknown hysteretic input name or
                fewer than 2 rows with an objective value.
        """
        if len(outcome_names) != 1:
            raise ValueError(
                f"the hysteresis model takes one objective and no constraints; "
                f"got outputs {outcome_names}."
            )
        unknown = [n for n in self.hysteretic_inputs if n not in input_names]
        if unknown:
            raise ValueError(
                f"hysteretic_inputs {unknown} are not VOCS variables {input_names}."
            )
        rows = data[list(input_names) + list(outcome_names)].dropna()
        if len(rows) < 2:
            raise ValueError(
                f"the hysteresis model needs >= 2 evaluated points; got {len(rows)}."
            )
        tk = {"dtype": dtype, "device": device}
        X = torch.tensor(rows[list(input_names)].to_numpy(dtype=float), **tk)
        Y = torch.tensor(rows[list(outcome_names)].to_numpy(dtype=float), **tk)
        if input_bounds is None:
            lo, hi = X.min(0).values, X.max(0).values
        else:
            b = torch.tensor([input_bounds[n] for n in input_names], **tk)
            lo, hi = b[:, 0], b[:, 1]
        bounds = torch.stack([lo, hi])
        hyst = {
            input_names.index(n): PreisachModel(
                PreisachMesh.triangular(n=self.mesh_n),
                input_range=(
                    float(lo[input_names.index(n)]),
                    float(hi[input_names.index(n)]),
                ),
                initial_state=self.initial_state,
                dtype=dtype,
            ).to(device)
            for n in self.hysteretic_inputs
        }
        model = HysteresisGP(
            X,
            Y,
            hysteresis=hyst,
            bounds=bounds,
            density_prior_scale=(
                self.density_prior_scale if hyst and self.fit_density else None
            ),
        )
        fit_hysteresis_gp(
            model,
            restarts=self.fit_restarts,
            max_iter=self.fit_max_iter,
            fit_density=self.fit_density,
            seed=self.seed + len(rows),
        )
        return model


class HysteresisBayesianGenerator(UpperConfidenceBoundGenerator):
    """Xopt UCB generator whose model is a :class:`HysteresisGP`.

    Options (besides those of ``UpperConfidenceBoundGenerator``: ``beta``,
    ``numerical_optimizer``, ...):

    Attributes:
        hysteretic_inputs: Names of the VOCS variables that are hysteretic
            magnet currents; passed to the model constructor.
        gp_constructor: A :class:`HysteresisModelConstructor` (or its dict,
            ``name: hysteresis``) with the Preisach and fit options.

    Candidates for ``n_candidates > 1`` are to be applied in the order given:
    the model judges each from the state left by the ones before it.
    """

    name = GENERATOR_NAME
    hysteretic_inputs: list[str] = Field(
        default_factory=list,
        description="VOCS variables whose effect goes through a Preisach model",
    )
    gp_constructor: SerializeAsAny[ModelConstructor] = Field(
        default_factory=HysteresisModelConstructor,
        description="constructor of the HysteresisGP model",
    )

    @field_validator("gp_constructor", mode="before")
    @classmethod
    def validate_gp_constructor(cls, value: Any) -> Any:
        """Accept a :class:`HysteresisModelConstructor`, its dict, or None."""
        if value is None or value == "hysteresis":
            return HysteresisModelConstructor()
        if isinstance(value, HysteresisModelConstructor):
            return value
        if isinstance(value, dict) and value.get("name", "hysteresis") == "hysteresis":
            return HysteresisModelConstructor(
                **{k: v for k, v in value.items() if k != "name"}
            )
        raise ValueError(
            f"{GENERATOR_NAME} builds its model with the 'hysteresis' constructor; "
            f"got gp_constructor={value!r}."
        )

    @model_validator(mode="after")
    def _pass_hysteretic_inputs(self) -> HysteresisBayesianGenerator:
        unknown = [n for n in self.hysteretic_inputs if n not in self.vocs.variables]
        if unknown:
            raise ValueError(
                f"hysteretic_inputs {unknown} are not VOCS variables "
                f"{list(self.vocs.variables)}."
            )
        constructor = self.gp_constructor
        if self.hysteretic_inputs and constructor.hysteretic_inputs not in (
            [],
            self.hysteretic_inputs,
        ):
            raise ValueError(
                f"hysteretic_inputs {self.hysteretic_inputs} differ from the "
                f"gp_constructor's {constructor.hysteretic_inputs}; give them once."
            )
        if self.hysteretic_inputs:
            constructor.hysteretic_inputs = list(self.hysteretic_inputs)
        return self


_xopt_generators[GENERATOR_NAME] = HysteresisBayesianGenerator
