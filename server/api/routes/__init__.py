"""One APIRouter per resource: health, models (``/submit``, ``/models``), auctions, jobs."""
