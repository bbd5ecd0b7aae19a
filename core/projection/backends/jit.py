"""numba compilation with an on-disk cache where one can be written."""

from __future__ import annotations

__all__ = ["cached"]


def cached(decorator, **options):
    """``decorator(cache=True, **options)``, or without the cache where numba has nowhere to write it.

    numba refuses ``cache=True`` when neither the source folder nor a user
    cache folder is writable (a read-only install); compiling in memory then
    costs a few seconds per process instead of failing.
    """

    def wrap(fn):
        try:
            return decorator(cache=True, **options)(fn)
        except RuntimeError as exc:
            if "cannot cache" not in str(exc):
                raise
            return decorator(**options)(fn)

    return wrap
