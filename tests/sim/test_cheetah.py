"""The half-cheetah package against the paper's reference: world, env, engine, grid, stages."""

from __future__ import annotations

import contextlib
import json
import os
import resource
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from gymnasium.utils.env_checker import check_env

import sim.cheetah.render as render
import sim.cheetah.world as world
from agents.cheetah_net import STABLE_POSE_X, STABLE_POSE_Z, HalfCheetahSRD, noisy_fc_weight
from server.cli import cli
from server.cli.launch import srd_command
from sim.cheetah import ENV_ID, CheetahConfig, HalfCheetahRunStop, run
from sim.cheetah.engine import HalfCheetahBatch, drive
from sim.cheetah.experiment import trial_generator
from sim.cheetah.world import (
    START_X,
    build_model,
    chunk_ends,
    evaluation_steps,
    inhibitor_active,
    relative_pose,
    stop_windows,
)
from sim.experiment import ConfigError, parse_config

NOMINAL = {  # the reference loop, noise-free weights, no SRD: final displacement (m)
    (1.0, 0.0): 10.19,
    (2.0, 0.0): 9.98,
    (3.0, 0.0): 10.98,
    (4.0, 0.0): 12.29,
    (5.0, 0.0): 10.21,
    (1.0, 2.0): 3.97,
    (2.0, 2.0): 3.97,
    (3.0, 2.0): 4.39,
    (4.0, 2.0): 5.10,
    (5.0, 2.0): 4.79,
}


def by_condition(result: dict) -> dict[tuple, list[dict]]:
    groups: dict[tuple, list[dict]] = {}
    for r in result["runs"]:
        groups.setdefault((r["backswing"], r["inhibitor"], r["srd"], r["lr"]), []).append(r)
    return groups


def single_trial_loop(backswing, inhibitor, weight, srd, lr, steps):
    """The reference's loop, literally: mj_step, read xpos, log x, maybe evaluate."""
    model = build_model()
    data = mujoco.MjData(model)
    net = HalfCheetahSRD(torch.tensor([backswing]), fc_weight=weight)
    torso_x = np.empty(steps)
    control, counter = None, 0
    for t in range(steps):
        mujoco.mj_step(model, data)
        pose = data.xpos[1:].copy()
        torso_x[t] = pose[0, 0]
        if t > 100:
            counter += 1
            if control is None or counter == 25:
                counter = 0
                u = torch.from_numpy(relative_pose(pose)[None]).to(torch.float32)
                on = t > 500 and t % 1000 < 600
                actions, _ = net.act(
                    u,
                    torch.tensor([inhibitor if on else 0.0]),
                    srd=torch.tensor([srd]),
                    lr=torch.tensor([lr]),
                )
                control = actions[0].to(torch.float64).numpy()
            data.ctrl[:] = control
    return torso_x, net


def env_episode(env, net, inhibitor, *, seed=None):
    """Drive the env with a one-trial network (no SRD): the observed iterations, the infos."""
    obs, info = env.reset(seed=seed)
    infos, truncated = [info], False
    while not truncated:
        u = torch.from_numpy(obs[None, :12]).to(torch.float32)
        actions, _ = net.act(u, torch.tensor([inhibitor * obs[12]], dtype=torch.float32))
        obs, reward, terminated, truncated, info = env.step(actions[0].numpy())
        assert not terminated
        infos.append(info | {"reward": reward})
    return infos


# ---------------------------------------------------------------------------------------------
# The world
# ---------------------------------------------------------------------------------------------
def test_model_is_gymnasiums_half_cheetah_with_the_reference_edits():
    model = build_model()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert data.xpos[1].tolist() == [-2.0, 0.0, 0.7]
    assert model.geom("floor").pos.tolist() == [0.0, 0.0, -0.5]
    assert model.opt.timestep == 0.01
    assert model.actuator_gear[:, 0].tolist() == [120, 90, 60, 120, 60, 30]
    assert model.actuator_ctrlrange.tolist() == [[-1.0, 1.0]] * 6
    assert model.body_mass.sum() == pytest.approx(14.0)
    assert data.qpos.tolist() == [0.0] * 9
    np.testing.assert_array_equal(data.sensordata.reshape(7, 3), data.xpos[1:])
    assert build_model(-1.0).body("torso").pos.tolist() == [-1.0, 0.0, 0.7]


def test_missing_gymnasium_names_the_pip_command(monkeypatch):
    def missing(name):
        raise ModuleNotFoundError(name)

    monkeypatch.setattr(world.importlib.resources, "files", missing)
    with pytest.raises(ModuleNotFoundError, match="pip install gymnasium"):
        build_model()


def test_controller_and_inhibitor_schedules():
    evals = evaluation_steps(3600)
    assert len(evals) == 140 and evals[0] == 101 and evals[-1] == 3576
    seen = [t for t in evals if inhibitor_active(t)]
    assert len(seen) == 76
    assert seen[:5] == [501, 526, 551, 576, 1001] and seen[-1] == 3576
    assert stop_windows(3600) == [(501, 599), (1000, 1599), (2000, 2599), (3000, 3599)]
    assert chunk_ends(3600, evals) == [*evals, 3599]
    assert chunk_ends(127, evaluation_steps(127)) == [101, 126]  # a decision on the last step
    assert chunk_ends(50, [60, 10, 10]) == [10, 49]


# ---------------------------------------------------------------------------------------------
# The env
# ---------------------------------------------------------------------------------------------
def test_env_passes_gymnasiums_checker():
    env = gym.make(ENV_ID, steps=200)
    assert isinstance(env.unwrapped, HalfCheetahRunStop)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (13,) and env.observation_space.contains(obs)
    assert env.action_space.shape == (6,)


def test_env_same_seed_same_episode_and_the_noise_comes_from_np_random():
    actions = np.random.default_rng(3).uniform(-1, 1, (6, 6)).astype(np.float32)

    def episode(seed, scale):
        env = HalfCheetahRunStop(steps=250, reset_noise_scale=scale)
        observations = [env.reset(seed=seed)[0]]
        observations += [env.step(a)[0] for a in actions]
        return np.array(observations)

    np.testing.assert_array_equal(episode(1, 0.1), episode(1, 0.1))
    assert np.abs(episode(1, 0.1) - episode(2, 0.1)).max() > 1e-3
    np.testing.assert_array_equal(episode(1, 0.0), episode(2, 0.0))  # no noise: the exact start


def test_env_info_agrees_with_the_physics():
    """Replay the env's actions in a plain mj_step loop: same torso x at every observation,
    velocity = Δx / held time, the reward is its terms' sum and follows the stop command."""
    env = HalfCheetahRunStop(steps=1100)
    obs, info = env.reset(seed=0)
    rng = np.random.default_rng(0)
    model = build_model()
    data = mujoco.MjData(model)
    mujoco.mj_step(model, data, 102)
    assert info["t"] == 101 and info["x_position"] == data.xpos[1, 0]
    seen, truncated = [info["t"]], False
    while not truncated:
        action = rng.uniform(-1, 1, 6).astype(np.float32)
        stopped, x_before, t_before = bool(obs[12]), info["x_position"], info["t"]
        assert stopped == info["stop_command"] == inhibitor_active(t_before)
        obs, reward, terminated, truncated, info = env.step(action)
        data.ctrl[:] = action
        mujoco.mj_step(model, data, info["t"] - t_before)
        assert info["x_position"] == data.xpos[1, 0]
        np.testing.assert_array_equal(obs[:12], relative_pose(data.xpos[1:]))
        held = (info["t"] - t_before) * 0.01
        assert info["x_velocity"] == pytest.approx((info["x_position"] - x_before) / held)
        assert reward == info["reward_run"] + info["reward_stop"]
        expected = -abs(info["x_velocity"]) if stopped else info["x_velocity"]
        assert reward == expected and not terminated
        seen.append(info["t"])
    assert seen == [*evaluation_steps(1100), 1099]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(6, dtype=np.float32))


def test_env_refuses_bad_arguments():
    with pytest.raises(ValueError, match="steps must be at least 103"):
        HalfCheetahRunStop(steps=102)
    with pytest.raises(ValueError, match="reset_noise_scale"):
        HalfCheetahRunStop(reset_noise_scale=-0.1)


def test_env_is_the_reference_loop():
    """Observed torso x of the env = the literal reference loop's, bit for bit."""
    steps = 1300
    weight = noisy_fc_weight([trial_generator(4, 0)])
    expected, _ = single_trial_loop(4.0, 2.0, weight, False, 1e-4, steps)
    net = HalfCheetahSRD(torch.tensor([4.0]), fc_weight=weight)
    infos = env_episode(HalfCheetahRunStop(steps=steps), net, 2.0)
    observed = [i["t"] for i in infos]
    np.testing.assert_array_equal([i["x_position"] for i in infos], expected[observed])


@pytest.mark.parametrize(("backswing", "inhibitor"), [(3.0, 2.0), (4.0, 0.0)])
def test_env_with_the_nominal_controller_travels_as_far_as_the_batched_grid(
    tmp_path, backswing, inhibitor
):
    net = HalfCheetahSRD(torch.tensor([backswing]))
    infos = env_episode(HalfCheetahRunStop(), net, inhibitor)
    env_displacement = infos[-1]["x_position"] - START_X
    config = CheetahConfig(
        backswing=(backswing,), inhibitor=(inhibitor,), srd="off", nominal=True, video=False
    )
    (grid,) = run(config, out_dir=tmp_path)["runs"]
    assert env_displacement == pytest.approx(grid["final_displacement"], abs=1e-9)
    assert env_displacement == pytest.approx(NOMINAL[(backswing, inhibitor)], abs=0.01)


# ---------------------------------------------------------------------------------------------
# The batched engine
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("backswing", "inhibitor", "noisy", "srd", "lr"),
    [(4.0, 2.0, False, False, 1e-4), (2.0, 2.0, True, True, 1e-4), (5.0, 0.0, True, True, 1e-2)],
)
def test_batched_chunks_equal_the_single_trial_loop(backswing, inhibitor, noisy, srd, lr):
    steps = 3600 if not noisy else 1700
    weight = noisy_fc_weight([trial_generator(9, 0)]) if noisy else None
    expected, reference_net = single_trial_loop(backswing, inhibitor, weight, srd, lr, steps)
    # trial 0 is the one under test; trial 1 is a different condition sharing the batch
    both = None if weight is None else torch.cat([weight, noisy_fc_weight([trial_generator(9, 1)])])
    net = HalfCheetahSRD(torch.tensor([backswing, 1.0]), fc_weight=both)
    inhibitors = torch.tensor([inhibitor, 2.0])

    def controller(t, positions):
        u = torch.from_numpy(relative_pose(positions)).to(torch.float32)
        actions, _ = net.act(
            u,
            inhibitors * inhibitor_active(t),
            srd=torch.tensor([srd, True]),
            lr=torch.tensor([lr, 1e-2]),
        )
        return actions.to(torch.float64).numpy()

    with HalfCheetahBatch(2, threads=2) as batch:
        traj = drive(batch, steps, evaluation_steps(steps), controller)
    np.testing.assert_allclose(traj.torso_x[0], expected, rtol=0, atol=1e-9)
    for p, q in zip(net.parameters(), reference_net.parameters(), strict=True):
        torch.testing.assert_close(p[0], q[0], rtol=0, atol=1e-9)


def test_first_control_follows_101_zero_steps():
    seen = {}

    def controller(t, positions):
        seen[t] = positions.copy()
        return np.ones((1, 6))

    with HalfCheetahBatch(1, threads=1) as batch:
        traj = drive(batch, 130, [101, 126], controller, record_poses=True)
    model = build_model()
    data = mujoco.MjData(model)
    for _ in range(102):  # iterations 0..101 run with zero control
        mujoco.mj_step(model, data)
    np.testing.assert_array_equal(seen[101][0], data.xpos[1:])
    assert traj.poses is not None
    np.testing.assert_array_equal(traj.poses[0, 101], data.xpos[1:])
    data.ctrl[:] = 1.0
    for _ in range(25):
        mujoco.mj_step(model, data)
    np.testing.assert_allclose(seen[126][0], data.xpos[1:], atol=1e-12)


# ---------------------------------------------------------------------------------------------
# The grid
# ---------------------------------------------------------------------------------------------
def test_nominal_runs_land_on_the_reference_displacements(tmp_path):
    config = CheetahConfig(
        backswing=(3.0, 4.0), inhibitor=(0.0, 2.0), srd="off", nominal=True, video=False
    )
    result = run(config, out_dir=tmp_path)
    assert result["trials"] == 1 and len(result["runs"]) == 4
    for r in result["runs"]:
        expected = NOMINAL[(r["backswing"], r["inhibitor"])]
        assert r["final_displacement"] == pytest.approx(expected, abs=0.05)
    assert {p.name for p in tmp_path.iterdir()} >= {
        "runs.csv",
        "summary.csv",
        "displacement.csv",
        "displacement.png",
        "weights.json",
    }
    lines = (tmp_path / "displacement.csv").read_text().splitlines()
    assert lines[0].split(",")[:3] == ["step", "mean_b3_i0_nosrd", "sd_b3_i0_nosrd"]
    assert len(lines) == 1 + 361 and lines[-2].startswith("3590,")
    last = dict(zip(lines[0].split(","), lines[-1].split(","), strict=True))
    assert last["sd_b3_i0_nosrd"] == "0"  # one trial: no spread, written as 0 (not "-0")
    assert last["step"] == "3599"  # the last step too: its mean is the final displacement
    final = next(r for r in result["runs"] if (r["backswing"], r["inhibitor"]) == (3.0, 0.0))
    assert float(last["mean_b3_i0_nosrd"]) == pytest.approx(final["final_displacement"], abs=1e-4)
    for row in result["summary"]:  # one trial each: a sample SD of one value is none
        assert row["n"] == 1 and row["mean_final_displacement"] is not None
        assert [value for key, value in row.items() if key.startswith("sd_")] == [None] * 3


def test_runs_come_in_grid_order_with_their_fields(tmp_path):
    config = CheetahConfig(
        backswing=(3.0, 4.0), inhibitor=(2.0,), srd="on", trials=2, steps=300, video=False, seed=3
    )
    result = run(config, out_dir=tmp_path)
    assert [(r["backswing"], r["trial"]) for r in result["runs"]] == [
        (3.0, 1),
        (3.0, 2),
        (4.0, 1),
        (4.0, 2),
    ]
    assert {"backswing", "inhibitor", "srd", "trial", "final_displacement"} <= set(
        result["runs"][0]
    )
    keys = list(result)
    assert keys[0] == "config" and keys[-2:] == ["artifacts", "elapsed_s"]
    assert result["elapsed_s"] > 0 and result["n_runs"] == 4
    assert result["video"] is None and result["video_note"] == "video off (--no-video)"
    # one inhibitor value, one column: the figure is still as wide as its title (was 4.2 in.)
    height, width = plt_imread(tmp_path / "displacement.png").shape[:2]
    assert width >= 7.5 * 80 and height < width
    with pytest.raises(ConfigError, match="srd"):
        parse_config(CheetahConfig, {"srd": "sometimes"})


def test_same_seed_same_numbers_and_threads_do_not_matter(tmp_path):
    config = CheetahConfig(
        backswing=(3.0,), inhibitor=(2.0,), srd="both", trials=2, steps=700, video=False
    )
    first = run(config, out_dir=tmp_path / "a")
    again = run(config, out_dir=tmp_path / "b")
    one_thread = run(CheetahConfig(**{**config.__dict__, "threads": 1}), out_dir=tmp_path / "c")
    other = run(CheetahConfig(**{**config.__dict__, "seed": 1}), out_dir=tmp_path / "d")
    assert first["runs"] == again["runs"] == one_thread["runs"]
    assert first["runs"] != other["runs"]
    # trials differ (noise), and SRD on/off of a trial start from the same weights
    on = [r["final_displacement"] for r in first["runs"] if r["srd"] == "on"]
    off = [r["final_displacement"] for r in first["runs"] if r["srd"] == "off"]
    assert on[0] != on[1]
    assert on == pytest.approx(off, abs=0.05)


def test_srd_at_the_reference_rate_moves_weights_by_tiny_amounts(tmp_path):
    config = CheetahConfig(
        backswing=(3.0,), inhibitor=(0.0, 2.0), srd="both", trials=1, video=False
    )
    groups = by_condition(run(config, out_dir=tmp_path))
    on_free, on_stop = groups[(3.0, 0.0, "on", 1e-4)][0], groups[(3.0, 2.0, "on", 1e-4)][0]
    off_free = groups[(3.0, 0.0, "off", None)][0]
    # the reference: controller ≤ 6.4e-5, PFC ≤ 6.3e-3 after a trial (seed 1, b3/i0)
    assert 1e-6 < on_free["controller_change"] < 2e-4
    assert 1e-3 < on_free["pfc_change"] < 2e-2
    assert off_free["controller_change"] == 0.0 and off_free["pfc_change"] == 0.0
    assert abs(on_free["final_displacement"] - off_free["final_displacement"]) < 0.1
    # the PFC says T at every evaluation without the inhibitor, F at the 76 with it
    assert on_free["true_verdict_fraction"] == 1.0
    assert on_stop["true_verdict_fraction"] == pytest.approx(64 / 140)
    assert off_free["true_verdict_fraction"] is None


def test_learning_rate_sweep_is_a_grid_axis_with_its_figure(tmp_path):
    config = CheetahConfig(
        backswing=(3.0,),
        inhibitor=(0.0, 2.0),
        srd="both",
        trials=2,
        steps=1200,
        lr=(1e-4, 1e-1),
        video=False,
    )
    result = run(config, out_dir=tmp_path)
    groups = by_condition(result)
    assert len(result["runs"]) == 2 * 3 * 2  # inhibitors × (two rates + off) × trials
    slow = max(r["controller_change"] for r in groups[(3.0, 0.0, "on", 1e-4)])
    fast = min(r["controller_change"] for r in groups[(3.0, 0.0, "on", 1e-1)])
    assert fast > 100 * slow
    assert (tmp_path / "lr_sweep.png").is_file()
    assert {(s["srd"], s["lr"]) for s in result["summary"]} == {
        ("on", 1e-4),
        ("on", 1e-1),
        ("off", None),
    }


def test_a_sweep_too_short_to_measure_still_draws_its_figure(tmp_path):
    """50 steps reach no stop window and no running measure: the sweep's panels say so (their
    log axis had failed the whole run after its simulation)."""
    config = CheetahConfig(
        backswing=(1.0,), inhibitor=(0.0,), trials=1, steps=50, lr=(0.1, 0.01), video=False
    )
    result = run(config, out_dir=tmp_path)
    assert result["n_runs"] == 3 and (tmp_path / "lr_sweep.png").is_file()


@pytest.mark.parametrize(
    ("params", "field", "words"),
    [
        ({"backswing": "1,1"}, "backswing", "1 is given twice"),
        ({"inhibitor": [2, 2]}, "inhibitor", "2 is given twice"),
        ({"lr": "0.1,0.1"}, "lr", "0.1 is given twice"),
        ({"backswing": list(range(1, 17)), "inhibitor": list(range(17))}, "backswing", "544 cells"),
        (
            {"trials": 205},
            "trials",
            "runs 4100 trials (20 cells × 205), at most 4096: lower trials to at most 204",
        ),
        # options that would change nothing are refused, not echoed as if they had
        ({"nominal": True, "trials": 3}, "trials", "one noise-free trial per condition"),
        ({"srd": "off", "lr": "0.001,0.01"}, "lr", "nothing is trained"),
        ({"stage": 2, "trials": 5}, "trials", "design stage 2 runs its own conditions"),
        ({"stage": 1, "nominal": True}, "nominal", "design stage 1 runs its own conditions"),
        # given, whatever its value: the default's value too (7 trials, both SRD variants)
        ({"nominal": True, "trials": 7}, "trials", "one noise-free trial per condition"),
        ({"stage": 1, "srd": "both"}, "srd", "design stage 1 runs its own conditions"),
        ({"stage": 0, "video": False}, "video", "design stage 0 draws its own figures"),
        # stage 2 averages its neurons over 50 steps before and after the swing at step 250:
        # none before it had printed NaN (not JSON) on the command line and null in a job's
        ({"stage": 2, "steps": 299}, "steps", "from step 250 and averages 50 steps after"),
    ],
)
def test_a_grid_with_a_value_twice_or_too_many_cells_is_refused(params, field, words):
    """A repeated value would count its trials twice in one cell's statistics; a grid of more
    than 512 cells would spend minutes and gigabytes on its figures alone, one of more than
    4096 trials would list megabytes of runs in its result."""
    with pytest.raises(ConfigError) as refused:
        parse_config(CheetahConfig, params)
    (error,) = refused.value.errors
    assert error["field"].split(".")[0] == field and words in error["message"]


def test_nominal_takes_the_one_trial_it_runs() -> None:
    """``--nominal --trials 1`` says what nominal runs (one noise-free trial per condition), as
    the contract's independent options allow: taken, one run per cell."""
    config = parse_config(CheetahConfig, {"nominal": True, "trials": 1, "srd": "off"})
    assert config.nominal and config.trials == 1


@pytest.mark.parametrize(
    ("value", "count"),
    [("," * 260_000, 260_001), ([""] * 60_000, 60_000), (list(range(33)), 33), ("1," * 40, 41)],
)
def test_an_over_long_list_is_refused_on_its_count_before_its_values_are_read(value, count):
    """One error naming the field and its bound, whatever its values (260,000 empty items
    cost seconds and 260,000 item errors when each was read first)."""
    started = time.perf_counter()
    with pytest.raises(ConfigError) as refused:
        parse_config(CheetahConfig, {"backswing": value})
    assert time.perf_counter() - started < 0.1
    assert refused.value.errors == [
        {"field": "backswing", "message": f"{count} values: at most 32"}
    ]


def test_the_command_line_refuses_an_over_long_list_naming_its_option(tmp_path):
    out = tmp_path / "never"
    args = ["cheetah", "--inhibitor", "," * 99, "--out", str(out)]
    refused = CliRunner().invoke(cli, [*args, "--json"])
    assert refused.exit_code == 2
    assert json.loads(refused.stdout)["errors"] == [
        {"option": "--inhibitor", "message": "100 values: at most 32"}
    ]
    assert not out.exists()


def test_a_design_stage_s_budget_counts_its_own_runs_and_names_steps():
    """A stage runs its own trials (one, or ten for stage 0): its estimate had been the main
    grid's 140 trials, naming trials, which a stage does not take."""
    one = parse_config(CheetahConfig, {"stage": 1, "steps": 1_000_000}).cost()
    assert one.option == "steps" and 25 < one.seconds < 40  # 1e6 steps of one trial
    devtest = parse_config(CheetahConfig, {"stage": 0, "steps": 100_000}).cost()
    assert devtest.option == "steps" and devtest.seconds > 9 * one.seconds / 10


@pytest.mark.slow  # a fresh srd process (torch and MuJoCo imported): the default run is full
def test_a_missing_opengl_back_end_named_in_mujoco_gl_does_not_stop_a_run(tmp_path):
    """MuJoCo binds the back end MUJOCO_GL names when it is imported and fails to import without
    it; the simulation draws nothing, so only the GIF's child process uses it."""
    env = {**os.environ, "MUJOCO_GL": "no-such-back-end"}
    args = ["cheetah", "--nominal", "--backswing", "4", "--inhibitor", "0", "--srd", "off"]
    done = subprocess.run(
        [*srd_command(), *args, "--steps", "200", "--no-video", "--json"],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    (run_row,) = json.loads(done.stdout)["runs"]
    assert run_row["final_displacement"] == pytest.approx(0.0, abs=2.0)


def test_the_budget_counts_each_trial_s_set_up_and_each_cell_s_figure():
    """A grid of single-step trials is not free: 16 × 16 cells and 3 trials ran 61 s."""
    config = parse_config(
        CheetahConfig,
        {"backswing": list(range(1, 17)), "inhibitor": list(range(16)), "srd": "off"},
    )
    wide = CheetahConfig(**{**config.__dict__, "trials": 3, "steps": 1})
    assert wide.cost().seconds > 30


# ---------------------------------------------------------------------------------------------
# The design stages and the video
# ---------------------------------------------------------------------------------------------
def test_stage1_rest_pose_matches_the_recorded_init_params(tmp_path):
    result = run(CheetahConfig(stage=1, video=False), out_dir=tmp_path)
    pose = json.loads((tmp_path / "stable_pose.json").read_text())
    np.testing.assert_allclose(pose["x_rel"], STABLE_POSE_X, atol=1e-8)
    np.testing.assert_allclose(pose["z_rel"], STABLE_POSE_Z, atol=1e-8)
    assert result["max_abs_difference_to_designed_pose"] < 1e-8
    assert (tmp_path / "stage1_pose.png").is_file()


def test_stage2_stable_pose_neurons_drop_when_the_front_thigh_swings(tmp_path):
    result = run(CheetahConfig(stage=2, steps=500, video=False), out_dir=tmp_path)
    act = result["activations"]
    assert act["xS_before_swing"] > 0.99 and act["zS_before_swing"] > 0.99
    assert act["xS_after_swing"] < 0.5 and act["zS_after_swing"] < 0.5
    assert (tmp_path / "stage2_stable_pose.png").is_file()


def reference_steps(seconds: float) -> int:
    """The steps of the reference's loop: ``mj_step`` while MuJoCo's time is below ``seconds``."""
    model = build_model()
    data = mujoco.MjData(model)
    steps = 0
    while data.time < seconds:
        mujoco.mj_step(model, data)
        steps += 1
    return steps


def test_the_reference_loop_takes_401_and_1201_steps_for_4_and_12_s():
    assert (reference_steps(4.0), reference_steps(12.0), reference_steps(36.0)) == (401, 1201, 3600)


@pytest.mark.parametrize("stage", [0, 3, 4])
def test_design_stages_move_the_cheetah_forward(tmp_path, stage):
    # as the command line and a job build it: no backswing given (stage 4: 5 alone)
    config = CheetahConfig(stage=stage, video=False).settled(frozenset({"stage", "video"}))
    result = run(config, out_dir=tmp_path)
    assert result["stage"] == stage
    assert result["steps"] == reference_steps(4.0 if stage == 0 else 12.0)
    grid_keys = {"backswing", "inhibitor", "srd", "trial", "final_displacement"}
    assert all(grid_keys <= set(row) for row in result["runs"])  # as the grid's rows
    if stage == 0:
        assert len(result["runs"]) == 10
        assert result["runs"][-1]["pattern"] == "cyclic"
    else:
        (only,) = result["runs"]
        assert only["backswing"] == (0.0 if stage == 3 else 5.0)
        assert only["final_displacement"] > 1.0  # the designed network runs without training
    assert all((tmp_path / name).is_file() for name in result["artifacts"])


@pytest.mark.parametrize(
    ("options", "backswing"),
    [
        (["--stage", "0"], None),
        (["--stage", "3"], [0.0]),
        (["--stage", "4"], [5.0]),
        (["--stage", "4", "--backswing", "2,3"], [2.0, 3.0]),
        # the grid's default list, given: the five (it ran 5 alone, as if none was given)
        (["--stage", "4", "--backswing", "1,2,3,4,5"], [1.0, 2.0, 3.0, 4.0, 5.0]),
    ],
)
def test_a_design_stage_s_config_shows_what_it_ran(tmp_path, options, backswing):
    """Its backswing gains (none before stage 3), and null for the options only the grid
    takes; the options it does take as given."""
    args = ["cheetah", *options, "--steps", "2", "--threads", "1", "--json"]
    done = CliRunner().invoke(cli, [*args, "--out", str(tmp_path)])
    assert done.exit_code == 0, done.output
    result = json.loads(done.stdout)
    grid_only = ("inhibitor", "srd", "lr", "trials", "nominal", "video", "seed")
    assert result["config"] == {
        "backswing": backswing,
        **dict.fromkeys(grid_only),
        "steps": 2,
        "stage": int(options[1]),
        "threads": 1,
    }
    if backswing is not None:
        assert [row["backswing"] for row in result["runs"]] == backswing


def test_the_grid_reports_its_artifacts_figures_and_gif_as_phases(tmp_path, monkeypatch):
    """After the steps, the progress names what the run is doing (the figures and the GIF take
    seconds): the job's progress shows it."""
    monkeypatch.setattr(render, "GL_BACKENDS", ("no-such-backend",))  # no GIF to draw
    reports: list[tuple[float, str]] = []
    config = CheetahConfig(backswing=(3.0,), inhibitor=(2.0,), srd="off", trials=1, steps=200)
    run(config, out_dir=tmp_path, progress=lambda f, m: reports.append((f, m)))
    messages = [m for _, m in reports]
    phases = ["writing artifacts", "drawing the figures", "rendering the GIF"]
    assert [m for m in messages if m in phases] == phases
    assert [f for f, _ in reports] == sorted(f for f, _ in reports)


def test_video_without_opengl_is_skipped_with_a_reason(tmp_path, monkeypatch):
    monkeypatch.setattr(render, "GL_BACKENDS", ("no-such-backend",))
    out = render.render_gif(tmp_path / "x.gif", np.zeros((30, 9)), -2.0, "test")
    assert out["video"] is None
    assert out["video_note"].startswith("no offscreen OpenGL context: no-such-backend")
    assert not (tmp_path / "x.gif").exists() and not (tmp_path / "x.npz").exists()


@pytest.mark.slow
def test_noisy_grid_reproduces_the_reference_figures(tmp_path):
    """140 trials: means within one trial SD of the reference's noise-free figures, backswing 4
    fastest, the stop command far slower."""
    result = run(CheetahConfig(video=False), out_dir=tmp_path)
    assert len(result["runs"]) == 140
    for row in result["summary"]:
        reference = NOMINAL[(row["backswing"], row["inhibitor"])]
        assert abs(row["mean_final_displacement"] - reference) <= row["sd_final_displacement"]
    for srd in ("on", "off"):
        for inhibitor in (0.0, 2.0):
            means = {
                r["backswing"]: r["mean_final_displacement"]
                for r in result["summary"]
                if r["srd"] == srd and r["inhibitor"] == inhibitor
            }
            assert max(means, key=means.__getitem__) == 4.0
        for b in (1.0, 2.0, 3.0, 4.0, 5.0):
            free, stop = (
                next(
                    r["mean_final_displacement"]
                    for r in result["summary"]
                    if (r["srd"], r["backswing"], r["inhibitor"]) == (srd, b, i)
                )
                for i in (0.0, 2.0)
            )
            assert stop < 0.5 * free


def _renders(parent: int) -> list[int]:
    """The render processes ``parent`` started (Linux's /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            command = (stat.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if int(fields[1]) == parent and b"sim.cheetah.render" in command:
            found.append(int(stat.parent.name))
    return found


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_render_ends_with_the_process_that_started_it(tmp_path):
    """A cancelled cheetah job's worker is terminated while its GIF is drawn: the drawing child
    must end with it, not go on writing the job's files."""
    script = (
        "import sys, numpy as np; from pathlib import Path; "
        "from sim.cheetah.render import render_gif; "
        "render_gif(Path(sys.argv[1]), np.zeros((1401, 9)), -2.0, 'cancelled')"
    )
    gif = tmp_path / "cancelled.gif"
    root = str(Path(__file__).resolve().parents[2])
    parent = subprocess.Popen([sys.executable, "-c", script, str(gif)], cwd=root)
    children: list[int] = []
    try:
        deadline = time.monotonic() + 30
        while not (children := _renders(parent.pid)):
            assert parent.poll() is None and time.monotonic() < deadline, "no render started"
            time.sleep(0.02)
        parent.send_signal(signal.SIGTERM)  # the child is starting, or importing MuJoCo
        parent.wait(10)
        # bound to its parent before its imports (a second or more): it ends at once
        deadline = time.monotonic() + 1.0
        while any(Path(f"/proc/{child}").exists() for child in children):
            status = Path(f"/proc/{children[0]}/status")
            if status.exists() and "zombie" in status.read_text():
                break
            assert time.monotonic() < deadline, "the render outlived the process that started it"
            time.sleep(0.05)
        time.sleep(1)
        assert not gif.exists()
    finally:
        parent.kill()
        for child in children:
            with contextlib.suppress(ProcessLookupError):
                os.kill(child, signal.SIGKILL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="sets RLIMIT_FSIZE")
def test_a_gif_that_cannot_be_written_fails_the_run_in_one_line_leaving_none_of_it(tmp_path):
    """The disk fills while the GIF is written (here a bound on a file's size, which the run
    and its render child inherit: the other files fit, the GIF does not). That is no missing
    OpenGL back end: the run says so in one line, exits 1 and leaves none of its files, no
    truncated GIF."""
    out = tmp_path / "run"
    args = ["--backswing", "4", "--inhibitor", "2", "--srd", "off", "--trials", "1"]

    def bounded() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (40_000, 40_000))  # the GIF takes 72 KB

    done = subprocess.run(
        [*srd_command(), "cheetah", *args, "--steps", "100", "--json", "--out", str(out)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        preexec_fn=bounded,
    )
    if done.returncode == 0 and "File too large" not in json.loads(done.stdout)["video_note"]:
        pytest.skip(json.loads(done.stdout)["video_note"])  # no back end: no GIF to write
    error = f"cannot write the run's files ({out / 'cheetah.gif'}): File too large"
    assert done.returncode == 1, done.stdout[-2000:]
    assert json.loads(done.stdout) == {"error": error}
    assert done.stderr.strip() == f"error: {error}"
    assert not out.exists()


@pytest.mark.slow
def test_video_is_rendered_when_an_offscreen_context_exists(tmp_path):
    from PIL import Image

    qpos = np.zeros((200, 9))
    out = render.render_gif(tmp_path / "x.gif", qpos, -2.0, "test")
    if out["video"] is None:
        pytest.skip(out["video_note"])
    assert out["video"] == "x.gif" and not (tmp_path / "x.npz").exists()
    with Image.open(tmp_path / "x.gif") as gif:
        assert gif.size == (render.FRAME_WIDTH, render.FRAME_HEIGHT)
        assert gif.n_frames == 20  # 1.99 s of steps at 10 frames per second


def test_the_rollout_uses_no_more_threads_than_cpus_and_gives_the_same_numbers() -> None:
    """``threads`` (a job's option, up to 64) is held to the CPUs the process may run on: more
    would only queue. The trials' numbers do not depend on it."""
    from sim.cheetah.engine import HalfCheetahBatch

    def tasks() -> int:
        return len(os.listdir("/proc/self/task"))

    cpus = len(os.sched_getaffinity(0))
    control = np.full((6, 6), 0.3)
    before = tasks()
    with HalfCheetahBatch(6, threads=64) as many:
        ends_many = many.advance(control, 50).copy()
        assert tasks() - before <= cpus
    with HalfCheetahBatch(6, threads=1) as one:
        ends_one = one.advance(control, 50).copy()
    assert np.array_equal(ends_many, ends_one)


def plt_imread(path: Path) -> Any:
    """A PNG as an array (rows, columns, channels), read by matplotlib."""
    import matplotlib.image

    return matplotlib.image.imread(path)
