"""The web view in headless Chromium (Debian's ``chromium``, driven by Playwright; never a
downloaded browser) against a live ``srd serve``: the auction page follows an auction as it
runs, the inspector draws a rejected saboteur with the screener's reasons on its neurons, and
user-supplied strings stay text. Any request to another origin fails the test (offline).

``SRD_UI_SCREENSHOTS=<dir>`` also saves the screenshots shown in the README there:
``SRD_UI_SCREENSHOTS=docs/figures .venv/bin/pytest tests/server/test_ui.py``.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import torch
from sqlalchemy import insert

from agents.manifest import DECISIONS, ES_NEURONS, JUDGEMENTS, PFC_SOURCES, VERDICTS
from server.db import Database
from server.launch import ServerProcess
from server.models import ModelVersion, Participant, utcnow
from tests.support.factories import honest
from tests.support.live import create_unstarted_auction, paced_auction, submit_population
from tests.support.server import ADMIN_TOKEN

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
VIEWPORT = {"width": 1100, "height": 1000}
WAIT_MS = 20_000

if not Path(CHROMIUM).exists():
    pytest.skip(
        f"{CHROMIUM} is missing (Debian's chromium package; .ci/run installs it)",
        allow_module_level=True,
    )


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    data_dir = tmp_path_factory.mktemp("ui")
    env = {"SRD_EVENT_POLL_INTERVAL_S": "0.05"}
    with ServerProcess(
        database_url=f"sqlite:///{data_dir / 'srd.db'}",
        data_dir=data_dir,
        admin_token=ADMIN_TOKEN,
        extra_env=env,
    ) as running:
        yield running


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
    final = int(chart.get_attribute("data-points") or 0)
    assert final == rounds + 1  # one point per round, and the next price
    assert seen[0] <= 2, seen  # the page was open before most rounds were played
    assert seen == sorted(seen) and len(seen) >= 3, seen  # the line grew while the auction ran
    assert page.locator("#rounds tbody tr").count() == rounds
    buyers = page.locator("#buyers tbody tr")
    assert auction["buyers"] and buyers.count() == len(auction["buyers"])
    names = {a["model_id"]: name for name, a in population.items()}
    for row, buyer in zip(buyers.all(), auction["buyers"], strict=True):
        cells = [cell.text_content() for cell in row.locator("td").all()]
        assert cells[0] == names[buyer["model_id"]]
        assert cells[3] == f"{buyer['price']:.3f}" and cells[4] == str(buyer["iteration"])
    summary = page.text_content("#auction-summary") or ""
    assert "finished" in summary and "sold out" in summary
    screenshot(page, "ui_auction.png", tmp_path, full_page=True)


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
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#liveness:has-text('Ended')", timeout=60_000)
    rows = page.locator("#fine-tuning tbody tr")
    assert page.locator("#fine-tuning").is_visible() and rows.count() == 2
    for row, expected in zip(
        rows.all(), api.get(f"/auctions/{auction_id}").json()["fine_tuning"], strict=True
    ):
        cells = [cell.text_content() for cell in row.locator("td").all()]
        assert cells[:3] == [str(expected["round"]), str(expected["iteration"]), "closed"]
        assert cells[4] == f"{len(expected['answers'])} missing"


def test_a_cancelled_auction_shows_its_status_and_why_it_stopped(
    page: Any, server: ServerProcess, api: httpx.Client, population: dict[str, dict[str, Any]]
) -> None:
    honest_ids = [a["model_id"] for name, a in population.items() if name.startswith("honest")]
    auction_id = create_unstarted_auction(server.database_url, honest_ids, n_fish=1, seed=2)
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    assert api.delete(f"/auctions/{auction_id}", headers=headers).status_code == 200
    page.goto(f"{server.url}/ui/#/auctions/{auction_id}")
    page.wait_for_selector("#liveness:has-text('Ended: cancelled')", timeout=WAIT_MS)
    summary = page.text_content("#auction-summary") or ""
    assert "Statuscancelled" in summary and "cancelled by the operator" in summary
    page.goto(f"{server.url}/ui/#/auctions")
    page.wait_for_selector("#auction-list tbody tr", timeout=WAIT_MS)
    rows = [
        [cell.text_content() for cell in row.locator("td").all()]
        for row in page.locator("#auction-list tbody tr").all()
    ]
    (cells,) = [r for r in rows if r[0] == f"Auction {auction_id}"]
    assert cells[1] == "cancelled" and cells[7] == "cancelled by the operator"


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
    decision = page.locator("#network-decision")
    pfc = page.locator("#network-pfc")
    for name in (*ES_NEURONS, *DECISIONS):
        assert decision.locator(f"g.neuron[data-neuron='{name}']").count() == 1
    for name in (*PFC_SOURCES, *JUDGEMENTS, *VERDICTS):
        assert pfc.locator(f"g.neuron[data-neuron='{name}']").count() == 1
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


def test_api_docs_render_offline(page: Any, server: ServerProcess) -> None:
    page.goto(f"{server.url}/docs")
    page.wait_for_selector(".swagger-ui .opblock", timeout=WAIT_MS)
    assert page.locator(".opblock-summary-path[data-path='/auctions/{auction_id}/events']").count()


def test_keyboard_reaches_every_section(page: Any, server: ServerProcess) -> None:
    page.goto(f"{server.url}/")
    page.wait_for_selector("#auction-list", timeout=WAIT_MS)
    assert page.url.endswith("/ui/")
    page.keyboard.press("Tab")
    assert page.evaluate("document.activeElement.id") == "skip"
    for section in ("Models", "Jobs"):
        page.get_by_role("link", name=section, exact=True).focus()
        page.keyboard.press("Enter")
        page.wait_for_selector(f"h1:has-text('{section}')", timeout=WAIT_MS)
        assert page.evaluate("document.activeElement.tagName") == "H1"  # focus follows the view
        current = page.get_by_role("link", name=section, exact=True)
        assert current.get_attribute("aria-current") == "page"
