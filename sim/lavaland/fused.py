"""The fused SRD step: Robot2NN's forward pass, imagined plans, hand-written gradient and SGD
update for one training map after another, in one compiled loop (numba).

It does exactly what ``training.train_srd`` does through torch autograd (one map per SGD step,
the same order, the same coins, hence the same plans), in float64 arithmetic on the float32
parameters, which are rounded back to float32 after every step as torch stores them. What does
not depend on the parameters (the DeconvSeq inputs, masks, starts, neighbours) is prepared once
for the whole epoch. Tests check the gradient against autograd and the parameters after short
epochs against ``train_srd``.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from agents.planning import GUARD_FRACTION
from agents.robot2nn import (
    DECONV_LAYERS,
    LEAVING_FACTOR,
    TARGET_CLASS,
    TINY,
    Robot2NN,
    deconv_inputs,
    neighbour_table,
)
from sim.experiment import ProgressFn, no_progress
from sim.lavaland.engine import MapSet, load_kernels


def user_cache_dir() -> Path | None:
    """The user's cache folder (``$XDG_CACHE_HOME``, else ``~/.cache``), or None when there is
    no home to find it in."""
    given = os.environ.get("XDG_CACHE_HOME", "")
    if os.path.isabs(given):  # the XDG spec: a relative path is to be ignored
        return Path(given)
    try:
        return Path.home() / ".cache"
    except RuntimeError:
        return None


if not os.environ.get("NUMBA_CACHE_DIR") and (cache := user_cache_dir()) is not None:
    # numba keeps the compiled step beside this module by default, in the source tree (a clone
    # gets files nobody wrote); NUMBA_CACHE_DIR, read when numba is imported, decides
    os.environ["NUMBA_CACHE_DIR"] = str(cache / "srd-auction" / "numba")

import numba  # noqa: E402  (after its cache folder is set)

Arr = np.ndarray

REPORT_BLOCKS = 16
"""Progress reports per epoch (the compiled loop runs this many blocks of steps)."""


@dataclass(frozen=True)
class EpochTrace:
    """Per SGD step: what the loss saw (for the failure-mode analysis in docs/lavaland.md)."""

    min_abs_v_plan: np.ndarray
    """(steps,) the smallest |v_plan| among the map's plans."""
    grad_norm: np.ndarray
    """(steps,) the L2 norm of the 180-weight gradient."""


@numba.njit(cache=True)
def _deconv(x: np.ndarray, kernel: np.ndarray, out: np.ndarray) -> None:
    """ConvTranspose2d(1, 1, 3, padding=1): out[i, j] = Σ_ab kernel[a, b]·x[i + 1 − a, j + 1 − b]
    (valid indices only)."""
    h, w = x.shape
    for i in range(h):
        for j in range(w):
            total = 0.0
            for a in range(3):
                u = i + 1 - a
                if 0 <= u < h:
                    for b in range(3):
                        v = j + 1 - b
                        if 0 <= v < w:
                            total += kernel[a, b] * x[u, v]
            out[i, j] = total


@numba.njit(cache=True)
def _forward(inputs: Arr, kernels: Arr, preferences: Arr, xs: Arr, ts: Arr, maxima: Arr) -> Arr:
    """The four DeconvSeqs of one map: xs[l] the layer inputs (xs[L] the outputs), ts[l] the
    Tanh values, maxima[l] the detached max |Tanh|; returns Σ_t p_t·DS_t (H, W)."""
    channels, h, w = inputs.shape
    s = np.zeros((h, w))
    for c in range(channels):
        xs[0, c] = inputs[c]
        for layer in range(DECONV_LAYERS):
            _deconv(xs[layer, c], kernels[c, layer], ts[layer, c])
            np.tanh(ts[layer, c], ts[layer, c])
            maxima[layer, c] = max(np.abs(ts[layer, c]).max(), TINY)
            xs[layer + 1, c] = ts[layer, c] / maxima[layer, c]
        s += preferences[c] * xs[DECONV_LAYERS, c]
    return s


@numba.njit(cache=True)
def _rollout(
    v_sigma: Arr,
    is_target: Arr,
    start: int,
    neighbours: Arr,
    coins: Arr,
    current: Arr,
    overwritten: Arr,
    reads: Arr,
) -> tuple[float, int]:
    """One imagined plan on the flat v_Σ (cells,): best or (coin) second-best neighbour, the
    tile left set to −0.9·max|v_Σ|. Fills reads[t] (times the never-left tile t was read) and
    returns (value of the reads of tiles already left, moves made)."""
    cells = v_sigma.shape[0]
    current[:cells] = v_sigma
    current[cells] = -np.inf  # off the grid
    overwritten[:] = False
    reads[:] = 0.0
    position, constants, moves = start, 0.0, 0
    for k in range(coins.shape[0]):
        if is_target[position]:
            break
        best, second = -1, -1
        for a in range(4):  # first maximum, then the first maximum of the rest: R, D, L, U ties
            if best < 0 or current[neighbours[position, a]] > current[neighbours[position, best]]:
                best = a
        for a in range(4):
            if a != best and (
                second < 0
                or current[neighbours[position, a]] > current[neighbours[position, second]]
            ):
                second = a
        destination = neighbours[position, second if coins[k] else best]
        if overwritten[destination]:
            constants += current[destination]
        else:
            reads[destination] += 1.0
        current[position] = -LEAVING_FACTOR * np.abs(current[:cells]).max()
        overwritten[position] = True
        position = destination
        moves += 1
    return constants, moves


@numba.njit(cache=True)
def _backward(
    g_s: Arr,
    kernels: Arr,
    preferences: Arr,
    xs: Arr,
    ts: Arr,
    maxima: Arr,
    grads: Arr,
    g_x: Arr,
    g_z: Arr,
) -> None:
    """Gradient of the loss on the 180 weights (grads) from its gradient on Σ_t p_t·DS_t."""
    channels, layers = kernels.shape[0], kernels.shape[1]
    h, w = g_s.shape
    for c in range(channels):
        g_x[:] = preferences[c] * g_s
        for layer in range(layers - 1, -1, -1):
            t = ts[layer, c]
            g_z[:] = g_x / maxima[layer, c] * (1.0 - t * t)
            x = xs[layer, c]
            for a in range(3):
                for b in range(3):
                    total = 0.0
                    for i in range(max(0, a - 1), min(h, h + a - 1)):
                        for j in range(max(0, b - 1), min(w, w + b - 1)):
                            total += g_z[i, j] * x[i + 1 - a, j + 1 - b]
                    grads[c, layer, a, b] = total
            if layer > 0:  # the input gradient: a correlation of g_z with the kernel
                kernel = kernels[c, layer]
                for u in range(h):
                    for v in range(w):
                        total = 0.0
                        for a in range(3):
                            i = u - 1 + a
                            if 0 <= i < h:
                                for b in range(3):
                                    j = v - 1 + b
                                    if 0 <= j < w:
                                        total += kernel[a, b] * g_z[i, j]
                        g_x[u, v] = total


@numba.njit(cache=True)
def _steps(
    stored: Arr,
    inputs: Arr,
    is_target: Arr,
    self_position: Arr,
    unknown: Arr,
    soft_target: Arr,
    starts: Arr,
    neighbours: Arr,
    order: Arr,
    coins: Arr,
    first: int,
    last: int,
    preferences: Arr,
    unknown_avoidance: float,
    anchors_set: bool,
    loss_mean: bool,
    lr: float,
    guard_fraction: float,
    min_abs_v_plan: Arr,
    grad_norm: Arr,
) -> None:
    """SGD steps ``first``..``last`` − 1 of the epoch, updating the ``stored`` parameters."""
    channels, h, w = inputs.shape[1:]
    layers, cells, plans = stored.shape[1], h * w, coins.shape[1]
    xs = np.zeros((layers + 1, channels, h, w))
    ts = np.zeros((layers, channels, h, w))
    maxima = np.zeros((layers, channels))
    grads = np.zeros(stored.shape)
    g_x, g_z = np.zeros((h, w)), np.zeros((h, w))
    current, overwritten = np.zeros(cells + 1), np.zeros(cells + 1, dtype=np.bool_)
    reads, g_v = np.zeros(cells), np.zeros(cells)
    for step in range(first, last):
        m = order[step]
        kernels = stored.astype(np.float64)
        s = _forward(inputs[m].astype(np.float64), kernels, preferences, xs, ts, maxima).ravel()
        v0 = np.abs(s).max()
        if anchors_set:  # paper: target and start set to ±v0
            s = np.where(is_target[m], v0, s)
            s = np.where(self_position[m] > 0, -v0, s)
        else:  # reference: ±v0 added through the soft ABA, then the max recomputed
            s = s + v0 * soft_target[m] - v0 * self_position[m]
            v0 = np.abs(s).max()
        v_sigma = s * (1.0 - unknown[m]) - unknown_avoidance * v0 * unknown[m]
        g_v[:] = 0.0
        floor = guard_fraction * np.abs(v_sigma).max()
        smallest = np.inf
        for p in range(plans):
            constants, moves = _rollout(
                v_sigma,
                is_target[m],
                starts[m],
                neighbours,
                coins[step, p],
                current,
                overwritten,
                reads,
            )
            v_plan = (constants + (reads * v_sigma).sum()) / moves
            smallest = min(smallest, abs(v_plan))
            magnitude = max(abs(v_plan), floor)
            if magnitude == 0.0:
                magnitude = 1.0  # v_plan exactly 0: N[v] = 0
            squashed = np.tanh(v_plan / magnitude)
            d_loss = -2.0 * (1.0 - squashed) * (1.0 - squashed * squashed) / magnitude
            if loss_mean:
                d_loss /= plans
            g_v += d_loss / moves * reads
        g_s = g_v * (1.0 - unknown[m])
        if anchors_set:  # set tiles carry no gradient
            g_s = np.where(is_target[m] | (self_position[m] > 0), 0.0, g_s)
        _backward(g_s.reshape(h, w), kernels, preferences, xs, ts, maxima, grads, g_x, g_z)
        stored[:] = kernels - lr * grads  # rounded to the parameters' dtype
        min_abs_v_plan[step] = smallest
        grad_norm[step] = np.sqrt((grads * grads).sum())


def train_srd_fused(
    model: Robot2NN,
    maps: MapSet,
    order: np.ndarray,
    explore: torch.Tensor,
    lr: float,
    progress: ProgressFn = no_progress,
) -> EpochTrace:
    """One SRD epoch as ``train_srd`` does it (loss guard included), compiled; updates
    ``model`` in place and returns what each step's loss saw."""
    seen, rules = maps.seen, model.rules
    n, h, w = seen.self_position.shape
    flat = (n, h * w)
    stored = model.kernel_stack().detach().numpy().copy()  # the parameters' own dtype
    steps = len(order)
    trace = EpochTrace(np.zeros(steps), np.zeros(steps))
    arguments = (
        stored,
        deconv_inputs(seen).numpy(),
        (seen.tile_class == TARGET_CLASS).reshape(flat).numpy(),
        seen.self_position.reshape(flat).double().numpy(),
        seen.unknown.reshape(flat).double().numpy(),
        seen.known[:, TARGET_CLASS].reshape(flat).double().numpy(),
        seen.self_position.reshape(flat).argmax(1).numpy(),
        neighbour_table(h, w).numpy(),
        np.ascontiguousarray(order, dtype=np.int64),
        explore.numpy(),
    )
    preferences = model.preferences.double().numpy()  # type: ignore[operator]
    bounds = np.linspace(0, steps, REPORT_BLOCKS + 1).astype(int)
    if not _steps.signatures:  # the first call compiles (a minute on a busy machine) or loads
        progress(0.0, "compiling the fused SRD step (once, then cached)")
    for first, last in itertools.pairwise(bounds.tolist()):
        _steps(
            *arguments,
            first,
            last,
            preferences,
            float(model.unknown_avoidance),
            rules.anchors == "set",
            rules.loss_reduction == "mean",
            float(lr),
            GUARD_FRACTION if rules.loss_guard else 0.0,
            trace.min_abs_v_plan,
            trace.grad_norm,
        )
        if last > first:
            progress(last / steps, f"SRD step {last}/{steps}")
    load_kernels(model, stored)
    return trace
