"""bubsub.clients: the BFGS optimiser, the reconstruction pipeline, the HTTP client and the CLI.

``fit(projector_or_job, surfaces, data)`` runs locally against a
:class:`bubsub.core.MeshProjector` or remotely against a :class:`RemoteJob`
of a projector server; the rest of the pipeline does not know the difference.
The HTTP client needs ``httpx`` (the ``client`` extra) and is imported lazily;
so is the optimiser (scipy), so that ``bubsub --help`` and refused arguments
answer within a second or two.
"""

__all__ = ["version", "fit", "estimate_radii", "FitResult", "ProjectorClient", "RemoteJob", "RemoteError",
           "RemoteValueError", "UnknownJobError"]


def version():
    """The installed bubsub version (``"unknown"`` for a source tree that is not installed)."""
    from importlib.metadata import PackageNotFoundError, version as dist_version

    try:
        return dist_version("bubsub")
    except PackageNotFoundError:  # pragma: no cover - an uninstalled source tree
        return "unknown"


def __getattr__(name):
    if name in ("fit", "estimate_radii", "FitResult"):
        from bubsub.clients.optimise import fit as module

        return getattr(module, name)
    # httpx is optional: import the client only when it is used
    if name in ("ProjectorClient", "RemoteJob", "RemoteError", "RemoteValueError", "UnknownJobError"):
        from bubsub.clients.remote import client

        return getattr(client, name)
    raise AttributeError(f"module 'bubsub.clients' has no attribute {name!r}")
