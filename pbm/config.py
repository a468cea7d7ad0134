"""Typed, validated configuration of the PBM stage.

Every field carries its unit in its name. Values that depend on the velocity table (the
length of the feed-weight lists must equal NY, the pulse time must fall inside the run) are
checked when the table is known; the feed left None is taken from the table's operating
point there (:func:`pbm.feed.resolve_feed`). Both are done in :func:`pbm.simulate.simulate`, and raise
:class:`coupling.errors.ConfigError` there.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator


class PbmConfig(BaseModel):
    """The PBM run: feed, noise, transfer rates, RTD pulse and solver."""

    # for every float field, including those added later without their own allow_inf_nan
    # strict=True: a boolean or a string where a number belongs is refused naming the key
    # (not read as 1 or as the number it spells); an integer is still a valid float
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)

    feed_rate_a_per_s: float | None = Field(
        None,
        ge=0,
        allow_inf_nan=False,
        description="feeder A's rate (particles per second); None = the velocity table's operating point (pbm.feed), "
        "the paper's 995 /s on a table that records none. A rate that differs from the table's is named",
    )
    feed_rate_b_per_s: float | None = Field(
        None, ge=0, allow_inf_nan=False, description="feeder B's rate (particles per second); None as feed_rate_a_per_s"
    )
    feed_weights_a: list[float] | None = Field(
        None,
        description="NY relative weights of feed A over the first slice's compartments "
        "(j = 0 at y = -D/2), or NX * NY over every compartment (i * NY + j) for a feed zone "
        "that spans slices; None = feeder A's zone of the table's operating point (pbm.feed), uniformly over "
        "the first slice's y > 0 half on a table that records none. Each weight >= 0, at least one > 0",
    )
    feed_weights_b: list[float] | None = Field(
        None, description="NY relative weights of feed B; None as feed_weights_a, on the y < 0 side"
    )
    duration_s: float | None = Field(
        None, gt=0, allow_inf_nan=False, description="simulated time of the PBM run; None = the velocity table's end"
    )
    output_interval_s: float = Field(
        1.0, gt=0, allow_inf_nan=False, description="interval of the PBM's CQA time series (output k at k times this)"
    )
    noise_sigma: float = Field(
        0.0,
        ge=0,
        allow_inf_nan=False,
        description="relative SD of the feed-rate noise factor N(1, sigma), clipped at 0; 0 = no noise",
    )
    noise_interval_s: float = Field(
        1.0, gt=0, allow_inf_nan=False, description="the feed-rate noise factors are redrawn every this much time"
    )
    feed_step_s: float | None = Field(
        None,
        ge=0,
        allow_inf_nan=False,
        description="feeder A's rate is multiplied by feed_step_factor_a from this time on; a multiple of "
        "noise_interval_s (the feed is piecewise constant over those intervals). None = no step",
    )
    feed_step_factor_a: float = Field(
        1.0, ge=0, allow_inf_nan=False, description="factor on feeder A's rate from feed_step_s on; 1 without a step"
    )
    seed: int = Field(
        12345, ge=0, description="seed of the feed-noise generator (members of an ensemble drawn one after another)"
    )
    rtd_pulse_s: float | None = Field(
        None, ge=0, allow_inf_nan=False, description="time of the RTD tracer pulse; None = at the detected steady state"
    )
    rtd_bin_s: float = Field(1.0, gt=0, allow_inf_nan=False, description="width of the bins of the PBM's RTD E(t)")
    rates: Literal["velocity", "measured", "phases"] = Field(
        "velocity",
        description="transfer rates: 'velocity' = v/dx from the table's velocities (the paper's eq. 4); "
        "'measured' = the table's measured transition rates (schema 2, DEM transition tracking); "
        "'phases' = the table's hidden-phase transport model (schema 3, fitted to the DEM's compartment "
        "sequences by dem.phases)",
    )
    rate_law: Literal["table", "fill"] = Field(
        "table",
        description="'table' = the rates of the table's windows whatever the blender holds (the paper's linear "
        "PBM); 'fill' = the axial rates follow each slice's hold-up (pbm.fill), from the table's steady rates "
        "and the law of fill_exponents, else one fitted to the table's own windows",
    )
    fill_exponents: list[list[float]] | None = Field(
        None,
        description="the fill law's exponents, one [forward, backward] pair per axial slice (pbm.fill.fit_fill_law "
        "on a run library), each finite and >= 0; None = fitted to the table's windows",
    )
    method: Literal["expm", "bdf"] = Field("expm", description="exact propagation or the solve_ivp BDF cross-check")
    kernel: Literal["auto", "dense", "action"] = Field(
        "auto",
        description="how the exact propagation applies its steps: 'dense' = each window's matrix exponential, "
        "'action' = uniformization over the generator's diagonals (pbm.action), 'auto' = the cheaper by "
        "pbm.solver.kernel_costs; the numbers agree to ~1e-12",
    )
    bdf_rtol: float = Field(1e-6, gt=0, lt=1, description="relative tolerance of the BDF cross-check (method = 'bdf')")

    @field_validator("feed_weights_a", "feed_weights_b")
    @classmethod
    def _weights_valid(cls, weights: list[float] | None) -> list[float] | None:
        if weights is None:
            return None
        if len(weights) == 0:
            raise ValueError("must hold NY weights (the first slice) or NX * NY (every compartment), got an empty list")
        bad = [w for w in weights if not math.isfinite(w) or w < 0]
        if bad:
            raise ValueError(f"weights must be finite and >= 0, got {bad[0]}")
        if sum(weights) <= 0:
            raise ValueError("at least one weight must be > 0")
        return weights

    @field_validator("fill_exponents")
    @classmethod
    def _exponents_valid(cls, exponents: list[list[float]] | None) -> list[list[float]] | None:
        if exponents is None:
            return None
        if not exponents or any(len(row) != 2 for row in exponents):
            raise ValueError("must hold one [forward, backward] pair per axial slice")
        bad = [v for row in exponents for v in row if not math.isfinite(v) or v < 0]
        if bad:
            raise ValueError(f"exponents must be finite and >= 0, got {bad[0]}")
        return exponents

    @model_validator(mode="after")
    def _step_on_the_feed_grid(self) -> PbmConfig:
        if self.feed_step_s is None:
            if self.feed_step_factor_a != 1.0:
                raise ValueError(f"feed_step_factor_a = {self.feed_step_factor_a} needs feed_step_s (when it happens)")
            return self
        intervals = self.feed_step_s / self.noise_interval_s
        if abs(intervals - round(intervals)) > 1e-9 * max(1.0, intervals):
            raise ValueError(
                f"feed_step_s = {self.feed_step_s} s must be a multiple of noise_interval_s = "
                f"{self.noise_interval_s} s, e.g. {round(intervals) * self.noise_interval_s:g} s"
            )
        return self
