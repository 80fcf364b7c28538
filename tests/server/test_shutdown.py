"""A graceful stop of ``srd serve`` (SIGTERM) does not wait out its long polls: an agent
waiting for the next round is answered at once with the current state, an agent on a round
socket is told to reconnect (close code 1012, service restart), an event stream ends (its
client resumes from its last id), and the server exits well within uvicorn's graceful-shutdown
timeout (10 s)."""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path

import httpx
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from server.cli.launch import ServerProcess
from tests.support.factories import honest, unique
from tests.support.live import create_unstarted_auction

WAIT_S = 30  # the longest wait a long poll may ask: far longer than the stop may take


def test_sigterm_answers_waiting_long_polls_and_exits_promptly(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'srd.db'}"
    with ServerProcess(database_url=url, data_dir=tmp_path / "data") as server:
        ids = [
            httpx.post(server.url + "/submit", json=honest(unique("stop")), timeout=60).json()[
                "model_id"
            ]
            for _ in range(2)
        ]
        auction_id = create_unstarted_auction(url, ids, n_fish=1, seed=1)  # it never opens
        answers: list[httpx.Response] = []

        def wait_for_a_round() -> None:
            answers.append(
                httpx.get(
                    f"{server.url}/auctions/{auction_id}/rounds/current",
                    params={"wait": WAIT_S},
                    timeout=WAIT_S + 30,
                )
            )

        closes: list[int | None] = []
        listening = threading.Event()

        async def listen_on_a_socket() -> None:
            socket_url = f"ws://127.0.0.1:{server.port}/auctions/{auction_id}/rounds/socket"
            async with connect(socket_url) as ws:
                await ws.recv()  # the first state: no round yet
                listening.set()
                try:
                    await asyncio.wait_for(ws.recv(), WAIT_S)
                except ConnectionClosed as closed:
                    closes.append(closed.rcvd.code if closed.rcvd else None)

        streams: list[str] = []

        def follow_the_events() -> None:
            url = f"{server.url}/auctions/{auction_id}/events"
            with httpx.stream("GET", url, timeout=WAIT_S + 30) as stream:
                streams.append("".join(stream.iter_text()))  # to its end

        waiters = [threading.Thread(target=wait_for_a_round) for _ in range(3)]
        waiters.append(threading.Thread(target=follow_the_events))
        waiters.append(threading.Thread(target=lambda: asyncio.run(listen_on_a_socket())))
        for waiter in waiters:
            waiter.start()
        assert listening.wait(30)  # the socket is served (the polls, sent first, wait too)
        time.sleep(1.0)
        assert not answers
        stopping = time.monotonic()
        server.stop()
        took = time.monotonic() - stopping
        for waiter in waiters:
            waiter.join(timeout=30)
    assert took < 7.0, f"the stop took {took:.1f} s"  # uvicorn alone waited its 10 s
    assert [a.status_code for a in answers] == [200, 200, 200]
    assert {a.json()["status"] for a in answers} == {"none"}
    assert closes == [1012]
    assert len(streams) == 1 and "event: end" not in streams[0]  # cut short, not ended
    assert "timeout graceful shutdown exceeded" not in (tmp_path / "data" / "serve.log").read_text()
