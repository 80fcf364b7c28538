"""``make demo``: the whole service end to end over HTTP, in about two minutes.

Starts ``srd serve`` on a fresh SQLite database under ``runs/demo__<time>/`` on a free port,
registers honest and saboteur participants through ``POST /submit`` (the screener turns the
saboteurs away, with reasons), runs one live auction among the admitted models, runs the
honest-vs-malicious ``comparison`` job, prints its table and where the plots are, and stops the
server.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from rich.console import Console
from rich.table import Table

from agents.negotiator import honest_manifest, saboteur_manifest
from server.launch import ServerProcess

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


def register(client: httpx.Client) -> None:
    """Submit honest and saboteur manifests; show the screener's verdicts."""
    rng = np.random.default_rng(DEMO_SEED)
    manifests = [honest_manifest(rng, f"honest-{i:02d}") for i in range(N_HONEST)]
    manifests += [saboteur_manifest(rng, f"saboteur-{i:02d}") for i in range(N_SABOTEURS)]
    table = Table(title="POST /submit", show_lines=False)
    for column in ("participant", "model", "verdict", "screener rules that fired"):
        table.add_column(column)
    for manifest in manifests:
        answer = client.post("/submit", json=manifest.model_dump(mode="json"))
        body = answer.raise_for_status().json()
        rules = dict.fromkeys(reason["rule"] for reason in body["reasons"])
        table.add_row(
            body["participant"],
            str(body["model_id"]),
            "[green]accepted" if body["accepted"] else "[red]rejected",
            ", ".join(rules),
        )
    console.print(table)
    console.print(f"every reason in full: GET {client.base_url}/models/<model>")


def auction(client: httpx.Client, admin: dict[str, str]) -> None:
    """One auction among every accepted model, watched round by round."""
    created = client.post("/auctions", json=AUCTION, headers=admin).raise_for_status().json()
    auction_id = created["auction_id"]
    console.print(f"\n[bold]POST /auctions[/bold] {AUCTION} → auction {auction_id}")
    shown = 0

    def show(state: dict[str, Any]) -> None:
        nonlocal shown
        for row in state["history"][shown:]:
            votes = row["votes"]
            console.print(
                f"  round {row['iteration']:>2}: price {row['price']:.4f}, "
                f"{row['n_available']} fish, votes buy {votes['buy']} / hold {votes['hold']} "
                f"/ quit {votes['quit']}"
            )
        shown = len(state["history"])

    final = _poll(client, f"/auctions/{auction_id}", {"finished", "failed"}, show)
    if final["status"] == "failed":
        raise RuntimeError(f"auction failed: {final['error']}")
    console.print(
        f"  → {final['status']} ({final['stop_reason']}): {len(final['buyers'])} of "
        f"{final['n_initial']} fish sold to {final['n_patrons']} patrons, revenue "
        f"{final['revenue']:.2f}, {len(final['quitters'])} quit"
    )


def comparison(client: httpx.Client, admin: dict[str, str], server: ServerProcess) -> None:
    """The honest vs malicious comparison job; its table and artifacts."""
    body = {"kind": "comparison", "params": COMPARISON}
    job_id = client.post("/jobs", json=body, headers=admin).raise_for_status().json()["job_id"]
    console.print(f"\n[bold]POST /jobs[/bold] {body} → job {job_id}")
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
        "rarity": "rarity",
        "n_fish": "fish",
        "mean_price": "mean price",
        "purchase_rate": "sold/on sale",
        "buyer_fraction": "buyers/patrons",
        "revenue": "revenue",
    }
    table = Table(
        title=f"comparison ({COMPARISON['trials']} auctions per row; refused = "
        "patrons the screener kept out, all auctions)"
    )
    for heading in ("configuration", "refused", *columns.values()):
        table.add_column(heading, justify="right")
    for name, configuration in final["result"]["configurations"].items():
        for row in configuration["rows"]:
            table.add_row(
                name,
                str(configuration["refused"]),
                *("—" if row[c] is None else f"{row[c]:.4g}" for c in columns),
            )
    console.print(table)
    folder = server.data_dir / "jobs" / str(job_id)
    console.print("artifacts:")
    for name in final["artifacts"]:
        console.print(f"  {server.url}/jobs/{job_id}/artifacts/{name}   {folder / name}")


def main() -> None:
    workdir = Path("runs") / f"demo__{int(time.time())}"
    server = ServerProcess(database_url=f"sqlite:///{workdir / 'srd.db'}", data_dir=workdir)
    console.print(f"[bold]srd serve[/bold] on SQLite in {workdir}/ ...")
    with server, httpx.Client(base_url=server.url, timeout=60) as client:
        token_file = workdir / "admin_token"
        console.print(
            f"up at {server.url} (docs {server.url}/docs); admin token generated into "
            f"{token_file} (mode {token_file.stat().st_mode & 0o777:o})\n"
        )
        admin = {"Authorization": f"Bearer {server.admin_token}"}
        register(client)
        auction(client, admin)
        comparison(client, admin, server)
    console.print(f"\nserver stopped; database, log and artifacts kept in {workdir}/")


if __name__ == "__main__":
    main()
