"""Service settings: the project's settings object plus what only the server needs."""

from __future__ import annotations

from functools import lru_cache

from pydantic import Field

from models.settings import Settings


class ServiceSettings(Settings):
    host: str = Field(default="127.0.0.1", description="Interface to bind.")
    port: int = Field(default=8000, ge=1, le=65535)
    torch_threads: int = Field(default=1, ge=1, description="Intra-op threads; 1 leaves the other core to the event loop.")


@lru_cache
def get_service_settings() -> ServiceSettings:
    return ServiceSettings()
