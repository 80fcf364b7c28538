"""The web view in headless Chromium (Debian's ``chromium``, driven by Playwright; never a
downloaded browser) against a live ``srd serve``: the auction page follows an auction as it
runs, the inspector draws a rejected saboteur with the screener's reasons on its neurons, and
user-supplied strings stay text. Any request to another origin fails the test (offline).

``SRD_UI_SCREENSHOTS=<dir>`` also saves the screenshots shown in the README there:
``SRD_UI_SCREENSHOTS=docs/figures .venv/bin/pytest tests/server/test_ui.py``.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import torch
from sqlalchemy import insert

from agents.manifest import DECISIONS, ES_NEURONS, JUDGEMENTS, PFC_SOURCES, VERDICTS
from server.cli.launch import ServerProcess
from server.store.db import Database
from server.store.tables import ModelVersion, Participant, utcnow
from tests.support.factories import honest, unique
from tests.support.factories import saboteur as saboteur_manifest
from tests.support.live import create_unstarted_auction, paced_auction, submit_population
from tests.support.server import ADMIN_TOKEN, module_server

playwright_api = pytest.importorskip("playwright.sync_api", reason="playwright is a dev extra")

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
PHONE = {"width": 320, "height": 740}
"""The narrowest screen a page must fit without scrolling sideways (WCAG 1.4.10's reflow)."""
VIEWPORT = {"width": 1100, "height": 1000}
WAIT_MS = 20_000
EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
NEXT_READ_MS = 5_000
"""The web view reads a list's first page, and a read that failed, again every 5 s, and an open
round every 3 s: ``read_again_now`` jumps its clock this far. A page showing a deadline (an
enrollment's) is not jumped: it would see the deadline pass seconds early."""

if not Path(CHROMIUM).exists():
    pytest.skip(
        f"{CHROMIUM} is missing (Debian's chromium package; .ci/run installs it)",
        allow_module_level=True,
    )


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    yield from module_server(tmp_path_factory, "ui")


@pytest.fixture(scope="module")
def api(server: ServerProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=30) as client:
        yield client


@pytest.fixture(scope="module")
def population(api: httpx.Client) -> dict[str, dict[str, Any]]:
    return submit_population(api)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with playwright_api.sync_playwright() as driver:
        launched = driver.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield launched
        launched.close()


@pytest.fixture
def page(browser: Any, server: ServerProcess) -> Iterator[Any]:
    """A fresh page that may talk to the server only; page errors fail the test."""
    context = browser.new_context(viewport=VIEWPORT)
    context.clock.install()  # its time flows as a real clock's until a test jumps it
    tab = context.new_page()
    foreign: list[str] = []
    errors: list[str] = []

    def only_ours(route: Any) -> None:
        if route.request.url.startswith(server.url):
            route.continue_()
        else:
            foreign.append(route.request.url)
            route.abort()

    tab.route("**/*", only_ours)
    tab.on("pageerror", lambda error: errors.append(str(error)))
    yield tab
    context.close()
    assert foreign == [], f"the page asked other origins: {foreign}"
    assert errors == [], f"script errors: {errors}"


def read_again_now(page: Any, ms: int = NEXT_READ_MS) -> None:
    """Jump the page's clock ``ms`` ahead, to its next timed reads (each fires once): a test
    sees what the page reads again without waiting the seconds it waits between reads."""
    page.clock.fast_forward(ms)


def screenshot(target: Any, name: str, tmp_path: Path, **options: Any) -> None:
    """Save a screenshot; also into $SRD_UI_SCREENSHOTS when set (the README's figures)."""
    path = tmp_path / name
    target.screenshot(path=str(path), **options)
    assert path.stat().st_size > 10_000  # something was drawn
    folder = os.environ.get("SRD_UI_SCREENSHOTS")
    if folder:
        shutil.copy(path, Path(folder) / name)


def test_auction_page_draws_the_price_line_as_rounds_arrive_then_the_buyers(
    page: Any,
    server: ServerProcess,
    api: httpx.Client,
    population: dict[str, dict[str, Any]],
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
) -> None:
    torch.set_num_threads(1)
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    auction_id = create_unstarted_auction(server.database_url, honest_ids, n_fish=1, seed=1)
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#liveness:has-text('Following live')", timeout=WAIT_MS)
    chart = page.locator("#price-chart")
    seen: list[int] = []
    with paced_auction(monkeypatch, server.database_url, server.data_dir, auction_id, pace_s=0.4):
        deadline = time.monotonic() + 60
        while "Ended" not in (page.text_content("#liveness") or ""):
            points = int(chart.get_attribute("data-points") or 0)
            if not seen or points != seen[-1]:
                seen.append(points)
            assert time.monotonic() < deadline, f"the page never showed the end; saw {seen}"
            time.sleep(0.05)
    auction = api.get(f"/auctions/{auction_id}").json()
    rounds = len(auction["history"])
    # one point per iteration; once it ended, no next price (a price never asked)
    page.wait_for_function(
        f"() => document.querySelector('#price-chart').dataset.points === '{rounds}'",
        timeout=WAIT_MS,
    )
    assert seen[0] <= 2, seen  # the page was open before most iterations were played
    growing = seen if seen[-1] >= seen[-2] else seen[:-1]  # (the end's drop of the next price)
    assert growing == sorted(growing) and len(growing) >= 3, seen  # it grew while the auction ran
    assert page.locator("#rounds tbody tr").count() == rounds
    # The chart in words, for a screen reader: where the price went and when fish sold.
    history, said = auction["history"], chart.get_attribute("aria-label") or ""
    sold: dict[int, int] = {}
    for buyer in auction["buyers"]:
        sold[buyer["iteration"]] = sold.get(buyer["iteration"], 0) + 1
    assert said.startswith(
        f"Price asked in each iteration: {history[0]['price']:.3f} at iteration 0, "
        f"{history[-1]['price']:.3f} at iteration {history[-1]['iteration']}, lowest "
    ), said
    sales = ", ".join(f"{i} ({n} sold)" for i, n in sorted(sold.items()))
    asked = [row["price"] for row in history]
    assert f", highest {max(asked):.3f}; fish sold in iteration {sales}. Every " in said, said
    assert "next price" not in said, said
    # Its labels are drawn at 12 px at least, on a phone too (the chart scrolls instead).
    smallest = """() => Math.min(...[
        ...document.querySelectorAll('.chart .tick, .chart .axis-label')]
        .filter((t) => t.getClientRects().length)
        .map((t) => {
            const m = t.getScreenCTM();  // its scale, turned or not (the price axis's label)
            return Math.hypot(m.a, m.b) * parseFloat(getComputedStyle(t).fontSize);
        }))"""
    for size in (PHONE, VIEWPORT):
        page.set_viewport_size(size)
        assert page.evaluate(smallest) >= 12 - 1e-6, size
    # Each iteration says why the price moved: demand against the fish, and the next price.
    for row, past in zip(page.locator("#rounds tbody tr").all(), auction["history"], strict=True):
        why = row.locator("td").nth(8).text_content() or ""
        votes = f"{past['votes']['buy']} buy vote" + ("" if past["votes"]["buy"] == 1 else "s")
        assert why.startswith(f"{votes} for {past['n_available']} fish")
        assert f"to {past['next_price']:.3f}" in why
        if past["votes"]["buy"] > past["n_available"]:  # demand: the price rose, less a draw
            drawn = max(0.0, 0.05 - (past["next_price"] - past["price"]))
            assert "nobody bought; +" in why, why
            assert f"(+0.05 less a random 0 to 0.04, here {drawn:.3f})" in why, why
    buyers = page.locator("#buyers tbody tr")
    assert auction["buyers"] and buyers.count() == len(auction["buyers"])
    names = {a["model_id"]: name for name, a in population.items()}
    for row, buyer in zip(buyers.all(), auction["buyers"], strict=True):
        cells = [cell.text_content() for cell in row.locator("td").all()]
        assert cells[0] == names[buyer["model_id"]]
        assert cells[1] == str(buyer["model_id"])  # the patron, as the API's model_id names it
        assert cells[2] == f"version {buyer['version']} (model {buyer['version_id']})"
        assert cells[3] == f"{buyer['price']:.3f}" and cells[4] == str(buyer["iteration"])
    summary = page.text_content("#auction-summary") or ""
    assert "finished" in summary and "sold out" in summary
    rate = f"{100 * auction['purchase_rate']:.1f}% of the fish on sale"
    fraction = f"{100 * auction['buyer_fraction']:.1f}% of the patrons bought"
    assert rate in summary and fraction in summary, summary
    assert f"Revenue{auction['revenue']:.3f}" in summary, summary  # to the cent's tenth, as prices
    assert f"Mean price paid{auction['mean_price']:.3f}" in summary, summary
    assert "Buy fractionall: every voter counts (the paper's)" in summary, summary
    screenshot(page, "ui_auction.png", tmp_path, full_page=True)
    assert page.text_content("#rounds-heading") == "Every committed iteration"
    # The buyer's participant page tells the purchase, linked to this auction; the address
    # spelt in capitals, the page names the participant as registered.
    buyer = auction["buyers"][0]
    name = names[buyer["model_id"]]
    page.goto(f"{server.url}/ui/#/participants/{name.upper()}")
    row = page.locator(f"#entries tr:has(a[href='#/auctions/{auction_id}'])")
    row.wait_for(timeout=WAIT_MS)
    told = f"bought a fish at {buyer['price']:.3f} in iteration {buyer['iteration']}"
    assert told in (row.text_content() or "")
    assert page.text_content("h1") == f"Participant {name}"
    assert page.title() == f"Participant {name} · srd-auction"
    assert page.locator("h2").all_text_contents() == ["Versions", "Auctions"]
    # The model it entered with is among its newest versions: its version number is named.
    versions = {v["id"]: v["version"] for v in api.get(f"/participants/{name}").json()["versions"]}
    entered = f"Model {buyer['model_id']} (version {versions[buyer['model_id']]})"
    assert row.locator("td").nth(2).text_content() == entered
    # Its model's page links the auction it entered, and shows every bar the screener set it.
    page.goto(f"{server.url}/ui/#/models/{buyer['model_id']}")
    page.wait_for_selector(f"#model-auctions a[href='#/auctions/{auction_id}']", timeout=WAIT_MS)
    evidence = api.get(f"/models/{buyer['model_id']}").json()["evidence"]
    assert evidence and page.locator("#evidence-table tbody tr").count() == len(evidence)


def test_auction_page_shows_remote_fine_tuning_rounds(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    body = {
        "n_fish": 1,
        "model_ids": honest_ids,
        "fine_tune_mode": "remote",
        "fine_tune_rounds": 2,
        "round_deadline_s": 0.5,
    }
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    auction_id = api.post("/auctions", json=body, headers=headers).json()["auction_id"]
    page.set_viewport_size(PHONE)  # a phone: tables scroll, not the page
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#liveness:has-text('Ended')", timeout=60_000)
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
    # Why the price moved keeps a readable width (the table scrolls): its rows had been a
    # screen tall, the sentence a word wide.
    tallest = page.evaluate(
        "Math.max(...[...document.querySelectorAll('#rounds tbody tr')]"
        ".map((row) => row.getBoundingClientRect().height))"
    )
    assert 0 < tallest < 200, tallest
    # Two facts a row, not one.
    tops = page.evaluate("[...document.querySelectorAll('.facts > div')].map((d) => d.offsetTop)")
    assert len(set(tops)) <= (len(tops) + 1) // 2, tops
    # A frame is a tab stop only while it scrolls: on a phone the wide tables do; on a wide
    # screen most show everything, and are no stop that does nothing.
    stops = """() => [...document.querySelectorAll('.scroll[role=region]')].filter(
        (f) => f.offsetParent).map((f) => [f.getAttribute('tabindex') === '0',
        f.scrollWidth > f.clientWidth + 1 || f.scrollHeight > f.clientHeight + 1])"""
    for width in (PHONE, VIEWPORT, PHONE):
        page.set_viewport_size(width)
        page.wait_for_function(f"() => ({stops})().every(([stop, scrolls]) => stop === scrolls)")
        frames = page.evaluate(stops)
        assert any(scrolls == (width == PHONE) for _, scrolls in frames), frames
    rows = page.locator("#fine-tuning tbody tr")
    assert page.locator("#fine-tuning").is_visible() and rows.count() == 2
    fine_tuning = api.get(f"/auctions/{auction_id}").json()["fine_tuning"]
    for row, expected in zip(rows.all(), fine_tuning, strict=True):
        cells = [cell.text_content() for cell in row.locator("td").all()]
        assert cells[:3] == [str(expected["round"]), str(expected["iteration"]), "closed"]
        assert cells[3].startswith("closed ") and "(deadline " in cells[3]  # when it closed
        assert cells[4] == f"{len(expected['answers'])} missing"
        each = row.locator("td").nth(5).locator("li[data-outcome]")
        assert each.count() == len(expected["answers"])
        for item, answer in zip(each.all(), expected["answers"], strict=True):
            assert item.get_attribute("data-outcome") == answer["outcome"] == "missing"
            words = "missing (no upload recorded before the deadline: none came, or each one was"
            assert words in (item.text_content() or "")
            version = item.locator(f"a[href='#/models/{answer['version_id']}']")
            assert version.text_content() == f"version {answer['version']}"
    # An upload after the deadline is recorded late once its round's closed event was sent,
    # and no event follows: the page reads the auction once more at the end. (The stream is
    # replayed as it was sent before the upload: the round closed with that patron missing.)
    late = fine_tuning[0]["answers"][0]
    token = next(a["token"] for a in population.values() if a["model_id"] == late["model_id"])
    put = api.put(
        f"/auctions/{auction_id}/rounds/1/models/{late['model_id']}",
        json=api.get(f"/models/{late['version_id']}").json()["manifest"],
        headers={"Authorization": f"Bearer {token}"},
    )
    assert put.status_code == 410, put.text
    sent = api.get(f"/auctions/{auction_id}/events?rounds=true").text  # as the page asks
    assert sent.count('"outcome":"late"') == 1
    before = sent.replace('"outcome":"late"', '"outcome":"missing"')
    page.route(
        f"{server.url}/auctions/{auction_id}/events*",
        lambda route: route.fulfill(status=200, content_type="text/event-stream", body=before),
    )
    page.reload()
    page.wait_for_selector("#liveness:has-text('Ended')", timeout=WAIT_MS)
    item = f"#fine-tuning tr[data-round='1'] li[data-model='{late['model_id']}']"
    page.wait_for_selector(f"{item}[data-outcome='late']", timeout=WAIT_MS)
    assert "1 late" in (page.locator("#fine-tuning tr[data-round='1'] td").nth(4).text_content())
    words = page.text_content(item) or ""
    assert "late (arrived after the deadline, not applied)" in words, words
    # A select as wide as a 64-character name stays within the page.
    page.evaluate("document.querySelector('#explain-patron').add(new Option('W'.repeat(64)))")
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")


def test_an_open_rounds_answers_appear_without_a_reload_and_a_cancel_says_why_it_closed(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    """An upload into an open round sends no event: the page reads the round again while the
    auction plays on, and shows the answer; the round a cancel closes says so."""
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    body = {
        "n_fish": 1,
        "model_ids": honest_ids,
        "fine_tune_mode": "remote",
        "fine_tune_rounds": 1,
        "round_deadline_s": 120,
        "seed": 1,
    }
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    auction_id = api.post("/auctions", json=body, headers=headers).json()["auction_id"]
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    row = page.locator("#fine-tuning tr[data-round='1']")
    page.wait_for_selector("#fine-tuning tr[data-round='1']", timeout=WAIT_MS)
    assert "none yet" in row.locator("td").nth(4).text_content()
    asked = api.get(f"/auctions/{auction_id}/rounds/current").json()["asked"]
    assert len(asked) >= 4, asked  # three answers leave the round open
    # While the round is open, the live view says it waits for it, not for an iteration.
    waiting = "#liveness:has-text('waiting for fine-tuning round 1 until')"
    page.wait_for_selector(f"{waiting}:has-text('(0 of {len(asked)} answered)')", timeout=WAIT_MS)
    # The second answer comes from a patron listed before the first: it is inserted above it.
    patron, second = asked[1], asked[0]
    token = next(a["token"] for a in population.values() if a["model_id"] == patron)
    put = api.put(
        f"/auctions/{auction_id}/rounds/1/models/{patron}",
        json=api.get(f"/models/{patron}").json()["manifest"],
        headers={"Authorization": f"Bearer {token}"},
    )
    assert put.status_code == 200 and put.json()["outcome"] == "accepted", put.text
    item = f"#fine-tuning tr[data-round='1'] li[data-model='{patron}'][data-outcome='accepted']"
    read_again_now(page)
    page.wait_for_selector(item, timeout=WAIT_MS)  # no reload
    assert row.locator("td").nth(4).text_content() == "1 accepted"
    assert "accepted (unchanged weights, not screened)" in page.locator(item).text_content()
    page.wait_for_selector(f"{waiting}:has-text('(1 of {len(asked)} answered)')", timeout=WAIT_MS)
    page.locator(f"{item} a").focus()  # the reader's place, which a redraw must keep
    # the row and its links change in place (each patron's item keeps its own node, however
    # the answers come in): a press that spans the change lands, on the link it began on
    mark, marked = "(node) => { node.marked = true; }", "(node) => node.marked === true"
    row.evaluate(mark)
    page.locator(f"{item} a").evaluate(mark)
    # A second patron uploads new weights: a new version, which says where it was made.
    token = next(a["token"] for a in population.values() if a["model_id"] == second)
    manifest = api.get(f"/models/{second}").json()["manifest"]
    manifest["decision"]["B"]["bias"] += 1e-6
    put = api.put(
        f"/auctions/{auction_id}/rounds/1/models/{second}",
        json=manifest,
        headers={"Authorization": f"Bearer {token}"},
    )
    assert put.status_code == 200 and put.json()["uploaded_id"] is not None, put.text
    uploaded = put.json()["uploaded_id"]
    read_again_now(page)
    page.wait_for_selector(f"#fine-tuning tr[data-round='1'] li[data-model='{second}']")
    focused = "document.activeElement.closest('li[data-model]')?.dataset.model"
    assert page.evaluate(focused) == str(patron)  # the row was redrawn, the focus stayed
    assert row.evaluate(marked) and page.locator(f"{item} a").evaluate(marked)
    # A third uploads weights that buy more as the price rises: refused, its reasons folded.
    third = asked[2]
    token = next(a["token"] for a in population.values() if a["model_id"] == third)
    manifest = api.get(f"/models/{third}").json()["manifest"]
    manifest["decision"]["B"]["weights"]["PG"] = 0.9
    put = api.put(
        f"/auctions/{auction_id}/rounds/1/models/{third}",
        json=manifest,
        headers={"Authorization": f"Bearer {token}"},
    )
    assert put.status_code == 200 and put.json()["outcome"] == "refused", put.text
    read_again_now(page)
    refused = page.locator(f"#fine-tuning li[data-model='{third}'][data-outcome='refused']")
    refused.wait_for(timeout=WAIT_MS)
    summary = refused.locator("details summary")
    page.wait_for_function(
        f"() => document.querySelector(\"#fine-tuning li[data-model='{third}'] summary\")"
        ".textContent.startsWith('decision-sign on B')"
    )
    assert not refused.locator("details ul.reasons").is_visible()  # folded until asked for
    summary.click()
    assert "buys more as the price rises" in (refused.locator("ul.reasons").text_content() or "")
    assert api.delete(f"/auctions/{auction_id}", headers=headers).status_code == 200
    page.wait_for_selector("#liveness:has-text('Ended')", timeout=WAIT_MS)
    closed = "#fine-tuning tr[data-round='1'] td:has-text('when the auction was cancelled')"
    page.wait_for_selector(closed, timeout=WAIT_MS)
    # A fourth uploads after the cancel, long before the deadline: late, and said why.
    fourth = asked[3]
    token = next(a["token"] for a in population.values() if a["model_id"] == fourth)
    put = api.put(
        f"/auctions/{auction_id}/rounds/1/models/{fourth}",
        json=api.get(f"/models/{fourth}").json()["manifest"],
        headers={"Authorization": f"Bearer {token}"},
    )
    assert put.status_code == 410, put.text
    page.reload()
    late = page.locator(f"#fine-tuning li[data-model='{fourth}'][data-outcome='late']")
    late.wait_for(timeout=WAIT_MS)
    assert "late (arrived after the round closed when the auction was cancelled, not applied)" in (
        late.text_content() or ""
    )
    page.goto(f"{server.url}/ui/#/models/{uploaded}")
    made = page.locator("dt:has-text('Uploaded in') + dd")
    made.wait_for(timeout=WAIT_MS)
    assert made.text_content() == f"auction {auction_id}, fine-tuning round 1, from model {second}"
    entered = page.text_content("#model-auctions") or ""  # it bid for its patron, not as one
    assert entered.startswith(
        f"none as a patron of its own: an upload bids for its patron, model {second}"
    )


def test_an_enrolling_auction_page_shows_the_patrons_it_started_with(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    """Opened while the auction takes patrons (none yet, its fish counted when it starts), the
    page lists them as they join, and reads the auction again once it plays: the summary and
    the patron picker name the patrons that joined."""
    joiners = [a for name, a in population.items() if name.startswith("honest")][:2]
    body = {"rarity": 0.5, "enrollment_s": 14, "max_iterations": 3, "seed": 5}
    created = api.post("/auctions", json=body, headers={"Authorization": f"Bearer {ADMIN_TOKEN}"})
    assert created.status_code == 201, created.text
    auction_id = created.json()["auction_id"]
    page.goto(f"{server.url}/ui/#/auctions")  # the list says what the page says
    listed = page.locator(f"#auction-list tr[data-id='{auction_id}'] td").nth(2)
    assert listed.text_content(timeout=WAIT_MS) == "counted when it starts"
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#auction-summary:has-text('Takes patrons until')", timeout=WAIT_MS)
    summary = page.text_content("#auction-summary") or ""
    assert "Joined so farnone yet" in summary and "Fish on salecounted when it starts" in summary
    assert "Buyer fraction—" in summary  # not "0.0% of the patrons bought" before it starts
    page.wait_for_selector("#liveness:has-text('taking patrons until')", timeout=WAIT_MS)
    # Sections without an iteration say so, and there is no vote to explain yet.
    assert page.text_content("#rounds tbody") == "none yet"
    assert page.is_visible("#price-none") and page.is_visible("#votes-none")
    assert page.locator("#explain-form button[type='submit']").is_disabled()
    for joiner in joiners:
        joined = api.post(
            f"/auctions/{auction_id}/patrons",
            json={"model_id": joiner["model_id"]},
            headers={"Authorization": f"Bearer {joiner['token']}"},
        )
        assert joined.status_code == 201, joined.text
    names = [a["participant"] for a in joiners]
    # read again every 3 s while it takes patrons (its clock is not jumped: the page would see
    # the enrollment's end come seconds early)
    page.wait_for_function(
        "names => names.every((n) => (document.querySelector('#joined') || {}).textContent"
        "?.includes(n))",
        arg=names,
        timeout=WAIT_MS,
    )
    # A joined patron's link keeps the keyboard's focus over the next read (it was redrawn,
    # the focus lost to the page, every 3 s).
    joined_link = page.locator("#joined a").first
    joined_link.focus()
    href = joined_link.get_attribute("href")
    with page.expect_response(
        lambda r: r.url.endswith(f"/auctions/{auction_id}"), timeout=WAIT_MS
    ) as reread:
        pass  # the next read of the auction while it takes patrons
    reread.value.finished()
    page.evaluate("() => new Promise((drawn) => requestAnimationFrame(() => setTimeout(drawn)))")
    assert page.evaluate("document.activeElement.getAttribute('href')") == href
    assert "Takes patrons until" in (page.text_content("#auction-summary") or "")
    page.wait_for_selector("#liveness:has-text('Ended')", timeout=WAIT_MS)
    page.wait_for_selector("#auction-summary:has-text('Patrons2')", timeout=WAIT_MS)
    summary = page.text_content("#auction-summary") or ""
    assert "Fish on sale1" in summary and "Takes patrons until" not in summary
    assert page.locator("#explain-patron option").count() >= 1
    assert page.locator("#explain-form button[type='submit']").is_enabled()
    assert page.is_visible("#price-chart") and not page.is_visible("#price-none")


def test_a_cancelled_auction_shows_its_status_and_why_it_stopped(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    auction_id = create_unstarted_auction(server.database_url, honest_ids, n_fish=1, seed=2)
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    assert api.delete(f"/auctions/{auction_id}", headers=headers).status_code == 200
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#liveness:has-text('Ended: cancelled')", timeout=WAIT_MS)
    # its status says why; the stop reason would only repeat it
    assert page.text_content("#liveness") == "Ended: cancelled; no iteration played."
    summary = page.text_content("#auction-summary") or ""
    assert "Statuscancelled" in summary and "cancelled by the operator" in summary
    assert "Startednever" in summary  # and when it was created and cancelled
    assert "Item rows64 (the reference's)" in summary
    ended_at = page.locator("#auction-summary dt:has-text('Ended (cancelled)') + dd")
    finished_at = api.get(f"/auctions/{auction_id}").json()["finished_at"]
    local = (
        "(iso) => new Date(iso).toLocaleString(undefined, {dateStyle: 'short', timeStyle: 'long'})"
    )
    assert finished_at and ended_at.text_content() == page.evaluate(local, finished_at)
    for empty in ("#price-none", "#votes-none", "#rounds tbody td", "#explain-round option"):
        assert page.text_content(empty) == "none: no iteration was played", empty
    assert page.locator("#explain-form button[type='submit']").is_disabled()
    # Had it failed, its error is why it stopped (no auction of these tests fails: the same
    # auction, its answers made a failure's).
    failed = {
        '"status":"cancelled"': '"status":"failed"',
        '"stop_reason":"cancelled"': '"stop_reason":null',
    }
    failed['"error":null'] = '"error":"the worker stopped"'

    def as_failed(route: Any) -> None:
        answer = route.fetch()
        body = answer.text()
        for was, now in failed.items():
            body = body.replace(was, now)
        route.fulfill(response=answer, body=body)

    page.route(re.compile(rf"/auctions/{auction_id}(/events.*)?$"), as_failed)
    page.reload()
    page.wait_for_selector("#liveness:has-text('Ended: failed')", timeout=WAIT_MS)
    stopped = page.locator("#auction-summary dt:has-text('Stopped because') + dd")
    assert stopped.text_content() == "it failed: the worker stopped"
    page.unroute(re.compile(rf"/auctions/{auction_id}(/events.*)?$"))
    page.goto(f"{server.url}/ui/#/auctions")
    page.wait_for_selector("#auction-list tbody tr", timeout=WAIT_MS)
    rows = [
        [cell.text_content() for cell in row.locator("td").all()]
        for row in page.locator("#auction-list tbody tr").all()
    ]
    (cells,) = [r for r in rows if r[0] == f"Auction {auction_id}"]
    assert cells[1] == "cancelled" and cells[7] == "cancelled by the operator"
    # The list is read again every 5 s: a read that fails says so (the rows stay as read, where
    # they were), and the next one that succeeds clears it.
    listed = re.compile(r"/auctions(\?.*)?$")
    table = page.locator("#auction-list")
    at = table.bounding_box()
    page.route(listed, lambda route: route.fulfill(status=503, body="{}"))
    read_again_now(page)
    state = page.locator("#list-state")
    state.wait_for(state="visible", timeout=WAIT_MS)
    assert "Not updated: the server answered 503." in (state.text_content() or "")
    assert page.locator("#auction-list tbody tr").count() == len(rows)
    assert table.bounding_box() == at  # the line showed in its room; the table did not move
    page.unroute(listed)
    read_again_now(page)
    state.wait_for(state="hidden", timeout=WAIT_MS)
    # Its patrons' pages say they were in it when it was cancelled (it never played).
    name = next(n for n, a in population.items() if a["model_id"] == honest_ids[0])
    page.goto(f"{server.url}/ui/#/participants/{name}")
    entry = page.locator(f"#entries tr:has(a[href='#/auctions/{auction_id}']) td").nth(4)
    assert entry.text_content(timeout=WAIT_MS) == "still in when the operator cancelled the auction"


def test_a_list_read_that_fails_is_said_whole_with_when_its_rows_were_read_on_a_phone(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    """On a 360 px screen the line saying the list could not be read again wraps and shows
    whole, the time its rows were read in its text (it was one line cut off with "…", the
    time in a tooltip only)."""
    api.post("/submit", json=honest(unique("ui-news")))
    page.set_viewport_size({"width": 360, "height": 800})
    page.goto(f"{server.url}/ui/#/models")
    page.wait_for_selector("#model-list tbody tr", timeout=WAIT_MS)
    listed = re.compile(r"/models(\?.*)?$")
    page.route(listed, lambda route: route.abort())
    read_again_now(page)
    state = page.locator("#list-state")
    state.wait_for(state="visible", timeout=WAIT_MS)
    whole = """(line) => {
        const box = line.getBoundingClientRect();
        return line.scrollWidth <= line.clientWidth && line.scrollHeight <= line.clientHeight
            && box.left >= 0 && box.right <= window.innerWidth;
    }"""
    assert state.evaluate(whole)  # every word of it on the screen, none cut off
    assert state.evaluate("(line) => line.getClientRects()[0].height") > 30  # it wraps
    words = state.text_content() or ""
    assert re.search(r"as read at \d+:\d\d:\d\d", words), words  # the time, in the text
    assert words.startswith("Not updated: the server could not be reached. Shown as read at ")
    assert words.endswith("; trying again every few seconds."), words
    box, table = state.bounding_box(), page.locator("#model-list").bounding_box()
    assert box and table and box["y"] + box["height"] <= table["y"]  # above the rows, not on them
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
    page.unroute(listed)
    read_again_now(page)
    state.wait_for(state="hidden", timeout=WAIT_MS)


def ended_auction_page(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> tuple[int, list[int]]:
    """An auction of 2 fish among the honest patrons, played to its end with its page open:
    its id and the patrons' model ids."""
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    body = {"n_fish": 2, "model_ids": honest_ids, "seed": 5}
    auction_id = api.post("/auctions", json=body, headers=headers).json()["auction_id"]
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#liveness:has-text('Ended')", timeout=60_000)
    return int(auction_id), honest_ids


def test_a_late_explanation_does_not_replace_the_one_asked_for_after_it(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    """The first patron's explanation answers slowly, the second's at once: the second stays
    shown (the first's late answer had replaced it under the second's name in the picker)."""
    auction_id, honest_ids = ended_auction_page(page, server, api, population)
    slow, fast = honest_ids[0], honest_ids[1]
    # An iteration and a patron are picked: the explainer says what to press, not to pick.
    page.wait_for_selector("#explain-hint:has-text('Press “Explain the vote”')", timeout=WAIT_MS)
    held: list[Any] = []  # the slow explanation's request, answered once the fast one shows
    page.route(f"**/auctions/{auction_id}/iterations/0/votes/{slow}", lambda r: held.append(r))
    page.locator("button.explain-round[data-iteration='0']").click()
    page.wait_for_selector("#explain-hint:has-text('Press “Its neurons” on a vote above')")
    page.locator(f"button.explain-vote[data-model='{slow}']").click()
    page.locator(f"button.explain-vote[data-model='{fast}']").click()
    fast_name = api.get(f"/auctions/{auction_id}/iterations/0/votes/{fast}").json()["participant"]
    shows_fast = "name => document.querySelector('#explanation h3')?.textContent.startsWith(name)"
    page.wait_for_function(shows_fast, arg=fast_name, timeout=WAIT_MS)
    assert page.locator("#explain-hint").count() == 0  # the vote shown replaced the hint
    # "Its neurons" moved the focus to the vote it shows, far below the button.
    page.wait_for_function("() => document.activeElement.id === 'explanation'", timeout=WAIT_MS)
    assert len(held) == 1
    with page.expect_response(f"**/votes/{slow}"):
        held[0].continue_()
    page.wait_for_timeout(300)  # the late answer's handler has run
    assert (page.text_content("#explanation h3") or "").startswith(fast_name)
    assert page.input_value("#explain-patron") == str(fast)


def test_inspector_draws_the_saboteur_neuron_by_neuron_with_the_screeners_reasons(
    page: Any,
    server: ServerProcess,
    api: httpx.Client,
    population: dict[str, dict[str, Any]],
    tmp_path: Path,
) -> None:
    sabotage = population["saboteur"]
    assert sabotage["accepted"] is False
    model = api.get(f"/models/{sabotage['model_id']}").json()
    page.goto(f"{server.url}/ui/#/models/{sabotage['model_id']}")
    page.wait_for_selector("#verdict", timeout=WAIT_MS)
    assert (page.text_content("#verdict") or "").startswith("Rejected")
    assert "its participant may appeal once" in (page.text_content("#verdict") or "")
    # Every reason right under the verdict, and why each missed bar was missed.
    listed = page.locator("#model-reasons li")
    assert listed.count() == len(model["reasons"])
    assert all(
        r["message"] in (page.text_content("#model-reasons") or "") for r in model["reasons"]
    )
    missed = [e for e in model["evidence"] if not e["passed"] and e["detail"].get("finding")]
    table_text = page.text_content("#evidence-table") or ""
    assert missed and all(e["detail"]["finding"] in table_text for e in missed)
    # a missed bar without a finding of its own says the reason given under its name
    (hold,) = [r["message"] for r in model["reasons"] if r["rule"] == "sincere-hold"]
    why = page.locator("#evidence-table tbody tr:has(td:text-is('sincere-hold')) td").last
    assert why.text_content() == hold
    # nothing printed for what it lacks (a model without reviews had a line reading "null")
    assert "null" not in (page.text_content("main") or "")
    facts = page.text_content("main") or ""
    epochs = model["manifest"]["fine_tuning"]["epochs"]
    assert f"{epochs} epoch{'' if epochs == 1 else 's'}," in facts
    decision = page.locator("#network-decision")
    pfc = page.locator("#network-pfc")
    for name in (*ES_NEURONS, *DECISIONS):
        assert decision.locator(f"g.neuron[data-neuron='{name}']").count() == 1
    for name in (*JUDGEMENTS, *VERDICTS):
        assert pfc.locator(f"g.neuron[data-neuron='{name}']").count() == 1
    for name in PFC_SOURCES:  # drawn again as the judge's sources, but one tab stop each
        assert pfc.locator(f"g.neuron[data-repeats='{name}']:not([tabindex])").count() == 1
        assert page.locator(f"g.neuron[data-neuron='{name}'][tabindex='0']").count() == 1
    manifest = model["manifest"]
    price_to_pg = manifest["external_sensor"]["PG"]["weights"]["price"]
    edge = decision.locator("line[data-edge='price->PG']")
    assert float(edge.get_attribute("data-weight") or "nan") == price_to_pg
    assert "pos" in (edge.get_attribute("class") or "")
    cut = [s for s, w in manifest["decision"]["B"]["weights"].items() if w == 0]
    assert cut  # the saboteur's buy neuron listens to nothing
    for source in cut:
        assert decision.locator(f"line[data-edge='{source}->B']").count() == 0
    named = {reason["neuron"] for reason in model["reasons"]}
    flagged = {
        node.get_attribute("data-neuron") for node in decision.locator("g.neuron.flagged").all()
    }
    assert named and flagged == named & {*ES_NEURONS, *DECISIONS}
    for reason in model["reasons"]:
        card = page.locator(f"#neuron-{reason['neuron']}")
        assert reason["message"] in (card.locator(".reasons").text_content() or "")
    weights_of_b = page.locator("table[data-weights-of='B'] tbody tr")
    assert weights_of_b.count() == len(manifest["decision"]["B"]["weights"]) + 1  # and the bias
    screenshot(page.locator("section:has(#network-decision)"), "ui_inspector.png", tmp_path)
    decision_cards = page.locator("section.layer:has(#neuron-B)")
    screenshot(decision_cards, "ui_inspector_reasons.png", tmp_path)
    decision.locator("g.neuron[data-neuron='B']").focus()
    page.keyboard.press("Enter")
    assert page.evaluate("document.activeElement.id") == "neuron-B"
    # On a phone the drawing keeps a readable size and scrolls sideways, not the page.
    page.set_viewport_size(PHONE)
    assert decision.bounding_box()["width"] >= 560
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")


def test_user_supplied_strings_are_shown_as_text(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    name = "<script>window.__pwned = 1</script>"
    attack = f'{name}<img src="x" onerror="window.__pwned = 2">'
    refused = api.post("/submit", json={**honest("named"), "participant": name})
    assert refused.status_code == 422  # not a name the API takes
    manifest = honest("described", seed=5)
    manifest["description"] = attack
    described = api.post("/submit", json=manifest).json()
    # A name the API would refuse, written straight into the database: the page must not rely
    # on the API's validation to stay safe.
    database = Database(server.database_url)
    try:
        with database.session(write=True) as session:
            participant_id = session.execute(
                insert(Participant)
                .values(name=name, token_hash="0" * 64, created_at=utcnow())
                .returning(Participant.id)
            ).scalar_one()
            forged = session.execute(
                insert(ModelVersion)
                .values(
                    participant_id=participant_id,
                    version=1,
                    manifest={**manifest, "participant": name},
                    accepted=False,
                    reasons=[{"rule": attack, "neuron": "B", "message": attack}],
                    created_at=utcnow(),
                )
                .returning(ModelVersion.id)
            ).scalar_one()
            session.commit()
    finally:
        database.close()
    page.goto(f"{server.url}/ui/#/models")
    row = page.locator("#model-list tbody tr", has_text="Model " + str(forged))
    row.wait_for(timeout=WAIT_MS)
    assert row.locator("td").nth(1).text_content() == name
    described_row = page.locator("#model-list tbody tr", has_text=f"Model {described['model_id']}")
    assert described_row.locator("td").nth(5).text_content() == attack
    page.goto(f"{server.url}/ui/#/models/{forged}")
    page.wait_for_selector("#verdict", timeout=WAIT_MS)
    assert (page.text_content("h1") or "").endswith(f"{name} version 1")
    assert page.text_content("#description") == attack
    assert attack in (page.locator("#neuron-B .reasons").text_content() or "")
    assert page.locator("main script, main img[src='x']").count() == 0
    assert page.evaluate("window.__pwned") is None


def test_a_held_models_page_links_its_inspection_and_reads_its_numbers_rounded(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    """A held model's page links the page its inspector decides it on; an activation's
    parameters read to six significant digits, as a fine-tuned value is shown elsewhere."""
    manifest = saboteur_manifest(unique("ui-rounded"))
    manifest["external_sensor"]["PG"]["activation"]["a"] = 20.000000123456789
    model_id = held_on_appeal_of(api, manifest)
    try:
        page.goto(f"{server.url}/ui/#/models/{model_id}")
        page.wait_for_selector(f"#verdict a[href='#/reviews/{model_id}']", timeout=WAIT_MS)
        said = " ".join(page.locator(".activation").all_text_contents())
        assert "a = 20," in said and "20.0000001" not in said, said
    finally:
        refuse(api, model_id)


def test_the_impact_chart_tells_apart_a_price_and_a_bar_four_decimals_would_tie(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    """The red team's opening-price bargainer is held: its copies' price passes the bar by
    0.00006 (5.09184 against 5.09178, over the second stage's 96 auctions). Its chart says the
    two apart, as its table does, and names the count of auctions it was judged on."""
    manifest = json.loads((EXAMPLES / "red_team" / "opening-price-bargainer.json").read_text())
    manifest["participant"] = unique("ui-near-tie")
    held = api.post("/submit", json=manifest).json()
    assert held["status"] == "held", held
    model_id = held["model_id"]
    try:
        page.goto(f"{server.url}/ui/#/reviews/{model_id}")
        page.fill("#admin-token", ADMIN_TOKEN)
        page.keyboard.press("Enter")
        chart = page.locator("#evidence figure svg").nth(1)
        chart.wait_for(timeout=WAIT_MS)
        said = chart.get_attribute("aria-label") or ""
        assert "bar 5.09178 (96 auctions)" in said, said
        assert "(96 auctions) 5.09184 passed" in said, said
    finally:
        refuse(api, model_id)


def held_on_appeal_of(api: httpx.Client, manifest: dict[str, Any], note: str = "x") -> int:
    """``manifest``, refused by the screener and appealed by its participant: held. Its id."""
    refused = api.post("/submit", json=manifest).json()
    assert refused["status"] == "refused", refused
    auth = {"Authorization": f"Bearer {refused['token']}"}
    appeal = api.post(f"/models/{refused['model_id']}/appeal", json={"note": note}, headers=auth)
    assert appeal.status_code == 200, appeal.text
    return int(refused["model_id"])


def held_on_appeal(
    api: httpx.Client, prefix: str, description: str | None = None, note: str = "x"
) -> int:
    """A saboteur refused by the screener and appealed by its participant (``note``): held for
    an inspector. Its id."""
    manifest = saboteur_manifest(unique(prefix))
    if description is not None:
        manifest["description"] = description
    return held_on_appeal_of(api, manifest, note)


def refuse(api: httpx.Client, model_id: int) -> None:
    """A held model decided, out of every later test's review queue."""
    decision = {"decision": "refuse", "inspector": "Ada", "note": "holds"}
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    api.post(f"/models/{model_id}/review", json=decision, headers=headers)


def test_a_participants_description_is_labelled_as_its_own_words(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    """A description written to pass for the screener's or an inspector's text is shown under
    a heading naming it the participant's words, quoted, and styled unlike the verdict and the
    screener's reasons: on the model's page, its inspection page and in the models list."""
    spoof = "Accepted by the screener: no reason.\n\nReview history\nadmitted by inspector Ada"
    # an appeal written as the screener's evidence reads: the participant's words too
    evidence = "market-impact: 5.1150 against 5.0918 (at least), passed by 0.0232: held for you"
    model_id = held_on_appeal(api, "ui-spoof", description=spoof, note=evidence)
    participant = api.get(f"/models/{model_id}").json()["participant"]

    def labelled() -> None:
        quoted = page.locator("#model-description #description")
        quoted.wait_for(timeout=WAIT_MS)
        assert page.text_content("#description-heading") == (
            "Description, in the participant's words"
        )
        heading = page.locator("#description-heading").bounding_box()
        words = quoted.bounding_box()
        assert heading and words and heading["y"] < words["y"]  # the label above the words
        assert quoted.text_content() == spoof
        style = (
            "(node) => [getComputedStyle(node).fontStyle, getComputedStyle(node).borderTopStyle]"
        )
        assert quoted.evaluate(style) == ["italic", "dashed"]
        for system in ("#verdict", "#model-reasons li"):
            assert page.locator(system).first.evaluate(style) != ["italic", "dashed"]

    page.goto(f"{server.url}/ui/#/models/{model_id}")
    labelled()
    try:
        page.goto(f"{server.url}/ui/#/reviews/{model_id}")
        page.fill("#admin-token", ADMIN_TOKEN)
        page.keyboard.press("Enter")
        page.wait_for_selector("#decision", timeout=WAIT_MS)
        labelled()
        appeal = page.locator("#appeal")
        assert appeal.text_content() == evidence
        assert page.text_content("#appeal-heading") == "The appeal, in the participant's words"
        assert page.locator("#evidence #appeal").count() == 0  # not among the screener's
        framed = "(n) => [getComputedStyle(n).fontStyle, getComputedStyle(n).borderTopStyle]"
        assert appeal.evaluate(framed) == ["italic", "dashed"]
        page.goto(f"{server.url}/ui/#/models?participant={participant}")
        row = page.locator(f"#model-list tr:has(a[href='#/models/{model_id}'])")
        row.wait_for(timeout=WAIT_MS)
        assert page.locator("#model-list th").nth(5).text_content() == (
            "Description (the participant's words)"
        )
        cell = row.locator("td").nth(5)
        quotes = "(q) => [getComputedStyle(q, '::before').content, getComputedStyle(q).fontStyle]"
        assert cell.locator("q").evaluate(quotes) == ["open-quote", "italic"]  # in quotes
    finally:
        refuse(api, model_id)


def test_jobs_page_follows_a_job_and_shows_its_plots(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    job = api.post("/jobs", json={"kind": "fish", "params": {"steps": 600}}, headers=headers)
    job_id = job.json()["job_id"]
    page.goto(f"{server.url}/ui/#/jobs/{job_id}")
    page.wait_for_selector("#liveness:has-text('Ended: succeeded')", timeout=60_000)
    done = api.get(f"/jobs/{job_id}").json()
    plots = [name for name in done["artifacts"] if name.endswith(".png")]
    images = page.locator("#artifacts img")
    assert plots and images.count() == len(plots)
    for image in images.all():
        image.scroll_into_view_if_needed()
        assert page.evaluate(
            "(img) => img.complete && img.naturalWidth > 0", image.element_handle()
        )
    page.goto(f"{server.url}/ui/#/jobs")
    listed = page.locator("#job-list tbody tr", has_text=f"Job {job_id}")
    listed.wait_for(timeout=WAIT_MS)
    assert "succeeded" in (listed.text_content() or "")
    # The list follows without a reload: a job queued now appears, and moves on to its end.
    later = api.post("/jobs", json={"kind": "fish", "params": {"steps": 10}}, headers=headers)
    row = f"#job-list tbody tr[data-id='{later.json()['job_id']}']"
    read_again_now(page)
    page.locator("#show-new").click(timeout=WAIT_MS)  # offered above the rows, not pushed in
    page.wait_for_selector(row, timeout=WAIT_MS)
    page.wait_for_selector(f"{row}[data-status='succeeded']", timeout=60_000)


def test_api_docs_render_offline(page: Any, server: ServerProcess) -> None:
    page.goto(f"{server.url}/docs")
    page.wait_for_selector(".swagger-ui .opblock", timeout=WAIT_MS)
    assert page.locator(".opblock-summary-path[data-path='/auctions/{auction_id}/events']").count()


def test_keyboard_reaches_every_section(page: Any, server: ServerProcess) -> None:
    page.goto(f"{server.url}/")
    page.wait_for_selector("#auction-list", timeout=WAIT_MS)
    assert page.url == f"{server.url}/"  # the page itself, not a redirect
    assert page.locator("link[rel=stylesheet]").count() == 1
    assert page.evaluate("getComputedStyle(document.body).margin") == "0px"  # style.css loaded
    page.keyboard.press("Tab")
    assert page.evaluate("document.activeElement.id") == "skip"
    for section in ("Models", "Jobs"):
        page.get_by_role("link", name=section, exact=True).focus()
        page.keyboard.press("Enter")
        page.wait_for_selector(f"h1:has-text('{section}')", timeout=WAIT_MS)
        assert page.evaluate("document.activeElement.tagName") == "H1"  # focus follows the view
        current = page.get_by_role("link", name=section, exact=True)
        assert current.get_attribute("aria-current") == "page"


def four(value: float) -> str:
    """A float as the page shows it: 4 significant digits, JavaScript's shortest form."""
    rounded = float(f"{value:.4g}")
    return str(int(rounded)) if rounded.is_integer() else repr(rounded)


STUDY = {"kind": "auction-study", "params": {"rarities": [0.3, 0.6], "patrons": 6, "trials": 1}}


def finished_job(api: httpx.Client, body: dict[str, Any]) -> dict[str, Any]:
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    job_id = api.post("/jobs", json=body, headers=headers).json()["job_id"]
    deadline = time.monotonic() + 120
    while (job := api.get(f"/jobs/{job_id}").json())["status"] not in ("succeeded", "failed"):
        assert time.monotonic() < deadline, job
        time.sleep(0.2)
    assert job["status"] == "succeeded", job["error"]
    return dict(job)


@pytest.fixture(scope="module")
def studies(api: httpx.Client) -> list[dict[str, Any]]:
    """Two auction studies that differ in their trials."""
    other = {**STUDY, "params": {**STUDY["params"], "trials": 2}}
    return [finished_job(api, STUDY), finished_job(api, other)]


def test_a_comparison_says_what_each_configuration_is_and_its_charts_are_named_apart(
    page: Any, server: ServerProcess, api: httpx.Client, axe_source: str
) -> None:
    """Each configuration's table is captioned with its line of the result's caption (an
    "honest-alone" configuration lists the saboteur share of the population it came from);
    two comparisons side by side draw a chart per configuration, each frame named apart."""
    body = {"kind": "comparison", "params": {"patrons": 16, "trials": 1, "rarities": [0.5]}}
    jobs = [
        finished_job(api, body),
        finished_job(api, {**body, "params": {**body["params"], "seed": 1}}),
    ]
    page.goto(f"{server.url}/ui/#/jobs/{jobs[0]['id']}")
    page.wait_for_selector("table caption", timeout=WAIT_MS)
    captions = [c.text_content() or "" for c in page.locator("table caption").all()]
    alone = next(c for c in captions if c.startswith("Configuration honest-alone"))
    assert alone.startswith("Configuration honest-alone: the compromised population's")
    assert "patrons the screening refused, over all its auctions:" in " ".join(captions)
    ids = ",".join(str(job["id"]) for job in jobs)
    page.goto(f"{server.url}/ui/#/jobs/compare?ids={ids}")
    page.wait_for_selector("svg#overlay-1 polyline.curve", state="attached", timeout=WAIT_MS)
    # Overlaid curves are told apart without colour: six dashes, each named in the legend.
    curves = page.evaluate(
        """[...document.querySelectorAll('svg[id^=overlay-]')].map((chart) =>
            [...chart.querySelectorAll('polyline.curve')].map(
                (c) => getComputedStyle(c).strokeDasharray))"""
    )
    assert len(curves) > 1 and all(len(set(c[:6])) == len(c[:6]) > 1 for c in curves), curves
    legend = page.locator("figure:has(svg#overlay-1) .legend-list li").all_text_contents()
    assert len(legend) == 2 and legend[1].startswith("(dashed) "), legend
    # Each chart says its curves in words: every curve named, where it begins and ends.
    said = page.get_attribute("svg#overlay-1", "aria-label") or ""
    names = [item.removeprefix("(dashed) ") for item in legend]
    assert all(f"{name}: " in said for name in names), (said, names)
    assert said.count(" at ") >= 4 and ", lowest " in said and ", highest " in said, said
    labels = page.evaluate(
        "[...document.querySelectorAll('[role=region]')].map((r) => r.getAttribute('aria-label'))"
    )
    assert len(labels) > 5 and len(labels) == len(set(labels)), labels
    page.evaluate(axe_source)
    found = page.evaluate(
        "axe.run(document, {runOnly: ['landmark-unique']}).then((r) => r.violations.length)"
    )
    assert found == 0
    # A mean price 0.00017 above the first job's is printed apart from it, not "5.1 (+0.00017)"
    # beside "5.1".
    first = jobs[0]["result"]["configurations"]["honest"]["rows"]

    def nudged(route: Any) -> None:
        answer = route.fetch()
        job = answer.json()
        for row, base in zip(job["result"]["configurations"]["honest"]["rows"], first, strict=True):
            row["mean_price"] = base["mean_price"] + 0.00017
        route.fulfill(response=answer, body=json.dumps(job))

    page.route(re.compile(rf"/jobs/{jobs[1]['id']}$"), nudged)
    page.reload()
    cell = page.locator("table[data-diff='configurations.honest'] td[data-delta]").first
    cell.wait_for(timeout=WAIT_MS)
    shown = [  # (delta, its cell, the first job's cell beside it)
        (
            c.get_attribute("data-delta"),
            c.text_content() or "",
            c.evaluate("(td) => td.previousElementSibling.textContent"),
        )
        for c in page.locator("table[data-diff='configurations.honest'] td[data-delta]").all()
    ]
    nudge = [(ours, theirs) for delta, ours, theirs in shown if abs(float(delta) - 0.00017) < 1e-9]
    assert nudge, shown
    for ours, theirs in nudge:
        assert ours.endswith("(+0.00017)") and ours.split(" (")[0] != theirs, (ours, theirs)
    page.unroute(re.compile(rf"/jobs/{jobs[1]['id']}$"))


def test_job_page_opens_on_its_headline_cards_tables_and_figures(
    page: Any, server: ServerProcess, studies: list[dict[str, Any]], tmp_path: Path
) -> None:
    job = studies[0]
    result = job["result"]
    page.goto(f"{server.url}/ui/#/jobs/{job['id']}")
    page.wait_for_selector("#headline .card", timeout=WAIT_MS)
    cards = {
        (c.locator("dt").text_content() or ""): c.locator("dd").text_content()
        for c in page.locator("#headline .card").all()
    }
    assert cards["Auctions"] == str(result["auctions"]) and cards["Refused"] == "0"
    assert cards["Elapsed (s)"] == four(result["elapsed_s"])
    for card in page.locator("#headline .card dd").all():  # no card overflows
        assert page.evaluate("(dd) => dd.scrollWidth <= dd.clientWidth + 1", card.element_handle())
    table = page.locator("table[data-table='rows']")
    assert table.locator("tbody tr").count() == len(result["rows"])
    headers = [th.text_content() for th in table.locator("th").all()]
    assert "Mean price" in headers and "Purchase rate" in headers and "mean_price" not in headers
    named = "async () => (await import('/ui/results.js')).words('sd_inhibited_abs_speed')"
    assert page.evaluate(named) == "SD of inhibited abs speed"  # as "SD of final displacement"
    # a price the network read is shown as its iteration's record shows it (5 decimals, then 3):
    # an outside review saw one iteration at 5.067 in its row and 5.068 above its votes
    shown = "async () => (await import('/ui/dom.js')).recordedPrice(5.067502900811699)"
    assert page.evaluate(shown) == page.evaluate("() => (5.0675).toFixed(3)") == "5.067"
    # Every column of the rows, those the kind names first (they had hidden the others).
    scalar = [k for k, v in result["rows"][0].items() if not isinstance(v, dict | list)]
    assert table.locator("thead th").count() == len(scalar), headers
    assert "Revenue" in headers and "Iterations" in headers, headers
    prices = [td.text_content() for td in table.locator("tbody tr td:nth-child(4)").all()]
    assert prices == [
        "—" if r["mean_price"] is None else four(r["mean_price"]) for r in result["rows"]
    ]
    images = page.locator("#artifacts img")
    assert images.count() == len([a for a in job["artifacts"] if a.endswith(".png")]) > 0
    raw = page.locator("details:has(summary:has-text('as JSON'))")
    assert raw.count() == 1 and raw.get_attribute("open") is None  # collapsed
    first = "(a, b) => document.querySelector(a).compareDocumentPosition(document.querySelector(b))"
    assert page.evaluate(f"({first})('#headline', 'details')") & 4  # the cards come first
    # When it was queued, started and ended.
    times = {
        (d.locator("dt").text_content() or ""): d.locator("dd").text_content()
        for d in page.locator("#job-state dl > div").all()
    }
    assert job["started_at"] and times["Started"] not in ("not yet", "—", None), times
    assert times["Queued"] not in ("—", None) and times["Ended"] not in ("—", None), times
    screenshot(page, "ui_job.png", tmp_path, full_page=True)


def test_jobs_compare_side_by_side_from_the_filtered_list_with_the_keyboard(
    page: Any, server: ServerProcess, studies: list[dict[str, Any]], tmp_path: Path
) -> None:
    first, second = studies
    page.goto(f"{server.url}/ui/#/jobs")
    page.wait_for_selector("#job-list tbody tr", timeout=WAIT_MS)
    page.select_option("#filter-kind", "auction-study")
    page.locator("#job-filters button[type='submit']").focus()
    page.keyboard.press("Enter")
    page.wait_for_url("**/#/jobs?kind=auction-study", timeout=WAIT_MS)
    # The unfiltered rows stay on screen until the filtered list arrives: wait for the list to
    # be filtered (rows of one kind), then check it holds exactly the studies.
    page.wait_for_function(
        """() => {
            // the new view's list (its caption names the filter), not the old one's
            const caption = document.querySelector('#job-list caption')?.textContent || '';
            const kinds = [...document.querySelectorAll('#job-list tbody tr td:nth-child(3)')]
                .map((cell) => cell.textContent);
            return caption.includes('kind auction-study') && kinds.length > 0
                && kinds.every((kind) => kind === 'auction-study');
        }""",
        timeout=WAIT_MS,
    )
    listed = {
        int(box.get_attribute("data-job") or "0")
        for box in page.locator("#job-list tbody input[data-job]").all()
    }
    assert {first["id"], second["id"]} <= listed
    assert page.locator("#compare").is_disabled()
    for job in (second, first):
        page.locator(f"input[data-job='{job['id']}']").focus()
        page.keyboard.press("Space")
    assert page.locator("#compare").is_enabled()
    page.locator("#compare").focus()
    page.keyboard.press("Enter")
    page.wait_for_selector("#compare-params", timeout=WAIT_MS)
    assert page.url.endswith(f"#/jobs/compare?ids={first['id']},{second['id']}")
    assert page.locator("tr[data-param='trials']").get_attribute("class") == "differs"
    assert page.locator("tr[data-param='patrons']").get_attribute("class") is None
    page.set_viewport_size(PHONE)  # a phone: the tables scroll
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
    page.set_viewport_size(VIEWPORT)
    diff = page.locator("table[data-diff='rows'] tbody tr")
    assert diff.count() == len(first["result"]["rows"])
    base = {r["rarity"]: r for r in first["result"]["rows"]}
    headers = [
        th.text_content() for th in page.locator("table[data-diff='rows'] th[scope='col']").all()
    ]
    rate = headers.index(f"Purchase rate, job {second['id']} (Δ)")
    for row in diff.all():
        rarity = float((row.get_attribute("data-row") or "").split("rarity ")[1].split(",")[0])
        theirs = next(r for r in second["result"]["rows"] if r["rarity"] == rarity)
        cell = row.locator("th, td").nth(rate)
        delta = float(cell.get_attribute("data-delta") or "nan")
        assert delta == pytest.approx(theirs["purchase_rate"] - base[rarity]["purchase_rate"])
    curves = page.locator("svg#overlay-0 polyline.curve")
    assert curves.count() == 2
    assert {c.get_attribute("data-line") for c in curves.all()} == {
        f"job {first['id']}, setting honest",
        f"job {second['id']}, setting honest",
    }
    screenshot(page, "ui_compare.png", tmp_path, full_page=True)
    page.reload()  # the address alone rebuilds the view
    page.wait_for_selector("svg#overlay-0 polyline.curve", state="attached", timeout=WAIT_MS)

    # Ended jobs whose results have no table will never have one; an id that is not a number
    # is named, not dropped silently.
    def without_tables(route: Any) -> None:
        answer = route.fetch()
        route.fulfill(response=answer, body=json.dumps({**answer.json(), "result": {}}))

    page.route(re.compile(r"/jobs/\d+$"), without_tables)
    page.goto(f"{server.url}/ui/#/jobs/compare?ids={first['id']},{second['id']},abc")
    page.wait_for_selector("#compare-no-table", timeout=WAIT_MS)
    assert page.text_content("#compare-no-table") == "None: these results have no table."
    assert '"abc"' in (page.text_content("#compare-unread") or "")
    page.unroute(re.compile(r"/jobs/\d+$"))
    # A filter that matches nothing says so (the studies all succeeded), and the caption names it.
    page.goto(f"{server.url}/ui/#/jobs?status=failed&kind=auction-study")
    none = page.locator("#no-jobs")
    none.wait_for(timeout=WAIT_MS)
    assert none.text_content() == "None matches this filter (status failed, kind auction-study)."
    caption = page.text_content("#job-list caption") or ""
    assert caption.startswith("Experiment jobs (status failed, kind auction-study)")
    page.goto(f"{server.url}/ui/#/jobs?kind=bogus")  # in words, as an unknown status is
    said = page.locator("p.problem")
    said.wait_for(timeout=WAIT_MS)
    assert said.text_content() == 'No job kind is called "bogus": pick one of the list.'


def test_every_vote_of_a_round_opens_its_explanation(
    page: Any,
    server: ServerProcess,
    api: httpx.Client,
    population: dict[str, dict[str, Any]],
    tmp_path: Path,
) -> None:
    auction_id, honest_ids = ended_auction_page(page, server, api, population)
    auction = api.get(f"/auctions/{auction_id}").json()
    last = auction["history"][-1]["iteration"]
    assert auction["buyers"]  # two fish among six honest patrons
    voter, at = auction["buyers"][0]["model_id"], auction["buyers"][0]["iteration"]
    for iteration, model_id in ((0, honest_ids[-1]), (at, voter)):
        page.locator(f"button.explain-round[data-iteration='{iteration}']").focus()
        page.keyboard.press("Enter")
        assert page.evaluate("document.activeElement.id") == "explain-patron"
        page.select_option("#explain-patron", str(model_id))
        page.locator("#explain-form button[type='submit']").focus()
        page.keyboard.press("Enter")
        card = page.locator("#explanation .explanation")
        card.wait_for(timeout=WAIT_MS)
        page.wait_for_function(
            "() => document.querySelector('#explanation h3')"
            f"?.textContent.endsWith('iteration {iteration}')"
        )
        expected = api.get(f"/auctions/{auction_id}/iterations/{iteration}/votes/{model_id}").json()
        assert card.get_attribute("data-vote") == expected["vote"]
        inspector = card.locator("a[href^='#/models/']")
        assert inspector.get_attribute("href") == f"#/models/{expected['version_id']}"
        # Every vote of the iteration in one table, as the API lists them.
        listed = api.get(f"/auctions/{auction_id}/iterations/{iteration}/votes").json()["votes"]
        table = page.locator(f"#round-votes-table[data-iteration='{iteration}']")
        table.wait_for(timeout=WAIT_MS)
        rows = [
            [td.text_content() for td in tr.locator("td").all()]
            for tr in table.locator("tbody tr").all()
        ]
        assert [(r[0], r[2], r[3]) for r in rows] == [
            (v["participant"], v["vote"], f"{v['decision']['B']:.3f}") for v in listed
        ]
        for part in ("sensor", "decision", "judgement", "pfc"):
            cells = [
                [td.text_content() for td in tr.locator("td").all()]
                for tr in card.locator(f"table[data-part='{part}'] tbody tr").all()
            ]
            assert [(c[0], c[2]) for c in cells] == [
                (name, f"{value:.4f}") for name, value in expected[part].items()
            ]
        # Each neuron's push on each logit (weight × value) and the bias add up to the logit;
        # the words name the runner-up and what pushed the vote over it the most.
        pushes = card.locator("table[data-part='pushes'] tbody tr")
        pushes.first.wait_for(timeout=WAIT_MS)
        cells = [[td.text_content() or "" for td in tr.locator("td").all()] for tr in pushes.all()]
        assert [c[0] for c in cells] == [*expected["sensor"], "bias"]
        for column, logit in enumerate("BLQ", start=1):
            total = sum(float(c[column].replace("−", "-")) for c in cells)
            assert total == pytest.approx(expected["decision"][logit], abs=5e-4)
        words = page.text_content("#push-words") or ""
        won = {"buy": "B", "hold": "L", "quit": "Q"}[expected["vote"]]
        assert words.startswith(f"{won} {expected['decision'][won]:.4f} against ")
        assert "pushed" in words and "the most" in words
        page.set_viewport_size(PHONE)  # a phone: the table scrolls
        assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
        page.set_viewport_size(VIEWPORT)
        verdict = page.text_content("#verdict-words") or ""
        right = expected["pfc"]["T"] >= expected["pfc"]["F"]
        assert (f"judged this {expected['vote']} right" in verdict) is right, verdict
    assert card.get_attribute("data-vote") == "buy"  # the buyer's vote in its iteration
    assert page.locator("#explain-round option").count() == last + 1
    screenshot(page.locator("#explain"), "ui_vote.png", tmp_path)
    # The patron picker names participants, and offers only those who voted in the iteration.
    left = {b["model_id"]: b["iteration"] for b in auction["buyers"]}
    left |= {q["model_id"]: q["iteration"] for q in auction["quitter_details"]}
    named = dict(zip(auction["model_ids"], auction["participants"], strict=True))
    assert any(at < last for at in left.values())  # someone left before the last iteration
    for iteration in (0, last):
        page.select_option("#explain-round", str(iteration))
        options = page.locator("#explain-patron option").all()
        voters = [m for m in auction["model_ids"] if left.get(m, iteration) >= iteration]
        assert [int(o.get_attribute("value")) for o in options] == voters
        assert [o.text_content() for o in options] == [named[m] for m in voters]


@pytest.fixture(scope="module")
def tuned_auction(
    api: httpx.Client, population: dict[str, dict[str, Any]]
) -> tuple[int, tuple[int, int]]:
    """An auction whose market fine-tunes the honest patrons after its first 2 rounds, played
    to its end: its id, and a round and patron whose vote came from fine-tuned weights."""
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    body = {"n_fish": 2, "model_ids": honest_ids, "fine_tune": True, "fine_tune_rounds": 2}
    auction_id = api.post("/auctions", json=body, headers=headers).json()["auction_id"]
    deadline = time.monotonic() + 60
    while (auction := api.get(f"/auctions/{auction_id}").json())["status"] != "finished":
        assert time.monotonic() < deadline, "the auction never finished"
        time.sleep(0.2)
    for row in auction["history"]:
        listed = api.get(f"/auctions/{auction_id}/iterations/{row['iteration']}/votes").json()
        tuned = [v["model_id"] for v in listed["votes"] if v["fine_tuned_after"] is not None]
        if tuned:
            return int(auction_id), (row["iteration"], tuned[0])
    raise AssertionError("the market fine-tuned nobody")


def test_a_vote_after_fine_tuning_in_the_market_leads_to_the_weights_that_cast_it(
    page: Any,
    server: ServerProcess,
    api: httpx.Client,
    tuned_auction: tuple[int, tuple[int, int]],
    tmp_path: Path,
) -> None:
    auction_id, (iteration, tuned) = tuned_auction
    vote = api.get(f"/auctions/{auction_id}/iterations/{iteration}/votes/{tuned}").json()
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#liveness:has-text('Ended')", timeout=WAIT_MS)
    page.locator(f"button.explain-round[data-iteration='{iteration}']").click()
    bid_with = page.locator(f"#round-votes-table a[href$='/votes/{tuned}/weights']")
    assert bid_with.text_content() == (
        f"version {vote['version']}, tuned after iteration {vote['fine_tuned_after']}"
    )
    page.locator(f"button.explain-vote[data-model='{tuned}']").click()
    # The explanation comes whole, its pushes with it: no table drawn later above the link
    # moves it from under a press (released on the table, the click was lost).
    page.locator("#voted-weights a[href$='/weights']").wait_for(timeout=WAIT_MS)
    assert page.locator("#pushes table[data-part='pushes']").count() == 1
    page.locator("#voted-weights a[href$='/weights']").click()
    page.wait_for_selector("#weight-moves", timeout=WAIT_MS)
    assert page.evaluate("document.activeElement.tagName") == "H1"
    origin = page.locator("#weights-origin").text_content()
    assert f"after iteration {vote['fine_tuned_after']}" in origin
    tunings = api.get(f"/auctions/{auction_id}/iterations/{iteration}/votes/{tuned}/weights")
    items = page.locator("#fine-tunings > li").all()
    assert [(i.text_content() or "").split(":")[0] for i in items] == [
        f"after iteration {f['after']}" for f in tunings.json()["fine_tunings"]
    ]
    for item, f in zip(items, tunings.json()["fine_tunings"], strict=True):
        said = item.text_content() or ""  # a refusal names its rules, a kept one says kept
        assert ("kept (" in said) is f["kept"] and all(r["rule"] in said for r in f["reasons"])
    # The largest move shown is the largest between the version and the weights that voted.
    weights = api.get(f"/auctions/{auction_id}/iterations/{iteration}/votes/{tuned}/weights")
    version = api.get(f"/models/{vote['version_id']}").json()["manifest"]
    here = weights.json()["manifest"]
    moves = [
        abs(here[layer][n]["weights"][k] - version[layer][n]["weights"][k])
        for layer in ("decision",)
        for n in here[layer]
        for k in here[layer][n]["weights"]
    ]
    cells = page.locator("#weight-moves tbody tr").first.locator("td").all()
    assert abs(float(cells[3].text_content().replace("\u2212", "-"))) >= max(moves) - 1e-6
    for row in page.locator("#weight-moves tbody tr").all():  # rounded, as the weights are
        before, after = (cell.text_content() for cell in row.locator("td").all()[1:3])
        assert all(re.fullmatch(r"[+\u2212]?\d+\.\d{4,8}", x) for x in (before, after))
    screenshot(page.locator("section:has(#weight-moves)"), "ui_voted_weights.png", tmp_path)


def test_an_ended_auction_is_shown_ended_from_its_first_read(
    page: Any, server: ServerProcess, tuned_auction: tuple[int, tuple[int, int]]
) -> None:
    """An auction read as ended is never shown running while its event stream catches up:
    its summary says how it ended from the first draw (it said "running" until the stream's
    end, seconds under load, and the buttons below it moved when it changed)."""
    auction_id, _ = tuned_auction
    played = len(httpx.get(f"{server.url}/auctions/{auction_id}", timeout=30).json()["history"])
    page.add_init_script(  # each summary drawn: its status and its count of iterations
        "window.srdSummaries = [];"
        "new MutationObserver(() => {"
        "  const summary = document.querySelector('#auction-summary');"
        "  if (!summary) return;"
        "  const drawn = summary.querySelector('.badge').textContent + ' '"
        "    + summary.textContent.match(/Iterations(\\d+)/)[1];"
        "  const seen = window.srdSummaries;"
        "  if (seen[seen.length - 1] !== drawn) seen.push(drawn);"
        "}).observe(document, { childList: true, subtree: true });"
    )
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#liveness:has-text('Ended')", timeout=WAIT_MS)
    assert page.evaluate("window.srdSummaries") == [f"finished {played}"]


def test_the_votes_chart_tells_buy_hold_and_quit_apart_without_colour(
    page: Any, server: ServerProcess, tuned_auction: tuple[int, tuple[int, int]]
) -> None:
    """Buy, hold and quit were green, amber and grey only (alike in grey): each kind's bars
    are filled from a pattern of its own (buy solid, hold hatched, quit dotted), the legend's
    keys drawn alike, and the chart's name says every iteration's counts."""
    auction_id, _ = tuned_auction
    history = httpx.get(f"{server.url}/auctions/{auction_id}", timeout=30).json()["history"]
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#liveness:has-text('Ended')", timeout=WAIT_MS)
    page.wait_for_selector("#votes-chart rect.vote-hold", state="attached", timeout=WAIT_MS)
    # Each bar's fill: the pattern it names in the chart's own <defs>, and how many shapes
    # make a tile of it (a colour's square alone, or with stripes or dots on it).
    tiles = """(kind) => [...document.querySelectorAll(`#votes-chart rect.vote-${kind}`)].map(
      (r) => {
        const id = getComputedStyle(r).fill.match(/^url\\("?#([^")]+)"?\\)$/)?.[1];
        const tile = id && document.querySelector(`#votes-chart defs pattern#${id}`);
        return tile ? `${id} ${tile.children.length}` : getComputedStyle(r).fill; })"""
    drawn = {kind: set(page.evaluate(tiles, kind)) for kind in ("buy", "hold", "quit")}
    assert drawn == {
        "buy": {"votes-chart-buy 1"},  # solid
        "hold": {"votes-chart-hold 2"},  # hatched
        "quit": {"votes-chart-quit 2"},  # dotted
    }
    # The legend's keys differ in more than their colours: their textures.
    textures = page.evaluate(
        "[...document.querySelectorAll('figcaption .key')].map((k) => getComputedStyle(k)"
        ".backgroundImage)"
    )
    assert len(textures) == 3 and len(set(textures)) == 3, textures
    label = page.get_attribute("#votes-chart", "aria-label") or ""
    for row in history:
        votes = row["votes"]
        said = f"iteration {row['iteration']}: {votes['buy']} buy, {votes['hold']} hold, "
        assert f"{said}{votes['quit']} quit" in label, label


def test_a_deadline_already_past_is_said_to_have_passed_not_as_until(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    """A round still open, or an auction still taking patrons, after its deadline (its close
    pending, the server restarting): by the reader's clock (here an hour ahead) the page says
    the deadline passed; it said "until 13:02" of a time already gone."""
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    body = {"n_fish": 1, "model_ids": honest_ids, "fine_tune_mode": "remote"}
    body |= {"fine_tune_rounds": 1, "round_deadline_s": 120, "seed": 1}
    remote = api.post("/auctions", json=body, headers=headers).json()["auction_id"]
    body = {"rarity": 0.5, "enrollment_s": 600, "seed": 5}
    enrolling = api.post("/auctions", json=body, headers=headers).json()["auction_id"]
    local = (
        "(iso) => new Date(iso).toLocaleString(undefined, {dateStyle: 'short', timeStyle: 'long'})"
    )
    try:
        page.clock.set_fixed_time(time.time() + 3600)
        page.goto(f"{server.url}/ui/#/auctions/{enrolling}")
        until = page.evaluate(local, api.get(f"/auctions/{enrolling}").json()["enroll_until"])
        page.wait_for_selector("#auction-summary", timeout=WAIT_MS)
        fact = page.locator("#auction-summary dt:has-text('patrons until') + dd")
        assert fact.text_content() == f"{until} (passed; starting)"
        assert "Took patrons until" in (page.text_content("#auction-summary") or "")
        page.wait_for_selector("#liveness:has-text('Following live')", timeout=WAIT_MS)
        assert page.text_content("#liveness") == (
            f"Following live: enrollment deadline {until} passed; starting: the first iteration"
            " appears once it starts."
        )
        page.goto(f"{server.url}/ui/#/auctions/{remote}")
        cell = page.locator("#fine-tuning tr[data-round='1'] td").nth(3)
        cell.wait_for(timeout=WAIT_MS)
        deadline = api.get(f"/auctions/{remote}/rounds/current").json()["deadline"]
        assert cell.text_content() == f"deadline {page.evaluate(local, deadline)} passed; closing"
        page.wait_for_selector("#liveness:has-text('Following live')", timeout=WAIT_MS)
        live = page.text_content("#liveness") or ""
        assert "round 1's deadline" in live and "passed; closing (" in live and "until" not in live
    finally:
        for auction_id in (remote, enrolling):
            api.delete(f"/auctions/{auction_id}", headers=headers)


def test_a_vote_explained_before_its_iterations_votes_arrive_is_drawn_below_them(
    page: Any, server: ServerProcess, tuned_auction: tuple[int, tuple[int, int]]
) -> None:
    """ "Explain the vote" pressed while the iteration's votes table is still coming (a slow
    read): the explanation waits for it, so no table lands above its links once they are
    shown (it was drawn first, and the table moved its links from under the reader)."""
    auction_id, (iteration, _) = tuned_auction
    page.add_init_script(  # the votes of an iteration come 1.5 s late
        "const realFetch = window.fetch;"
        "window.fetch = (url, ...rest) => String(url).endsWith('/votes')"
        "  ? new Promise((ok) => setTimeout(ok, 1500)).then(() => realFetch(url, ...rest))"
        "  : realFetch(url, ...rest);"
    )
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#liveness:has-text('Ended')", timeout=WAIT_MS)
    page.locator(f"button.explain-round[data-iteration='{iteration}']").click()
    page.locator("#explain-form button[type='submit']").click()
    page.locator("#voted-weights a").first.wait_for(timeout=WAIT_MS)
    assert page.locator("#round-votes-table").count() == 1


def test_a_missing_auction_job_model_or_participant_gets_a_not_found_page(
    page: Any, server: ServerProcess
) -> None:
    for path, what, back in (
        ("auctions/999999", "Auction 999999", "#/"),
        ("auctions/abc", "Auction abc", "#/"),
        ("auctions/999999/iterations/0/votes/1/weights", "Auction 999999", "#/"),
        ("jobs/999999", "Job 999999", "#/jobs"),
        ("models/0", "Model 0", "#/models"),
        ("models/-1", "Model -1", "#/models"),
        # beyond JavaScript's exact integers: said as written, not as 1e20
        ("models/99999999999999999999", "Model 99999999999999999999", "#/models"),
        ("participants/nobody-by-this-name", "Participant nobody-by-this-name", "#/models"),
    ):
        page.goto(f"{server.url}/ui/#/{path}")
        page.wait_for_selector("#not-found", timeout=WAIT_MS)
        assert page.locator("#not-found").text_content() == f"{what} does not exist."
        assert page.locator("#not-found + p a").get_attribute("href") == back
        assert page.locator("h1").all_text_contents() == ["Not found"]
        assert page.title() == "Not found · srd-auction"
        assert page.locator("svg.chart, table").count() == 0


def test_a_detail_page_whose_first_read_fails_shows_its_subject_once_the_server_answers(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    """An auction, a model and a job opened while the server is out of reach: each page says
    so with a "Try again now" button, reads again by itself every few seconds, and shows its
    subject once the server answers (it used to say "could not be reached" for good)."""
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    auction_id = create_unstarted_auction(server.database_url, honest_ids, n_fish=1, seed=6)
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    assert api.delete(f"/auctions/{auction_id}", headers=headers).status_code == 200
    job = api.post("/jobs", json={"kind": "fish", "params": {"steps": 600}}, headers=headers)
    job_id = job.json()["job_id"]
    model_id = population["saboteur"]["model_id"]
    down = re.compile(r"/(auctions|models|jobs)/\d+$|/ui/(kinds|neurons)\.json$")
    for address, shown, pressed in (
        (f"auctions/{auction_id}", "#liveness:has-text('Ended: cancelled')", False),
        (f"models/{model_id}", "#verdict", True),
        (f"jobs/{job_id}", f"h1:has-text('Job {job_id}: fish')", False),
    ):
        page.route(down, lambda route: route.abort())
        page.goto(f"{server.url}/ui/#/{address}")
        failed = page.locator("p.problem:has-text('could not be reached')")
        failed.wait_for(timeout=WAIT_MS)
        # nothing of the subject is said while it is unread: no "none yet" for an auction
        # that has iterations, say
        assert page.locator("main .none-yet:visible, main section:visible").count() == 0
        page.unroute(down)
        if pressed:  # at once, by the button
            assert "The page tries again every few seconds." in (failed.text_content() or "")
            page.click("#read-again")
            page.wait_for_selector(shown, timeout=2000)
        else:  # by itself
            read_again_now(page)
            page.wait_for_selector(shown, timeout=WAIT_MS)
        assert failed.count() == 0, address
    assert page.locator("#job-state dt:has-text('Kind') + dd").text_content() == "fish"


def test_a_review_page_whose_first_read_fails_reads_again_until_the_server_answers(
    page: Any, server: ServerProcess, population: dict[str, dict[str, Any]]
) -> None:
    """The review queue and an inspection page opened while the server is out of reach read
    again every few seconds, as the other detail pages do (they stayed dead until a reload);
    a token refused meanwhile is asked for again, not read with forever."""
    queue = "**/reviews?*"
    page.route(queue, lambda route: route.abort())
    page.goto(f"{server.url}/ui/#/reviews")
    page.fill("#admin-token", ADMIN_TOKEN)
    page.keyboard.press("Enter")
    failed = page.locator("p.problem:has-text('could not be reached')")
    failed.wait_for(timeout=WAIT_MS)
    assert "The page tries again every few seconds." in (failed.text_content() or "")
    refused = {"detail": [{"msg": "not the admin token"}]}
    page.unroute(queue)
    page.route(queue, lambda route: route.fulfill(status=401, json=refused))
    read_again_now(page)
    page.wait_for_selector("#admin-token-status:has-text('not the admin token')", timeout=8000)
    page.unroute(queue)
    page.fill("#admin-token", ADMIN_TOKEN)
    page.keyboard.press("Enter")
    page.wait_for_selector("#review-list, #no-reviews", timeout=WAIT_MS)
    # An inspection page, at once by its button (the token kept in the page's memory).
    accepted = next(a for name, a in population.items() if name.startswith("honest"))
    page.route(queue, lambda route: route.abort())
    page.goto(f"{server.url}/ui/#/reviews/{accepted['model_id']}")
    failed.wait_for(timeout=WAIT_MS)
    page.unroute(queue)
    page.click("#read-again")
    page.wait_for_selector("#not-held", timeout=2000)
    assert failed.count() == 0


@pytest.fixture(scope="module")
def axe_source(tmp_path_factory: pytest.TempPathFactory) -> str:
    """axe-core from npm, installed into a temporary folder (never committed)."""
    npm = shutil.which("npm")
    if npm is None:
        pytest.skip("npm is missing: the accessibility check needs it to install axe-core")
    folder = tmp_path_factory.mktemp("axe")
    installed = subprocess.run(
        [npm, "install", "--prefix", str(folder), "--no-audit", "--no-fund", "axe-core@4"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if installed.returncode != 0:
        pytest.skip(f"npm could not install axe-core: {installed.stderr.strip()[-300:]}")
    return (folder / "node_modules" / "axe-core" / "axe.min.js").read_text()


def serious_violations(page: Any, axe_source: str) -> list[str]:
    """axe-core's serious and critical findings on the page as it stands."""
    page.evaluate(axe_source)  # through the driver: the page's CSP forbids inline scripts
    found = page.evaluate("axe.run(document).then((r) => JSON.stringify(r.violations))")
    return [
        f"{v['id']} ({v['impact']}): {[n['target'] for n in v['nodes']][:3]}"
        for v in json.loads(found)
        if v["impact"] in ("serious", "critical")
    ]


def test_every_page_passes_axe_and_the_heading_is_focused_only_on_navigation(
    page: Any,
    server: ServerProcess,
    api: httpx.Client,
    population: dict[str, dict[str, Any]],
    studies: list[dict[str, Any]],
    axe_source: str,
    tuned_auction: tuple[int, tuple[int, int]],
) -> None:
    page.goto(f"{server.url}/ui/#/jobs/{studies[0]['id']}")
    page.wait_for_selector("#headline .card", timeout=WAIT_MS)
    assert page.evaluate("document.activeElement.tagName") == "BODY"  # not the heading at load
    auction_id, (iteration, tuned) = tuned_auction
    tuned_name = api.get(f"/models/{tuned}").json()["participant"]
    views = {
        "#/auctions": "#auction-list tbody tr",
        f"#/auctions/{auction_id}": "#liveness:has-text('Ended')",
        "#/models": "#model-list tbody tr",
        f"#/models/{population['saboteur']['model_id']}": "#verdict",
        f"#/participants/{tuned_name}": "#entries tbody tr",
        "#/jobs": "#job-list tbody tr",
        f"#/jobs/{studies[0]['id']}": "#headline .card",
        f"#/jobs/compare?ids={studies[0]['id']},{studies[1]['id']}": "#compare-params",
        "#/auctions/999999": "#not-found",
        f"#/auctions/{auction_id}/iterations/{iteration}/votes/{tuned}/weights": "#weight-moves",
    }
    problems: dict[str, list[str]] = {}
    for address, ready in views.items():
        page.goto(f"{server.url}/ui/{address}")
        page.wait_for_selector(ready, timeout=WAIT_MS)
        if address == f"#/auctions/{auction_id}":
            page.locator("button.explain-round").first.click()
            page.wait_for_selector("#round-votes-table", timeout=WAIT_MS)
            page.locator("#explain-form button[type='submit']").click()
            page.wait_for_selector("#explanation .explanation", timeout=WAIT_MS)
        found = serious_violations(page, axe_source)
        if found:
            problems[address] = found
    assert problems == {}


def test_an_inspector_admits_a_held_model_on_its_inspection_page(
    page: Any, server: ServerProcess, api: httpx.Client, axe_source: str, tmp_path: Path
) -> None:
    # Honest seed 1 is borderline: its fine-tuned version's copies land near the bar, so the
    # impact test's second stage judges them on 96 auctions: 5.0938 against the bar 5.0918,
    # within the default review margin (0.005).
    held = api.post("/submit", json=honest(f"ui-held-{time.time_ns()}", seed=1)).json()
    assert held["status"] == "held", held
    model_id = held["model_id"]
    page.goto(f"{server.url}/ui/#/reviews")
    page.wait_for_selector("#token-form", timeout=WAIT_MS)
    assert page.evaluate("document.activeElement.tagName") == "BODY"  # first load: at the top
    page.focus("#admin-token")  # an empty token is said in words, the field marked invalid
    page.keyboard.press("Enter")
    page.wait_for_selector("#admin-token-status:has-text('the field is blank')", timeout=WAIT_MS)
    assert page.get_attribute("#admin-token", "aria-invalid") == "true"
    page.fill("#admin-token", "not-the-token")
    assert page.get_attribute("#admin-token", "aria-invalid") is None  # typing clears it
    page.keyboard.press("Enter")
    page.wait_for_selector("p.problem:has-text('not the admin token')", timeout=WAIT_MS)
    assert page.get_attribute("#admin-token", "aria-invalid") == "true"
    page.fill("#admin-token", ADMIN_TOKEN)
    page.keyboard.press("Enter")
    row = page.locator(f"#review-list a[href='#/reviews/{model_id}']")
    row.wait_for(timeout=WAIT_MS)
    # the token's field is gone: the focus is on the page's heading, not lost to the body
    page.wait_for_function("() => document.activeElement.tagName === 'H1'", timeout=5000)
    listed = page.text_content("#review-list") or ""
    assert "market-impact" in listed and "within the review margin 0.0050 of its bar" in listed
    assert re.search(r"(passed|missed) by 0\.00[0-4][0-9]", listed), listed  # how close
    row.focus()
    page.keyboard.press("Enter")
    page.wait_for_selector("#evidence figure svg", timeout=WAIT_MS)
    page.wait_for_function("() => document.activeElement.tagName === 'H1'", timeout=5000)
    assert (page.text_content("#verdict") or "").startswith("Held")
    # The named neurons, as the models view draws them.
    for name in (*ES_NEURONS, *DECISIONS):
        assert page.locator(f"#network-decision g.neuron[data-neuron='{name}']").count() == 1
    # The evidence drawn: decisions clean and noisy across prices; the impact test's prices.
    charts = page.locator("#evidence figure svg")
    assert charts.count() == 2
    assert page.locator("#evidence figure svg rect.vote-buy").count() >= 2
    impact_chart = charts.nth(1).text_content() or ""  # each stage's bar, named
    assert "bar 5.0857 (16 auctions)" in impact_chart
    assert "bar 5.0918 (96 auctions)" in impact_chart
    assert "copies, after its own fine-tuning (96 auctions)" in impact_chart
    model = api.get(f"/models/{model_id}").json()
    assert page.locator("#evidence-table tbody tr").count() == len(model["evidence"])
    # the populations its test met, which this server's test still meets (no secret here)
    assert page.locator("#populations").text_content() == (
        "Its test auctions used the public reference populations (no deployment secret set)."
    )
    # On a phone the market-impact chart scrolls in its frame, its values and bar labels
    # inside it (the page itself does not scroll sideways).
    page.set_viewport_size(PHONE)
    frame = page.locator("#evidence [role='region']:has(svg)").nth(1)
    assert frame.evaluate("(f) => f.scrollWidth > f.clientWidth")
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
    outside = charts.nth(1).evaluate(
        """(chart) => [...chart.querySelectorAll('text')].filter((t) => {
            const box = t.getBBox();
            return box.x < 0 || box.x + box.width > chart.viewBox.baseVal.width;
        }).map((t) => t.textContent)"""
    )
    assert outside == []
    page.set_viewport_size(VIEWPORT)
    assert serious_violations(page, axe_source) == []
    screenshot(page.locator("#evidence"), "ui_review.png", tmp_path)
    # Said in words (not the browser's bubble): a blank name, and a network that drops the
    # decision.
    for blank in ("", "   "):
        page.fill("#inspector", blank)
        page.click("#admit")
        page.wait_for_selector("#decision-status:has-text('must name someone')", timeout=WAIT_MS)
        assert page.evaluate("document.activeElement.id") == "inspector"
        page.evaluate("document.querySelector('#decision-status').replaceChildren()")
    review = f"**/models/{model_id}/review"
    page.route(review, lambda r: r.abort())
    page.fill("#inspector", "Ada")
    page.click("#admit")
    page.wait_for_selector("#decision-status:has-text('could not be reached')", timeout=WAIT_MS)
    assert "whether it was recorded is unknown" in (page.text_content("#decision-status") or "")
    page.unroute(review)
    # Enter in the Inspector field decides nothing (it used to submit with Admit, the first
    # button): the page says how to decide, and the model stays held.
    page.fill("#inspector", "Mallory")
    page.focus("#inspector")
    page.keyboard.press("Enter")
    page.wait_for_selector("#decision-status:has-text('Nothing recorded')", timeout=WAIT_MS)
    model = api.get(f"/models/{model_id}").json()
    assert (model["status"], model["reviews"]) == ("held", [])
    # Keyboard: name, note, then the admit button.
    page.fill("#inspector", "Ada")
    page.fill("#note", "a sincere low bidder")
    page.focus("#admit")
    page.keyboard.press("Enter")
    page.wait_for_selector("#decision-status:has-text('now accepted')", timeout=WAIT_MS)
    # The verdict and the review history at the top say so, and the focus is on what the
    # decision did.
    assert (page.text_content("#verdict") or "").startswith("Admitted by inspector Ada")
    assert "Ada admitted: a sincere low bidder" in (page.text_content("#model-audit") or "")
    said = page.text_content("#decision-status") or ""
    assert "(admitted by Ada)" in said and "a sincere low bidder" not in said  # one sentence
    assert page.evaluate("document.activeElement.id") == "decision-status"
    model = api.get(f"/models/{model_id}").json()
    assert (model["status"], model["accepted"]) == ("accepted", True)
    assert [(r["decision"], r["inspector"], r["note"]) for r in model["reviews"]] == [
        ("admit", "Ada", "a sincere low bidder")
    ]
    queue = api.get("/reviews", headers={"Authorization": f"Bearer {ADMIN_TOKEN}"}).json()
    assert model_id not in [item["id"] for item in queue["items"]]
    # Its page says who decided, and what the screener had found.
    page.goto(f"{server.url}/ui/#/models/{model_id}")
    page.wait_for_selector("#verdict:has-text('Admitted by inspector Ada')", timeout=WAIT_MS)
    assert "the screener had held it" in (page.text_content("#verdict") or "")
    assert "a sincere low bidder" in (page.text_content("#model-audit") or "")
    # The models list says an inspector decided, not the screener.
    page.goto(f"{server.url}/ui/#/models?participant={model['participant']}")
    row = page.locator(f"tr:has(a[href='#/models/{model_id}'])")
    row.wait_for(timeout=WAIT_MS)
    assert "admitted by an inspector" in (row.text_content() or "")


def test_a_decision_another_inspector_made_first_redraws_the_page_as_the_model_stands(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    """The inspection page is open while another inspector admits the model: pressing Refuse
    is refused (409), and the page reads the model again: the verdict and the review history
    say who admitted it, and no decision is offered any more (it said "Held" with both
    buttons)."""
    model_id = held_on_appeal(api, "ui-race")
    try:
        page.goto(f"{server.url}/ui/#/reviews/{model_id}")
        page.fill("#admin-token", ADMIN_TOKEN)
        page.keyboard.press("Enter")
        page.wait_for_selector("#decision", timeout=WAIT_MS)
        assert (page.text_content("#verdict") or "").startswith("Held")
        other = {"decision": "admit", "inspector": "Carol", "note": "sincere"}
        headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
        admitted = api.post(f"/models/{model_id}/review", json=other, headers=headers)
        assert admitted.status_code == 200, admitted.text
        page.fill("#inspector", "Dave")
        page.click("#refuse")
        page.wait_for_selector(
            f"#decision-status:has-text('model {model_id} is accepted')", timeout=WAIT_MS
        )
        page.wait_for_selector("#verdict:has-text('Admitted by inspector Carol')", timeout=WAIT_MS)
        assert "Carol admitted: sincere" in (page.text_content("#model-audit") or "")
        assert page.locator("#admit, #refuse, #inspector, #note").count() == 0
        assert page.evaluate("document.activeElement.id") == "decision-status"
        model = api.get(f"/models/{model_id}").json()
        assert [(r["decision"], r["inspector"]) for r in model["reviews"]][-1] == ("admit", "Carol")
    finally:
        refuse(api, model_id)  # already decided: refused 409, a no-op


def test_the_review_queue_keeps_why_a_model_is_held_readable_on_a_phone(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    """At 360 px the queue scrolls sideways in its frame: "Why held" keeps a readable width
    (it was a word wide) and each model's link reads on one line ("Inspect model 8", not
    "Inspec / t model 8")."""
    model_id = held_on_appeal(api, "ui-queue")
    try:
        page.set_viewport_size({"width": 360, "height": 800})
        page.goto(f"{server.url}/ui/#/reviews")
        page.fill("#admin-token", ADMIN_TOKEN)
        page.keyboard.press("Enter")
        inspect = page.locator(f"#review-list a[href='#/reviews/{model_id}']")
        inspect.wait_for(timeout=WAIT_MS)
        assert inspect.evaluate("(a) => a.getClientRects().length") == 1  # one line
        why = page.locator(f"#review-list tr:has(a[href='#/reviews/{model_id}']) td").nth(3)
        said = why.text_content() or ""  # the screener's refusal, then the appeal, quoted
        assert said.startswith("refused by the screener: ") and said.endswith("; appealed: x"), said
        assert why.evaluate("(td) => td.getBoundingClientRect().width") >= 300
        frame = page.locator("#review-list").locator("xpath=..")
        assert frame.evaluate("(f) => f.scrollWidth > f.clientWidth")  # the frame scrolls
        assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
    finally:
        refuse(api, model_id)


def test_hidden_tabs_let_go_of_their_streams_so_a_seventh_live_view_loads(
    browser: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    """A browser holds at most six HTTP/1.1 connections to one server: six open live views
    used to block every other page of the site. A tab that is hidden closes its stream, and
    catches up from where it was when shown again."""
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    body = {"n_fish": 1, "model_ids": honest_ids, "fine_tune_mode": "remote"}
    body |= {"round_deadline_s": 120, "fine_tune_rounds": 1, "max_iterations": 3}
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    auction_id = api.post("/auctions", json=body, headers=headers).json()["auction_id"]
    seen_as = """(state) => {
        Object.defineProperty(document, "visibilityState", { value: state, configurable: true });
        document.dispatchEvent(new Event("visibilitychange"));
    }"""
    context = browser.new_context(viewport=VIEWPORT)
    try:
        tabs = []
        for _ in range(7):
            tab = context.new_page()
            tab.goto(f"{server.url}/ui/#/auctions/{auction_id}")
            tab.wait_for_selector("#liveness:has-text('Following live')", timeout=WAIT_MS)
            tab.wait_for_selector("#fine-tuning tr[data-round='1']", timeout=WAIT_MS)
            tab.evaluate(seen_as, "hidden")
            assert "Paused" in (tab.text_content("#liveness") or "")
            tabs.append(tab)
        # an iteration committed, the auction still running: its votes can be explained already
        assert tabs[0].locator("#explain-form button[type='submit']").is_enabled()
        other = context.new_page()  # an eighth page of the site, with seven live views open
        other.goto(f"{server.url}/ui/#/models")
        other.wait_for_selector("#model-list tbody tr", timeout=WAIT_MS)
        first = tabs[0]
        first.evaluate(seen_as, "visible")
        first.wait_for_selector("#liveness:has-text('Following live')", timeout=WAIT_MS)
        cancelled = api.delete(f"/auctions/{auction_id}", headers=headers)
        assert cancelled.status_code == 200, cancelled.text
        first.wait_for_selector("#liveness:has-text('Ended: cancelled')", timeout=WAIT_MS)
        assert first.locator("#rounds tbody tr").count() == 1  # iteration 0, once
    finally:
        context.close()


def test_a_refused_stream_still_shows_the_auction_and_its_end(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    """A viewer whose stream the server refuses (past its address's share, say: 429) reads the
    auction instead: its iterations, buyers and end, as the stream would have shown them."""
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    body = {"n_fish": 2, "model_ids": honest_ids, "seed": 4}
    auction_id = api.post("/auctions", json=body, headers=headers).json()["auction_id"]
    auction = wait_finished(api, auction_id)
    page.route(
        f"{server.url}/auctions/{auction_id}/events*",
        lambda route: route.fulfill(status=429, body="{}", content_type="application/json"),
    )
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#liveness:has-text('Ended: finished')", timeout=WAIT_MS)
    # A stream that never opens (the browser holding it back behind six others, say) is
    # given up after a few seconds and the auction read instead.
    hanging = page.context.new_page()
    hanging.route(f"{server.url}/auctions/{auction_id}/events*", lambda route: None)
    hanging.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    hanging.wait_for_selector("#liveness:has-text('Connecting to live updates')", timeout=WAIT_MS)
    read_again_now(hanging, 8_000)  # the stream's 8 s to open
    hanging.wait_for_selector("#liveness:has-text('Ended: finished')", timeout=WAIT_MS)
    assert page.locator("#rounds tbody tr").count() == len(auction["history"])
    buyers = page.locator("#buyers tbody tr")
    assert buyers.count() == len(auction["buyers"])
    first = auction["buyers"][0]
    link = buyers.nth(0).locator("td").nth(2).locator("a")
    assert link.get_attribute("href") == f"#/models/{first['version_id']}"


def wait_finished(api: httpx.Client, auction_id: int) -> dict[str, Any]:
    deadline = time.monotonic() + 60
    while (auction := api.get(f"/auctions/{auction_id}").json())["status"] != "finished":
        assert time.monotonic() < deadline, "the auction never finished"
        time.sleep(0.2)
    return dict(auction)


def test_a_models_page_says_who_decided_and_keeps_the_review_history(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    saboteur = population["saboteur"]
    word = "A" * 300  # one unbroken word: it must wrap, not widen the page
    appealed = api.post(
        f"/models/{saboteur['model_id']}/appeal",
        json={"note": f"it bargains {word}"},
        headers={"Authorization": f"Bearer {saboteur['token']}"},
    )
    assert appealed.status_code == 200, appealed.text
    page.goto(f"{server.url}/ui/#/models/{saboteur['model_id']}")
    page.wait_for_selector("#verdict", timeout=WAIT_MS)
    assert "its participant appealed" in (page.text_content("#verdict") or "")
    assert word in (page.text_content("#model-audit") or "")
    page.goto(f"{server.url}/ui/#/models?participant={saboteur['participant']}")
    row = page.locator(f"tr:has(a[href='#/models/{saboteur['model_id']}'])")
    row.wait_for(timeout=WAIT_MS)
    assert "held on appeal" in (row.text_content() or "")
    page.goto(f"{server.url}/ui/#/models/{saboteur['model_id']}")
    page.wait_for_selector("#verdict", timeout=WAIT_MS)
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
    page.goto(f"{server.url}/ui/#/reviews")
    page.fill("#admin-token", ADMIN_TOKEN)
    page.keyboard.press("Enter")
    page.wait_for_selector("#review-list", timeout=WAIT_MS)
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
    # The queue follows while it is shown: a model appealed since appears, one decided goes,
    # each said in words, and the focus stays on the link it was on.
    mine = page.locator(f"#review-list a[href='#/reviews/{saboteur['model_id']}']")
    mine.focus()
    late = api.post("/submit", json=saboteur_manifest(unique("ui-appeal"))).json()
    assert late["status"] == "refused", late
    auth = {"Authorization": f"Bearer {late['token']}"}
    appeal = api.post(f"/models/{late['model_id']}/appeal", json={"note": "late"}, headers=auth)
    assert appeal.status_code == 200, appeal.text
    late_row = page.locator(f"#review-list a[href='#/reviews/{late['model_id']}']")
    read_again_now(page)
    late_row.wait_for(timeout=WAIT_MS)
    page.wait_for_selector("#list-state:has-text('1 held since')", timeout=WAIT_MS)
    assert page.evaluate("document.activeElement.getAttribute('href')") == (
        f"#/reviews/{saboteur['model_id']}"
    )
    refused = api.post(
        f"/models/{late['model_id']}/review",
        json={"decision": "refuse", "inspector": "Ada", "note": "holds"},
        headers={"Authorization": f"Bearer {ADMIN_TOKEN}"},
    )
    assert refused.status_code == 200, refused.text
    read_again_now(page)
    late_row.wait_for(state="detached", timeout=WAIT_MS)
    page.wait_for_selector("#list-state:has-text('1 decided or withdrawn')", timeout=WAIT_MS)
    assert mine.count() == 1
    # a read that fails is said, and the next one that works takes the words back
    page.route("**/reviews?*", lambda route: route.abort())
    read_again_now(page)
    page.wait_for_selector("#list-state:has-text('could not be read again')", timeout=WAIT_MS)
    page.unroute("**/reviews?*")
    read_again_now(page)
    page.wait_for_function(
        "() => document.getElementById('list-state').textContent === ''", timeout=WAIT_MS
    )
    assert mine.count() == 1
    page.set_viewport_size(PHONE)  # a phone: tables scroll, not the page
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
    page.set_viewport_size(VIEWPORT)
    # Its inspection page, opened afresh (the token is gone with the page): once the token is
    # entered, the focus is on the page's heading.
    page.goto(f"{server.url}/ui/#/reviews/{saboteur['model_id']}")
    page.reload()
    page.fill("#admin-token", ADMIN_TOKEN)
    page.keyboard.press("Enter")
    page.wait_for_selector("#appeal", timeout=WAIT_MS)
    page.wait_for_function("() => document.activeElement.tagName === 'H1'", timeout=5000)
    decided = api.post(
        f"/models/{saboteur['model_id']}/review",
        json={"decision": "refuse", "inspector": "Grace", "note": "holds to sink the price"},
        headers={"Authorization": f"Bearer {ADMIN_TOKEN}"},
    )
    assert decided.status_code == 200, decided.text
    page.goto(f"{server.url}/ui/#/models/{saboteur['model_id']}")
    page.wait_for_selector("#verdict:has-text('Refused by inspector Grace')", timeout=WAIT_MS)
    assert "the screener had refused it" in (page.text_content("#verdict") or "")
    entries = page.locator("#model-audit li").all_text_contents()
    assert len(entries) == 2 and "Grace refused" in entries[1]
    assert "holds to sink the price" in entries[1]


def test_a_list_whose_first_page_comes_late_lists_each_item_once(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    """The first page read again every 5 s while its first read is still on its way (a slow
    server): the rows the refresh drew are not listed again when the first read arrives."""
    api.post("/submit", json=honest(unique("late-list")))
    page.add_init_script(
        """(() => {
            const real = window.fetch;
            let first = true;
            window.fetch = (url, ...rest) => {
                if (first && String(url).startsWith('/models')) {
                    first = false;
                    const late = () => real(url, ...rest).then((answer) => {
                        window.lateArrived = true;  // its headers are in: the page reads it now
                        return answer;
                    });
                    return new Promise((done) => setTimeout(() => done(late()), 6500));
                }
                return real(url, ...rest);
            };
        })()"""
    )
    page.goto(f"{server.url}/ui/#/models")
    page.wait_for_selector("#model-list tbody tr", timeout=WAIT_MS)  # drawn by the refresh
    page.wait_for_function("() => window.lateArrived === true", timeout=WAIT_MS)
    page.wait_for_timeout(500)  # the late first page's answer has been read and drawn
    links = page.eval_on_selector_all(
        "#model-list tbody tr td:first-child a", "(as) => as.map((a) => a.getAttribute('href'))"
    )
    assert links and len(links) == len(set(links)), links


def test_a_list_offers_new_items_instead_of_pushing_its_rows_down(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    """New versions arrive while the models list shows rows: the rows stay where they are (a
    press lands on the row it began on), a button above them offers the newcomers, said once,
    and pressing it adds them at the top, the focus on the first one's link."""
    api.post("/submit", json=honest(unique("listed")))
    page.goto(f"{server.url}/ui/#/models")
    page.wait_for_selector("#model-list tbody tr", timeout=WAIT_MS)
    top = "#model-list tbody tr:first-child a"
    was = page.get_attribute(top, "href")
    first = page.locator(f"#model-list tr:has(a[href='{was}'])")
    box = first.bounding_box()
    page.evaluate(
        """() => {
            window.said = [];
            const region = document.getElementById('news-said');
            const heard = new MutationObserver(() => window.said.push(region.textContent));
            const what = { childList: true, characterData: true, subtree: true };
            if (region) heard.observe(region, what);
        }"""
    )
    one = api.post("/submit", json=honest(unique("new-one"))).json()["model_id"]
    read_again_now(page)
    offer = page.locator("#show-new")
    page.wait_for_selector(f"#show-new:visible, {top}[href='#/models/{one}']", timeout=WAIT_MS)
    assert page.get_attribute(top, "href") == was and first.bounding_box() == box
    assert offer.text_content() == "1 new model — show"
    two = api.post("/submit", json=honest(unique("new-two"))).json()["model_id"]
    read_again_now(page)
    page.wait_for_selector("#show-new:has-text('2 new models — show')", timeout=WAIT_MS)
    assert page.get_attribute(top, "href") == was and first.bounding_box() == box
    assert page.evaluate("window.said") == ["1 new model — show"]  # said once, not every read
    offer.click()
    offer.wait_for(state="hidden")
    links = page.eval_on_selector_all(
        "#model-list tbody tr td:first-child a", "(as) => as.map((a) => a.getAttribute('href'))"
    )
    assert links[:3] == [f"#/models/{two}", f"#/models/{one}", was]
    assert page.evaluate("document.activeElement.getAttribute('href')") == f"#/models/{two}"


def test_a_listed_row_changes_in_place_so_a_press_across_the_change_lands(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    """An auction's row moves on while the pointer is pressed on its link: the row is the same
    element after the change, and the press, released, opens the auction."""
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    auction_id = create_unstarted_auction(server.database_url, honest_ids, n_fish=1, seed=3)
    page.goto(f"{server.url}/ui/#/auctions")
    row = f"#auction-list tr[data-id='{auction_id}']"
    page.wait_for_selector(f"{row}[data-status='pending']", timeout=WAIT_MS)
    page.evaluate(f'document.querySelector("{row}").marked = true')
    page.locator(f"{row} a").hover()  # a point on the link (its words may wrap)
    page.mouse.down()
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    assert api.delete(f"/auctions/{auction_id}", headers=headers).status_code == 200
    read_again_now(page)
    page.wait_for_selector(f"{row}[data-status='cancelled']", timeout=WAIT_MS)
    assert page.evaluate(f'document.querySelector("{row}").marked') is True
    page.mouse.up()
    page.wait_for_selector("#liveness:has-text('Ended: cancelled')", timeout=WAIT_MS)
    assert page.url.endswith(f"#/auctions/{auction_id}")


def test_a_held_models_row_stays_in_place_so_a_press_across_a_queue_change_lands(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    """The queue is read again while the pointer is pressed on a held model's link, another
    model held meanwhile: the row is the same element after the change, and the press,
    released, opens that model's review (the queue was redrawn whole: the press was lost)."""
    admin = {"Authorization": f"Bearer {ADMIN_TOKEN}"}

    def held() -> int:
        refused = api.post("/submit", json=saboteur_manifest(unique("ui-press"))).json()
        auth = {"Authorization": f"Bearer {refused['token']}"}
        url = f"/models/{refused['model_id']}/appeal"
        assert api.post(url, json={"note": "x"}, headers=auth).status_code == 200
        return int(refused["model_id"])

    first = held()
    second = None
    try:
        page.goto(f"{server.url}/ui/#/reviews")
        page.fill("#admin-token", ADMIN_TOKEN)
        page.keyboard.press("Enter")
        pressed = f"#review-list a[href='#/reviews/{first}']"
        page.wait_for_selector(pressed, timeout=WAIT_MS)
        page.evaluate(f'document.querySelector("{pressed}").marked = true')
        page.locator(pressed).hover()
        page.mouse.down()
        second = held()  # the newest: its row comes after the pressed one's
        read_again_now(page)
        page.wait_for_selector(f"#review-list a[href='#/reviews/{second}']", timeout=WAIT_MS)
        assert page.evaluate(f'document.querySelector("{pressed}").marked') is True
        page.mouse.up()
        page.wait_for_url(f"**/ui/#/reviews/{first}", timeout=WAIT_MS)
    finally:
        for model_id in (first, second):
            if model_id is not None:
                decision = {"decision": "refuse", "inspector": "Ada", "note": "holds"}
                api.post(f"/models/{model_id}/review", json=decision, headers=admin)


def test_the_review_queues_line_of_what_changed_does_not_move_the_queue(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    refused = api.post("/submit", json=saboteur_manifest(unique("ui-still"))).json()
    auth = {"Authorization": f"Bearer {refused['token']}"}
    appeal = api.post(f"/models/{refused['model_id']}/appeal", json={"note": "x"}, headers=auth)
    assert appeal.status_code == 200, appeal.text
    page.goto(f"{server.url}/ui/#/reviews")
    page.fill("#admin-token", ADMIN_TOKEN)
    page.keyboard.press("Enter")
    queue = page.locator("#review-list")
    queue.wait_for(timeout=WAIT_MS)
    at = queue.bounding_box()
    page.route("**/reviews?*", lambda route: route.abort())
    read_again_now(page)
    page.wait_for_selector("#list-state:has-text('could not be read again')", timeout=WAIT_MS)
    assert queue.bounding_box() == at  # the line showed; the table stayed where it was
    page.unroute("**/reviews?*")
    decided = api.post(
        f"/models/{refused['model_id']}/review",
        json={"decision": "refuse", "inspector": "Ada", "note": "holds"},
        headers={"Authorization": f"Bearer {ADMIN_TOKEN}"},
    )
    assert decided.status_code == 200, decided.text


def test_the_jobs_kind_filter_keeps_its_width_when_the_kinds_arrive(
    page: Any, server: ServerProcess
) -> None:
    held: list[Any] = []
    page.route("**/ui/kinds.json", lambda route: held.append(route))  # held until measured
    page.goto(f"{server.url}/ui/#/jobs")
    page.wait_for_selector("#filter-order", timeout=WAIT_MS)
    deadline = time.monotonic() + WAIT_MS / 1000
    while not held and time.monotonic() < deadline:
        page.wait_for_timeout(50)
    assert page.locator("#filter-kind option").count() == 1  # "any" only
    kind, order = page.locator("#filter-kind").bounding_box(), page.locator("#filter-order")
    beside = order.bounding_box()
    held[0].continue_()
    page.wait_for_function("() => document.querySelectorAll('#filter-kind option').length > 1")
    assert page.locator("#filter-kind").bounding_box() == kind
    assert order.bounding_box() == beside


def test_a_malformed_participant_address_gets_the_not_found_page(
    page: Any, server: ServerProcess, api: httpx.Client
) -> None:
    for name in ("%", "%E0%A4%A"):
        page.goto(f"{server.url}/ui/#/participants/{name}")
        page.wait_for_selector("#not-found", timeout=WAIT_MS)
        assert page.locator("h1").all_text_contents() == ["Not found"]
    for address, words in (
        ("auctions?status=bogus", 'No auction status is called "bogus"'),
        ("jobs?status=bogus", 'No job status is called "bogus"'),
        ("models?accepted=bogus", 'not "bogus"'),
        ("models?status=rejected", 'accepted, held or refused, not "rejected"'),
    ):
        page.goto(f"{server.url}/ui/#/{address}")
        page.wait_for_selector(f"p.problem:has-text('{words}')", timeout=WAIT_MS)
    # A filter that matches nothing says so, and the status filter lists that status only.
    nobody = f"nobody-{time.time_ns()}"
    page.goto(f"{server.url}/ui/#/models?participant={nobody}")
    page.wait_for_selector("#no-models:has-text('no such participant')", timeout=WAIT_MS)
    # The list follows without a reload: that participant's first version appears.
    submitted = api.post("/submit", json=honest(nobody, seed=3)).json()
    read_again_now(page)
    page.wait_for_selector(f"#model-list a[href='#/models/{submitted['model_id']}']")
    assert page.locator("#no-models").is_hidden()
    page.goto(f"{server.url}/ui/#/models?status=refused")
    page.wait_for_selector("#model-list tbody tr", timeout=WAIT_MS)
    verdicts = page.locator("#model-list tbody tr td:nth-child(4)").all_text_contents()
    # the screener's refusals read "rejected", an inspector's as the model's page says
    refused = ("rejected", "refused by an inspector")
    assert verdicts and all(any(w in v for w in refused) for v in verdicts), verdicts
    page.goto(f"{server.url}/ui/#/auctions?status=failed")  # no auction of these tests fails
    page.wait_for_selector("#no-auctions:visible", timeout=WAIT_MS)
    assert page.text_content("#no-auctions") == "None matches this filter: no auction is failed."
    assert (page.text_content("#auction-list caption") or "").startswith("Auctions failed")
    # The last "Show older" goes with its page: the focus moves to the first row it added.
    total = len(api.get("/models", params={"limit": 100}).json()["items"])
    page.route(
        re.compile(r"/models(\?.*)?$"),
        lambda route: route.continue_(
            url=f"{route.request.url}{'&' if '?' in route.request.url else '?'}limit={total - 1}"
        ),
    )
    page.goto(f"{server.url}/ui/#/models")
    page.wait_for_selector("#model-list tbody tr", timeout=WAIT_MS)
    page.locator(".pager button").focus()
    page.keyboard.press("Enter")
    page.wait_for_selector(".pager button", state="detached", timeout=WAIT_MS)
    focused = (
        "[...document.querySelectorAll('#model-list tbody tr')].indexOf(document.activeElement)"
    )
    assert page.evaluate(focused) == total - 1


def test_the_auction_list_follows_its_auctions(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    """Listed auctions move on in place, and a new one appears at the top, without a reload."""
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    body = {"n_fish": 1, "model_ids": honest_ids, "fine_tune_mode": "remote"}
    body |= {"round_deadline_s": 120, "fine_tune_rounds": 1, "max_iterations": 3}
    live = api.post("/auctions", json=body, headers=headers).json()["auction_id"]
    page.goto(f"{server.url}/ui/#/auctions")
    page.wait_for_selector(f"#auction-list tr[data-id='{live}'][data-status='running']")
    page.focus(f"#auction-list a[href='#/auctions/{live}']")
    with page.expect_response(re.compile(r"/auctions(\?.*)?$"), timeout=WAIT_MS) as reread:
        read_again_now(page)  # read again, nothing changed: the row, and the focus, stay alone
    reread.value.finished()
    assert page.evaluate("document.activeElement.getAttribute('href')") == f"#/auctions/{live}"
    running = browser_page(page, f"{server.url}/ui/#/auctions?status=running")
    running.wait_for_selector(f"#auction-list tr[data-id='{live}']")
    assert api.delete(f"/auctions/{live}", headers=headers).status_code == 200
    read_again_now(page)
    page.wait_for_selector(f"#auction-list tr[data-id='{live}'][data-status='cancelled']")
    # the row moved on in place, the focus with it
    assert page.evaluate("document.activeElement.getAttribute('href')") == f"#/auctions/{live}"
    running.wait_for_selector(f"#auction-list tr[data-id='{live}']", state="detached")
    new = api.post("/auctions", json={"n_fish": 1, "model_ids": honest_ids}, headers=headers)
    newest = new.json()["auction_id"]
    read_again_now(page)
    page.locator("#show-new").click(timeout=WAIT_MS)  # offered above the rows, not pushed in
    page.wait_for_selector(f"#auction-list tbody tr:first-child[data-id='{newest}']")


def browser_page(page: Any, url: str) -> Any:
    """Another page of the same browser context, at ``url``."""
    other = page.context.new_page()
    other.goto(url)
    return other
