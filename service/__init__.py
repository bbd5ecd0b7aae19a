"""bubsub.service: HTTP projection server (FastAPI).

Start it with ``bubsub serve`` or ``uvicorn bubsub.service.app:app``; see
``docs/service.md``. Importing this package imports nothing heavy: the
application lives in :mod:`bubsub.service.app`.
"""
