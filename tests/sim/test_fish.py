"""Robot fish 1D: the ring-tape world and the SRD experiment."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from agents.fish_net import EAT, MOVE
from sim.experiment import ConfigError, parse_config
from sim.fish import FishConfig, RobotFish1D, run, simulate, window_means

SHORT_STEPS = 4200
"""Long enough for both SRD improvements (at steps ≈1690 and ≈3610), a few seconds to run."""


@pytest.fixture(scope="module")
def untrained() -> np.ndarray:
    return simulate(FishConfig(steps=SHORT_STEPS, srd=False)).energy


@pytest.fixture(scope="module")
def trained() -> np.ndarray:
    return simulate(FishConfig(steps=SHORT_STEPS, srd=True)).energy


def meal_energies(energy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(steps of the meals, energy just before each meal)."""
    before = np.concatenate(([1.0], energy[:-1]))
    meals = np.nonzero(energy > before)[0]
    return meals, before[meals]


# --- the environment -------------------------------------------------------------------------


def test_check_env_passes() -> None:
    check_env(RobotFish1D(), skip_render_check=True)


def test_view_rolls_over_the_ring_tape() -> None:
    env = RobotFish1D()
    observation, info = env.reset(seed=0)
    seen = [observation[:3].tolist()]
    for _ in range(5):
        observation, reward, terminated, truncated, info = env.step(MOVE)
        seen.append(observation[:3].tolist())
        assert reward == pytest.approx(-0.05)
        assert not terminated and not truncated
    assert seen == [[0, 0, 0], [0, 0, 0], [0, 0, 0.5], [0, 0.5, 0], [0.5, 0, 0], [0, 0, 0]]
    assert info["pointer"] == 0
    assert info["energy"] == pytest.approx(0.75)


def test_eat_food_then_empty_cell_then_food_returns() -> None:
    env = RobotFish1D()
    env.reset()
    for _ in range(4):
        env.step(MOVE)
    observation, reward, _, _, info = env.step(EAT)  # F 0.80 → 1.30, capped at 1
    assert info["ate"] and info["tile"] == 0.0
    assert observation.tolist() == [0.0, 0.0, 0.0, 1.0]
    assert reward == pytest.approx(0.2)
    observation, reward, _, _, info = env.step(EAT)  # nothing left to eat here
    assert not info["ate"] and reward == pytest.approx(-0.05)
    assert observation[:3].tolist() == [0.0, 0.0, 0.0]
    for _ in range(5):
        observation, *_ = env.step(MOVE)
    assert observation[:3].tolist() == [0.5, 0.0, 0.0]  # the tape keeps its food


def test_info_matches_observation_and_reward() -> None:
    env = RobotFish1D()
    observation, info = env.reset()
    energy = info["energy"]
    for action in [MOVE, EAT] * 20:
        observation, reward, _, _, info = env.step(action)
        assert observation[3] == np.float32(info["energy"])
        assert observation[0] == info["tile"]
        assert reward == pytest.approx(info["energy"] - energy)
        energy = info["energy"]


def test_starving_fish_dies_and_episode_terminates() -> None:
    env = RobotFish1D(tape=(0.0, 0.0, 0.0))
    env.reset()
    energies, terminated = [], False
    while not terminated:
        _, _, terminated, _, info = env.step(MOVE)
        energies.append(info["energy"])
    assert len(energies) == 20  # 1.0 − 20 × 0.05 is −3·10⁻¹⁶ in floats: dead on step 20
    assert energies[-1] <= 0 < energies[-2]
    with pytest.raises(RuntimeError, match="dead"):  # no step leaves the observation space
        env.step(EAT)
    observation, _ = env.reset()
    assert env.observation_space.contains(observation) and observation[3] == 1.0


def test_the_env_is_registered() -> None:
    env = gym.make("RobotFish1D-v0")
    observation, _ = env.reset(seed=0)
    assert observation.tolist() == [0, 0, 0, 1]
    env.close()


def test_reset_is_deterministic() -> None:
    env = RobotFish1D()
    runs = []
    for seed in (0, 0, 7):
        observation, _ = env.reset(seed=seed)
        trace = [observation.tolist()]
        for action in [MOVE] * 4 + [EAT, EAT, MOVE]:
            trace.append(env.step(action)[0].tolist())
        runs.append(trace)
    assert runs[0] == runs[1] == runs[2]


def test_bad_action_and_bad_tape_are_refused() -> None:
    env = RobotFish1D()
    env.reset()
    with pytest.raises(ValueError, match="action must be 0"):
        env.step(2)
    with pytest.raises(ValueError, match=r"each 0 or 0\.5"):
        RobotFish1D(tape=(0.0, 0.3, 0.0))
    with pytest.raises(ValueError, match="at least 3 cells"):
        RobotFish1D(tape=(0.5, 0.0))


# --- the experiment --------------------------------------------------------------------------


def test_untrained_fish_runs_the_11_step_cycle(untrained: np.ndarray) -> None:
    expected_start = [0.95, 0.9, 0.85, 0.8, 0.75, 0.7, 0.65, 0.6, 0.55, 0.5, 0.45, 0.4, 0.35, 0.3]
    assert untrained[:14] == pytest.approx(expected_start)
    cycle = untrained[13:24]
    assert sorted(cycle) == pytest.approx(np.linspace(0.3, 0.8, 11))
    assert untrained[13:] == pytest.approx(np.resize(cycle, len(untrained) - 13), abs=1e-9)
    assert cycle.mean() == pytest.approx(0.55)
    assert untrained.min() == pytest.approx(0.3)
    _, before = meal_energies(untrained)
    assert before == pytest.approx(0.3)  # passes food at 0.80 and 0.55, eats at 0.30


def test_starving_fish_is_reported_dead() -> None:
    trace = simulate(FishConfig(steps=100, srd=True), tape=(0.0, 0.0, 0.0))
    assert trace.died_at == 19
    assert len(trace.energy) == 20 and trace.meals == 0


def test_a_fish_that_dies_reports_its_lowest_energy_as_zero(tmp_path) -> None:
    result = run(FishConfig(steps=3000, lr=0.5), out_dir=tmp_path)  # trains itself to death
    assert result["died"] and result["died_at_step"] == 19
    assert result["min_energy"] == 0 and math.copysign(1.0, result["min_energy"]) == 1.0
    assert (tmp_path / "energy.csv").read_text().splitlines()[-1] == "19,0.0,0.0"  # not -0.0


def test_srd_first_improvement_stages(untrained: np.ndarray, trained: np.ndarray) -> None:
    first_difference = int(np.nonzero(trained != untrained)[0][0])
    assert 1600 <= first_difference <= 1800  # reference: ≈1690
    meals, before = meal_energies(trained)
    assert before[meals < first_difference] == pytest.approx(0.3)
    assert before[meals >= first_difference][0] == pytest.approx(0.55)
    eats_at_075 = int(meals[np.isclose(before, 0.75)][0])
    assert 3500 <= eats_at_075 <= 3700  # reference: ≈3610
    assert before[meals > eats_at_075] == pytest.approx(0.75)  # every food visit now
    windows = [trained[k : k + 1000].mean() for k in range(0, 4000, 1000)]
    assert windows == pytest.approx([0.552, 0.612, 0.750, 0.799], abs=2e-3)
    assert trained[-100:].mean() == pytest.approx(0.875, abs=5e-3)
    assert trained.min() == pytest.approx(0.3)


def test_srd_is_deterministic(trained: np.ndarray) -> None:
    again = simulate(FishConfig(steps=SHORT_STEPS, srd=True, seed=3))
    assert np.array_equal(again.energy, trained)


def test_window_means_pad_with_last_value() -> None:
    assert window_means(np.array([1.0, 2.0, 3.0, 4.0, 5.0]), 2).tolist() == [1.5, 3.5, 5.0]
    assert window_means(np.arange(6.0), 3).tolist() == [1.0, 4.0]


def test_run_writes_artifacts_and_result(tmp_path) -> None:
    progress: list[float] = []
    result = run(
        FishConfig(steps=300, srd=True),
        out_dir=tmp_path,
        progress=lambda fraction, _: progress.append(fraction),
    )
    energy = simulate(FishConfig(steps=300, srd=True)).energy
    assert result["steps"] == 300 and result["srd"] is True and result["died"] is False
    assert result["died_at_step"] is None
    # fewer than 1000 steps: both 1000-step means are the mean of the whole run
    assert result["mean_energy_first_1000"] == pytest.approx(energy.mean(), abs=1e-6)
    assert result["mean_energy_last_1000"] == result["mean_energy_first_1000"]
    assert result["mean_energy_per_1000"] == [result["mean_energy"]]
    assert result["min_energy"] == pytest.approx(0.3)
    assert result["meals"] == 26  # steps 14, 25, ..., 289
    assert result["elapsed_s"] >= 0
    assert progress == sorted(progress) and 0 < len(progress) <= 50
    rows = (tmp_path / "energy.csv").read_text().splitlines()
    assert rows[0] == "step,energy,tile" and len(rows) == 301
    assert rows[1] == "0,0.95,0.0" and rows[15] == "14,0.8,0.0"
    assert (tmp_path / "fish.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_config_ranges_are_enforced() -> None:
    assert parse_config(FishConfig, {"steps": 50, "srd": False}) == FishConfig(50, False)
    with pytest.raises(ConfigError, match="steps"):
        parse_config(FishConfig, {"steps": "50"})  # a number must be a number
    with pytest.raises(ConfigError) as caught:
        parse_config(FishConfig, {"steps": 0})
    assert caught.value.errors[0]["field"] == "steps"
    # a command line's negation takes a flag's value, and a wrong one is named as sent
    assert parse_config(FishConfig, {"steps": 50, "no-srd": True}) == FishConfig(50, False)
    with pytest.raises(ConfigError) as caught:
        parse_config(FishConfig, {"no-srd": "yes"})
    assert caught.value.errors == [{"field": "no-srd", "message": "must be true or false"}]
    with pytest.raises(ConfigError, match="average_every"):
        parse_config(FishConfig, {"average-every": 0})


@pytest.mark.slow
def test_full_12000_step_reproduction(tmp_path) -> None:
    plain = run(FishConfig(steps=12000, srd=False), out_dir=tmp_path / "untrained")
    srd = run(FishConfig(steps=12000, srd=True), out_dir=tmp_path / "srd")
    assert plain["mean_energy_first_1000"] == pytest.approx(0.5517, abs=1e-3)
    assert plain["mean_energy_last_1000"] == pytest.approx(0.5501, abs=1e-3)
    assert plain["mean_energy"] == pytest.approx(0.5501, abs=1e-3)
    assert plain["meals"] == 1090 and not plain["died"]
    assert srd["mean_energy_first_1000"] == pytest.approx(0.5517, abs=1e-3)
    assert srd["mean_energy_last_1000"] == pytest.approx(0.8748, abs=1e-3)
    assert srd["mean_energy"] == pytest.approx(0.8094, abs=1e-3)
    assert srd["min_energy"] == pytest.approx(0.30) and not srd["died"]
    expected = [0.552, 0.612, 0.750, 0.799] + [0.875] * 8
    assert srd["mean_energy_per_1000"] == pytest.approx(expected, abs=2e-3)
