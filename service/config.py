"""Server settings, read from ``BUBSUB_*`` environment variables.

Every field of :class:`Settings` is one environment variable: the field name
in upper case with the prefix ``BUBSUB_`` (``job_ttl_seconds`` ->
``BUBSUB_JOB_TTL_SECONDS``). A ``.env`` file is not read; pass the variables
through the environment (or a docker-compose ``environment:`` block).
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["Settings", "get_settings"]

MiB = 1 << 20
GiB = 1 << 30


def _default_workers():
    return max(1, min(4, os.cpu_count() or 1))


class Settings(BaseSettings):
    """Projection server settings.

    Attributes
    ----------
    host, port : str, int
        Default bind address of ``bubsub serve``.
    workers : int
        Projections computed at the same time (threads of the compute pool).
    projector_threads : int or None
        Threads one projection may use inside the core projector (None: the
        core's default).
    blas_threads : int or None
        BLAS (OpenBLAS/MKL) threads of the server process (None: leave them).
        The server parallelises over requests and rays; idle BLAS threads that
        spin after each small matrix product would steal cores from the
        projections and from clients on the same machine.
    max_queue : int
        Compute requests that may wait for a free worker; beyond it the server
        answers 503 with ``Retry-After``.
    retry_after_seconds : int
        Value of the ``Retry-After`` header on 503.
    max_body_bytes : int
        Largest request body; larger bodies get 413 before they are read whole.
    job_max_bytes : int
        Memory cap of one job (its arrays: geometry, topology, subdivision
        matrices, data, background); over it: 413.
    max_memory_bytes : int
        Memory cap of all jobs together; over it: 507.
    max_jobs : int
        Jobs held at once; beyond it: 507.
    job_ttl_seconds : float
        A job unused this long is deleted.
    sweep_interval_seconds : float or None
        How often expired jobs are looked for (None: ``min(ttl / 4, 30)``).
    tokens : str
        Comma-separated bearer tokens; empty together with ``tokens_file``
        means no authentication.
    tokens_file : Path or None
        File with one bearer token per line (``#`` comments allowed).
    scan_dir : Path or None
        Directory from which jobs may load data files server-side.
    shutdown_grace_seconds : float
        After SIGTERM/SIGINT, ``/readyz`` reports not ready for this long while
        requests are still served; then the server drains and stops.
    shutdown_timeout_seconds : float
        ``bubsub serve`` waits this long for in-flight requests to finish
        before it cancels them.
    max_supersampling : int
        Largest ``supersampling`` a job may ask for.
    job_compute_max_bytes : int or None
        Memory one computation on a job may need (estimated before it runs);
        over it: 413. None: ``job_max_bytes``, so that a request's memory
        stays within the per-job cap (plus the constant of
        :data:`~bubsub.service.budget.OVERHEAD_BYTES`).
    max_compute_bytes : int
        Memory budget of all computations running at once (estimated per
        request before it runs, see :mod:`bubsub.service.budget`); a request
        that fits alone but not next to the running ones gets 503.
    crossings_per_ray : int
        Crossings a sub-ray is assumed to have with each surface whose
        bounding box it meets, in the compute memory estimate (2 for convex
        bubbles; more leaves room for non-convex ones).
    token_max_jobs, token_max_memory_bytes, token_max_computations : int or None
        Per-token quotas: jobs, bytes of jobs, computations admitted at once.
        None: the global cap (``max_jobs``, ``max_memory_bytes``, ``workers +
        max_queue``) when authentication is off or only one token exists,
        otherwise half of it.
    decode_workers, decode_queue : int
        Threads that decode request bodies (``.npy``, ``.npz``, multipart,
        JSON) off the event loop, and how many decodes may wait (then 503).
    max_json_bytes : int
        Largest JSON document (job metadata, file reference); larger: 413.
    max_connections : int
        Open connections at once, lowered at start to fit the file-descriptor
        limit (:func:`~bubsub.service.server.connection_limits`). A connection
        beyond it takes the place of the oldest one still waiting for its
        request head, or gets 503 when all are busy; requests at once are
        bounded a little lower (503 beyond), keeping connections for
        ``/healthz``, ``/readyz`` and ``/metrics``.
    backlog : int
        Pending connections the kernel queues (and asyncio accepts in one go);
        lowered to a third of the connections.
    header_timeout_seconds : float
        A connection must deliver a complete request head within this time
        (from connecting, or from the end of the previous response); else it
        is closed.
    body_timeout_seconds : float
        The whole request body must arrive within this time; else 408.
    keepalive_timeout_seconds : int
        An idle keep-alive connection is closed after this time.
    compute_timeout_seconds : float
        Longest a forward, vjp or objective may compute (a job may ask for
        less, never more); past it the projection stops between chunks of
        views and the request is answered 504.
    log_level : str
        ``critical``, ``error``, ``warning``, ``info`` or ``debug``.
    """

    model_config = SettingsConfigDict(env_prefix="BUBSUB_", extra="ignore", frozen=True)

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    workers: int = Field(default_factory=_default_workers, ge=1, le=256)
    projector_threads: int | None = Field(None, ge=1, le=1024)
    blas_threads: int | None = Field(1, ge=1, le=1024)
    max_queue: int = Field(16, ge=0)
    retry_after_seconds: int = Field(1, ge=0)
    max_body_bytes: int = Field(256 * MiB, ge=1024)
    job_max_bytes: int = Field(1 * GiB, ge=1024)
    max_memory_bytes: int = Field(4 * GiB, ge=1024)
    max_jobs: int = Field(1000, ge=1)
    job_ttl_seconds: float = Field(3600.0, gt=0)
    sweep_interval_seconds: float | None = Field(None, gt=0)
    tokens: str = Field("", repr=False)
    tokens_file: Path | None = None
    scan_dir: Path | None = None
    shutdown_grace_seconds: float = Field(0.0, ge=0)
    shutdown_timeout_seconds: float = Field(60.0, ge=0)
    max_supersampling: int = Field(8, ge=1, le=64)
    job_compute_max_bytes: int | None = Field(None, ge=1024)
    max_compute_bytes: int = Field(4 * GiB, ge=1024)
    crossings_per_ray: int = Field(2, ge=1, le=1024)
    token_max_jobs: int | None = Field(None, ge=1)
    token_max_memory_bytes: int | None = Field(None, ge=1024)
    token_max_computations: int | None = Field(None, ge=1)
    decode_workers: int = Field(2, ge=1, le=64)
    decode_queue: int = Field(32, ge=0)
    max_json_bytes: int = Field(8 * MiB, ge=1024)
    max_connections: int = Field(200, ge=1)
    backlog: int = Field(128, ge=1, le=65535)
    header_timeout_seconds: float = Field(10.0, gt=0)
    body_timeout_seconds: float = Field(120.0, gt=0)
    keepalive_timeout_seconds: int = Field(5, ge=1)
    compute_timeout_seconds: float = Field(120.0, gt=0)
    log_level: Literal["critical", "error", "warning", "info", "debug", "trace"] = "info"

    @field_validator("tokens_file", "scan_dir", "sweep_interval_seconds", "projector_threads", "blas_threads",
                     "token_max_jobs", "token_max_memory_bytes", "token_max_computations", "job_compute_max_bytes",
                     mode="before")
    @classmethod
    def _empty_is_none(cls, value):
        return None if isinstance(value, str) and not value.strip() else value

    @field_validator("log_level", mode="before")
    @classmethod
    def _lower(cls, value):
        return value.strip().lower() if isinstance(value, str) else value

    @property
    def sweep_interval(self) -> float:
        """Seconds between two looks for expired jobs."""
        if self.sweep_interval_seconds is not None:
            return self.sweep_interval_seconds
        return max(0.05, min(self.job_ttl_seconds / 4.0, 30.0))

    @property
    def compute_cap(self) -> int:
        """Largest estimated memory of one computation on a job (413 beyond)."""
        return self.job_compute_max_bytes or self.job_max_bytes

    def token_quotas(self, n_tokens):
        """``(jobs, bytes, computations)`` one token may hold, given ``n_tokens`` configured tokens."""
        share = 2 if n_tokens >= 2 else 1  # with several tokens none may take the whole server by default
        computations = self.workers + self.max_queue
        return (self.token_max_jobs or max(1, self.max_jobs // share),
                self.token_max_memory_bytes or self.max_memory_bytes // share,
                self.token_max_computations or max(1, computations // share))

    def load_tokens(self) -> tuple[str, ...]:
        """Bearer tokens from ``tokens`` and ``tokens_file`` (empty: no auth).

        Raises
        ------
        OSError
            If ``tokens_file`` is set but cannot be read.
        """
        found = [t.strip() for t in self.tokens.split(",") if t.strip()]
        if self.tokens_file is not None:
            for line in Path(self.tokens_file).read_text(encoding="utf-8").splitlines():
                line = line.strip()
                if line and not line.startswith("#"):
                    found.append(line)
        return tuple(dict.fromkeys(found))


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """Settings of this process, read once from the environment."""
    return Settings()
