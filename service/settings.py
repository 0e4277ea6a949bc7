"""Service settings from the environment (prefix ``FPM_``; ``REDIS_URL`` too).

Examples: ``FPM_MAX_NODES=20000``, ``FPM_API_KEYS=key1,key2``, ``REDIS_URL=redis://redis:6379/0``.
Tests override the dependency :func:`service.deps.settings` through FastAPI's dependency overrides.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Annotated

from pydantic import AliasChoices, Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from fpm import limits
from store.graph import JobOptions


class Settings(BaseSettings):
    """What the service may accept and where its Redis is."""

    model_config = SettingsConfigDict(env_prefix="FPM_", extra="ignore")

    redis_url: str = Field(
        "redis://localhost:6379/0",
        validation_alias=AliasChoices("FPM_REDIS_URL", "REDIS_URL"),
        description="Redis holding the queue and the stored results",
    )
    redis_timeout: float = Field(2.0, gt=0, description="socket timeouts for Redis calls, s")
    api_keys: Annotated[list[SecretStr], NoDecode] = Field(
        default_factory=list,
        description="accepted X-API-Key values (comma-separated); empty = no authentication",
    )
    max_nodes: int = Field(
        limits.MAX_NODES,
        ge=8,
        description="largest solid, in nodes (a 93,705-node organ was measured to calibrate "
        "within the job timeouts in under 5 GB; docs/service.md); fpmcal applies it too",
    )
    max_load_cases: int = Field(limits.MAX_LOAD_CASES, ge=1)
    max_active_per_key: int = Field(
        20,
        ge=0,
        description="calibrations one API key may have queued or running (0 = unlimited); "
        "over it, 429 with Retry-After",
    )
    max_nodes_per_key: int = Field(
        1_000_000,
        ge=0,
        description="lattice nodes one API key may have in calibrations queued or running (0 = "
        "unlimited)",
    )
    quota_retry_after: int = Field(60, ge=1, description="Retry-After of a 429 over a quota, s")
    max_chains: int = Field(
        limits.MAX_CHAINS, ge=1, description="most annealing chains per calibration"
    )
    max_body_bytes: int = Field(2_000_000, ge=1024, description="largest request body, bytes")
    max_mesh_bytes: int = Field(
        32_000_000, ge=1024, description="largest body of a mesh upload (POST /v1/meshes), bytes"
    )
    max_mesh_tetrahedra: int = Field(
        limits.MAX_MESH_TETRAHEDRA,
        ge=1,
        description="most tetrahedra of an uploaded mesh or a spec's reference.mesh",
    )
    page_size_limit: int = Field(200, ge=1, description="most items per page of a listing")
    fem_timeout: int = Field(JobOptions.fem_timeout, ge=1, description="wall time of a FEM job, s")
    chain_timeout: int = Field(
        JobOptions.chain_timeout, ge=1, description="wall time of one annealing chain, s"
    )
    finalize_timeout: int = Field(
        JobOptions.finalize_timeout, ge=1, description="wall time of a finalize job, s"
    )
    job_retries: int = Field(
        JobOptions.retries, ge=0, description="re-runs of a job whose worker died"
    )

    @field_validator("api_keys", mode="before")
    @classmethod
    def _split_keys(cls, v: object) -> object:
        if isinstance(v, str):
            return [key.strip() for key in v.split(",") if key.strip()]
        return v

    @property
    def job_options(self) -> JobOptions:
        return JobOptions(
            fem_timeout=self.fem_timeout,
            chain_timeout=self.chain_timeout,
            finalize_timeout=self.finalize_timeout,
            retries=self.job_retries,
        )


@lru_cache
def get_settings() -> Settings:
    """The settings, read from the environment once."""
    return Settings()
