"""Remote agents: participants that take part in auctions over HTTP and fine-tune their own Fish
Sale Negotiator in each remote fine-tuning round (paper, "Implicit augmentation": only the item
rows travel; the agent's own model makes the D_ic noisy copies).

``RemoteAgent`` is the Python API for one participant with one model: ``submit`` it, find or
join an auction, ``play`` it to the end. In each round the agent receives the round (a long poll,
or pushed on its round socket with ``transport="websocket"``), runs its
``fine_tuner`` (any code: ``(current manifest, RoundInfo) -> fine-tuned manifest``) and uploads
the result with its token. ``faithful_fine_tune`` is what the server itself would do
(``agents.fine_tuning.fine_tune_round`` on the agent's model alone, with the round's seeds and the
patron's position), so a population of faithful agents replays the in-process auction.
``always_hold`` is the bait-and-switch of a saboteur: always-hold weights on the model it was
admitted with.

``run_population`` drives many agents from one asyncio loop (``srd agents``): honest agents
from the paper's randomisation, saboteurs that submit an honest-looking model and then upload
``always_hold``. Every request retries with exponential backoff on connection errors, 429 and
503 (honouring Retry-After) until ``give_up_s`` has passed, then ``ServerGoneError`` names the
server. Bytes of request and response bodies are counted, as the server counts them.

Modules, one job each:

* ``client``: ``Client``, JSON over HTTP with retries and byte counting;
* ``fine_tuners``: ``RoundInfo`` and the fine-tuners ``faithful_fine_tune`` and ``always_hold``;
* ``socket``: ``RoundSocket``, one agent's WebSocket to an auction's rounds;
* ``agent``: ``RemoteAgent``, one participant's protocol (submit, find, play);
* ``population``: ``PopulationConfig`` and ``run_population``, many agents at once.
"""

from __future__ import annotations

from agents.remote.agent import (
    ROUND_WAIT_S,
    TRANSPORTS,
    RemoteAgent,
    RoundLog,
    Transport,
    Uploads,
)
from agents.remote.client import (
    GIVE_UP_S,
    HTTP_TIMEOUT_S,
    ONE_CONNECTION,
    Client,
    RemoteError,
    ServerGoneError,
    Traffic,
)
from agents.remote.fine_tuners import FineTuner, RoundInfo, always_hold, faithful_fine_tune
from agents.remote.population import (
    AUCTION_WAIT_S,
    MAX_AGENTS,
    PopulationConfig,
    PopulationReport,
    Progress,
    SoFar,
    population,
    run_population,
)
from agents.remote.socket import RoundSocket, socket_url

__all__ = [
    "AUCTION_WAIT_S",
    "GIVE_UP_S",
    "HTTP_TIMEOUT_S",
    "MAX_AGENTS",
    "ONE_CONNECTION",
    "ROUND_WAIT_S",
    "TRANSPORTS",
    "Client",
    "FineTuner",
    "PopulationConfig",
    "PopulationReport",
    "Progress",
    "RemoteAgent",
    "RemoteError",
    "RoundInfo",
    "RoundLog",
    "RoundSocket",
    "ServerGoneError",
    "SoFar",
    "Traffic",
    "Transport",
    "Uploads",
    "always_hold",
    "faithful_fine_tune",
    "population",
    "run_population",
    "socket_url",
]
