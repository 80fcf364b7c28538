"""Service settings: the one place that reads the environment (prefix ``SRD_``)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Annotated

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Every knob of the auction house; each can be set as ``SRD_<NAME>`` in the environment."""

    model_config = SettingsConfigDict(env_prefix="SRD_", extra="ignore")

    database_url: str = "sqlite:///./srd.db"
    """SQLAlchemy URL; SQLite (WAL mode) by default, ``postgresql+psycopg://...`` works too."""
    data_dir: Path = Path("./data")
    """Job artifacts (``jobs/<id>/``) and the generated admin token file live here."""
    admin_token: SecretStr | None = None
    """Operator token; when unset one is generated at first start into ``admin_token_file``."""
    max_body_bytes: Annotated[int, Field(ge=1024)] = 262_144
    """Request bodies larger than this are refused with 413."""
    auction_workers: Annotated[int, Field(ge=1, le=64)] = 1
    """Auctions run at the same time, each in its own worker process."""
    job_workers: Annotated[int, Field(ge=1, le=64)] = 1
    """Jobs run at the same time, each in its own worker process."""
    worker_torch_threads: Annotated[int, Field(ge=1, le=256)] = 1
    """Torch threads per auction/job worker process (the API keeps the remaining cores)."""
    worker_nice: Annotated[int, Field(ge=0, le=19)] = 10
    """Scheduling niceness added to auction/job worker processes (POSIX ``nice``): background
    computation yields the CPU to the API's requests under load, and takes it all when idle."""
    progress_interval_s: Annotated[float, Field(gt=0)] = 0.5
    """Minimum time between two progress writes of a running job."""
    host: str = "127.0.0.1"
    """Address ``srd serve`` binds by default."""
    port: Annotated[int, Field(ge=0, le=65535)] = 8000
    """Port ``srd serve`` binds by default."""

    @property
    def admin_token_file(self) -> Path:
        """Where a generated admin token is kept (mode 0600)."""
        return self.data_dir / "admin_token"

    @property
    def jobs_dir(self) -> Path:
        """Root of the job artifact folders."""
        return self.data_dir / "jobs"


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The settings of this process, read once from the environment."""
    return Settings()
