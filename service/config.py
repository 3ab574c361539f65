"""The service's one settings object: every knob, read from LEARNEST_* environment variables (or a
``.env`` file) and validated once, at start.  Nothing else in learnest reads the environment.

    LEARNEST_HOME               folder of the SQLite database and the blobs (default ./.learnest)
    LEARNEST_DATABASE_URL       PostgreSQL (or any SQLAlchemy URL) instead of the SQLite file
    LEARNEST_API_KEY            an admin token kept outside the registry (the tokens of people:
                                `learnest tokens create`); once it or any token exists, every route but
                                /health needs a token (service.api.access)
    LEARNEST_PUBLIC_READS       1: reads need no token, on purpose (writes and deletes still do)
    LEARNEST_SESSION_HOURS      a web sign-in lasts this long (default 12)
    LEARNEST_ALLOWED_HOSTS      host names the server answers to, comma-separated (default the loopback
                                names; add the machine's name or address to serve a network; * = any)
    LEARNEST_MAX_UPLOAD_MB      upload size limit (default 200)
    LEARNEST_SCHEDULE_SECONDS   evaluate new flights with the aliased model on this interval (0 = off)
    LEARNEST_SCHEDULE_ALIAS     ... with the version holding this alias (default production)
    LEARNEST_SCHEDULE_METHODS   ... and these estimators (default all four)
    LEARNEST_DASK               address of a Dask scheduler (default: a local process pool)
    LEARNEST_POOL_WORKERS       local pool size (default min(2, cores))
    LEARNEST_GIT_COMMIT         code version recorded in the registry when the install has no git
    LEARNEST_MAX_EPOCHS         training / diagnosis epochs a request may ask for (default 5000)
    LEARNEST_MAX_HIDDEN         hidden units per layer a training request may ask for (default 256)
    LEARNEST_MAX_TRAINING_WORK  epochs x flight samples x hidden units of one training (default 2e9;
                                not calibrated to a wall time); 0 = no limit
    LEARNEST_CANCEL_GRACE_S     seconds a cancelled job's running task gets to stop itself before its
                                worker is killed (default 10)
    LEARNEST_JOB_STALL_S        a running job that wrote no progress for this long is failed and its worker
                                killed (default 21600, 6 h; 0 = never)
    LEARNEST_EXPORT_BUDGET_MB   disk the estimate exports may take, kept and being written (default 2048);
                                beyond it the least recently served go, and an export that does not fit is
                                refused with 507 (service.storage.export_cache)
    LEARNEST_MAX_QUEUED_JOBS    jobs waiting to start beyond which a new one is refused with 503 (default 64;
                                0 = no limit)
  uploads are decoded in their own worker processes (service.jobs.decoding):
    LEARNEST_DECODE_WORKERS     uploads decoded at once (default 2)
    LEARNEST_DECODE_QUEUE       uploads that may wait for a decode worker; more get 503 (default 16)
    LEARNEST_DECODE_TIMEOUT_S   one upload's decode time limit; past it the upload is refused (default 60)
  connections (service.api.server; `learnest serve` options of the same names):
    LEARNEST_HEADER_TIMEOUT_S   a request's headers must arrive within this (default 10)
    LEARNEST_BODY_TIMEOUT_S     a body gets this many seconds ... (default 30)
    LEARNEST_BODY_MIN_RATE      ... plus one per this many bytes received (default 10000 B/s); else 408
    LEARNEST_BODY_MAX_S         ... and never more than this in all (default 900)
    LEARNEST_KEEP_ALIVE_S       an idle keep-alive connection is closed after this (default 5)
    LEARNEST_LIMIT_CONCURRENCY  connections + requests in progress beyond which uvicorn answers 503
                                (default 200; 0 = no limit)
    LEARNEST_MAX_CLIENT_CONNECTIONS  open connections from one client network (an IPv4 /24, an IPv6 /64)
                                beyond which a new one gets 503 (default 32; 0 = no limit; proxies exempt)
    LEARNEST_MAX_HEADER_BYTES   request line + headers (default 16384)
    LEARNEST_GRACEFUL_SHUTDOWN_S  requests in progress get this long to finish on SIGTERM (default 10)
    LEARNEST_SEND_TIMEOUT_S     a client that takes no byte of an answer for this long is dropped (default 60)
    LEARNEST_KEY_FAILURES       failed API-key attempts from one address within ...
    LEARNEST_KEY_FAILURE_WINDOW_S  ... this many seconds after which it gets 429 (defaults 10, 60; 0 = off)
    LEARNEST_TRUSTED_PROXIES    addresses of reverse proxies whose X-Forwarded-For / X-Forwarded-Proto name
                                the client, comma-separated (default none: the headers are ignored and the
                                client is the connection's peer, as the key throttle counts it)
"""
from __future__ import annotations

import os
from pathlib import Path

from pydantic import AliasChoices, Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from learnest.models.presets import METHODS, PRODUCTION_ALIAS, parse_methods

DEFAULT_METHODS = ",".join(METHODS)


class Settings(BaseSettings):
    """Every knob of the service; ``Settings()`` reads the environment, keyword arguments override it."""

    model_config = SettingsConfigDict(env_prefix="LEARNEST_", env_file=".env", extra="ignore", frozen=True,
                                      populate_by_name=True)

    home: Path = Path(".learnest")
    database_url: str | None = None          # None: SQLite file home/learnest.db
    max_upload_mb: float = Field(200.0, gt=0)
    api_key: str | None = None               # an admin token (None: only the registry's tokens)
    public_reads: bool = False               # reads open to anyone on the allowed hosts, on purpose
    session_hours: float = Field(12.0, gt=0)  # a web sign-in's life
    allowed_hosts: str = "localhost,127.0.0.1,::1"   # Host header names served (DNS rebinding): comma list
    schedule_seconds: float = Field(0.0, ge=0)   # 0: scheduler off
    schedule_alias: str = PRODUCTION_ALIAS
    schedule_methods: str = DEFAULT_METHODS
    dask_address: str | None = Field(None, validation_alias=AliasChoices("dask_address", "LEARNEST_DASK"))
    pool_workers: int = Field(default_factory=lambda: max(1, min(2, os.cpu_count() or 1)), ge=1)
    git_commit: str | None = None
    # quotas: a request past one is a 422 naming it (service.jobs.quotas)
    max_epochs: int = Field(5000, ge=1)
    max_hidden: int = Field(256, ge=1)
    max_training_work: float = Field(2e9, ge=0)   # epochs x samples x hidden; 0: no limit
    cancel_grace_s: float = Field(10.0, ge=0)
    job_stall_s: float = Field(6 * 3600.0, ge=0)   # 0: never fail a job for making no progress
    export_budget_mb: float = Field(2048.0, gt=0)   # estimate exports on disk, cached and being written
    max_queued_jobs: int = Field(64, ge=0)          # 0: no limit (service.jobs.runner)
    # uploads: decoded in worker processes, bounded in number, waiting room and time (service.jobs.decoding)
    decode_workers: int = Field(2, ge=1)
    decode_queue: int = Field(16, ge=0)
    decode_timeout_s: float = Field(60.0, gt=0)
    # connections (service.api.server)
    header_timeout_s: float = Field(10.0, gt=0)
    body_timeout_s: float = Field(30.0, gt=0)
    body_min_rate: float = Field(10_000.0, gt=0)   # bytes/s
    body_max_s: float = Field(900.0, gt=0)          # the body's ceiling, however fast its bytes came
    keep_alive_s: float = Field(5.0, gt=0)
    limit_concurrency: int = Field(200, ge=0)       # 0: no limit
    max_client_connections: int = Field(32, ge=0)   # per client network; 0: no limit
    max_header_bytes: int = Field(16_384, ge=1024)
    graceful_shutdown_s: float = Field(10.0, ge=0)
    send_timeout_s: float = Field(60.0, gt=0)
    key_failures: int = Field(10, ge=0)             # 0: no throttling
    key_failure_window_s: float = Field(60.0, gt=0)
    trusted_proxies: str = ""                       # "": no proxy headers are believed

    @property
    def trusted_proxy_addresses(self) -> tuple[str, ...]:
        """`trusted_proxies` as a tuple of addresses (empty: proxy headers off)."""
        return tuple(a.strip() for a in self.trusted_proxies.split(",") if a.strip())

    @field_validator("database_url", "api_key", "dask_address", "git_commit", mode="before")
    @classmethod
    def _empty_is_unset(cls, value):
        return None if isinstance(value, str) and not value.strip() else value

    @field_validator("schedule_methods")
    @classmethod
    def _known_methods(cls, value: str) -> str:
        return ",".join(parse_methods(value))  # names the unknown ones

    @property
    def allowed_host_names(self) -> tuple[str, ...]:
        """`allowed_hosts` as a tuple of lower-case names."""
        return tuple(name.strip().lower() for name in self.allowed_hosts.split(",") if name.strip())

    @property
    def url(self) -> str:
        """The SQLAlchemy URL: ``database_url``, else the SQLite file ``home/learnest.db``."""
        return self.database_url or f"sqlite:///{(self.home / 'learnest.db').resolve()}"

    @property
    def export_budget_bytes(self) -> int:
        """``export_budget_mb`` in bytes (MiB, 1024²)."""
        return int(self.export_budget_mb * 1024 * 1024)

    @property
    def max_upload_bytes(self) -> int:
        """``max_upload_mb`` in bytes (MiB, 1024²)."""
        return int(self.max_upload_mb * 1024 * 1024)
