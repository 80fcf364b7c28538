"""Background experiments (``POST /jobs``): the backend interface and the local backend."""

from server.jobs.backend import JobBackend, requeue_unfinished
from server.jobs.local import LocalJobBackend

__all__ = ["JobBackend", "LocalJobBackend", "requeue_unfinished"]
