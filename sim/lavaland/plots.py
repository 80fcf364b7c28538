"""Lavaland figures: tile histograms, the 180 weights and a trajectory GIF."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image, ImageDraw

from agents.planning import MOVE_LIMIT
from agents.robot2nn import (
    NAMED_INPUTS,
    Robot2NN,
    imagine,
)
from sim.experiment import pyplot
from sim.lavaland.engine import Evaluation, MapSet
from sim.lavaland.world import DIRT, GRASS, LAVA, TILE_RGB, picture


def plot_histograms(
    path: Path,
    title: str,
    untrained: Sequence[Evaluation],
    srd: Sequence[Evaluation],
    with_lava: bool,
) -> None:
    """Cumulative histograms of dirt / grass (/ lava) tiles traversed, repeats pooled."""
    plt = pyplot()
    classes = [(DIRT, "dirt"), (GRASS, "grass")] + ([(LAVA, "lava")] if with_lava else [])
    fig, axes = plt.subplots(1, len(classes), figsize=(3.2 * len(classes), 2.8), dpi=100)
    bins = np.arange(MOVE_LIMIT + 3) - 0.5
    series = [("no SRD", untrained, "tab:gray"), ("SRD", srd, "tab:red")]
    for ax, (tile, name) in zip(axes, classes, strict=True):
        for label, runs, colour in series:
            if runs:
                counts = np.concatenate([ev.tile_counts[:, tile] for ev in runs])
                ax.hist(
                    counts,
                    bins=bins,
                    cumulative=True,
                    density=True,
                    histtype="step",
                    color=colour,
                    label=label,
                )
        ax.set_title(f"{name} tiles traversed", fontsize=10)
        ax.set_xlabel("tiles")
        ax.set_xlim(-0.5, MOVE_LIMIT + 1)
    axes[0].set_ylabel("fraction of maps (cumulative)")
    axes[0].legend(loc="lower right")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_repeats(path: Path, title: str, rows: Sequence[dict[str, Any]]) -> None:
    """Accuracy of every repeat before (grey) and after SRD (red), a line joining each pair."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(4.8, 3.0), dpi=100)
    repeats = [row["repeat"] for row in rows]
    untrained = [row["accuracy_untrained"] for row in rows]
    ax.plot(repeats, untrained, "o", color="tab:gray", label="no SRD")
    if rows[0]["accuracy_srd"] is not None:
        trained = [row["accuracy_srd"] for row in rows]
        ax.vlines(repeats, untrained, trained, color="tab:red", alpha=0.4)
        ax.plot(repeats, trained, "o", color="tab:red", label="SRD")
    ax.set_xlabel("repeat")
    ax.set_ylabel("accuracy")
    ax.set_xticks(repeats)
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def kernel_mosaic(weights: np.ndarray) -> np.ndarray:
    """(4, 5, 3, 3) kernels → one image, rows = DeconvSeqs, columns = layers, NaN gutters."""
    mosaic = np.full((4 * 4 - 1, 5 * 4 - 1), np.nan)
    for s in range(4):
        for layer in range(5):
            mosaic[4 * s : 4 * s + 3, 4 * layer : 4 * layer + 3] = weights[s, layer]
    return mosaic


def plot_weights(path: Path, panels: list[tuple[str, np.ndarray]]) -> None:
    """The 180 weights as heat maps, one panel per (title, (4, 5, 3, 3) kernels); red positive,
    blue negative, each panel on its own symmetric scale."""
    plt = pyplot()
    fig, axes = plt.subplots(
        1, len(panels), figsize=(3.6 * len(panels), 3.0), dpi=90, constrained_layout=True
    )
    for ax, (title, weights) in zip(np.atleast_1d(axes), panels, strict=True):
        limit = float(np.abs(weights).max())
        image = ax.imshow(kernel_mosaic(weights), cmap="bwr", vmin=-limit, vmax=limit)
        ax.set_title(title, fontsize=8)
        ax.set_xticks([4 * i + 1 for i in range(5)], [f"L{i + 1}" for i in range(5)], fontsize=7)
        ax.set_yticks([4 * i + 1 for i in range(4)], list(NAMED_INPUTS), fontsize=7)
        fig.colorbar(image, ax=ax, shrink=0.7)
    fig.suptitle(
        "Robot2NN DeconvSeq kernels (180 weights; rows: DeconvSeq, columns: layer)", fontsize=9
    )
    fig.savefig(path)
    plt.close(fig)


def trajectory_gif(path: Path, model: Robot2NN, one: MapSet, explore: torch.Tensor) -> None:
    """GIF of the executed plan on one map: the map with the robot (left) and v_Σ as the plan
    updates it (right; red positive, blue negative, white 0), one frame per move."""
    with torch.no_grad():
        v_sigma = model.v_sigma(one.seen)
        plans = imagine(v_sigma, one.seen, explore, model.rules)
    chosen = int(plans.executed(model.rules)[0])
    moves = int(plans.n_moves[0, chosen])
    w = v_sigma.shape[2]
    flat = plans.path[0, chosen, : moves + 1].numpy()
    xy = [(int(i % w), int(i // w)) for i in flat]
    values = v_sigma[0].numpy().copy()
    limit = float(np.abs(values).max())
    colours = TILE_RGB[one.maps.tiles[0]]
    pyplot()  # matplotlib on the Agg backend
    import matplotlib

    heat = matplotlib.colormaps["bwr"]
    status = "reached" if bool(plans.reached[0, chosen]) else "not reached"
    caption = f"v_plan {float(plans.v_plan[0, chosen]):+.3f}, {status}"
    frames = []
    for k in range(moves + 1):
        if k > 0:
            left_x, left_y = xy[k - 1]
            values[left_y, left_x] = float(plans.left_values[0, chosen, k - 1])
        scores = (heat((values / limit + 1) / 2)[..., :3] * 255).astype(np.uint8)
        left, right = picture(colours, xy[: k + 1], 20), picture(scores, xy[: k + 1], 20)
        frame = Image.new("RGB", (2 * left.shape[1] + 10, left.shape[0] + 18), "white")
        frame.paste(Image.fromarray(left), (0, 18))
        frame.paste(Image.fromarray(right), (left.shape[1] + 10, 18))
        ImageDraw.Draw(frame).text((4, 3), f"move {k}/{moves}   {caption}", fill=(0, 0, 0))
        frames.append(frame.quantize(64, Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE))
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=350, loop=0)
