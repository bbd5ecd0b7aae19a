"""Process-wide state of one server: settings, job store, pools, auth, metrics."""

from __future__ import annotations

from dataclasses import dataclass, field

from bubsub.service.auth import TokenAuth
from bubsub.service.budget import ComputeBudget
from bubsub.service.compute import ComputePool
from bubsub.service.config import Settings
from bubsub.service.metrics import RequestMetrics
from bubsub.service.store import JobStore

__all__ = ["ServiceState"]


@dataclass
class ServiceState:
    """Everything a request handler needs besides the request.

    Attributes
    ----------
    settings : Settings
    store : JobStore
    pool : ComputePool
        Projections (and other work on jobs).
    decoder : ComputePool
        Decoding of request bodies (``.npy``, ``.npz``, multipart, JSON), off the event loop.
    auth : TokenAuth
    requests : RequestMetrics
    ready : bool
        False before start-up has finished and from the moment shutdown begins.
    limits : ConnectionLimits or None
        Connection and request limits, derived from the descriptor limit when the app is made.
    """

    settings: Settings
    store: JobStore
    pool: ComputePool
    decoder: ComputePool
    auth: TokenAuth
    requests: RequestMetrics = field(default_factory=RequestMetrics)
    ready: bool = False
    limits: object = None

    @classmethod
    def from_settings(cls, settings):
        """Build the state; reads the token file (``OSError`` if it is unreadable)."""
        tokens = settings.load_tokens()
        jobs, nbytes, computations = settings.token_quotas(len(tokens))
        retry = settings.retry_after_seconds
        return cls(
            settings=settings,
            store=JobStore(settings.job_max_bytes, settings.max_memory_bytes, settings.max_jobs,
                           settings.job_ttl_seconds, token_max_jobs=jobs, token_max_bytes=nbytes),
            pool=ComputePool(settings.workers, settings.max_queue, retry, per_owner=computations,
                             budget=ComputeBudget(settings.max_compute_bytes, retry)),
            decoder=ComputePool(settings.decode_workers, settings.decode_queue, retry, name="decode"),
            auth=TokenAuth(tokens),
        )
