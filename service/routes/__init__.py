"""HTTP routes, one module per resource."""

from bubsub.service.routes import compute, data, health, jobs, metrics

__all__ = ["compute", "data", "health", "jobs", "metrics", "ROUTERS"]

#: every router of the service, in the order they appear in the docs
ROUTERS = (health.router, metrics.router, jobs.router, data.router, compute.router)
