"""The participant's library (``agents.remote.RemoteAgent``) against a real server: an agent
resumed with its token and model id fine-tunes the version the server lets it bid with, and a
slow fine-tuner holds no other agent of its event loop."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from agents.manifest import Manifest, parse_manifest
from agents.remote import Client, RemoteAgent, RoundInfo, faithful_fine_tune
from server.cli.launch import ServerProcess
from tests.support.remote import honest_remote_auction, next_round, stored_manifest
from tests.support.server import module_server

SEEDS = (4, 2, 5)
"""Honest models that fine-tune (epochs > 0) and that the screener accepts; with the auction's
seed ``AUCTION_SEED``, the first is asked in rounds 1 and 2."""
AUCTION_SEED = 0


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    yield from module_server(tmp_path_factory, "remote-agent")


def auction_of_seeds(
    server: ServerProcess, *, name: str, rounds: int, deadline_s: float
) -> tuple[int, list[Any]]:
    """A remote auction of the ``SEEDS`` models, one fish, seeded ``AUCTION_SEED``."""
    return honest_remote_auction(
        server, SEEDS, name=name, n_fish=1, fine_tune_rounds=rounds,
        round_deadline_s=deadline_s, seed=AUCTION_SEED,
    )  # fmt: skip


def upload(server: ServerProcess, state: dict[str, Any], position: int, entry: Any) -> Any:
    model_id, token, manifest = entry
    tuned = faithful_fine_tune(parse_manifest(manifest), RoundInfo.from_state(state, position))
    answer = httpx.put(
        f"{server.url}/auctions/{state['auction_id']}/rounds/{state['round']}/models/{model_id}",
        content=tuned.model_dump_json(),
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
        timeout=60,
    )
    assert answer.status_code == 200, answer.text
    return answer.json()


def test_a_resumed_agent_fine_tunes_the_version_the_server_holds(server: ServerProcess) -> None:
    """Round 1 answered by hand (the first run of the agent); the agent then resumes with its
    token, its model id and its first manifest: its round-2 upload is the faithful fine-tuning
    of version 2, the version the server lets it bid with. Before, it fine-tuned version 1
    again (and was accepted: silently not faithful)."""
    auction_id, entered = auction_of_seeds(server, name="agent", rounds=3, deadline_s=60)
    first = next_round(server, auction_id, 0, 120)
    assert first["status"] == "open" and first["round"] == 1
    asked = [(p, e) for p, e in enumerate(entered) if e[0] in first["asked"]]
    answers = [upload(server, first, p, e) for p, e in asked]
    assert asked[0][0] == 0
    assert answers[0]["accepted"] and answers[0]["version"] == 2
    second = next_round(server, auction_id, 1, 120)
    assert second["status"] == "open" and entered[0][0] in second["asked"], second
    model_id, token, manifest = entered[0]

    async def resume() -> RemoteAgent:
        async with httpx.AsyncClient(base_url=server.url) as http:
            agent = RemoteAgent(Client(http, give_up_s=20), parse_manifest(manifest),
                                token=token, model_id=model_id)  # fmt: skip
            playing = asyncio.ensure_future(agent.play(auction_id))
            while not agent.log and not playing.done():  # its round 2 answered: enough
                await asyncio.sleep(0.05)
            playing.cancel()
            return agent

    agent = asyncio.run(resume())
    assert [entry.outcome for entry in agent.log] == ["accepted"]
    version_2: Manifest = stored_manifest(server, answers[0]["model_id"])
    expected = faithful_fine_tune(version_2, RoundInfo.from_state(second, 0))
    auction = httpx.get(f"{server.url}/auctions/{auction_id}").json()
    mine = next(a for a in auction["fine_tuning"][1]["answers"] if a["model_id"] == model_id)
    assert mine["uploaded_id"] is not None
    assert stored_manifest(server, mine["uploaded_id"]) == expected


def test_a_slow_fine_tuner_holds_no_other_agent(server: ServerProcess) -> None:
    """Three agents on one event loop: the first fine-tunes for 3 s, the others at once. The
    fast ones' uploads are answered long before the slow one's (before, the slow fine-tuner
    held the loop: the fast agent's upload waited for it, and came late)."""
    auction_id, entered = auction_of_seeds(server, name="agent", rounds=3, deadline_s=30)
    finished: dict[int, float] = {}

    def slow(current: Manifest, info: RoundInfo) -> Manifest:
        time.sleep(3)
        return faithful_fine_tune(current, info)

    async def play() -> None:
        async with httpx.AsyncClient(base_url=server.url) as http:
            agents = [
                RemoteAgent(Client(http, give_up_s=20), parse_manifest(manifest), token=token,
                            model_id=model_id, fine_tuner=slow if p == 0 else faithful_fine_tune)
                for p, (model_id, token, manifest) in enumerate(entered)
            ]  # fmt: skip
            started = time.monotonic()

            def done(p: int) -> Any:
                return lambda _entry: finished.setdefault(p, time.monotonic() - started)

            plays = [
                asyncio.ensure_future(a.play(auction_id, done(p))) for p, a in enumerate(agents)
            ]
            while len(finished) < len(agents) and not all(p.done() for p in plays):
                await asyncio.sleep(0.05)
            for playing in plays:
                playing.cancel()

    asyncio.run(play())
    assert finished[0] >= 3.0
    assert max(finished[1], finished[2]) < 2.5, finished


@pytest.fixture(scope="module")
def one_socket_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    """A server that lets one address hold one round socket."""
    yield from module_server(tmp_path_factory, "one-socket", {"SRD_LIMIT_CLIENT_SOCKETS": "1"})


@pytest.mark.slow  # the default run keeps its neighbours (docs/development.md)
def test_agents_past_the_hosts_share_of_sockets_play_over_long_polls(
    one_socket_server: ServerProcess,
) -> None:
    """Three agents on round sockets from one host that may hold one: the first keeps its
    socket, the others play over long polls and every asked patron answers (before, their
    handshakes kept getting 429 until they gave up, and the whole population failed)."""
    server = one_socket_server
    auction_id, entered = auction_of_seeds(server, name="share", rounds=1, deadline_s=60)

    async def play() -> list[RemoteAgent]:
        async with httpx.AsyncClient(base_url=server.url) as http:
            agents = [
                RemoteAgent(Client(http, give_up_s=15), parse_manifest(manifest), token=token,
                            model_id=model_id, transport="websocket")
                for model_id, token, manifest in entered
            ]  # fmt: skip
            await asyncio.gather(*(agent.play(auction_id) for agent in agents))
            return agents

    agents = asyncio.run(play())
    auction = httpx.get(f"{server.url}/auctions/{auction_id}").json()
    answers = [a for r in auction["fine_tuning"] for a in r["answers"]]
    assert answers and all(a["outcome"] == "accepted" for a in answers), answers
    assert sum(len(agent.log) for agent in agents) == len(answers)
