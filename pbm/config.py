"""Typed, validated configuration of the PBM stage.

Extended by the PBM implementation; every field carries its unit in its name.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class PbmConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    feed_rate_a_per_s: float = Field(995.0, ge=0)
    feed_rate_b_per_s: float = Field(995.0, ge=0)
    output_interval_s: float = Field(1.0, gt=0)
    noise_sigma: float = Field(0.0, ge=0, description="relative SD of the feed-rate noise factor")
    noise_interval_s: float = Field(1.0, gt=0)
    seed: int = Field(12345, ge=0)
    rtd_pulse_s: float | None = Field(None, ge=0, description="tracer pulse time; None = at detected steady state")
