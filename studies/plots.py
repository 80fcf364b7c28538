"""The figures of the auction studies (paper, Fig. C/D): purchase price and rate against item
supply, and the honest vs malicious comparison."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sim.experiment import pyplot

if TYPE_CHECKING:
    from studies.auctions import AuctionResult

JITTER = 0.02
"""Half-width of the x jitter of the purchase dots (the reference's)."""


def plot_study(
    auctions: Sequence[AuctionResult], rows: Sequence[dict[str, Any]], out_dir: Path, seed: int
) -> list[str]:
    """Fig. C/D: price vs supply (every purchase a jittered dot, mean lines) and purchase rate
    vs supply (both definitions); one column per saboteur share. Returns the file names."""
    plt = pyplot()
    jitter = np.random.default_rng(seed)
    shares = sorted({a.setting.saboteurs for a in auctions})
    colours = {True: "tab:red", False: "tab:blue"}
    files = []
    for kind in ("price", "rate"):
        fig, axes = plt.subplots(  # one price axis: the saboteurs' drop shows beside the honest
            1, len(shares), figsize=(5.2 * len(shares), 4), squeeze=False, sharey=True
        )
        for ax, share in zip(axes[0], shares, strict=True):
            for fine_tune in (False, True):
                label = "fine-tune (Optim)" if fine_tune else "no fine-tune (noOptim)"
                mine = [r for r in rows if r["saboteurs"] == share and r["fine_tune"] == fine_tune]
                if not mine:
                    continue
                colour = colours[fine_tune]
                xs = [r["rarity"] for r in mine]
                if kind == "price":
                    for a in auctions:
                        if a.setting.saboteurs == share and a.setting.fine_tune == fine_tune:
                            prices = a.purchases
                            dx = jitter.uniform(-JITTER, JITTER, size=len(prices))
                            ax.scatter(a.rarity + dx, prices, s=4, alpha=0.25, color=colour)
                    ys = [math.nan if r["mean_price"] is None else r["mean_price"] for r in mine]
                    ax.plot(xs, ys, "-o", color=colour, label=label)
                    ax.set_ylabel("purchase price")
                else:
                    rates = [
                        math.nan if r["purchase_rate"] is None else r["purchase_rate"] for r in mine
                    ]
                    ax.plot(xs, rates, "-o", color=colour, label=f"sold / on sale, {label}")
                    ax.plot(
                        xs,
                        [r["buyer_fraction"] for r in mine],
                        "--s",
                        color=colour,
                        alpha=0.7,
                        label=f"buyers / patrons, {label}",
                    )
                    ax.set_ylabel("purchase rate")
                    ax.set_ylim(0, 1.05)
            title = "honest patrons" if share == 0 else f"{share:g} saboteurs"
            screened = any(a.setting.screen for a in auctions if a.setting.saboteurs == share)
            ax.set_title(title + (" (screened)" if screened else ""))
            ax.set_xlabel("item supply")
            ax.set_xlim(0, 1)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
        fig.tight_layout()
        name = "price_vs_supply.png" if kind == "price" else "purchase_rate.png"
        fig.savefig(out_dir / name, dpi=110)
        plt.close(fig)
        files.append(name)
    return files


COMPARED = (
    ("mean_price", "mean purchase price"),
    ("purchase_rate", "purchase rate (sold / on sale)"),
    ("buyer_fraction", "buyer fraction (buyers / patrons)"),
    ("revenue", "revenue per auction"),
)


def plot_comparison(table: dict[str, list[dict[str, Any]]], path: Path, caption: str) -> None:
    """Side by side: mean price, purchase rate, buyer fraction and revenue per supply, one line
    per configuration; ``caption`` (a sentence per line) printed under the panels."""
    plt = pyplot()
    lines = caption.count("\n") + 1
    height = 3.6 + 0.2 * lines
    fig, axes = plt.subplots(1, len(COMPARED), figsize=(4.2 * len(COMPARED), height))
    styles = {
        "honest": "-o",
        "honest+screened": "--o",
        "compromised": "-x",
        "compromised+screened": "--s",
        "honest-alone": ":^",
    }
    for ax, (field, label) in zip(axes, COMPARED, strict=True):
        for name, rows in table.items():
            ys = [math.nan if r[field] is None else r[field] for r in rows]
            ax.plot([r["rarity"] for r in rows], ys, styles.get(name, "-"), label=name)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("item supply")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    below = 0.2 * lines / height  # the caption's share of the figure's height
    fig.text(0.01, 0.01, caption, ha="left", va="bottom", fontsize=8)
    fig.tight_layout(rect=(0, below + 0.02, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
