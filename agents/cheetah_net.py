"""HalfCheetahSRD: the designed network that makes MuJoCo's half-cheetah run and stop on command.

Every parameter tensor carries a leading trial axis, so one module instance drives a whole
experiment grid (each trial with its own weights, backswing and inhibitor) in one batched call.

Neuron by neuron (the paper's "MuJoCo with SRD" section and its appendix, as the reference code
implements them):

* input u (12): x then z of the bodies bthigh, bshin, bfoot, fthigh, fshin, ffoot relative to
  the torso body origin (world-frame differences).
* xS, zS (StablePoseNeuron): ε / (ε + ‖u − p‖⁴), ε = 1e-4, one on the six x values and one on
  the six z values; p is the pose the cheetah rests in (design stage 1). ≈1 while standing.
* xS_inv = 1 − xS, zS_inv = 1 − zS: "away from the resting pose".
* BS (backswing neuron): backswing × z of bthigh relative to the torso, a pitch signal
  (positive when the nose is down) that drives the back thigh.
* inhibitor path: h' = LeakyReLU(h − inhibitor), slope 0.01; inhibitor 2 pushes every feature
  below zero so the actuators fall silent and the cheetah stops.
* FC to the six actuators bt, bs, bf, ft, fs, ff: a = tanh(2 (W h' + b)).
* PFC (prefrontal cortex): iN = inhibitor, Ac = mean a²; g = tanh(4 · PFC1 [iN, Ac]);
  [T, F] = PFC2 g + bias. The self-reward loss CEL(z, argmax z) is minimised by plain SGD over
  all parameters, PFC included (SRD).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from agents.neurons import selective, self_reward_loss

BODIES = ("torso", "bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot")
"""The cheetah's bodies in MuJoCo order (``data.xpos`` rows 1..7)."""
LIMBS = BODIES[1:]
"""The six bodies whose position relative to the torso is the input."""
ACTUATORS = ("bt", "bs", "bf", "ft", "fs", "ff")
"""Back thigh, back shin, back foot, front thigh, front shin, front foot (model order)."""
FEATURES = ("xS", "zS", "xS_inv", "zS_inv", "BS")
"""First-layer neurons feeding the FC layer."""
VERDICTS = ("T", "F")
"""PFC outputs: the action was right (T) or wrong (F)."""
BACK_HIP_Z = 6
"""Index in u of the z of bthigh relative to the torso, read by the BS neuron."""

# ---------------------------------------------------------------------------------------------
# The designed numbers, all in one place.
# ---------------------------------------------------------------------------------------------
STABLE_POSE_X = (-0.49932091, -0.36147206, -0.65965156, 0.49932091, 0.36095878, 0.51588857)
"""p of xS: x of bthigh..ffoot relative to the torso once the cheetah rests (design stage 1)."""
STABLE_POSE_Z = (0.02605056, -0.23681384, -0.33215001, -0.02605056, -0.26699853, -0.42604808)
"""p of zS: z of bthigh..ffoot relative to the torso at rest (the nose points slightly down)."""
STABLE_POSE_EPSILON = 1e-4
"""ε of the stable-pose neurons: activation 0.5 at ‖u − p‖ = ε^¼ = 0.1 m."""

FC_WEIGHT = (
    # xS    zS   xS_inv zS_inv  BS
    (0.0, 0.0, -0.2, -0.2, 1.0),  # bt: swing the back thigh once away from rest (−0.2 each,
    #                                reduced from −1: big back swings settle into a stable
    #                                stance) and by the pitch signal BS (+1)
    (0.0, 0.0, 0.0, 0.0, 0.0),  # bs: not driven by design, only by the initial noise
    (0.0, 0.0, 0.0, 0.0, 0.0),  # bf: idem
    (-1.0, -1.0, 0.0, 0.0, 0.0),  # ft: at rest (xS = zS = 1) swing the front thigh forward,
    #                                tanh(2·(−2)) ≈ −1
    (0.0, 0.0, 0.0, 0.0, 0.0),  # fs: noise only
    (0.0, 0.0, 0.0, 0.0, 0.0),  # ff: noise only
)
"""W of the FC layer, rows = actuators, columns = FEATURES (stage-4 design, main experiment)."""
DESIGN_STAGE_OFFSET = 1e-4
"""Added to every FC weight in the design stages 3 and 4 (not in the main experiment)."""
WEIGHT_NOISE = 0.01
"""Standard deviation of the Gaussian noise on the 30 FC weights that makes trials differ."""
ACTUATOR_GAIN = 2.0
"""a = tanh(ACTUATOR_GAIN · y): steepens the actuator response."""
INHIBITOR_SLOPE = 0.01
"""LeakyReLU slope below zero on the inhibited features (PyTorch's default)."""

PFC_GAIN = 4.0
"""g = tanh(PFC_GAIN · PFC1 [iN, Ac])."""
PFC1_WEIGHT = (
    # iN    Ac
    (-1.0, 1.0),  # g0: actuation without an inhibitor
    (1.0, 1.0),  # g1: actuation or inhibitor
)
"""PFC layer 1 (no bias), rows = g0, g1, columns = [iN, Ac]."""
PFC2_WEIGHT = (
    # g0    g1
    (1.0, 0.01),  # T: moving while free to move is right
    (-0.01, 1.0),  # F: the inhibitor is on (moving then is wrong)
)
"""PFC layer 2, rows = T, F, columns = g0, g1."""
PFC2_BIAS = (0.0, -0.2)
"""PFC layer-2 bias of T and F: without the inhibitor g0 = g1 = g, so T − F = 0.02 g + 0.2 > 0."""


def nominal_fc_weight(*, design_offset: bool = False) -> Tensor:
    """The designed FC weights (6×5, float32); ``design_offset`` adds stage 3/4's +1e-4."""
    weight = torch.tensor(FC_WEIGHT, dtype=torch.float32)
    return weight + DESIGN_STAGE_OFFSET if design_offset else weight


def noisy_fc_weight(generators: list[torch.Generator]) -> Tensor:
    """One noisy copy of the designed FC weights per generator: W + 0.01·N(0, 1), (n, 6, 5)."""
    base = nominal_fc_weight()
    noise = torch.stack([torch.randn(base.shape, generator=g) for g in generators])
    return base + WEIGHT_NOISE * noise


def _per_trial(values: tuple[float, ...] | tuple[tuple[float, ...], ...], n: int) -> Tensor:
    """A designed constant repeated along a leading trial axis (float32)."""
    one = torch.tensor(values, dtype=torch.float32)
    return one.expand(n, *one.shape).clone()


class StablePoseNeuron(nn.Module):
    """xS / zS: ε / (ε + (Σᵢ (uᵢ − pᵢ)²)²), the selective activation of the squared distance.

    ``pose`` p has shape (n_trials, 6) and is trainable.
    """

    def __init__(self, pose: Tensor, epsilon: float = STABLE_POSE_EPSILON) -> None:
        super().__init__()
        self.pose = nn.Parameter(pose.clone())
        self.epsilon = epsilon

    def forward(self, u: Tensor) -> Tensor:
        """u (n, 6) → activation (n,) in (0, 1], 1 at u = p."""
        distance = ((u - self.pose) ** 2).sum(dim=-1)
        return selective(distance, self.epsilon)


class HalfCheetahSRD(nn.Module):
    """The controller and its PFC for ``n`` trials at once (leading axis = trial).

    Args:
        backswing: (n,) the BS neuron's gain per trial (0 removes the BS neuron: stage 3).
        fc_weight: (n, 6, 5) FC weights; default: the designed weights for every trial.
        inhibitor_path: subtract the inhibitor and apply LeakyReLU before the FC layer (main
            experiment); the design stages 3 and 4 feed the features straight in.
    """

    def __init__(
        self, backswing: Tensor, *, fc_weight: Tensor | None = None, inhibitor_path: bool = True
    ) -> None:
        super().__init__()
        n = backswing.shape[0]
        self.n_trials = n
        self.inhibitor_path = inhibitor_path
        self.register_buffer("backswing", backswing.to(torch.float32).clone())
        self.pose_x = StablePoseNeuron(_per_trial(STABLE_POSE_X, n))
        self.pose_z = StablePoseNeuron(_per_trial(STABLE_POSE_Z, n))
        weight = nominal_fc_weight().expand(n, -1, -1) if fc_weight is None else fc_weight
        if weight.shape != (n, len(ACTUATORS), len(FEATURES)):
            raise ValueError(f"fc_weight must have shape ({n}, 6, 5), got {tuple(weight.shape)}")
        self.fc_weight = nn.Parameter(weight.to(torch.float32).clone())
        self.fc_bias = nn.Parameter(torch.zeros(n, len(ACTUATORS)))
        self.pfc1_weight = nn.Parameter(_per_trial(PFC1_WEIGHT, n))
        self.pfc2_weight = nn.Parameter(_per_trial(PFC2_WEIGHT, n))
        self.pfc2_bias = nn.Parameter(_per_trial(PFC2_BIAS, n))

    def features(self, u: Tensor) -> Tensor:
        """h = [xS, zS, xS_inv, zS_inv, BS] (n, 5) from the pose input u (n, 12)."""
        x_stable = self.pose_x(u[:, :6])
        z_stable = self.pose_z(u[:, 6:])
        backswing = self.backswing * u[:, BACK_HIP_Z]
        return torch.stack([x_stable, z_stable, 1 - x_stable, 1 - z_stable, backswing], dim=-1)

    def forward(self, u: Tensor, inhibitor: Tensor) -> Tensor:
        """Actuator commands a = tanh(2 (W h' + b)) ∈ (−1, 1), (n, 6); inhibitor (n,)."""
        h = self.features(u)
        if self.inhibitor_path:
            h = F.leaky_relu(h - inhibitor[:, None], INHIBITOR_SLOPE)
        y = (self.fc_weight * h[:, None, :]).sum(dim=-1) + self.fc_bias
        return torch.tanh(ACTUATOR_GAIN * y)

    def judge(self, actions: Tensor, inhibitor: Tensor) -> Tensor:
        """The PFC's logits z = [T, F] (n, 2) for actions (n, 6) under inhibitor iN (n,)."""
        actuation = (actions**2).mean(dim=-1)
        pfc_input = torch.stack([inhibitor, actuation], dim=-1)
        g = torch.tanh(PFC_GAIN * (self.pfc1_weight * pfc_input[:, None, :]).sum(dim=-1))
        return (self.pfc2_weight * g[:, None, :]).sum(dim=-1) + self.pfc2_bias

    def act(
        self, u: Tensor, inhibitor: Tensor, *, srd: Tensor | None = None, lr: Tensor | None = None
    ) -> tuple[Tensor, Tensor | None]:
        """One network evaluation: the actions, then one SRD step on the trials where ``srd``.

        The SRD step (plain SGD, per-trial learning rate ``lr`` (n,)) minimises the summed
        per-trial loss CEL(z, argmax z), so each trial's gradient is its own. The returned
        actions are those computed before the update (the control is already latched). Returns
        (actions (n, 6), logits z (n, 2) or None when no trial learns).
        """
        if srd is None or lr is None or not bool(srd.any()):
            with torch.no_grad():
                return self(u, inhibitor), None
        with torch.enable_grad():
            actions = self(u, inhibitor)
            logits = self.judge(actions, inhibitor)
            loss = self_reward_loss(logits, reduction="none")
            self.zero_grad(set_to_none=True)
            (loss * srd.to(loss.dtype)).sum().backward()
        with torch.no_grad():
            for param in self.parameters():
                if param.grad is not None:
                    step = lr.view(-1, *([1] * (param.dim() - 1))) * param.grad
                    param.sub_(step)
        self.zero_grad(set_to_none=True)
        return actions.detach(), logits.detach()

    def controller_parameters(self) -> list[Tensor]:
        """Stable poses, FC weights and bias (everything but the PFC)."""
        return [self.pose_x.pose, self.pose_z.pose, self.fc_weight, self.fc_bias]

    def pfc_parameters(self) -> list[Tensor]:
        """The PFC's own weights and bias (also trained by SRD)."""
        return [self.pfc1_weight, self.pfc2_weight, self.pfc2_bias]

    def named_weights(self, trial: int) -> dict[str, float]:
        """Every number of one trial's network, by meaning (``fc.bt.xS_inv``, ``pfc.T.g1`` …)."""
        names: dict[str, float] = {}
        fc_weight, fc_bias = self.fc_weight.detach(), self.fc_bias.detach()
        pfc1, pfc2, pfc2_bias = (p.detach() for p in self.pfc_parameters())
        for prefix, neuron in (("xS", self.pose_x), ("zS", self.pose_z)):
            for limb, value in zip(LIMBS, neuron.pose[trial].detach().tolist(), strict=True):
                names[f"{prefix}.p.{limb}"] = value
        for row, actuator in enumerate(ACTUATORS):
            for col, feature in enumerate(FEATURES):
                names[f"fc.{actuator}.{feature}"] = float(fc_weight[trial, row, col])
            names[f"fc.{actuator}.bias"] = float(fc_bias[trial, row])
        for row, unit in enumerate(("g0", "g1")):
            for col, source in enumerate(("iN", "Ac")):
                names[f"pfc.{unit}.{source}"] = float(pfc1[trial, row, col])
        for row, verdict in enumerate(VERDICTS):
            for col, source in enumerate(("g0", "g1")):
                names[f"pfc.{verdict}.{source}"] = float(pfc2[trial, row, col])
            names[f"pfc.{verdict}.bias"] = float(pfc2_bias[trial, row])
        names["BS.backswing"] = float(self.backswing[trial])
        return names
