"""In-memory job store with memory caps and idle expiry.

Jobs live in the server process. The store is used from the event loop only
(routes), so its dictionary needs no lock; compute threads touch only the
:class:`~bubsub.service.jobs.Job` objects themselves.
"""

from __future__ import annotations

import secrets
import time

from bubsub.service.errors import APIError

__all__ = ["JobStore"]


def _unknown(job_id):
    return APIError(404, f"unknown job {job_id!r} (it never existed, expired, was deleted, or belongs "
                         f"to another token); create it again", "unknown_job")


class JobStore:
    """Jobs by id, with per-job, per-owner and total memory caps.

    Parameters
    ----------
    job_max_bytes : int
        Cap of one job (413 beyond it).
    max_memory_bytes : int
        Cap of all jobs together (507 beyond it).
    max_jobs : int
        Most jobs at once (507 beyond it).
    ttl : float
        Seconds a job may stay unused before :meth:`expire` removes it.
    token_max_jobs, token_max_bytes : int, optional
        Jobs and bytes one owner (token) may hold (507 beyond them); default:
        the global caps.
    """

    def __init__(self, job_max_bytes, max_memory_bytes, max_jobs, ttl, token_max_jobs=None, token_max_bytes=None):
        self.job_max_bytes = int(job_max_bytes)
        self.max_memory_bytes = int(max_memory_bytes)
        self.max_jobs = int(max_jobs)
        self.token_max_jobs = int(token_max_jobs or max_jobs)
        self.token_max_bytes = int(token_max_bytes or max_memory_bytes)
        self.ttl = float(ttl)
        self._jobs = {}
        self.created_total = 0
        self.deleted_total = 0
        self.expired_total = 0

    # -- accounting ----------------------------------------------------------------
    def __len__(self):
        return len(self._jobs)

    @property
    def memory_bytes(self):
        """Bytes held by all jobs' arrays."""
        return sum(job.nbytes() for job in self._jobs.values())

    def owner_bytes(self, owner):
        """Bytes held by the jobs of ``owner``."""
        return sum(job.nbytes() for job in self.owned(owner))

    def admit(self, new_bytes, replacing=0, owner=None):
        """Check that a job of ``new_bytes`` (replacing one of ``replacing``) fits the caps.

        Raises
        ------
        APIError
            413 over the per-job cap; 507 over the owner's quota or the server-wide cap.
        """
        if new_bytes > self.job_max_bytes:
            raise APIError(413, f"the job would hold {new_bytes} bytes, over the per-job cap of "
                                f"{self.job_max_bytes} bytes (BUBSUB_JOB_MAX_BYTES) by "
                                f"{new_bytes - self.job_max_bytes} bytes", "job_too_large")
        total = self.memory_bytes - replacing + new_bytes
        if total > self.max_memory_bytes:
            raise APIError(507, f"the server holds {self.memory_bytes} bytes of jobs; {new_bytes - replacing} "
                                f"more would pass its cap of {self.max_memory_bytes} bytes "
                                f"(BUBSUB_MAX_MEMORY_BYTES); delete jobs or retry later", "server_full")
        if owner is not None:
            mine = self.owner_bytes(owner) - replacing + new_bytes
            if mine > self.token_max_bytes:
                raise APIError(507, f"this token's jobs would hold {mine} bytes, over its quota of "
                                    f"{self.token_max_bytes} bytes (BUBSUB_TOKEN_MAX_MEMORY_BYTES) by "
                                    f"{mine - self.token_max_bytes} bytes; delete jobs", "token_quota")

    # -- jobs ----------------------------------------------------------------------
    @staticmethod
    def new_id():
        """An unguessable job id."""
        return secrets.token_urlsafe(18)

    def add(self, job):
        """Store ``job`` after checking the caps."""
        mine = len(self.owned(job.owner))
        if mine >= self.token_max_jobs:
            raise APIError(507, f"this token holds {mine} jobs, its quota (BUBSUB_TOKEN_MAX_JOBS); delete jobs",
                           "token_quota")
        if len(self._jobs) >= self.max_jobs:
            raise APIError(507, f"the server holds its maximum of {self.max_jobs} jobs (BUBSUB_MAX_JOBS); "
                                f"delete jobs or retry later", "server_full")
        self.admit(job.nbytes(), owner=job.owner)
        self._jobs[job.id] = job
        self.created_total += 1
        return job

    def get(self, job_id, owner):
        """The job ``job_id`` of ``owner``; 404 for unknown, expired or foreign jobs."""
        job = self._jobs.get(job_id)
        if job is None or not secrets.compare_digest(job.owner, owner):
            raise _unknown(job_id)
        if job.active == 0 and time.monotonic() - job.last_used > self.ttl:
            self._remove(job_id)
            self.expired_total += 1
            raise _unknown(job_id)
        job.touch()
        return job

    def owned(self, owner):
        """Jobs of ``owner``, oldest first."""
        return [j for j in self._jobs.values() if secrets.compare_digest(j.owner, owner)]

    def delete(self, job_id, owner):
        """Remove a job of ``owner`` (404 if it is not theirs)."""
        self.get(job_id, owner)
        self._remove(job_id)
        self.deleted_total += 1

    def expire(self, now=None):
        """Remove jobs idle for longer than the TTL; returns how many."""
        now = time.monotonic() if now is None else now
        old = [k for k, j in self._jobs.items() if j.active == 0 and now - j.last_used > self.ttl]
        for k in old:
            self._remove(k)
        self.expired_total += len(old)
        return len(old)

    def clear(self):
        """Drop every job (shutdown)."""
        self._jobs.clear()

    def _remove(self, job_id):
        self._jobs.pop(job_id, None)
