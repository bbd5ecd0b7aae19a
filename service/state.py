"""Process-wide state of one server: settings, job store, compute pool, auth, metrics."""

from __future__ import annotations

from dataclasses import dataclass, field

from .auth import TokenAuth
from .compute import ComputePool
from .config import Settings
from .metrics import RequestMetrics
from .store import JobStore

__all__ = ["ServiceState"]


@dataclass
class ServiceState:
    """Everything a request handler needs besides the request.

    Attributes
    ----------
    settings : Settings
    store : JobStore
    pool : ComputePool
    auth : TokenAuth
    requests : RequestMetrics
    ready : bool
        False before start-up has finished and from the moment shutdown begins.
    """

    settings: Settings
    store: JobStore
    pool: ComputePool
    auth: TokenAuth
    requests: RequestMetrics = field(default_factory=RequestMetrics)
    ready: bool = False

    @classmethod
    def from_settings(cls, settings):
        """Build the state; reads the token file (``OSError`` if it is unreadable)."""
        return cls(
            settings=settings,
            store=JobStore(settings.job_max_bytes, settings.max_memory_bytes, settings.max_jobs,
                           settings.job_ttl_seconds),
            pool=ComputePool(settings.workers, settings.max_queue, settings.retry_after_seconds),
            auth=TokenAuth(settings.load_tokens()),
        )
