"""The Fish Sale Negotiator's forward pass, batched: one tensor pass evaluates patrons × rows ×
copies, whatever activation each manifest chose. The reference's Conv1d with dilation D_ic is
exactly a per-copy linear map, which is how it is computed here; ``make_noise`` draws the
augmentation (implicit contrastive) noise."""

from __future__ import annotations

import torch
from torch import Tensor

from agents.batch import BELOW_THRESHOLD, SELECTIVE, THRESHOLD, FSNBatch
from agents.manifest import (
    DECISIONS,
    ES_NEURONS,
    INPUTS,
    JUDGEMENTS,
    VERDICTS,
)

ACTIONS = ("buy", "hold", "quit")
"""Decision codes 0, 1, 2 (the order of the FC neurons B, L, Q)."""
NEURONS = ES_NEURONS + DECISIONS + JUDGEMENTS + VERDICTS
"""Every named neuron reported by ``activations``."""


def make_noise(batch: FSNBatch, n_rows: int, generator: torch.Generator) -> Tensor:
    """Augmentation noise (P, R, D, 8), D = the batch's largest D_ic: σ_p·N(0, 1) on copies
    1..D_ic(p)−1 and jittered inputs, exactly 0 on copy 0, on noiseless inputs and on copies a
    patron does not have."""
    normal = standard_normal((batch.n_patrons, n_rows, batch.max_copies), generator)
    return normal.to(batch.dtype) * noise_scale(batch)[:, None]


def standard_normal(
    shape: tuple[int, ...], generator: torch.Generator, out: Tensor | None = None
) -> Tensor:
    """N(0, 1) draws of shape (*shape, 8), made in float32: CPU float64 normals are several
    times slower and σ = 0.01 jitter needs no more precision. ``out``, if given, must be a
    contiguous float32 tensor of that shape (the draws are the same)."""
    return torch.randn((*shape, len(INPUTS)), generator=generator, dtype=torch.float32, out=out)


def noise_scale(batch: FSNBatch) -> Tensor:
    """(P, D, 8): σ_p on the jittered (copy, input) cells, 0 elsewhere."""
    d = torch.arange(batch.max_copies)
    copy_on = ((d >= 1) & (d[None, :] < batch.copies[:, None])).to(batch.dtype)  # (P, D)
    return batch.noise_std[:, None, None] * copy_on[:, :, None] * batch.noise_mask[:, None, :]


# The forward pass works neuron-major: tensors are (neuron, row, copy, patron), patron last, so
# every per-patron parameter broadcasts along the contiguous axis (several times faster on CPU
# than patron-major broadcasting). Public functions return (patron, row, ...) tensors.


def _per_patron(values: Tensor) -> Tensor:
    """(P, K) parameters → (K, 1, 1, P) for broadcasting over (K, R, D, P)."""
    return values.T.contiguous()[:, None, None, :]


def _sensor(batch: FSNBatch, x: Tensor, noise: Tensor | None) -> Tensor:
    """ES activations per copy, (4, R, D, P) (D = 1 when there is no noise)."""
    x = x.to(batch.dtype)
    equation = "rj,pkj->krp" if x.dim() == 2 else "prj,pkj->krp"
    clean = torch.einsum(equation, x, batch.es_weight) + batch.es_bias.T[:, None, :]
    clean = clean.contiguous()[:, :, None, :]  # (4, R, 1, P)
    groups = batch.activation_groups
    parts = [_activate(batch, kind, neurons, clean, noise) for kind, neurons in groups]
    return torch.cat(parts) if len(parts) > 1 else parts[0]


def _activate(
    batch: FSNBatch, kind: int | None, neurons: slice, clean: Tensor, noise: Tensor | None
) -> Tensor:
    """The activations of the ES neurons ``neurons`` (all of one ``kind``; None = mixed)."""
    weight = batch.es_weight[:, neurons]
    a, c = _per_patron(batch.es_a[:, neurons]), _per_patron(batch.es_c[:, neurons])
    slope = _per_patron(batch.es_slope[:, neurons])
    eps = _per_patron(batch.es_epsilon[:, neurons])

    def jitter(w: Tensor) -> Tensor:  # W·ε per copy: the linear map of the noise
        assert noise is not None
        return torch.einsum("prdj,pkj->krdp", noise, w).contiguous()

    if kind == SELECTIVE:
        pre = clean[neurons] if noise is None else clean[neurons] + jitter(weight)
        return eps / (eps + pre * pre)
    if kind is not None:
        # a·(W·(x + ε) + b − c) = a·(W·x + b − c) + (a·W)·ε
        z = (clean[neurons] - c) * a
        if noise is not None:
            z = z + jitter(weight * batch.es_a[:, neurons, None])
        # leaky_relu(z, ns) = max(z, ns·z) because 0 ≤ ns ≤ 1 (the manifest's range).
        fired = torch.tanh(torch.maximum(z, slope * z))
        return fired if kind == THRESHOLD else 1.0 - fired  # BT = tanh(−lrelu) + 1 = 1 − T
    pre = clean[neurons] if noise is None else clean[neurons] + jitter(weight)
    z = (pre - c) * a
    fired = torch.tanh(torch.maximum(z, slope * z))
    codes = batch.es_kind[:, neurons]
    below = _per_patron((codes == BELOW_THRESHOLD).to(batch.dtype))
    chosen = _per_patron((codes == SELECTIVE).to(batch.dtype))
    out = fired + below * (1.0 - 2.0 * fired)
    return out + chosen * (eps / (eps + pre * pre) - out)


def _linear(weight: Tensor, bias: Tensor, inputs: Tensor) -> Tensor:
    """A per-patron linear layer on (K_in, R, D, P) → (K_out, R, D, P)."""
    return torch.einsum("krdp,pjk->jrdp", inputs, weight).contiguous() + _per_patron(bias)


def _copy_mean(batch: FSNBatch, values: Tensor) -> Tensor:
    """Average (K, R, D, P) over each patron's own copies → (K, R, P)."""
    n_copies = values.shape[2]
    if n_copies == 1:
        return values[:, :, 0]
    on = (torch.arange(n_copies)[:, None] < batch.copies[None, :]).to(batch.dtype)  # (D, P)
    return (values * (on / on.sum(dim=0))).sum(dim=2)


def _pfc(batch: FSNBatch, sensor: Tensor, decision: Tensor) -> tuple[Tensor, Tensor]:
    """Judgements [PGL, BC, FQ] (before their tanh) and verdicts [T, F], per copy."""
    sources = torch.cat((sensor, decision), dim=0)
    e = torch.exp(sources - sources.detach().amax(dim=0, keepdim=True))
    judgement = _linear(batch.judgement_weight, batch.judgement_bias, e / e.sum(dim=0))
    verdict = _linear(batch.verdict_weight, batch.verdict_bias, torch.tanh(judgement))
    return judgement, verdict


def _patron_major(values: Tensor) -> Tensor:
    """(K, R, P) → (P, R, K)."""
    return values.permute(2, 1, 0).contiguous()


def sensors(batch: FSNBatch, x: Tensor, noise: Tensor | None = None) -> Tensor:
    """The ES neurons PG, SZ, LSR, ST (after their activations) averaged over the copies,
    (P, R, 4): ``activations``' first four without the layers above them."""
    return _patron_major(_copy_mean(batch, _sensor(batch, x, noise)))


def decision_logits(batch: FSNBatch, x: Tensor, noise: Tensor | None = None) -> Tensor:
    """[B, L, Q] averaged over the copies, (P, R, 3); ``x`` is (R, 8) shared by every patron or
    (P, R, 8); ``noise`` (P, R, D, 8) from ``make_noise``, None = every copy clean."""
    # The FC is linear: averaging the sensor over copies first gives the same mean, cheaper.
    mean_sensor = _patron_major(_copy_mean(batch, _sensor(batch, x, noise)))  # (P, R, 4)
    return torch.einsum("prk,pjk->prj", mean_sensor, batch.fc_weight) + batch.fc_bias[:, None, :]


def clean_logits(batch: FSNBatch, x: Tensor) -> Tensor:
    """``decision_logits(batch, x)`` for rows ``x`` (R, 8) shared by every patron, every copy
    clean, computed patron-major with the rows last: for many rows (the screener's probes)
    each per-patron parameter then broadcasts along a contiguous run of rows, and no layer
    needs its input laid out anew. The same formulas and products (on the screener's rows the
    same numbers bit for bit; the BLAS kernels may round a dot product's last bit differently
    for a handful of rows), and in a batch of one activation kind per neuron each patron's
    scores are exactly those it gets alone. A (P, R, 3) view."""
    P, n_es = batch.n_patrons, len(ES_NEURONS)
    x = x.to(batch.dtype)
    pre = torch.mm(batch.es_weight.reshape(P * n_es, -1), x.T).view(P, n_es, -1)
    pre = pre + batch.es_bias[:, :, None]  # (P, 4, R)
    sensor = torch.empty_like(pre)
    for kind, neurons in batch.activation_groups:
        _activate_rows(batch, kind, neurons, pre[:, neurons], sensor[:, neurons])
    logits = torch.bmm(batch.fc_weight, sensor) + batch.fc_bias[:, :, None]  # (P, 3, R)
    return logits.transpose(1, 2)


def _activate_rows(
    batch: FSNBatch, kind: int | None, neurons: slice, pre: Tensor, out: Tensor
) -> None:
    """``_activate`` without noise on (P, n, R) pre-activations, into ``out``."""

    def per_patron(values: Tensor) -> Tensor:
        return values[:, neurons, None]

    a, c = per_patron(batch.es_a), per_patron(batch.es_c)
    slope, eps = per_patron(batch.es_slope), per_patron(batch.es_epsilon)
    if kind == SELECTIVE:
        torch.div(eps, eps + pre * pre, out=out)
    elif kind is not None:
        z = (pre - c) * a
        if kind == THRESHOLD:
            torch.tanh(torch.maximum(z, slope * z), out=out)
        else:
            torch.sub(1.0, torch.tanh(torch.maximum(z, slope * z)), out=out)
    else:
        z = (pre - c) * a
        fired = torch.tanh(torch.maximum(z, slope * z))
        codes = batch.es_kind[:, neurons, None]
        below = (codes == BELOW_THRESHOLD).to(batch.dtype)
        chosen = (codes == SELECTIVE).to(batch.dtype)
        mixed = fired + below * (1.0 - 2.0 * fired)
        torch.add(mixed, chosen * (eps / (eps + pre * pre) - mixed), out=out)


def decide(batch: FSNBatch, x: Tensor, noise: Tensor | None = None) -> Tensor:
    """Greedy decisions (P, R) int64: 0 buy, 1 hold, 2 quit (ties → the lowest index)."""
    return decision_logits(batch, x, noise).argmax(dim=-1)


def self_reward(batch: FSNBatch, x: Tensor, noise: Tensor | None) -> Tensor:
    """The PFC's verdicts [T, F] averaged over the copies, (P, R, 2)."""
    sensor = _sensor(batch, x, noise)
    _, verdict = _pfc(batch, sensor, _linear(batch.fc_weight, batch.fc_bias, sensor))
    return _patron_major(_copy_mean(batch, verdict))


def activations(batch: FSNBatch, x: Tensor, noise: Tensor | None = None) -> dict[str, Tensor]:
    """Every named neuron averaged over the copies, (P, R) each: PG, SZ, LSR, ST (after their
    activations), B, L, Q (FC outputs), PGL, BC, FQ (judgements before their tanh), T, F."""
    sensor = _sensor(batch, x, noise)
    decision = _linear(batch.fc_weight, batch.fc_bias, sensor)
    judgement, verdict = _pfc(batch, sensor, decision)
    stacked = _copy_mean(batch, torch.cat((sensor, decision, judgement, verdict), dim=0))
    return {name: stacked[i].T.contiguous() for i, name in enumerate(NEURONS)}
