"""The project's one settings object: every tunable path and limit, read from the environment
(prefix `STYLESTREAM_`) or a `.env` file. The service extends it with its own fields."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

REPO_ROOT = Path(__file__).resolve().parent.parent


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="STYLESTREAM_", env_file=".env", extra="ignore")

    data_dir: Path = Field(
        default=REPO_ROOT.parent / "shared" / "data",
        description="Folder with the mocap archives (*.tar.xz + SHA256SUMS) or already unpacked dataset folders.",
    )
    cache_dir: Path = Field(
        default=REPO_ROOT / ".data",
        description="Git-ignored folder for unpacked archives and parsed-array caches.",
    )
    weights_dir: Path = Field(default=REPO_ROOT / "models" / "weights", description="Committed model weights.")
    stages_off: list[str] = Field(
        default_factory=list,
        description="Stages after a method's core to switch off, as `method.stage` (JSON list, e.g. "
        '`["lpn.carriage"]`; the names a method declares: `models.lpn.runtime.STAGES`). For comparisons, or to '
        "serve a method without a stage; a name the method does not declare is an error at load.",
    )
    bfloat16_products: bool = Field(
        default=True,
        description="LPN-FiLM's expert products in bfloat16 (float32 sums) where this CPU multiplies bfloat16 "
        "natively (AVX512-BF16 or AMX) with rows independent of the batch (checked at first use; models/rowwise.py); "
        "false: always float32.",
    )


@lru_cache
def get_settings() -> Settings:
    return Settings()
