"""The remote fitting jobs of one reconstruction: made on a projector server, deleted when it ends.

>>> with remote_projectors("http://127.0.0.1:8000") as factory:      # doctest: +SKIP
...     rec = reconstruct(scan, settings, projector_factory=factory)

``bubsub reconstruct --server`` and each slab of a scan reconstructed in slabs
(:func:`bubsub.clients.pipeline.regions.slabs.run_slab`) run their fit this way: the
jobs hold the server's memory until they expire, so they are deleted as soon as
the reconstruction ends, also when it ends with an error or Ctrl-C.
"""

from __future__ import annotations

from contextlib import contextmanager

__all__ = ["remote_projectors"]


@contextmanager
def remote_projectors(server, token=None, *, supersampling=1, on_cleanup_error=None):
    """A projector factory that fits against ``server``, its jobs deleted and connection closed on exit.

    Parameters
    ----------
    server : str or None
        URL of a ``bubsub serve`` projector server; None yields None (every projection local).
    token : str, optional
        Its bearer token.
    supersampling : int
        Rays per pixel and axis of every job.
    on_cleanup_error : callable(Exception), optional
        Told about a job that could not be deleted (the reconstruction's result matters more than the
        server's clean-up, so it is not raised); None: such an error is ignored.

    Yields
    ------
    callable(geometry, data, surfaces) -> RemoteJob, or None
        :func:`~bubsub.clients.pipeline.reconstruct.reconstruct`'s ``projector_factory``: each call creates a
        job holding ``data`` (``geometry.shape``) and the surfaces' topology.

    Raises
    ------
    ValueError
        When the server does not answer or refuses the token (:func:`~bubsub.clients.remote.client.connect`),
        before anything is computed.
    """
    if server is None:
        yield None
        return
    from bubsub.clients.remote.client import connect  # the 'client' extra (httpx): only with a server

    http = connect(server, token)  # the projector server's HTTP client
    jobs = []

    def factory(geometry, data, surfaces):
        job = http.create_job(geometry, data=data, surfaces=surfaces, supersampling=supersampling)
        jobs.append(job)
        return job

    try:
        yield factory
    finally:  # also on errors and KeyboardInterrupt: free the server's memory now rather than at expiry
        for job in jobs:
            try:
                job.delete()
            except Exception as exc:  # noqa: BLE001 - the result matters more than the clean-up
                if on_cleanup_error is not None:
                    on_cleanup_error(exc)
        http.close()
