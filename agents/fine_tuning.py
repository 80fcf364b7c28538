"""SRD fine-tuning of Fish Sale Negotiators, batched over patrons: each patron takes SGD
steps on CEL([T, F], argmax [T, F]) with its own epochs, shuffles, batch size and learning rate,
the gradient written out (``_band_gradient``) and checked against autograd in the tests.
``fine_tune_round`` is one round of an auction, the same in the market and in a remote agent:
its randomness is derived per (round seeds, patron position)."""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from agents.batch import BELOW_THRESHOLD, PARAMETERS, PFC_PARAMETERS, SELECTIVE, FSNBatch
from agents.forward import noise_scale, standard_normal
from agents.manifest import (
    DECISIONS,
    ES_NEURONS,
    INPUTS,
    JUDGEMENTS,
    PFC_SOURCES,
    VERDICTS,
)

# --- SRD fine-tuning --------------------------------------------------------------------------


@dataclass
class FineTuneDraws:
    """The random numbers of one fine-tuning round, drawn for every patron of a batch.

    ``order`` (P, E, R): patron p's shuffle of the R rows in epoch e; ``normal``
    (P, E, R, D, 8): float32 N(0, 1) draws that ``scale`` (P, D, 8) (``noise_scale``) turns
    into ``noise``, the augmentation noise row r receives when patron p visits it in epoch e.
    E is the largest epoch count of the batch. A per-patron loop that slices these sees the
    same numbers.
    """

    order: Tensor
    normal: Tensor
    scale: Tensor

    @functools.cached_property
    def noise(self) -> Tensor:
        """(P, E, R, D, 8) (``fine_tune`` itself scales only the rows it visits)."""
        return self.normal.to(self.scale.dtype) * self.scale[:, None, None]


def draw_fine_tune(batch: FSNBatch, n_rows: int, generator: torch.Generator) -> FineTuneDraws:
    """Draw one round's shuffles and noise (empty when no patron has epochs)."""
    return draw_fine_tune_blocks(batch, n_rows, [(batch.n_patrons, generator)])


def draw_fine_tune_blocks(
    batch: FSNBatch, n_rows: int, blocks: Sequence[tuple[int, torch.Generator]]
) -> FineTuneDraws:
    """One round's draws for consecutive blocks of patrons, given as (size, generator): each
    block draws what ``draw_fine_tune`` would draw for it alone (its epochs and copies are
    padded to the batch's: a padded epoch is never visited, a padded copy has no noise)."""
    P, E, D = batch.n_patrons, int(batch.epochs.max()), batch.max_copies
    bounds = list(itertools.pairwise(np.cumsum([0, *(size for size, _ in blocks)]).tolist()))
    order = torch.empty((P, E, n_rows), dtype=torch.long)
    normal = torch.empty((P, E, n_rows, D, len(INPUTS)), dtype=torch.float32)
    for (_, generator), (start, stop) in zip(blocks, bounds, strict=True):
        epochs, copies = int(batch.epochs[start:stop].max()), int(batch.copies[start:stop].max())
        keys = torch.rand((stop - start, epochs, n_rows), generator=generator, dtype=torch.float64)
        order[start:stop, :epochs] = keys.argsort(dim=-1)
        order[start:stop, epochs:] = torch.arange(n_rows)
        shape = (stop - start, epochs, n_rows, copies)
        if (epochs, copies) == (E, D):
            standard_normal(shape, generator, out=normal[start:stop])
        else:
            normal[start:stop, :epochs, :, :copies] = standard_normal(shape, generator)
            normal[start:stop, epochs:] = 0.0
            normal[start:stop, :epochs, :, copies:] = 0.0
    return FineTuneDraws(order=order, normal=normal, scale=noise_scale(batch))


SEED_BITS = 53
"""Derived seeds have 53 bits: exact as JSON numbers in any language (IEEE doubles)."""
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX = (np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB))


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64's output function of x + golden ratio (uint64, wrapping), element-wise."""
    z = x + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _MIX[0]
    z = (z ^ (z >> np.uint64(27))) * _MIX[1]
    return z ^ (z >> np.uint64(31))


def derive_seeds(parent: int | np.ndarray, child: int | Sequence[int] | np.ndarray) -> np.ndarray:
    """Seeds derived from (parent, child) pairs, element-wise (uint64 array, < 2**SEED_BITS):
    splitmix64(splitmix64(parent) XOR child) keeping its low SEED_BITS bits. Cheap and
    vectorised, so a round can derive one seed per patron without a Python loop."""
    with np.errstate(over="ignore"):
        mixed = _splitmix64(np.asarray(parent, dtype=np.uint64)) ^ np.asarray(child, np.uint64)
        return np.atleast_1d(_splitmix64(mixed) & np.uint64((1 << SEED_BITS) - 1))


def draw_fine_tune_seeded(
    batch: FSNBatch, n_rows: int, shuffle_seeds: np.ndarray, noise_seeds: np.ndarray
) -> FineTuneDraws:
    """One round's draws with every patron's own generators: patron p's shuffle keys (its
    epochs × R uniforms, argsorted per epoch) from a torch generator seeded with
    ``shuffle_seeds[p]``, its N(0, 1) augmentation draws (epochs × R × its D_ic × 8) from one
    seeded with ``noise_seeds[p]``. A patron's draws depend on its own settings and seeds
    only, so it draws the same numbers alone (a remote agent) as in any batch (patrons with
    the same seeds, epochs and copies, as in the screener's projection, draw them once).
    Patrons without epochs draw nothing (they are never visited)."""
    P, E, D = batch.n_patrons, int(batch.epochs.max()), batch.max_copies
    keys = torch.zeros((P, E, n_rows), dtype=torch.float64)
    normal = torch.empty((P, E, n_rows, D, len(INPUTS)), dtype=torch.float32)
    generator = torch.Generator()
    epochs, copies = batch.epochs.tolist(), batch.copies.tolist()
    shuffle, noise = shuffle_seeds.tolist(), noise_seeds.tolist()
    drawn: dict[tuple[int, int, int, int], int] = {}
    for p in range(P):
        e, c = epochs[p], copies[p]
        if e == 0:
            continue
        same = drawn.setdefault((shuffle[p], noise[p], e, c), p)
        if same != p:
            keys[p] = keys[same]
            normal[p] = normal[same]
            continue
        generator.manual_seed(shuffle[p])
        torch.rand((e, n_rows), generator=generator, dtype=torch.float64, out=keys[p, :e])
        generator.manual_seed(noise[p])
        if (e, c) == (E, D):
            standard_normal((e, n_rows, c), generator, out=normal[p])
        else:  # padded epochs are never visited; padded copies must hold finite zeros
            normal[p, :e, :, :c] = standard_normal((e, n_rows, c), generator)
            normal[p, :e, :, c:] = 0.0
    return FineTuneDraws(order=keys.argsort(dim=-1), normal=normal, scale=noise_scale(batch))


def _flat_parameters(batch: FSNBatch) -> Tensor:
    """The trainable tensors side by side, (P, N_θ), in ``PARAMETERS`` order."""
    P = batch.n_patrons
    return torch.cat([t.reshape(P, -1) for t in batch.parameters().values()], dim=1)


def _unflatten(batch: FSNBatch, flat: Tensor) -> dict[str, Tensor]:
    """The inverse of ``_flat_parameters``."""
    shapes = [t.shape for t in batch.parameters().values()]
    widths = [math.prod(shape[1:]) for shape in shapes]
    parts = torch.split(flat, widths, dim=1)
    return {
        name: part.reshape(shape).clone()
        for name, part, shape in zip(PARAMETERS, parts, shapes, strict=True)
    }


_LAYER_SHAPES = (
    (len(ES_NEURONS), len(INPUTS)),
    (len(ES_NEURONS), 1),
    (len(DECISIONS), len(ES_NEURONS)),
    (len(DECISIONS), 1),
    (len(JUDGEMENTS), len(PFC_SOURCES)),
    (len(JUDGEMENTS), 1),
    (len(VERDICTS), len(JUDGEMENTS)),
    (len(VERDICTS), 1),
)
"""Per patron, the trainable tensors of ``PARAMETERS`` as matrices (biases as columns)."""
_PFC_COLUMNS = torch.cat(
    [
        torch.full((rows * cols,), name in PFC_PARAMETERS)
        for name, (rows, cols) in zip(PARAMETERS, _LAYER_SHAPES, strict=True)
    ]
)
"""The columns of the flat parameters (``_flat_parameters``) that belong to the PFC."""


def _layer_views(theta: Tensor) -> list[Tensor]:
    """Views (k, out, in) and (k, out, 1) of the flat parameters ``theta`` (k, N_θ)."""
    parts = torch.split(theta, [rows * cols for rows, cols in _LAYER_SHAPES], dim=1)
    return [p.view(-1, *shape) for p, shape in zip(parts, _LAYER_SHAPES, strict=True)]


def _threshold_and_slope(
    u: Tensor, numbers: dict[str, Tensor], out: Tensor | None = None, d_out: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """T(u) = tanh(lrelu(a·(u − c), ns)) and dT/du (into ``out`` and ``d_out`` if given)."""
    z = (u - numbers["c"]) * numbers["a"]
    fired = torch.tanh(torch.maximum(z, numbers["slope"] * z), out=out)
    # a·d max(z, ns·z)/dz: a above 0, ns·a below, their mean at a tie (as autograd).
    bend = torch.addcmul(numbers["bend_mid"], torch.sign(z), numbers["bend_half"])
    return fired, torch.mul(torch.rsub(fired * fired, 1.0), bend, out=d_out)


def _selective_and_slope(
    u: Tensor, numbers: dict[str, Tensor], out: Tensor | None = None, d_out: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """S(u) = ε/(ε + u²) and dS/du = −2u·S²/ε (into ``out`` and ``d_out`` if given)."""
    eps = numbers["epsilon"]
    chosen = torch.div(eps, eps + u * u, out=out)
    return chosen, torch.mul(chosen * chosen, u * numbers["minus_two_over_epsilon"], out=d_out)


def _sensor_and_slope(
    groups: Sequence[tuple[int | None, dict[str, Tensor], Tensor, Tensor, Tensor]],
) -> None:
    """ES activations and their derivatives, group by group of ES neurons: each group is (its
    kind (None: mixed), its numbers (see ``_activation_table``, (k, n, 1)), its pre-activations
    (k, n, M), where its activations go, where their derivatives go)."""
    for kind, mine, u, out, d_out in groups:
        if kind == SELECTIVE:
            _selective_and_slope(u, mine, out, d_out)
        elif kind is not None:
            _threshold_and_slope(u, mine, out, d_out)
            if kind == BELOW_THRESHOLD:  # BT = 1 − T
                out.neg_().add_(1.0)
                d_out.neg_()
        else:
            fired, d_fired = _threshold_and_slope(u, mine)
            chosen, d_chosen = _selective_and_slope(u, mine)
            below, selective = mine["kind"] == BELOW_THRESHOLD, mine["kind"] == SELECTIVE
            out.copy_(torch.where(selective, chosen, torch.where(below, 1.0 - fired, fired)))
            d_out.copy_(torch.where(selective, d_chosen, torch.where(below, -d_fired, d_fired)))


def _activation_table(batch: FSNBatch, patrons: Tensor) -> dict[str, Tensor]:
    """The ES activation numbers of ``patrons`` as (k, 4, 1) columns, with the constants of
    their derivatives."""
    a, ns, eps = batch.es_a[patrons], batch.es_slope[patrons], batch.es_epsilon[patrons]
    table = {
        "kind": batch.es_kind[patrons],
        "a": a,
        "c": batch.es_c[patrons],
        "slope": ns,
        "epsilon": eps,
        "bend_mid": 0.5 * (a + ns * a),
        "bend_half": 0.5 * (a - ns * a),
        "minus_two_over_epsilon": -2.0 / eps,
    }
    return {name: value[:, :, None].contiguous() for name, value in table.items()}


class _Prefix:
    """The first k patrons of a band, stepping together over B·D (row, copy) columns: views of
    their flat parameters ``theta`` (k, N_θ) per layer (updated in place, the views follow),
    their activation numbers per group of ES neurons, their copy weights, noise scales and
    learning rates, and the buffers of one step's pre-activations, sources and slopes. A band
    steps with the same k for many steps, so all of this is sliced once per k."""

    def __init__(
        self,
        groups: list[tuple[int | None, slice]],
        theta: Tensor,
        numbers: dict[str, Tensor],
        copy_weight: Tensor,
        scale: Tensor,
        rate: Tensor,
        rows: int,
        copies: int,
    ) -> None:
        k = len(theta)
        self.k = k
        self.theta = theta
        self.rate = rate
        self.scale = scale
        self.layers = _layer_views(theta)
        _, _, fc_w, _, j_w, _, v_w, _ = self.layers
        self.fc_w_t, self.j_w_t, self.v_w_t = (w.transpose(1, 2) for w in (fc_w, j_w, v_w))
        self.copy_weight = copy_weight  # (k, D)
        self.copy_cell = copy_weight[:, None, None, :]
        n_es, columns = len(ES_NEURONS), rows * copies
        self.minus_one = theta.new_full((k, 1, rows), -1.0)  # the one-hot, subtracted
        # one step's gradient, written layer by layer, then side by side as theta's columns
        self.grad_layers = [theta.new_empty((k, *shape)) for shape in _LAYER_SHAPES]
        self.grad_columns = [g.view(k, -1) for g in self.grad_layers]
        self.grad = torch.empty_like(theta)
        self.pre = theta.new_empty((k, n_es, columns))
        self.sources = theta.new_empty((k, len(PFC_SOURCES), columns))
        self.sensor = self.sources[:, :n_es]
        self.slope = torch.empty_like(self.pre)
        self.groups = [
            (
                kind,
                {name: value[:, neurons] for name, value in numbers.items()},
                self.pre[:, neurons],
                self.sensor[:, neurons],
                self.slope[:, neurons],
            )
            for kind, neurons in groups
        ]


def _band_gradient(band: _Prefix, xe: Tensor, weight: Tensor) -> Tensor:
    """∇θ of Σ_rows weight·CEL([T, F], argmax [T, F]) for the k patrons of ``band`` (k, N_θ):
    ``xe`` (k, B, D, 8) their batch rows plus each copy's noise, ``weight`` (k, 1, B) (1/rows
    in the batch, 0 on padding); the band's ``copy_weight`` (k, D) is 1/D_ic on a patron's
    copies. The forward pass of ``self_reward`` and its backward written out, each layer one
    batch of per-patron matrix products over the B·D (row, copy) columns, into the band's
    buffers (the gradient returned is overwritten by its next step)."""
    k, B, D, n_in = xe.shape
    n_es = len(ES_NEURONS)
    es_w, es_b, fc_w, fc_b, j_w, j_b, v_w, v_b = band.layers
    inputs = xe.view(k, B * D, n_in)
    # Forward: ES → FC → softmax of the 7 sources → judgements → tanh → verdicts.
    pre, sources, sensor, slope = band.pre, band.sources, band.sensor, band.slope
    torch.baddbmm(es_b, es_w, inputs.transpose(1, 2), out=pre)  # (k, 4, B·D)
    _sensor_and_slope(band.groups)
    sources[:, n_es:] = torch.baddbmm(fc_b, fc_w, sensor)
    soft = torch.softmax(sources, dim=1)
    judged = torch.tanh(torch.baddbmm(j_b, j_w, soft))
    # The verdicts are linear in the judgements, so their mean over the copies (Σ_d w_d = 1)
    # is the verdict of the copies' mean judgement: (k, 3, B) → [T, F] (k, 2, B).
    n_j = len(JUDGEMENTS)
    # (a product and a sum, not a matrix-vector product: its kernel's order of summing
    # depends on the band's size, this one's does not)
    judged_mean = (judged.view(k, n_j, B, D) * band.copy_cell).sum(dim=3)
    mean = torch.baddbmm(v_b, v_w, judged_mean)
    # Backward: d CEL / d logits = softmax − one-hot(argmax), times the row's weight; the
    # argmax of [T, F] is T unless F is larger (argmax takes the first of equals).
    g_mean = torch.softmax(mean, dim=1)
    g_mean.scatter_add_(1, mean.argmax(dim=1, keepdim=True), band.minus_one)
    g_mean *= weight
    g_judged_mean = torch.bmm(band.v_w_t, g_mean)  # (k, 3, B)
    g_judged = torch.rsub(judged * judged, 1.0).view(k, n_j, B, D)
    g_judged = (g_judged * g_judged_mean[..., None] * band.copy_cell).view(k, n_j, B * D)
    g_soft = torch.bmm(band.j_w_t, g_judged)
    # soft·(g_soft − Σ soft·g_soft), fused.
    g_sources = torch._softmax_backward_data(g_soft, soft, 1, soft.dtype)
    g_decision = g_sources[:, n_es:]
    g_pre = torch.baddbmm(g_sources[:, :n_es], band.fc_w_t, g_decision) * slope
    g_es_w, g_es_b, g_fc_w, g_fc_b, g_j_w, g_j_b, g_v_w, g_v_b = band.grad_layers
    torch.bmm(g_pre, inputs, out=g_es_w)
    torch.sum(g_pre, -1, keepdim=True, out=g_es_b)
    torch.bmm(g_decision, sensor.transpose(1, 2), out=g_fc_w)
    torch.sum(g_decision, -1, keepdim=True, out=g_fc_b)
    torch.bmm(g_judged, soft.transpose(1, 2), out=g_j_w)
    torch.sum(g_judged, -1, keepdim=True, out=g_j_b)
    torch.bmm(g_mean, judged_mean.transpose(1, 2), out=g_v_w)
    torch.sum(g_mean, -1, keepdim=True, out=g_v_b)
    return torch.cat(band.grad_columns, dim=1, out=band.grad)


_INPUT_CHUNK = 1 << 15
"""(step, patron, row, copy, input) cells of the SGD steps' inputs made at once (256 KB)."""
ROWS_PADDED_TO = 16
"""A band pads its patrons' batch sizes up to multiples of this, and their copy counts not at
all (``_bands``). Measured, one round of 64 patrons, one thread: the paper's patrons (batch
4-15, 5 copies: one band) 11.7 ms, as with the bands of nearby sizes this replaced (12.3 ms);
patrons of every batch size and copy count 110 ms (66 ms before). Copies padded to multiples
of 4 turned that round about: 16 and 85 ms."""


def _padded(n: int, multiple: int) -> int:
    """n rounded up to a multiple of ``multiple``."""
    return -(-n // multiple) * multiple


ALIGN_BYTES = 64
"""While a band steps, each patron's flat parameters start on a boundary of this many bytes
(``_aligned``). The batched matrix products read a patron's layers from its parameters' row:
a row that starts off a 64-byte boundary takes another path through the vector kernels, which
rounds the last bits otherwise, so 83 parameters of 8 bytes a patron made a patron's result
depend on whether its place in its band is even or odd (in ulps: 2·10⁻¹⁹ a round, seen where
a batch fills its padded rows)."""


def _aligned(theta: Tensor) -> Tensor:
    """``theta`` (n, N_θ) as a view whose every row starts on an ``ALIGN_BYTES`` boundary (of
    a padded copy; torch's CPU allocations start on one)."""
    n, width = theta.shape
    out = theta.new_zeros((n, _padded(width, ALIGN_BYTES // theta.element_size())))
    out[:, :width] = theta
    return out[:, :width]


def _bands(size: Tensor, steps: Tensor, copies: Tensor) -> list[Tensor]:
    """The patrons that take SGD steps, in bands of one padded shape (the batch size padded up
    to a multiple of ``ROWS_PADDED_TO``, and the copy count), each sorted by steps, most first,
    so the patrons still stepping at any step are a prefix. A patron's padded shape is its
    own, whoever shares its band, so every sum of its steps has the same length and order as
    when it is fine-tuned alone, and its parameters are read from the same alignment wherever
    it stands (``_aligned``): its result does not depend on the others (a faithful remote
    agent's fine-tuning is the server's, bit for bit)."""
    moving = torch.nonzero(steps > 0).flatten()
    by_shape: dict[tuple[int, int], list[int]] = {}
    for patron, b, d in zip(
        moving.tolist(), size[moving].tolist(), copies[moving].tolist(), strict=True
    ):
        by_shape.setdefault((_padded(b, ROWS_PADDED_TO), d), []).append(patron)
    bands = []
    for shape in sorted(by_shape):
        members = torch.tensor(by_shape[shape])
        bands.append(members[torch.argsort(steps[members], descending=True, stable=True)])
    return bands


def _tune_band(
    batch: FSNBatch,
    band: Tensor,
    steps: Tensor,
    theta: Tensor,
    rate: Tensor,
    x: Tensor,
    dataset: Tensor,
    draws: FineTuneDraws,
) -> Tensor:
    """SGD of the patrons ``band`` (sorted by ``steps``, most first) from their flat parameters
    ``theta`` (updated in place and returned) with per-column learning rates ``rate``; patron p
    learns from the rows ``x[dataset[p]]``."""
    n, R = len(band), x.shape[-2]
    _, E, _, all_copies, n_in = draws.normal.shape
    theta = _aligned(theta)  # a patron's arithmetic, wherever it stands in the band
    size = batch.batch_size[band].clamp(max=R)
    per_epoch = torch.div(R + size - 1, size, rounding_mode="floor")
    B, D = _padded(int(size.max()), ROWS_PADDED_TO), int(batch.copies[band].max())  # ``_bands``
    # Each patron's shuffled rows, epoch after epoch; its step s takes batch s of them. The
    # (step, patron, slot) tables: the row visited (its draw and its dataset row) and its
    # weight, 1/rows in the batch (0 on the padding slots past the batch's last row).
    S = int(steps[0])
    step = torch.arange(S)[:, None, None]
    epoch = torch.div(step, per_epoch[:, None], rounding_mode="floor")  # (S, n, 1)
    start = (step - epoch * per_epoch[:, None]) * size[:, None]
    count = torch.minimum(size[:, None], R - start)
    slot = torch.arange(B)
    position = epoch * R + start + torch.minimum(slot, count - 1)  # (S, n, B)
    position = position.clamp(max=E * R - 1)  # past a patron's last step: never used
    sequence = draws.order[band].reshape(n, 1, E * R).expand(n, S, E * R)
    row = sequence.gather(2, position.transpose(0, 1)).transpose(0, 1)
    # (a chunk of steps reads past a patron's last step: its epoch is clamped, never used)
    visit = ((band[:, None] * E + epoch.clamp(max=E - 1)) * R + row).reshape(S, n * B)
    at = (dataset[band, None] * R + row).reshape(S, n * B)
    weight = ((slot < count) / count.to(batch.dtype))[:, :, None]  # (S, n, 1, B)
    stepping = (steps > step[:, 0, 0, None]).sum(dim=1).tolist()  # patrons still stepping
    normal = draws.normal.reshape(-1, all_copies, n_in)[:, :D]
    scale = draws.scale[band, None, :D]
    rows = x.to(batch.dtype).reshape(-1, n_in)
    on = (torch.arange(D) < batch.copies[band, None]).to(batch.dtype)
    copy_weight = on / on.sum(dim=1, keepdim=True)
    numbers = _activation_table(batch, band)
    groups = batch.activation_groups
    # The steps' inputs (rows plus noise) are made a chunk of steps at a time: every step at
    # once for a few patrons (one model's projection: dozens of steps of a few rows), one step
    # at a time for a wide band (its inputs stay in the cache).
    chunk = max(1, _INPUT_CHUNK // (n * B * D * n_in))
    prefix: _Prefix | None = None
    step_inputs = rows.new_empty(0)
    for s, k in enumerate(stepping):
        if prefix is None or prefix.k != k:
            prefix = _Prefix(
                groups,
                theta[:k],
                {name: value[:k] for name, value in numbers.items()},
                copy_weight[:k],
                scale[:k],
                rate[:k],
                B,
                D,
            )
        if s % chunk == 0:  # stepping only falls: k patrons cover the chunk
            steps_here = min(chunk, S - s)
            noise = normal.index_select(0, visit[s : s + steps_here, : k * B].flatten())
            data = rows.index_select(0, at[s : s + steps_here, : k * B].flatten())
            step_inputs = torch.addcmul(
                data.view(steps_here, k, B, 1, n_in),
                noise.view(steps_here, k, B, D, n_in),
                prefix.scale,
            )
        xe = step_inputs[s % chunk, :k]
        prefix.theta -= prefix.rate * _band_gradient(prefix, xe, weight[s, :k])
    return theta


def fine_tune(
    batch: FSNBatch,
    x: Tensor,
    draws: FineTuneDraws,
    train: Tensor | None = None,
    dataset: Tensor | None = None,
) -> FSNBatch:
    """SRD fine-tuning of every patron at once (the reference's SGD over all parameters).

    Each patron has its own epochs, shuffles, batch size (last partial batch kept) and learning
    rate. At each of its steps a patron takes the mean CEL([T, F], argmax [T, F]) over its
    batch and plain SGD moves its own parameters, θ_p ← θ_p − lr_p·∇θ_p. Patrons outside
    ``train`` (bool (P,)) keep their parameters; PFC parameters move only where
    pfc.trainable. Patrons of one padded shape step together (``_bands``): one step of a band is one
    pass of small per-patron matrix products over their (row, copy) columns, with the
    gradient of ``self_reward``'s loss written out (autograd's bookkeeping would cost more
    than the arithmetic on these small tensors).

    ``x`` is the item dataset, (R, 8) shared or (P, R, 8), or several datasets (N, R, 8) with
    ``dataset`` (P,) the one of each patron. Returns the updated batch.
    """
    P, R = batch.n_patrons, x.shape[-2]
    if x.dim() == 2:
        x, dataset = x[None], torch.zeros(P, dtype=torch.long)
    elif dataset is None:
        dataset = torch.arange(P)
    epochs = batch.epochs if train is None else torch.where(train, batch.epochs, 0)
    if P == 0 or R == 0 or int(epochs.max()) == 0:  # no rows: nothing to learn from
        return batch
    size = batch.batch_size.clamp(max=R)
    steps = epochs * torch.div(R + size - 1, size, rounding_mode="floor")
    theta = _flat_parameters(batch)
    frozen = _PFC_COLUMNS[None, :] & ~batch.pfc_trainable[:, None]
    rate = torch.where(frozen, 0.0, batch.learning_rate[:, None])
    for band in _bands(size, steps, batch.copies):
        theta[band] = _tune_band(
            batch, band, steps[band], theta[band], rate[band], x, dataset, draws
        )
    return batch.with_parameters(_unflatten(batch, theta))


def fine_tune_round(
    batch: FSNBatch,
    x: Tensor,
    fine_tune_seeds: np.ndarray,
    augmentation_seeds: np.ndarray,
    positions: np.ndarray,
    dataset: Tensor | None = None,
) -> FSNBatch:
    """One fine-tuning round of an auction, the same in the market and in a remote agent:
    patron p, at position ``positions[p]`` of its auction, shuffles its rows with the seed
    ``derive_seeds(fine_tune_seeds[p], position)`` and jitters its copies with
    ``derive_seeds(augmentation_seeds[p], position)``, then ``fine_tune`` runs (``x`` and
    ``dataset`` as there)."""
    draws = draw_fine_tune_seeded(
        batch,
        x.shape[-2],
        derive_seeds(fine_tune_seeds, positions),
        derive_seeds(augmentation_seeds, positions),
    )
    return fine_tune(batch, x, draws, dataset=dataset)
