"""The API's side of remote fine-tuning rounds: ``watcher`` (the long polls of
``GET /auctions/{id}/rounds/current``) and ``sockets`` (the same rounds and uploads over one
WebSocket per agent). Uploads are checked and stored by ``server.services.rounds``; the
auction's steps open and close the rounds (``server.auctions``)."""

from server.remote_rounds.sockets import RoundSockets, SocketLimitError
from server.remote_rounds.watcher import (
    MAX_WAIT_S,
    Published,
    RoundWatcher,
    TooManyWaitersError,
)

__all__ = [
    "MAX_WAIT_S",
    "Published",
    "RoundSockets",
    "RoundWatcher",
    "SocketLimitError",
    "TooManyWaitersError",
]
