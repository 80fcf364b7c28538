"""kill -9 of the server in the middle of a remote fine-tuning round, then a restart: the round
resumes with the same absolute deadline and the answers given before the kill, the auction
finishes with contiguous iterations, no version or purchase twice, and the same records as the
market replaying the accepted versions."""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import func, select

from agents.manifest import parse_manifest
from agents.remote import RoundInfo, faithful_fine_tune
from server.db import Database
from server.launch import ServerProcess
from server.models import Auction, FineTuneAnswer, FineTuneRound, ModelVersion, Purchase
from sim.market import MarketConfig
from tests.support.factories import honest
from tests.support.processes import server_pair
from tests.support.remote import replay
from tests.support.server import wait_for

N_PATRONS = 6
HELD_OPEN_S = 120.0
"""The round's deadline: long enough that only the answers close it, before and after the kill."""
TIMEOUT_S = 120


def current(server: ServerProcess, auction_id: int, after: int) -> dict[str, Any]:
    return wait_for(
        lambda: httpx.get(
            f"{server.url}/auctions/{auction_id}/rounds/current",
            params={"wait": 5, "after": after},
            timeout=30,
        ).json(),
        lambda r: (
            (r["status"] == "open" and r["round"] > after)
            or r["auction_status"] not in ("pending", "running")
        ),
        TIMEOUT_S,
    )


@dataclass
class RemoteAuction:
    """A remote-mode auction of ``N_PATRONS`` honest patrons, uploading as their agents would."""

    auction_id: int
    ids: list[int]
    manifests: list[dict[str, Any]]
    tokens: list[str]

    @classmethod
    def create(cls, server: ServerProcess, admin: dict[str, str]) -> RemoteAuction:
        manifests = [
            honest(f"kill-{secrets.token_hex(3)}-{i}", seed=600 + i) for i in range(N_PATRONS)
        ]
        submitted = [
            httpx.post(server.url + "/submit", json=m, timeout=30).json() for m in manifests
        ]
        ids = [s["model_id"] for s in submitted]
        body = {
            "n_fish": 1,
            "model_ids": ids,
            "fine_tune_mode": "remote",
            "fine_tune_rounds": 2,
            "round_deadline_s": HELD_OPEN_S,
            "seed": 3,
        }
        created = httpx.post(server.url + "/auctions", json=body, headers=admin, timeout=30)
        tokens = [s["token"] for s in submitted]
        return cls(created.json()["auction_id"], ids, manifests, tokens)

    def upload(self, server: ServerProcess, state: dict[str, Any], model_id: int) -> httpx.Response:
        """The patron's faithful fine-tuning of the open round ``state``, uploaded."""
        position = self.ids.index(model_id)
        tuned = faithful_fine_tune(
            parse_manifest(self.manifests[position]), RoundInfo.from_state(state, position)
        )
        return httpx.put(
            f"{server.url}/auctions/{self.auction_id}/rounds/{state['round']}/models/{model_id}",
            content=tuned.model_dump_json().encode(),
            headers={
                "Authorization": f"Bearer {self.tokens[position]}",
                "Content-Type": "application/json",
            },
            timeout=30,
        )


def check_rows_at_kill(database: Database, auction_id: int) -> None:
    """What the killed server left: the round open with its 2 answers, the auction running."""
    with database.session(write=False) as session:
        round_row = session.scalars(
            select(FineTuneRound).where(FineTuneRound.auction_id == auction_id)
        ).one()
        answered = session.scalar(
            select(func.count()).where(FineTuneAnswer.round_id == round_row.id)
        )
        at_kill = session.scalars(select(Auction).where(Auction.id == auction_id)).one()
    assert round_row.status == "open" and answered == 2
    assert at_kill.status == "running" and at_kill.iteration == 1


def check_stored_once(database: Database, auction: dict[str, Any]) -> None:
    """Each upload stored as one version (the retry included), each purchase once."""
    uploads = sum(
        a["uploaded_id"] is not None for r in auction["fine_tuning"] for a in r["answers"]
    )
    with database.session(write=False) as session:
        versions = session.scalar(
            select(func.count()).where(ModelVersion.auction_id == auction["id"])
        )
        purchases = session.scalar(select(func.count()).where(Purchase.auction_id == auction["id"]))
    assert versions == uploads
    assert purchases == len(auction["buyers"])
    assert len({b["model_id"] for b in auction["buyers"]}) == len(auction["buyers"])


def test_kill_9_in_the_middle_of_a_round_then_restart(
    fresh_database_url: str, tmp_path: Path
) -> None:
    (first, second), admin = server_pair(fresh_database_url, tmp_path)
    try:
        first.start()
        remote = RemoteAuction.create(first, admin)
        auction_id = remote.auction_id
        state = current(first, auction_id, after=0)
        assert state["round"] == 1 and state["status"] == "open"
        asked = [i for i in remote.ids if i in state["asked"]]
        assert len(asked) >= 3
        before = {i: remote.upload(first, state, i) for i in asked[:2]}
        assert all(r.status_code == 200 for r in before.values()), [r.text for r in before.values()]
        first.kill()  # the round is open, its other patrons have not answered
        database = Database(fresh_database_url)
        check_rows_at_kill(database, auction_id)

        second.start()
        resumed = current(second, auction_id, after=0)
        assert resumed["round"] == 1 and resumed["status"] == "open"
        assert resumed["deadline"] == state["deadline"]  # the same absolute deadline
        assert resumed["rows"] == state["rows"] and resumed["asked"] == state["asked"]
        again = remote.upload(second, resumed, asked[0])  # a retry after the crash: same answer
        assert again.status_code == 200 and again.content == before[asked[0]].content
        for model_id in asked[2:]:
            assert remote.upload(second, resumed, model_id).status_code == 200
        nxt = current(second, auction_id, after=1)  # closed at its last answer
        assert nxt["round"] == 2 and nxt["status"] == "open"
        for model_id in nxt["asked"]:
            assert remote.upload(second, nxt, model_id).status_code == 200
        auction = wait_for(
            lambda: httpx.get(f"{second.url}/auctions/{auction_id}", timeout=30).json(),
            lambda a: a["status"] in ("finished", "failed"),
            TIMEOUT_S,
        )
        assert auction["status"] == "finished", auction["error"]
        history = auction["history"]
        assert [row["iteration"] for row in history] == list(range(len(history)))
        first_round = auction["fine_tuning"][0]
        assert sorted(a["model_id"] for a in first_round["answers"]) == sorted(asked)
        assert all(a["outcome"] in ("accepted", "refused") for a in first_round["answers"])
        config = MarketConfig(
            n_fish=1, fine_tune=True, fine_tune_rounds=2, seed=3, fine_tune_mode="remote"
        )
        assert replay(second, auction, config) == history
        check_stored_once(database, auction)
        database.close()
    finally:
        first.kill()
        second.stop()
