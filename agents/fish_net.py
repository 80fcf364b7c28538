"""FishNN: the robot fish's brain (paper, "Robot fish: 1D toy example"; docs/fish.md).

Input x = [e1, e2, e3, F]: the three visible tape cells (0.5 = food) and the energy F.

* Food Location Detector (FLD): conv_FLD over [e1, e2, e3] with two neurons and the selective
  activation S(y) = ε/(ε + y²): ``food_here`` fh = 1 exactly when e1 = 0.5 and e2 = e3 = 0,
  ``food_there`` ft = 1 exactly when food is one or two cells ahead (and not here). With no
  food in sight both are ≈ 4·10⁻⁴ (= S(−0.5)).
* FC: [fh, ft, F] → [eat, move], the decision logits (greedy action = argmax, ties → eat).
* PFC (the self-reward judge): v0 = [fh, ft, F, softmax(eat, move)] → conv_PFC → [e1, m1, ex]
  → softmax → T(· − 0.5) → FC_PFC → softmax → [T, F] (T = "the decision is right").

Both convolutions (the paper's and the reference's Conv1d) have a kernel as wide as their
input, so they have one output position and are exactly linear maps; they are held as
``nn.Linear`` (same numbers, weight (out, kernel) instead of (out, 1, kernel)), which runs
several times faster on CPU. Checked against a Conv1d, one-verdict-per-step version of the
12000-step SRD run: the same energy trace, final weights equal within float32 rounding (3·10⁻⁷).

Fidelity notes (the reference is followed exactly; see docs/decisions.md):
* The paper's text gives the fh bias as +0.5; its table and the reference code use −0.5
  (only −0.5 makes fh = S(0.5 − 0.5) = 1 when food is here).
* The reference's comments call e1 "eat when hungry and food there" and m1 "move when hungry
  and food here"; their weights say the opposite: e1 reads fh (food here), m1 reads ft.
* Beyond the paper's "conv, softmax, threshold", the PFC subtracts 0.5 before the threshold
  and ends with a softmax after FC_PFC, whose bias is (0, 0.4).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from agents.neurons import SELECTIVE_EPSILON, selective, threshold

# ---------------------------------------------------------------------------------------------
# The hand-designed weights: every number FishNN starts from, with its meaning.
# ---------------------------------------------------------------------------------------------
DELTA = 1e-3
"""δ: a small positive weight that breaks ties without carrying meaning of its own."""

FLD_WEIGHTS = (
    (1.0, 0.0, 0.0),  # fh, food here: reads only the fish's own cell e1
    (0.0, 1.0, 1.0),  # ft, food there: reads the two cells ahead, e2 and e3
)
"""Conv_FLD kernel over [e1, e2, e3]; one row per neuron (fh, ft)."""
FLD_BIAS = (
    -0.5,  # fh: e1 − 0.5 = 0 exactly when the food (0.5) is here → S = 1
    -0.5,  # ft: e2 + e3 − 0.5 = 0 exactly when one food (0.5) is ahead → S = 1
)
"""Conv_FLD bias (the paper's text prints +0.5 for fh; its table and the code say −0.5)."""

FC_WEIGHTS = (
    (1.0, DELTA, -1.0),  # eat  = fh + δ·ft − F: eat when food is here, the hungrier the more
    (DELTA, 1.0, 1.0),  # move = δ·fh + ft + F: move toward food ahead, or while well fed
)
"""FC over [fh, ft, F]; rows (eat, move). With food here the fish eats only when F < ≈0.4995."""
FC_BIAS = (0.0, 0.0)
"""FC bias (eat, move): none."""

PFC_CONV_WEIGHTS = (
    (1.0, 0.0, -1.0, 1.0, 0.0),  # e1 = fh − F + p_eat: food here, hungry, and eating
    (0.0, 1.0, -1.0, 0.0, 1.0),  # m1 = ft − F + p_move: food ahead, hungry, and moving
    (-1.0, -1.0, 0.0, 0.0, 1.0),  # ex = −fh − ft + p_move: no food in sight, and exploring
)
"""Conv_PFC kernel over v0 = [fh, ft, F, p_eat, p_move] (no bias); rows (e1, m1, ex).

The reference's comments swap the e1 and m1 descriptions; the weights above are what it runs.
"""
PFC_OFFSET = 0.5
"""A judgement neuron counts as active once its softmax share exceeds one half: T(s − 0.5)."""
PFC_FC_WEIGHTS = (
    (1.0, 1.0, 1.0),  # T: any active judgement (e1, m1 or ex) says the decision is right
    (DELTA, DELTA, DELTA),  # F: (almost) deaf to the judgements
)
"""FC_PFC over [e1, m1, ex]; rows (T, F)."""
PFC_FC_BIAS = (
    0.0,  # T: no prior
    0.4,  # F: the default verdict when no judgement fires
)
"""FC_PFC bias (T, F)."""

FH, FT = 0, 1
"""Channel indices of the Food Location Detector."""
EAT, MOVE = 0, 1
"""Action indices (decision logits and the robot fish environment's actions)."""
NEURONS = ("fh", "ft", "F", "eat", "move", "e1", "m1", "ex", "T", "F_verdict")
"""Names of the activations returned by :meth:`FishNN.activations`."""


def _tensor(values: tuple[float, ...] | tuple[tuple[float, ...], ...]) -> Tensor:
    return torch.tensor(values, dtype=torch.float32)


class FishNN(nn.Module):
    """The robot fish's FishNN with its PFC, initialised to the hand-designed weights.

    ``forward(x)`` takes x of shape (batch, 4) = [e1, e2, e3, F] and returns the decision
    logits [eat, move] and the PFC's probabilities [T, F], both (batch, 2). Every parameter is
    trainable (SRD trains the detector, the FC and the PFC together, as the reference does).
    """

    def __init__(self, epsilon: float = SELECTIVE_EPSILON) -> None:
        super().__init__()
        self.epsilon = epsilon
        self.food_detector = nn.Linear(3, 2)  # conv_FLD (see the module docstring)
        self.fc = nn.Linear(3, 2)
        self.pfc_conv = nn.Linear(5, 3, bias=False)  # conv_PFC
        self.pfc_fc = nn.Linear(3, 2)
        self.load_designed_weights()

    @torch.no_grad()
    def load_designed_weights(self) -> None:
        """Set every parameter to its hand-designed value (the module constants above)."""
        self.food_detector.weight.copy_(_tensor(FLD_WEIGHTS))
        self.food_detector.bias.copy_(_tensor(FLD_BIAS))
        self.fc.weight.copy_(_tensor(FC_WEIGHTS))
        self.fc.bias.copy_(_tensor(FC_BIAS))
        self.pfc_conv.weight.copy_(_tensor(PFC_CONV_WEIGHTS))
        self.pfc_fc.weight.copy_(_tensor(PFC_FC_WEIGHTS))
        self.pfc_fc.bias.copy_(_tensor(PFC_FC_BIAS))

    def _decision(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """(x1 = [fh, ft, F], decision logits [eat, move])."""
        cells, energy = x[:, :3], x[:, 3:]
        food = selective(self.food_detector(cells), self.epsilon)
        x1 = torch.cat((food, energy), dim=1)
        return x1, self.fc(x1)

    def _trace(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(x1 = [fh, ft, F], decision logits [eat, move], judgements [e1, m1, ex], [T, F])."""
        x1, logits = self._decision(x)
        choice = torch.softmax(logits, dim=1)
        v0 = torch.cat((x1, choice), dim=1)
        judged = self.pfc_conv(v0)
        v1 = threshold(torch.softmax(judged, dim=1), c=PFC_OFFSET)
        verdict = torch.softmax(self.pfc_fc(v1), dim=1)
        return x1, logits, judged, verdict

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Decision logits [eat, move] and the PFC verdict [T, F] for x = [e1, e2, e3, F]."""
        _, logits, _, verdict = self._trace(x)
        return logits, verdict

    def decide(self, x: Tensor) -> Tensor:
        """The greedy actions argmax(eat, move) for x (batch, 4); ties → eat (index 0).

        Runs only the detector and the FC (the PFC does not take part in acting).
        """
        return self._decision(x)[1].argmax(dim=1)

    def activations(self, x: Tensor) -> dict[str, Tensor]:
        """Every named neuron for x (batch, 4), each of shape (batch,); see ``NEURONS``.

        ``e1, m1, ex`` are the conv_PFC outputs before softmax and threshold; ``T`` and
        ``F_verdict`` are the final PFC probabilities.
        """
        x1, logits, judged, verdict = self._trace(x)
        columns = torch.cat((x1, logits, judged, verdict), dim=1)
        return {name: columns[:, i] for i, name in enumerate(NEURONS)}
