"""The API's side of remote fine-tuning rounds, one module per job: ``watcher`` (the long
polls of ``GET /auctions/{id}/rounds/current``), ``sockets`` (the same rounds and uploads over
one WebSocket per agent), ``lookup`` (what an upload is checked
against) and ``writer`` (uploads stored in group commits, by the screening process, and the
published-bytes counters).
The worker opens and closes the rounds itself (``server.auctions``)."""

from server.remote_rounds.lookup import UploadLookup
from server.remote_rounds.sockets import RoundSockets, SocketLimitError
from server.remote_rounds.watcher import (
    MAX_WAIT_S,
    Published,
    RoundWatcher,
    TooManyWaitersError,
)
from server.remote_rounds.writer import (
    Answered,
    PublishedBytes,
    UploadOutcome,
    UploadRefused,
    UploadRequest,
    UploadWriter,
    answer_bytes,
)

__all__ = [
    "MAX_WAIT_S",
    "Answered",
    "Published",
    "PublishedBytes",
    "RoundSockets",
    "RoundWatcher",
    "SocketLimitError",
    "TooManyWaitersError",
    "UploadLookup",
    "UploadOutcome",
    "UploadRefused",
    "UploadRequest",
    "UploadWriter",
    "answer_bytes",
]
