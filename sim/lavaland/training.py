"""SRD training: one epoch over the training maps, one SGD step per map."""

from __future__ import annotations

import numpy as np
import torch

from agents.robot2nn import Robot2NN, imagine
from sim.experiment import ProgressFn, no_progress
from sim.lavaland.engine import MapSet


def train_srd(
    model: Robot2NN,
    maps: MapSet,
    order: np.ndarray,
    explore: torch.Tensor,
    lr: float,
    progress: ProgressFn = no_progress,
) -> None:
    """One SRD epoch: for each map in ``order``, one SGD step on its own plans' loss.

    ``explore[i]`` are the coins of the i-th step (map ``order[i]``).
    """
    parameters = list(model.parameters())
    report_every = max(1, len(order) // 16)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one map's tensors are tiny: more threads only add overhead
    try:
        for step, index in enumerate(order.tolist()):
            one = maps.seen.select(index)
            v_sigma = model.v_sigma(one)
            plans = imagine(v_sigma, one, explore[step : step + 1], model.rules)
            model.srd_loss(plans.differentiable_v_plan(v_sigma), v_sigma).backward()
            with torch.no_grad():  # plain SGD: no momentum, no weight decay
                for weight in parameters:
                    if weight.grad is not None:
                        weight.sub_(weight.grad, alpha=lr)
                        weight.grad = None
            if (step + 1) % report_every == 0:
                progress((step + 1) / len(order), f"SRD step {step + 1}/{len(order)}")
    finally:
        torch.set_num_threads(threads)
