"""Robot2NN: the lavaland robot of the paper ("2D robot lavaland" and its appendix;
docs/lavaland.md).

The robot sees the whole map ``x_attn`` (RGB in [0, 1], shape (N, 3, H, W)) and its own start
``w_self`` (one-hot (N, H, W)), scores every tile, then imagines plans on that score map.

Neuron by neuron:

* **Receptors (ABA)**: w_t = σ_sa(μ_c[(x_attn − t)²]) for the known tiles t ∈ {target, dirt,
  grass}: ≈1 on tiles of colour t, small elsewhere (σ_sa = ``agents.neurons.selective``).
* **Unknown detector**: w_unknown = [1 − Σ_t w_t > τ_recog]; lava was never shown to the
  designer, so only lava lights it.
* **DeconvSeq DS⁵_t**, one per named input (self, target, dirt, grass): five 3×3 transposed
  convolutions (1 → 1 channel, no bias), each followed by Tanh and a division by its detached
  max |·|. 4 × 5 × 9 = **180 trainable parameters**, the robot's PFC.
* **v1**: [v1]_self = p_self·DS_self(w_self), [v1]_target = p_target·DS_target(w_target),
  [v1]_t = p_t·DS_t((w_target − w_self)⊙w_t) for t = dirt, grass (favourability gradients).
* **v_Σ** = Σ_t [v1]_t, then the target/start anchors ±v0 (v0 = max|v_Σ|, detached) and the
  unknown avoidance v_Σ ← v_Σ⊙(1 − w_unknown) − u_a·v0·w_unknown.
* **Imagined plans**: from the start, move to the best or (10 %) the second-best neighbour,
  setting the tile being left to −0.9·max|v_Σ|; v_plan = mean of the values moved into.
* **Self reward**: loss = Σ or mean over plans of (1 − tanh(N[v_plan]))², N[v] = v/|v|
  (detached |v|): the robot always wants its plans to be worth more.

Everything is batched over maps (and plans): the DeconvSeqs run on (N, 4, H, W) as one grouped
transposed convolution, and ``imagine`` advances all maps × plans one move per tensor step.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import cast

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from agents.neurons import selective
from agents.planning import GUARD_FRACTION, PRESETS, PlanningRules

# ---------------------------------------------------------------------------------------------
# Designed constants: every hand-set number of Robot2NN, with its meaning.
# ---------------------------------------------------------------------------------------------
RECOGNITION_THRESHOLD = 1e-4
"""τ_recog: a tile the known receptors leave more than this unexplained is unknown; a receptor
above 1 − τ_recog recognises its tile (used for "target reached" and tile bookkeeping)."""
KNOWN_TILE_RGB: dict[str, tuple[int, int, int]] = {
    "target": (255, 215, 0),  # yellow: where the robot must go
    "dirt": (139, 69, 19),  # brown: easy ground
    "grass": (0, 128, 0),  # green: hard ground
}
"""The designer's colour knowledge (0-255). Lava is deliberately missing: it is the unknown."""
P_SELF = -1.0
"""p_self: the start tile (and what the self DeconvSeq spreads around it) repels."""
DEFAULT_P_TARGET = 10.0
"""p_target (reference default; Project A uses 2.0): the target attracts."""
DEFAULT_P_DIRT = 0.2
"""p_dirt: dirt is easy to walk on, mildly favoured."""
DEFAULT_P_GRASS = -0.8
"""p_grass: grass is hard to walk on, disfavoured."""
DEFAULT_UNKNOWN_AVOIDANCE = 2.0
"""u_a: unknown tiles score −u_a·v0, i.e. worse than anything known."""
DECONV_LAYERS = 5
"""n of DS^n_t: layers per DeconvSeq (each widens the area of effect by one tile)."""
KERNEL_CENTRE = 1.0
"""Initial centre weight of every 3×3 kernel: a tile's own evidence dominates."""
KERNEL_SIDE = 0.1
"""Initial weight of the 8 neighbours: a little evidence spreads, a centred area of effect."""
LEAVING_FACTOR = 0.9
"""The tile being left is set to −0.9·max|v_Σ|: going back is unattractive (no oscillation)."""
EXPLORATION = 0.1
"""Probability of taking the second-best move (the 9:1 coin), on in training and evaluation."""
NAMED_INPUTS = ("self", "target", "dirt", "grass")
"""The four DeconvSeqs, in state-dict order."""

TINY = 1e-30
"""Guards divisions by a max |·| or |v_plan| that is exactly zero (never happens on real maps)."""

TARGET_CLASS, DIRT_CLASS, GRASS_CLASS, UNKNOWN_CLASS = 0, 1, 2, 3
"""Recognised tile classes (order of recognition: target, dirt, grass, else unknown)."""


def tile_rgb(name: str) -> Tensor:
    """A known tile's colour scaled to [0, 1], shape (3,)."""
    return torch.tensor(KNOWN_TILE_RGB[name], dtype=torch.float32) / 255.0


@dataclass(frozen=True)
class Receptors:
    """What the robot registers of a batch of maps (no gradient: designed, not trained)."""

    known: Tensor
    """ABA (N, 3, H, W): w_target, w_dirt, w_grass."""
    self_position: Tensor
    """w_self (N, H, W): one-hot start."""
    unknown: Tensor
    """w_unknown (N, H, W): 1.0 on unrecognised tiles."""
    tile_class: Tensor
    """(N, H, W) int64: recognised class (TARGET/DIRT/GRASS/UNKNOWN_CLASS)."""

    def to(self, dtype: torch.dtype) -> Receptors:
        """The same receptors in another float dtype (float64 for a reference computation)."""
        return Receptors(
            self.known.to(dtype),
            self.self_position.to(dtype),
            self.unknown.to(dtype),
            self.tile_class,
        )

    def select(self, index: int | slice) -> Receptors:
        """The receptors of some maps (an int keeps a batch of one)."""
        rows = slice(index, index + 1) if isinstance(index, int) else index
        return Receptors(
            self.known[rows], self.self_position[rows], self.unknown[rows], self.tile_class[rows]
        )


def receptors(maps: Tensor, self_position: Tensor) -> Receptors:
    """ABA, unknown mask and recognised classes of RGB maps (N, 3, H, W) in [0, 1], with the
    robot's one-hot position (N, H, W) (the lavaland env's ``map`` and ``self``)."""
    colours = torch.stack([tile_rgb(t) for t in KNOWN_TILE_RGB])  # (3 tiles, 3 channels)
    distance = ((maps[:, None] - colours[None, :, :, None, None]) ** 2).mean(dim=2)
    known = selective(distance)  # neurons.SELECTIVE_EPSILON: ≈1 only on an exact colour match
    unknown = ((1.0 - known.sum(dim=1)) > RECOGNITION_THRESHOLD).float()
    recognised = known > 1.0 - RECOGNITION_THRESHOLD
    first = recognised.float().argmax(dim=1)  # first recognised class in the order T, D, G
    tile_class = torch.where(recognised.any(dim=1), first, torch.full_like(first, UNKNOWN_CLASS))
    return Receptors(known, self_position, unknown, tile_class)


class DeconvSeq(nn.Module):
    """DS⁵_t: five ConvTranspose2d(1, 1, 3, padding=1, bias=False), each → Tanh → /max|·|."""

    def __init__(self) -> None:
        super().__init__()
        self.layers = nn.ModuleList(
            nn.ConvTranspose2d(1, 1, kernel_size=3, padding=1, bias=False)
            for _ in range(DECONV_LAYERS)
        )
        with torch.no_grad():
            for kernel in self.kernels():
                kernel.fill_(KERNEL_SIDE)
                kernel[0, 0, 1, 1] = KERNEL_CENTRE

    def kernels(self) -> list[Tensor]:
        """The five (1, 1, 3, 3) kernels, first layer first."""
        return [cast(nn.ConvTranspose2d, layer).weight for layer in self.layers]

    def forward(self, x: Tensor) -> Tensor:
        """(N, 1, H, W) → (N, 1, H, W) with max |·| = 1 per map."""
        for kernel in self.kernels():
            x = normalise(torch.tanh(F.conv_transpose2d(x, kernel, padding=1)))
        return x


def normalise(x: Tensor) -> Tensor:
    """Divide each map's channel by its max |·| (the divisor carries no gradient)."""
    return x / x.detach().abs().amax(dim=(-2, -1), keepdim=True).clamp_min(TINY)


class Robot2NN(nn.Module):
    """The lavaland robot: receptors → four DeconvSeqs (180 weights) → v_Σ → imagined plans.

    Args:
        p_target, p_dirt, p_grass: the designer's tile preferences p_t (untrainable).
        unknown_avoidance: u_a ≥ 0, how strongly unknown tiles are avoided.
        rules: planning rules (``PRESETS["paper"]`` or ``PRESETS["reference"]``).
    """

    def __init__(
        self,
        p_target: float = DEFAULT_P_TARGET,
        p_dirt: float = DEFAULT_P_DIRT,
        p_grass: float = DEFAULT_P_GRASS,
        unknown_avoidance: float = DEFAULT_UNKNOWN_AVOIDANCE,
        rules: PlanningRules = PRESETS["paper"],
    ) -> None:
        super().__init__()
        self.deconv_self = DeconvSeq()
        self.deconv_target = DeconvSeq()
        self.deconv_dirt = DeconvSeq()
        self.deconv_grass = DeconvSeq()
        self.register_buffer("preferences", torch.tensor([P_SELF, p_target, p_dirt, p_grass]))
        self.unknown_avoidance = unknown_avoidance
        self.rules = rules

    def sequences(self) -> list[DeconvSeq]:
        """The DeconvSeqs in the order of ``NAMED_INPUTS``."""
        return [self.deconv_self, self.deconv_target, self.deconv_dirt, self.deconv_grass]

    def kernel_stack(self) -> Tensor:
        """All 180 weights as (4 DeconvSeqs in ``NAMED_INPUTS`` order, 5 layers, 3, 3)."""
        return torch.stack([torch.cat(seq.kernels()) for seq in self.sequences()])[:, :, 0]

    def v1(self, seen: Receptors) -> Tensor:
        """[v1]_t for t in NAMED_INPUTS, shape (N, 4, H, W)."""
        x = deconv_inputs(seen)
        kernels = self.kernel_stack()
        for layer in range(DECONV_LAYERS):  # the four DeconvSeqs as one grouped convolution
            grouped = kernels[:, layer, None]  # (4, 1, 3, 3)
            x = normalise(torch.tanh(F.conv_transpose2d(x, grouped, padding=1, groups=4)))
        preferences = cast(Tensor, self.preferences)  # p_self, p_target, p_dirt, p_grass
        return preferences[None, :, None, None] * x

    def v_sigma(self, seen: Receptors) -> Tensor:
        """v_Σ (N, H, W): summed v1, target/start anchors, unknown avoidance."""
        s = self.v1(seen).sum(dim=1)
        v0 = max_abs(s)
        if self.rules.anchors == "add":
            s = s + v0 * seen.known[:, TARGET_CLASS] - v0 * seen.self_position
            v0 = max_abs(s)
        else:
            s = torch.where(seen.tile_class == TARGET_CLASS, v0, s)
            s = torch.where(seen.self_position > 0, -v0, s)
        return s * (1.0 - seen.unknown) - self.unknown_avoidance * v0 * seen.unknown

    def srd_loss(self, v_plan: Tensor, v_sigma: Tensor) -> Tensor:
        """Σ or mean over plans (N, P) of (1 − tanh(N[v_plan]))², N[v] = v/|v| with |v|
        detached; with ``rules.loss_guard`` the divisor is max(|v|, GUARD_FRACTION·max|v_Σ|)."""
        magnitude = v_plan.detach().abs()
        if self.rules.loss_guard:
            floor = GUARD_FRACTION * max_abs(v_sigma).reshape(-1, 1)
            magnitude = torch.maximum(magnitude, floor)
        normalised = v_plan / torch.where(magnitude > 0, magnitude, torch.ones_like(magnitude))
        per_plan = (1.0 - torch.tanh(normalised)) ** 2
        return per_plan.sum() if self.rules.loss_reduction == "sum" else per_plan.mean()


def deconv_inputs(seen: Receptors) -> Tensor:
    """The DeconvSeqs' inputs (N, 4, H, W) in ``NAMED_INPUTS`` order: w_self, w_target and the
    favourability gradients (w_target − w_self)⊙w_dirt and (w_target − w_self)⊙w_grass."""
    w_target, w_dirt, w_grass = seen.known.unbind(dim=1)
    toward_target = w_target - seen.self_position
    return torch.stack(
        [seen.self_position, w_target, toward_target * w_dirt, toward_target * w_grass], dim=1
    )


def max_abs(x: Tensor) -> Tensor:
    """max |x| per map over (H, W), detached, shape (N, 1, 1)."""
    return x.detach().abs().amax(dim=(-2, -1), keepdim=True)


@dataclass(frozen=True)
class Plans:
    """Imagined plans of N maps × P plans (all tensors detached).

    Positions are flat tile indices y·W + x. ``path[..., 0]`` is the start; entries after
    ``n_moves`` are meaningless (rollouts that stopped keep being advanced, masked out).
    """

    reached: Tensor
    """(N, P) bool: the target was detected."""
    n_moves: Tensor
    """(N, P) int64: moves made."""
    path: Tensor
    """(N, P, MOVE_LIMIT + 1) int64: start, then the tile entered by each move."""
    actions: Tensor
    """(N, P, MOVE_LIMIT) int64: 0 R, 1 D, 2 L, 3 U; −1 after the last move."""
    read_values: Tensor
    """(N, P, MOVE_LIMIT): v_Σ of the tile moved into, as read at the time of the choice."""
    read_overwritten: Tensor
    """(N, P, MOVE_LIMIT) bool: that tile had been left before (its value was a constant)."""
    left_values: Tensor
    """(N, P, MOVE_LIMIT): the value −0.9·max|v_Σ| written on the tile left by each move."""
    moved: Tensor
    """(N, P, MOVE_LIMIT) bool: the move was made."""

    @property
    def v_plan(self) -> Tensor:
        """(N, P): mean value of the tiles moved into."""
        return (self.read_values * self.moved).sum(-1) / self.n_moves

    def executed(self, rules: PlanningRules) -> Tensor:
        """(N,) index of the executed plan: highest v_plan (ties → first) or the last plan."""
        if rules.executed == "best":
            return self.v_plan.argmax(dim=-1)
        return torch.full(self.reached.shape[:1], self.reached.shape[1] - 1, dtype=torch.long)

    def differentiable_v_plan(self, v_sigma: Tensor) -> Tensor:
        """v_plan (N, P) with gradient into v_Σ (N, H, W).

        A value read from a tile never left before is that tile's v_Σ entry (gradient 1 per
        read); a tile already left holds the constant −0.9·max|v_Σ| (no gradient). This equals
        reading elements of an in-place-updated v_Σ, without in-place writes on the graph.
        """
        n, p, _ = self.read_values.shape
        flat = v_sigma.reshape(n, -1)
        fresh = self.moved & ~self.read_overwritten
        reads = torch.zeros(n, p, flat.shape[1] + 1).scatter_add_(
            -1, self.path[..., 1:], fresh.float()
        )[..., :-1]
        constants = (self.read_values * (self.moved & self.read_overwritten)).sum(-1)
        return (constants + (reads * flat[:, None, :]).sum(-1)) / self.n_moves


@functools.cache
def neighbour_table(height: int, width: int) -> Tensor:
    """(H·W + 1, 4) flat index of the R, D, L, U neighbour; off-grid → H·W (a −∞ sentinel)."""
    y, x = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    off = height * width
    columns = [
        torch.where(x + 1 < width, y * width + x + 1, off),
        torch.where(y + 1 < height, (y + 1) * width + x, off),
        torch.where(x > 0, y * width + x - 1, off),
        torch.where(y > 0, (y - 1) * width + x, off),
    ]
    table = torch.stack([c.reshape(-1) for c in columns], dim=1)
    return torch.cat([table, torch.full((1, 4), off)])


@torch.no_grad()
def imagine(v_sigma: Tensor, seen: Receptors, explore: Tensor, rules: PlanningRules) -> Plans:
    """Imagine P plans on each of N maps at once, one move per tensor step.

    Maps need at least 2 rows and 2 columns, so that every tile has two neighbours on the grid.

    Args:
        v_sigma: (N, H, W) tile scores (read detached).
        seen: the maps' receptors (start, recognised target).
        explore: (N, P, MOVE_LIMIT) bool, the coins: True at [n, p, k] = plan p of map n takes
            the second-best move at iteration k (probability ``EXPLORATION``).
        rules: ``final_check`` decides whether a target entered on the last move counts.
    """
    n, h, w = v_sigma.shape
    p, limit = explore.shape[1], explore.shape[2]
    cells, rollouts = h * w, n * p
    neighbours = neighbour_table(h, w)
    # Every (map, plan) pair is one row: its own copy of v_Σ with a −∞ off-grid sentinel.
    sentinel = torch.full((n, 1), float("-inf"), dtype=v_sigma.dtype)
    current = torch.cat([v_sigma.detach().reshape(n, cells), sentinel], 1)
    current = current.repeat_interleave(p, dim=0)
    overwritten = torch.zeros(rollouts, cells + 1, dtype=torch.bool)
    is_target = (seen.tile_class.reshape(n, cells) == TARGET_CLASS).repeat_interleave(p, dim=0)
    start = seen.self_position.reshape(n, cells).argmax(-1).repeat_interleave(p)[:, None]
    position = start
    coins = torch.split(explore.reshape(rollouts, limit), 1, dim=1)
    done = torch.zeros(rollouts, 1, dtype=torch.bool)
    steps: list[tuple[Tensor, ...]] = []
    for k in range(limit):
        done |= is_target.gather(1, position)
        if bool(done.all()):
            break
        targets = neighbours[position[:, 0]]  # (rollouts, 4): R, D, L, U
        values = current.gather(1, targets)
        best = values.argmax(1, keepdim=True)  # first maximum: ties keep R, D, L, U
        second = values.scatter(1, best, float("-inf")).argmax(1, keepdim=True)
        choice = torch.where(coins[k], second, best)
        destination = targets.gather(1, choice)
        leaving = current[:, :cells].abs().amax(1, keepdim=True).mul_(-LEAVING_FACTOR)
        steps.append(
            (
                ~done,
                choice,
                values.gather(1, choice),
                overwritten.gather(1, destination),
                leaving,
                destination,
            )
        )
        current.scatter_(1, position, leaving)
        overwritten.scatter_(1, position, True)
        position = destination
    reached = done
    if rules.final_check:
        reached = done | is_target.gather(1, position)

    def record(i: int, blank: Tensor) -> Tensor:
        """Column i of the steps as (N, P, limit), padded with ``blank`` after a stop."""
        columns = [step[i] for step in steps] + [blank.expand(rollouts, limit - len(steps))]
        return torch.cat(columns, 1).reshape(n, p, limit)

    false, zero = torch.zeros(1, 1, dtype=torch.bool), torch.zeros(1, 1)
    moved = record(0, false)
    n_moves = moved.sum(-1)
    path = torch.cat([start.reshape(n, p, 1), record(5, position)], -1)
    return Plans(
        reached=reached.reshape(n, p),
        n_moves=n_moves,
        path=path,
        actions=torch.where(moved, record(1, zero.long()), -1),
        read_values=record(2, zero),
        read_overwritten=record(3, false),
        left_values=record(4, zero),
        moved=moved,
    )
