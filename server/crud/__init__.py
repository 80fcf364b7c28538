"""Database reads and writes used by the services (keyword-only, no commits: the caller
commits), one module per resource; everything is exported here (``crud.get_auction``).

Reads that are polled or sit on a hot path are Core statements built once (no ORM identity
map, no object loading). Lists are newest first, in keyset pages on the id: ``before`` is the
last id of the previous page (the routes wrap it in an opaque cursor), so a page costs one
index range scan however deep it is, and rows added meanwhile never shift a page.
"""

from server.crud.auctions import (
    AnswerView,
    AuctionHead,
    AuctionSummary,
    AuctionView,
    RoundView,
    cancel_auction,
    create_auction,
    fine_tune_rounds,
    get_auction,
    list_auctions,
)
from server.crud.events import (
    AuctionRound,
    AuctionState,
    JobState,
    PatronRef,
    RoundPurchase,
    auction_rounds,
    auction_state,
    job_state,
)
from server.crud.jobs import (
    JobSummary,
    cancel_job,
    create_job,
    fail_unfinished,
    get_job,
    list_jobs,
)
from server.crud.models import (
    PARTICIPANT_TOKEN_PREFIX,
    ModelSummary,
    ParticipantRow,
    ParticipantView,
    StoredModel,
    get_model,
    get_model_view,
    get_models,
    get_participant,
    insert_model_versions,
    insert_participants,
    latest_accepted_models,
    latest_versions,
    list_models,
    participants_by_names,
    patron_auctions,
)
from server.crud.rounds import RoundBody, RoundHead, add_published_bytes, round_body, round_head
from server.crud.uploads import UploadKey, UploadLookupError, UploadTarget, upload_targets

__all__ = [
    "PARTICIPANT_TOKEN_PREFIX",
    "AnswerView",
    "AuctionHead",
    "AuctionRound",
    "AuctionState",
    "AuctionSummary",
    "AuctionView",
    "JobState",
    "JobSummary",
    "ModelSummary",
    "ParticipantRow",
    "ParticipantView",
    "PatronRef",
    "RoundBody",
    "RoundHead",
    "RoundPurchase",
    "RoundView",
    "StoredModel",
    "UploadKey",
    "UploadLookupError",
    "UploadTarget",
    "add_published_bytes",
    "auction_rounds",
    "auction_state",
    "cancel_auction",
    "cancel_job",
    "create_auction",
    "create_job",
    "fail_unfinished",
    "fine_tune_rounds",
    "get_auction",
    "get_job",
    "get_model",
    "get_model_view",
    "get_models",
    "get_participant",
    "insert_model_versions",
    "insert_participants",
    "job_state",
    "latest_accepted_models",
    "latest_versions",
    "list_auctions",
    "list_jobs",
    "list_models",
    "participants_by_names",
    "patron_auctions",
    "round_body",
    "round_head",
    "upload_targets",
]
