"""Service settings: environment variables ``BDF_*`` over a TOML file over the defaults.

The TOML file is named by ``BDF_CONFIG`` (or ``bdf serve --config``). Tokens map a secret
to its scopes, e.g. ``BDF_TOKENS='{"s3cret": ["read", "write"]}'`` or, in TOML::

    [tokens]
    s3cret = ["read", "write", "admin"]
"""

from __future__ import annotations

import ipaddress
import os
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

Scope = Literal["read", "write", "admin"]
#: a bearer token shorter than this is refused at startup (guessable)
MIN_TOKEN_CHARS = 16


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="BDF_", extra="forbid")

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    workers: int = Field(
        1, ge=1, le=64, description="uvicorn worker processes (SQLite: one host; PostgreSQL: across hosts)"
    )
    data_dir: Path = Field(Path("bdf-data"), description="where the default SQLite store lives")
    store_url: str | None = Field(
        None, description="sqlite:///dir or postgresql://...; default: SQLite in data_dir"
    )
    threads: int = Field(
        2, ge=1, le=256, description="light requests (region reads, small queries) at work at once per worker"
    )
    queue: int = Field(32, ge=0, le=10_000, description="light requests waiting for a thread (503 beyond)")
    heavy_threads: int = Field(
        1,
        ge=1,
        le=256,
        description="heavy requests (fits, large queries, grids and uploads) at work at once",
    )
    heavy_queue: int = Field(
        4, ge=0, le=10_000, description="heavy requests waiting for a thread (503 beyond)"
    )
    max_waiting: int = Field(
        64, ge=1, le=10_000, description="requests waiting for a map being computed (503 beyond)"
    )
    light_cost: int = Field(
        50_000,
        ge=0,
        description="points or voxels x the map's posteriors (1, or 2 + model_directions) a light "
        "request may ask",
    )
    light_body_mb: float = Field(1.0, ge=0, description="uploads with larger bodies are heavy")
    request_timeout_s: float = Field(
        30.0, gt=0, description="every request's deadline: 503 past it, and its work stops where it can"
    )
    request_memory_mb: float = Field(
        1024.0, gt=0, description="what one answer may take in memory, estimated before any work (422 above)"
    )
    map_memory_mb: float = Field(
        4096.0,
        gt=0,
        description="what computing one region's map may take (a spec needing more is refused, 422)",
    )
    store_timeout_s: float = Field(
        5.0, gt=0, description="longest wait for one database statement or lock (503 past it)"
    )
    ready_timeout_s: float = Field(2.0, gt=0, description="/readyz: longest wait for the store")
    max_connections: int = Field(
        1000,
        ge=1,
        description="open client connections per worker (beyond: the one waiting longest on its client goes)",
    )
    header_timeout_s: float = Field(
        10.0,
        gt=0,
        description="a request's line and headers must arrive within this (else the connection closes)",
    )
    keep_alive_s: float = Field(5.0, gt=0, description="an idle keep-alive connection closes after this")
    max_header_kb: float = Field(
        64.0, gt=0, description="a request's line and headers together (431 above, before they are parsed)"
    )
    max_headers: int = Field(100, ge=1, description="header fields per request (431 above)")
    cache_mb: float = Field(512.0, gt=0, description="memory for cached tile posteriors, per worker")
    viewer_basemap_url: str | None = Field(
        None,
        pattern=r"^https?://[^\s\"<>]+$",
        description="a MapLibre style URL drawn under the viewer's map (a basemap); none: the region's "
        "outline and a graticule on a plain background, nothing fetched from elsewhere",
    )
    tokens: dict[SecretStr, list[Scope]] = Field(default_factory=dict, description="bearer token -> scopes")
    max_body_mb: float = Field(256.0, gt=0, description="largest request body (413 above)")
    max_points: int = Field(2_000_000, ge=1, description="observations per upload or fit request")
    max_query_points: int = Field(200_000, ge=1, description="points per query request")
    max_decoded_mb: float = Field(
        256.0, gt=0, description="what an Arrow or Parquet body may decode into (413 above; checked first)"
    )
    max_json_mb: float = Field(16.0, gt=0, description="largest JSON body (413 above: send Arrow or Parquet)")
    max_grid_voxels: int = Field(4_000_000, ge=1, description="voxels per grid or tube request")
    max_json_voxels: int = Field(20_000, ge=1, description="voxels a JSON grid may hold (binary above)")
    fit_job_points: int = Field(100_000, ge=0, description="fits with more rows run as background jobs")
    fit_job_hinges: int = Field(
        20_000,
        ge=0,
        description="fits of regions with more hinges x traffic classes run as background jobs "
        "(their evidence search takes minutes whatever the rows)",
    )
    cors_origins: list[str] = Field(
        default_factory=list, description="origins whose browser pages may call the API (none: CORS off)"
    )
    log_level: str = "info"

    @classmethod
    def settings_customise_sources(
        cls, settings_cls, init_settings, env_settings, dotenv_settings, file_secret_settings
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        sources = [init_settings, env_settings]
        config = os.environ.get("BDF_CONFIG")
        if config:
            if not Path(config).is_file():
                raise ValueError(f"BDF_CONFIG names {config!r}, which is not a file")
            sources.append(TomlConfigSettingsSource(settings_cls, toml_file=config))
        return tuple(sources)

    @field_validator("tokens")
    @classmethod
    def _long_tokens(cls, tokens: dict[SecretStr, list[Scope]]) -> dict[SecretStr, list[Scope]]:
        short = sum(len(t.get_secret_value().strip()) < MIN_TOKEN_CHARS for t in tokens)
        if short:
            raise ValueError(
                f"{short} token(s) shorter than {MIN_TOKEN_CHARS} characters (or empty): a bearer token "
                "must not be guessable; make one with "
                "`python -c 'import secrets; print(secrets.token_urlsafe())'`"
            )
        return tokens

    @property
    def store(self) -> str:
        return self.store_url or f"sqlite:///{self.data_dir}"

    @property
    def open(self) -> bool:
        """No tokens: every request has every scope (local development only)."""
        return not self.tokens

    def check_bind(self) -> None:
        """Refuse to serve without tokens anywhere but on a loopback address."""
        if self.open and not is_loopback(self.host):
            raise ValueError(
                f"refusing to listen on {self.host!r} without tokens: configure BDF_TOKENS "
                "(or [tokens] in the config file), or bind to 127.0.0.1"
            )


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
