"""``make demo``: the whole service end to end over HTTP, in about two minutes.

Starts ``srd serve`` on a fresh SQLite database under
``runs/demo__<seed>__<YYYYmmdd-HHMMSS>/`` on a free port,
registers honest and saboteur participants through ``POST /submit`` (the screener turns the
saboteurs away, with reasons), runs one live auction among the admitted models, runs the
honest-vs-malicious ``comparison`` job, prints its table and the files of its plots, and stops
the server. It ends by printing how to serve the saved run again and which pages to open there.
With ``--keep-serving`` (``.venv/bin/python -m server.cli.demo --keep-serving``) it keeps the server
up instead and prints the live pages, until Ctrl-C.
"""

from __future__ import annotations

import contextlib
import json
import time
from typing import Any

import click
import httpx
import numpy as np
from rich.console import Console
from rich.table import Table

from agents.negotiator import honest_manifest, saboteur_manifest
from server.cli.launch import ServerProcess
from server.config import Settings
from sim.experiment import default_out_dir

N_HONEST = 24
N_SABOTEURS = 8
DEMO_SEED = 0
AUCTION = {"rarity": 0.5, "seed": DEMO_SEED}  # default patrons: every accepted model
COMPARISON = {"trials": 3, "patrons": 32, "seed": DEMO_SEED}
POLL_S = 0.25
TIMEOUT_S = 900

console = Console(width=120)


def _poll(client: httpx.Client, path: str, done: set[str], on_state: Any) -> dict[str, Any]:
    deadline = time.monotonic() + TIMEOUT_S
    while True:
        state: dict[str, Any] = client.get(path).raise_for_status().json()
        on_state(state)
        if state["status"] in done:
            return state
        if time.monotonic() > deadline:
            raise TimeoutError(f"{path} still {state['status']} after {TIMEOUT_S} s")
        time.sleep(POLL_S)


def register(client: httpx.Client) -> int:
    """Submit honest and saboteur manifests; show the screener's verdicts. The id of the first
    rejected model."""
    rng = np.random.default_rng(DEMO_SEED)
    manifests = [honest_manifest(rng, f"honest-{i:02d}") for i in range(N_HONEST)]
    manifests += [saboteur_manifest(rng, f"saboteur-{i:02d}") for i in range(N_SABOTEURS)]
    rejected: list[int] = []
    table = Table(title="POST /submit", show_lines=False)
    for column in ("participant", "model", "verdict", "screener rules that fired"):
        table.add_column(column)
    for manifest in manifests:
        answer = client.post("/submit", json=manifest.model_dump(mode="json"))
        body = answer.raise_for_status().json()
        rules = dict.fromkeys(reason["rule"] for reason in body["reasons"])
        if not body["accepted"]:
            rejected.append(body["model_id"])
        table.add_row(
            body["participant"],
            str(body["model_id"]),
            "[green]accepted" if body["accepted"] else "[red]rejected",
            ", ".join(rules),
        )
    console.print(table)
    console.print("every reason in full, on the neuron it names: the inspector's view (below)")
    return rejected[0]


def auction(client: httpx.Client, admin: dict[str, str]) -> int:
    """One auction among every accepted model, watched iteration by iteration."""
    created = client.post("/auctions", json=AUCTION, headers=admin).raise_for_status().json()
    auction_id = created["auction_id"]
    console.print(f"\n[bold]POST /auctions[/bold] {json.dumps(AUCTION)} → auction {auction_id}")
    shown = 0

    def show(state: dict[str, Any]) -> None:
        nonlocal shown
        for row in state["history"][shown:]:
            votes = row["votes"]
            console.print(
                f"  iteration {row['iteration']:>2}: price {row['price']:.4f}, "
                f"{row['n_available']} fish, votes buy {votes['buy']} / hold {votes['hold']} "
                f"/ quit {votes['quit']}"
            )
        shown = len(state["history"])

    final = _poll(client, f"/auctions/{auction_id}", {"finished", "failed", "cancelled"}, show)
    if final["status"] != "finished":
        raise RuntimeError(f"auction {final['status']}: {final['error'] or 'by the operator'}")
    console.print(
        f"  → {final['status']} ({final['stop_reason']}): {len(final['buyers'])} of "
        f"{final['n_initial']} fish sold, revenue {final['revenue']:.2f}; of "
        f"{final['n_patrons']} patrons, {len(final['buyers'])} bought and "
        f"{len(final['quitters'])} quit"
    )
    return int(auction_id)


def comparison(client: httpx.Client, admin: dict[str, str], server: ServerProcess) -> int:
    """The honest vs malicious comparison job; its table and the files of its artifacts."""
    body = {"kind": "comparison", "params": COMPARISON}
    job_id = client.post("/jobs", json=body, headers=admin).raise_for_status().json()["job_id"]
    console.print(f"\n[bold]POST /jobs[/bold] {json.dumps(body)} → job {job_id}")
    seen: set[tuple[str, str]] = set()

    def show(state: dict[str, Any]) -> None:
        key = (state["status"], state["message"])
        if key not in seen:
            seen.add(key)
            console.print(f"  {state['status']} {state['progress']:.0%} {state['message']}")

    final = _poll(client, f"/jobs/{job_id}", {"succeeded", "failed", "cancelled"}, show)
    if final["status"] != "succeeded":
        raise RuntimeError(f"comparison job {final['status']}: {final['error']}")
    columns = {  # result field -> short heading
        "rarity": "supply (fish per patron)",
        "n_fish": "fish",
        "mean_price": "mean price",
        "purchase_rate": "sold/on sale",
        "buyer_fraction": "buyers/patrons",
        "revenue": "revenue",
    }
    table = Table(
        title=f"comparison ({COMPARISON['trials']} auctions per row; refused = "
        "patrons the screener kept out of each auction)"
    )
    for heading in ("configuration", "refused", *columns.values()):
        table.add_column(heading, justify="right")
    for name, configuration in final["result"]["configurations"].items():
        for row in configuration["rows"]:
            table.add_row(
                name,
                f"{row.get('refused', configuration['refused']):.4g}",
                *("—" if row[c] is None else f"{row[c]:.4g}" for c in columns),
            )
    console.print(table)
    console.print(final["result"].get("caption", ""), soft_wrap=True)  # what each row is
    folder = server.data_dir / "jobs" / str(job_id)
    console.print("artifacts (files):")
    for name in final["artifacts"]:
        console.print(f"  {folder / name}")
    return int(job_id)


def pages(base: str, auction_id: int, rejected_id: int, job_id: int) -> list[str]:
    """The web view's pages of this run."""
    return [
        f"  {base}/ui/#/auctions/{auction_id}   the auction, iteration by iteration",
        f"  {base}/ui/#/models/{rejected_id}   the inspector's view of a rejected saboteur",
        f"  {base}/ui/#/jobs/{job_id}   the comparison job and its plots",
    ]


@click.command()
@click.option(
    "--keep-serving",
    is_flag=True,
    help="Keep the server up at the end (and print its pages) until Ctrl-C.",
)
def main(keep_serving: bool) -> None:
    """Run the auction house end to end over HTTP."""
    workdir = default_out_dir("demo", DEMO_SEED)
    server = ServerProcess(database_url=f"sqlite:///{workdir / 'srd.db'}", data_dir=workdir)
    console.print(f"[bold]srd serve[/bold] on SQLite in {workdir}/ ...")
    with server, httpx.Client(base_url=server.url, timeout=60) as client:
        token_file = workdir / "admin_token"
        console.print(
            f"up; admin token generated into {token_file} "
            f"(mode {token_file.stat().st_mode & 0o777:o})\n"
        )
        admin = {"Authorization": f"Bearer {server.admin_token}"}
        rejected_id = register(client)
        auction_id = auction(client, admin)
        job_id = comparison(client, admin, server)
        if keep_serving:
            console.print(f"\n[bold]the web view[/bold] at {server.url}/ui/ (Ctrl-C stops it):")
            console.print("\n".join(pages(server.url, auction_id, rejected_id, job_id)))
            assert server.process is not None
            with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C stops the server too
                server.process.wait()
    console.print(f"\nserver stopped; database, log and artifacts kept in {workdir}/")
    if not keep_serving:
        settings = Settings()
        console.print(
            "to browse this run in the web view, serve it again:\n"
            f"  SRD_DATABASE_URL=sqlite:///{workdir / 'srd.db'} SRD_DATA_DIR={workdir} "
            ".venv/bin/srd serve\nthen open",
            soft_wrap=True,  # one line, to paste as it is
        )
        base = f"http://{settings.host}:{settings.port}"
        console.print("\n".join(pages(base, auction_id, rejected_id, job_id)), soft_wrap=True)


if __name__ == "__main__":
    main()
