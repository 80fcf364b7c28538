"""FishNN: the hand-designed neurons respond as the paper and the reference say."""

from __future__ import annotations

import pytest
import torch

from agents.fish_net import (
    EAT,
    FC_WEIGHTS,
    FLD_BIAS,
    MOVE,
    NEURONS,
    PFC_CONV_WEIGHTS,
    PFC_FC_BIAS,
    FishNN,
)
from agents.neurons import self_reward_loss

NO_FOOD_RESPONSE = 1e-4 / (1e-4 + 0.25)
"""S(−0.5): what fh and ft read when their food is absent."""


def x(cells: tuple[float, float, float], energy: float) -> torch.Tensor:
    return torch.tensor([[*cells, energy]])


@pytest.fixture
def net() -> FishNN:
    return FishNN()


def test_designed_weights_are_the_reference_numbers(net: FishNN) -> None:
    assert net.food_detector.weight.tolist() == [[1, 0, 0], [0, 1, 1]]
    assert net.food_detector.bias.tolist() == list(FLD_BIAS) == [-0.5, -0.5]
    assert torch.allclose(net.fc.weight, torch.tensor([[1, 1e-3, -1], [1e-3, 1, 1]]))
    assert torch.allclose(net.fc.weight, torch.tensor(FC_WEIGHTS))
    assert net.pfc_conv.bias is None
    assert net.pfc_conv.weight.tolist() == [list(row) for row in PFC_CONV_WEIGHTS]
    assert net.pfc_fc.bias.tolist() == pytest.approx(list(PFC_FC_BIAS))
    assert net.pfc_fc.bias.tolist() == pytest.approx([0.0, 0.4])


@pytest.mark.parametrize(
    ("cells", "fh", "ft"),
    [
        ((0.5, 0.0, 0.0), 1.0, NO_FOOD_RESPONSE),  # food here
        ((0.0, 0.5, 0.0), NO_FOOD_RESPONSE, 1.0),  # food one cell ahead
        ((0.0, 0.0, 0.5), NO_FOOD_RESPONSE, 1.0),  # food two cells ahead
        ((0.0, 0.0, 0.0), NO_FOOD_RESPONSE, NO_FOOD_RESPONSE),  # no food in sight
    ],
)
def test_food_location_detector(net: FishNN, cells, fh, ft) -> None:
    acts = net.activations(x(cells, 0.6))
    assert acts["fh"].item() == pytest.approx(fh, rel=1e-5)
    assert acts["ft"].item() == pytest.approx(ft, rel=1e-5)
    assert acts["F"].item() == pytest.approx(0.6)


@pytest.mark.parametrize(
    ("cells", "energy", "action"),
    [
        ((0.5, 0.0, 0.0), 0.30, EAT),  # hungry, food here
        ((0.5, 0.0, 0.0), 0.49, EAT),
        ((0.5, 0.0, 0.0), 0.50, MOVE),  # the untrained fish passes food at F ≥ ≈0.4995
        ((0.5, 0.0, 0.0), 0.55, MOVE),
        ((0.5, 0.0, 0.0), 0.80, MOVE),
        ((0.0, 0.5, 0.0), 0.05, MOVE),  # food ahead: go there, however hungry
        ((0.0, 0.0, 0.5), 0.05, MOVE),
        ((0.0, 0.0, 0.0), 0.05, MOVE),  # never eat on an empty cell
        ((0.0, 0.0, 0.0), 1.00, MOVE),
    ],
)
def test_greedy_decision(net: FishNN, cells, energy, action) -> None:
    assert net.decide(x(cells, energy)).item() == action
    logits, _ = net(x(cells, energy))
    assert logits.argmax().item() == action


def test_decision_logits_are_the_fc_formulas(net: FishNN) -> None:
    acts = net.activations(x((0.5, 0.0, 0.0), 0.3))
    fh, ft, energy = acts["fh"], acts["ft"], acts["F"]
    assert acts["eat"].item() == pytest.approx((fh + 1e-3 * ft - energy).item(), abs=1e-6)
    assert acts["move"].item() == pytest.approx((1e-3 * fh + ft + energy).item(), abs=1e-6)


def test_ties_go_to_eat(net: FishNN) -> None:
    with torch.no_grad():
        net.fc.weight.zero_()
    assert net.decide(x((0.0, 0.0, 0.0), 0.7)).item() == EAT


def test_pfc_judgements_and_verdicts(net: FishNN) -> None:
    batch = torch.tensor(
        [
            [0.5, 0.0, 0.0, 0.3],  # food here, hungry → eats
            [0.0, 0.5, 0.0, 0.6],  # food ahead → moves
            [0.0, 0.0, 0.0, 0.95],  # nothing in sight, well fed → explores
            [0.5, 0.0, 0.0, 0.8],  # food here but passes it
        ]
    )
    acts = net.activations(batch)
    judgements = torch.stack((acts["e1"], acts["m1"], acts["ex"]), dim=1)
    assert judgements.argmax(dim=1).tolist()[:3] == [0, 1, 2]  # e1, m1, ex respectively
    true, false = acts["T"], acts["F_verdict"]
    assert torch.allclose(true + false, torch.ones(4))
    assert (true[:3] > false[:3]).all()  # the designed behaviour is judged right
    assert false[3] > true[3]  # passing food is judged wrong: SRD pushes toward eating
    assert true[0].item() == pytest.approx(0.5748, abs=1e-4)
    assert true[3].item() == pytest.approx(0.4280, abs=1e-4)


def test_forward_matches_activations_and_batches(net: FishNN) -> None:
    batch = torch.tensor([[0.5, 0, 0, 0.3], [0, 0.5, 0, 0.7], [0, 0, 0, 0.2]])
    logits, verdict = net(batch)
    acts = net.activations(batch)
    assert set(acts) == set(NEURONS)
    assert torch.equal(logits, torch.stack((acts["eat"], acts["move"]), dim=1))
    assert torch.equal(verdict, torch.stack((acts["T"], acts["F_verdict"]), dim=1))
    for row in range(3):
        one_logits, one_verdict = net(batch[row : row + 1])
        assert torch.allclose(one_logits[0], logits[row], atol=1e-7)
        assert torch.allclose(one_verdict[0], verdict[row], atol=1e-7)


def test_self_reward_loss_trains_every_parameter(net: FishNN) -> None:
    _, verdict = net(torch.tensor([[0.5, 0, 0, 0.8], [0, 0, 0.5, 0.6]]))
    self_reward_loss(verdict.sum(dim=0, keepdim=True)).backward()
    for name, parameter in net.named_parameters():
        assert parameter.grad is not None, name
        assert parameter.grad.abs().sum() > 0, name


def test_load_designed_weights_restores(net: FishNN) -> None:
    before = {k: v.clone() for k, v in net.state_dict().items()}
    with torch.no_grad():
        for parameter in net.parameters():
            parameter.add_(1.0)
    net.load_designed_weights()
    for key, value in net.state_dict().items():
        assert torch.equal(value, before[key]), key
