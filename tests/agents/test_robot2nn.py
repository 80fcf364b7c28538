"""Robot2NN: receptors, DeconvSeqs, v_Σ, batched imagined plans and the SRD step."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from agents.planning import MOVE_LIMIT, PRESETS, PlanningRules
from agents.robot2nn import (
    KERNEL_CENTRE,
    KERNEL_SIDE,
    KNOWN_TILE_RGB,
    LEAVING_FACTOR,
    NAMED_INPUTS,
    TARGET_CLASS,
    DeconvSeq,
    Receptors,
    Robot2NN,
    imagine,
    receptors,
)

LAVA_RGB = (255, 0, 0)
CHAR_RGB = {
    "T": KNOWN_TILE_RGB["target"],
    ".": KNOWN_TILE_RGB["dirt"],
    "S": KNOWN_TILE_RGB["dirt"],
    "g": KNOWN_TILE_RGB["grass"],
    "L": LAVA_RGB,
}
STEPS = ((1, 0), (0, 1), (-1, 0), (0, -1))  # R, D, L, U as (dx, dy)


def rgb_maps(*maps: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
    """Map strings → (N, 3, H, W) RGB in [0, 1] and one-hot starts (N, H, W)."""
    images, starts = [], []
    for rows in maps:
        images.append([[CHAR_RGB[c] for c in row] for row in rows])
        y = next(i for i, row in enumerate(rows) if "S" in row)
        starts.append((rows[y].index("S"), y))
    rgb = torch.tensor(images, dtype=torch.float32).permute(0, 3, 1, 2) / 255.0
    one_hot = torch.zeros(rgb.shape[0], rgb.shape[2], rgb.shape[3])
    for i, (x, y) in enumerate(starts):
        one_hot[i, y, x] = 1.0
    return rgb, one_hot


def random_maps(n: int, seed: int, lava: float = 0.1, h: int = 11, w: int = 13) -> Receptors:
    """Random maps built here (independently of sim.lavaland): 30 % grass, some lava."""
    rng = np.random.default_rng(seed)
    maps = []
    for _ in range(n):
        u = rng.random((h, w))
        grid = np.where(u < 0.3, "g", np.where(u < 0.3 + lava, "L", "."))
        cells = rng.choice(h * w, size=2, replace=False)
        grid[divmod(int(cells[0]), w)] = "S"
        grid[divmod(int(cells[1]), w)] = "T"
        maps.append(["".join(r) for r in grid])
    return receptors(*rgb_maps(*maps))


def test_exactly_180_trainable_parameters_initialised_as_designed():
    robot = Robot2NN()
    params = dict(robot.named_parameters())
    assert sum(p.numel() for p in params.values() if p.requires_grad) == 180
    assert len(params) == 20
    assert next(iter(params)) == "deconv_self.layers.0.weight"
    for weight in params.values():
        assert weight.shape == (1, 1, 3, 3)
        assert weight[0, 0, 1, 1].item() == KERNEL_CENTRE
        mask = torch.ones(3, 3, dtype=torch.bool)
        mask[1, 1] = False
        assert torch.all(weight[0, 0][mask] == KERNEL_SIDE)
    assert [name for name, _ in robot.named_children()] == [f"deconv_{t}" for t in NAMED_INPUTS]


def test_aba_values_match_the_spec_table():
    maps, starts = rgb_maps(["T.gL", "S..."])
    seen = receptors(maps, starts)
    got = seen.known[0, :, 0, :].T.double()  # rows: actual tile T, D, G, L; cols: w_T, w_D, w_G
    spec = torch.tensor(
        [
            [1, 0.00307, 0.00072],
            [0.00307, 1, 0.00704],
            [0.00072, 0.00704, 1],
            [0.00178, 0.0109, 0.00057],
        ],
        dtype=torch.float64,
    )
    assert torch.allclose(got, spec, rtol=1e-2, atol=0)  # the table is rounded
    actual = [(255, 215, 0), (139, 69, 19), (0, 128, 0), LAVA_RGB]
    for i, tile in enumerate(actual):
        for j, name in enumerate(KNOWN_TILE_RGB):
            d = np.mean(
                [((a - b) / 255.0) ** 2 for a, b in zip(tile, KNOWN_TILE_RGB[name], strict=True)]
            )
            assert got[i, j].item() == pytest.approx(1e-4 / (1e-4 + d * d), rel=1e-4)


def test_unknown_only_on_lava_and_recognised_classes():
    maps, starts = rgb_maps(["TgLL.", "S.g.L"])
    seen = receptors(maps, starts)
    lava = torch.tensor([[0, 0, 1, 1, 0], [0, 0, 0, 0, 1]], dtype=torch.float32)
    assert torch.equal(seen.unknown[0], lava)
    assert torch.equal(seen.tile_class[0], torch.tensor([[0, 2, 3, 3, 1], [1, 1, 2, 1, 3]]))
    assert torch.equal(seen.self_position[0], torch.tensor([[0.0] * 5, [1.0] + [0.0] * 4]))


def test_grouped_deconv_equals_the_four_deconvseqs_with_true_transposed_semantics():
    torch.manual_seed(0)
    robot = Robot2NN(p_target=2.0, rules=PRESETS["reference"])
    with torch.no_grad():
        for weight in robot.parameters():
            weight.add_(0.2 * torch.randn_like(weight))  # break the kernel symmetry
    seen = random_maps(3, seed=1)
    v1 = robot.v1(seen)
    w_target, w_dirt, w_grass = seen.known.unbind(1)
    toward = w_target - seen.self_position
    inputs = [seen.self_position, w_target, toward * w_dirt, toward * w_grass]
    for i, (seq, x, p) in enumerate(
        zip(robot.sequences(), inputs, robot.preferences.tolist(), strict=True)
    ):
        assert torch.allclose(v1[:, i], p * seq(x[:, None])[:, 0], atol=1e-6)
        # transposed convolution = correlation with the spatially flipped kernel
        y = x[:, None]
        for layer in seq.layers:
            y = torch.tanh(F.conv2d(y, layer.weight.flip(-1, -2), padding=1))
            y = y / y.abs().amax(dim=(-2, -1), keepdim=True)
        assert torch.allclose(v1[:, i], p * y[:, 0], atol=1e-6)
    assert torch.allclose(seq(inputs[3][:, None]).abs().amax(dim=(-2, -1)), torch.ones(3, 1))
    assert isinstance(robot.deconv_grass, DeconvSeq)


@pytest.mark.parametrize("preset", ["paper", "reference"])
def test_v_sigma_batched_equals_one_map_at_a_time(preset):
    robot = Robot2NN(rules=PRESETS[preset])
    seen = random_maps(6, seed=2)
    batched = robot.v_sigma(seen)
    for i in range(6):
        assert torch.allclose(batched[i], robot.v_sigma(seen.select(i))[0], atol=1e-6)


def test_v_sigma_anchors_and_unknown_avoidance():
    maps, starts = rgb_maps(["..g..L", ".S..T.", "L.g..."])
    seen = receptors(maps, starts)
    lava = seen.unknown[0] > 0
    for u_a in (2.0, 0.0):
        paper = Robot2NN(unknown_avoidance=u_a, rules=PRESETS["paper"]).v_sigma(seen)[0]
        v0 = paper[~lava].abs().max()
        assert paper[1, 4].item() == pytest.approx(v0.item())  # target set to +v0
        assert paper[1, 1].item() == pytest.approx(-v0.item())  # start set to −v0
        assert torch.allclose(paper[lava], torch.full((2,), -u_a * v0.item()))
        robot = Robot2NN(unknown_avoidance=u_a, rules=PRESETS["reference"])
        reference = robot.v_sigma(seen)[0]
        s = robot.v1(seen).sum(1)[0]
        v0 = s.abs().max()
        added = s + v0 * seen.known[0, TARGET_CLASS] - v0 * seen.self_position[0]
        assert torch.allclose(reference[~lava], added[~lava], atol=1e-6)
        assert torch.allclose(reference[lava], -u_a * added.abs().max() * torch.ones(2))
    assert torch.all(reference[lava] == 0.0)  # u_a = 0: lava is exactly neutral


def test_srd_loss_values_and_reductions():
    v_plan = torch.tensor([[0.3, -2.0, 5.0, -0.01]])
    good, bad = (1 - math.tanh(1)) ** 2, (1 - math.tanh(-1)) ** 2
    assert good == pytest.approx(0.0568, abs=1e-4)
    assert bad == pytest.approx(3.10, abs=5e-3)
    v_sigma = torch.full((1, 3, 3), 100.0)  # the guard's scale; unused without the guard
    paper = Robot2NN(rules=PRESETS["paper"]).srd_loss(v_plan, v_sigma)
    reference = Robot2NN(rules=PRESETS["reference"]).srd_loss(v_plan, v_sigma)
    assert paper.item() == pytest.approx(2 * good + 2 * bad, rel=1e-6)
    assert reference.item() == pytest.approx((2 * good + 2 * bad) / 4, rel=1e-6)


# --- the batched rollout against a plain one-map-at-a-time loop ------------------------------


def plain_plan(
    v_sigma: np.ndarray, classes: np.ndarray, start: tuple[int, int], coins, final_check: bool
) -> dict:
    """One imagined plan, written as directly as the paper's rollout reads."""
    h, w = v_sigma.shape
    v = v_sigma.astype(np.float32).copy()
    x, y = start
    total, actions, path = 0.0, [], [(x, y)]
    reached, moves = False, MOVE_LIMIT
    for k in range(MOVE_LIMIT):
        if classes[y, x] == TARGET_CLASS:
            reached, moves = True, k
            break
        values = []
        for dx, dy in STEPS:
            nx, ny = x + dx, y + dy
            values.append(float(v[ny, nx]) if 0 <= nx < w and 0 <= ny < h else -math.inf)
        ranked = sorted(range(4), key=lambda a: -values[a])  # stable: ties keep R, D, L, U
        action = ranked[1] if coins[k] else ranked[0]
        total += values[action]
        v[y, x] = np.float32(-LEAVING_FACTOR) * np.abs(v).max()
        x, y = x + STEPS[action][0], y + STEPS[action][1]
        actions.append(action)
        path.append((x, y))
    if final_check and not reached:
        reached = bool(classes[y, x] == TARGET_CLASS)
    return {
        "reached": reached,
        "moves": moves,
        "actions": actions,
        "v_plan": total / moves,
    }


@pytest.mark.parametrize("preset", ["paper", "reference"])
def test_batched_rollout_equals_a_plain_per_map_loop(preset):
    rules = PRESETS[preset]
    robot = Robot2NN(p_target=2.0, rules=rules)
    n, p = 40, rules.n_plans
    seen = random_maps(n, seed=3)
    explore = torch.from_numpy(np.random.default_rng(4).random((n, p, MOVE_LIMIT)) < 0.1)
    v_sigma = robot.v_sigma(seen).detach()
    plans = imagine(v_sigma, seen, explore, rules)
    executed = plans.executed(rules)
    reached_any = False
    for i in range(n):
        start = tuple(seen.self_position[i].nonzero()[0].flip(0).tolist())
        plain = [
            plain_plan(
                v_sigma[i].numpy(),
                seen.tile_class[i].numpy(),
                start,
                explore[i, j].tolist(),
                rules.final_check,
            )
            for j in range(p)
        ]
        for j, one in enumerate(plain):
            assert plans.reached[i, j].item() == one["reached"]
            assert plans.n_moves[i, j].item() == one["moves"]
            assert plans.actions[i, j, : one["moves"]].tolist() == one["actions"]
            assert torch.all(plans.actions[i, j, one["moves"] :] == -1)
            assert plans.v_plan[i, j].item() == pytest.approx(one["v_plan"], rel=1e-5, abs=1e-6)
            reached_any |= one["reached"]
        values = [one["v_plan"] for one in plain]
        expected = int(np.argmax(values)) if rules.executed == "best" else p - 1
        assert executed[i].item() == expected
    assert reached_any and not plans.reached.all()


def corridor(length: int) -> tuple[torch.Tensor, Receptors]:
    """A 2-row corridor: start at the left, target `length` moves to the right, v_Σ rising."""
    row = "S" + "." * (length - 1) + "T"
    maps, starts = rgb_maps([row, "." * len(row)])
    v = torch.stack([torch.arange(len(row), dtype=torch.float32), torch.full((len(row),), -50.0)])
    return v[None], receptors(maps, starts)


@pytest.mark.parametrize(("length", "paper_reached", "reference_reached"), [(35, 1, 1), (36, 1, 0)])
def test_target_entered_on_the_36th_move_counts_only_in_the_paper_preset(
    length, paper_reached, reference_reached
):
    v, seen = corridor(length)
    explore = torch.zeros(1, 1, MOVE_LIMIT, dtype=torch.bool)
    for preset, expected in (("paper", paper_reached), ("reference", reference_reached)):
        plans = imagine(v, seen, explore, PRESETS[preset])
        assert plans.reached.item() == bool(expected)
        assert plans.n_moves.item() == length
        assert plans.actions[0, 0, :length].tolist() == [0] * length


def test_ties_keep_right_down_left_up_and_the_coin_takes_the_second():
    maps, starts = rgb_maps([".....", "..S..", "....T"])
    seen = receptors(maps, starts)
    flat = torch.zeros(1, 3, 5)
    first = torch.zeros(1, 2, MOVE_LIMIT, dtype=torch.bool)
    first[0, 1, 0] = True
    plans = imagine(flat, seen, first, PRESETS["paper"])
    assert plans.actions[0, :, 0].tolist() == [0, 1]  # R wins a tie; the coin takes D
    # a clear best neighbour (up, value 5); the start is then set to −0.9·max|v_Σ| = −4.5
    v = torch.tensor([[[0.0, 0, 5, 0, 0], [0, 1, 0, 0, 0], [0, 0, 0, 0, 2]]])
    plans = imagine(v, seen, first[:, :1], PRESETS["paper"])
    assert plans.actions[0, 0, 0].item() == 3  # up to the 5
    assert plans.left_values[0, 0, 0].item() == pytest.approx(-0.9 * 5)


@pytest.mark.parametrize("preset", ["paper", "reference"])
def test_gradient_equals_autograd_through_an_in_place_updated_v_sigma(preset):
    rules = PRESETS[preset]
    seen = random_maps(1, seed=5)
    explore = torch.from_numpy(np.random.default_rng(6).random((1, rules.n_plans, 36)) < 0.1)

    batched = Robot2NN(p_target=2.0, rules=rules)
    v_sigma = batched.v_sigma(seen)
    plans = imagine(v_sigma, seen, explore, rules)
    batched.srd_loss(plans.differentiable_v_plan(v_sigma), v_sigma).backward()

    plain = Robot2NN(p_target=2.0, rules=rules)
    v = plain.v_sigma(seen)[0]
    h, w = v.shape
    classes = seen.tile_class[0]
    start = tuple(seen.self_position[0].nonzero()[0].flip(0).tolist())
    v_plans = []
    for j in range(rules.n_plans):
        overlay: dict[tuple[int, int], torch.Tensor] = {}  # tiles written in place

        def read(x, y, overlay=overlay):
            return overlay.get((y, x), v[y, x])

        (x, y), chosen = start, []
        for k in range(MOVE_LIMIT):
            if classes[y, x] == TARGET_CLASS:
                break
            options = [
                (x + dx, y + dy) if 0 <= x + dx < w and 0 <= y + dy < h else None
                for dx, dy in STEPS
            ]
            values = [-math.inf if o is None else read(*o).item() for o in options]
            ranked = sorted(range(4), key=lambda a: -values[a])
            nx, ny = options[ranked[1] if explore[0, j, k] else ranked[0]]
            chosen.append(read(nx, ny))
            current = torch.stack([read(cx, cy) for cy in range(h) for cx in range(w)])
            overlay[(y, x)] = (-LEAVING_FACTOR * current.abs().max()).detach()
            x, y = nx, ny
        v_plans.append(torch.stack(chosen).mean())
    plain.srd_loss(torch.stack(v_plans)[None], v[None]).backward()

    for (name, a), b in zip(batched.named_parameters(), plain.parameters(), strict=True):
        assert torch.allclose(a.grad, b.grad, rtol=1e-4, atol=1e-7), name
    assert all(p.grad.abs().sum() > 0 for p in batched.parameters())


def test_one_srd_step_changes_every_weight_and_executed_rules():
    rules = PlanningRules(
        n_plans=3, executed="last", loss_reduction="mean", anchors="add", final_check=False
    )
    robot = Robot2NN(rules=rules)
    before = [p.detach().clone() for p in robot.parameters()]
    seen = random_maps(1, seed=7)
    explore = torch.zeros(1, 3, MOVE_LIMIT, dtype=torch.bool)
    v_sigma = robot.v_sigma(seen)
    plans = imagine(v_sigma, seen, explore, rules)
    assert plans.executed(rules).tolist() == [2]
    robot.srd_loss(plans.differentiable_v_plan(v_sigma), v_sigma).backward()
    with torch.no_grad():
        for p in robot.parameters():
            p -= 1e-2 * p.grad
    changed = [not torch.equal(a, b) for a, b in zip(before, robot.parameters(), strict=True)]
    assert all(changed)
    assert torch.allclose(plans.differentiable_v_plan(v_sigma.detach()), plans.v_plan, atol=1e-5)
