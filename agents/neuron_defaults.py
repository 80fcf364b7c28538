"""The activations' default parameters (``agents.neurons``), in a module without torch: the
design table (``agents.negotiator``) and the server read them without loading the tensors."""

from __future__ import annotations

SELECTIVE_EPSILON = 1e-4
"""ε of the selective activation as it runs in the reference (its configured 1e-5 is unused)."""
THRESHOLD_SHARPNESS = 5.0
"""Default a of the threshold activation."""
THRESHOLD_CENTRE = 0.0
"""Default c of the threshold activation."""
NEGATIVE_SLOPE = 0.01
"""Default leaky-ReLU slope below the threshold (PyTorch's default)."""
