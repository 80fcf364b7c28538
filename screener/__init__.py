"""The inspector: reads a submitted manifest weight by weight and probes its behaviour.

``screen(manifest) -> Verdict`` is the one entry point every caller uses (``/submit``,
``srd screen``, ``srd auction-study --screen``, re-screening of fine-tuned versions).
"""

from __future__ import annotations

from agents.manifest import Manifest
from screener.verdict import Reason, Verdict

__all__ = ["Reason", "Verdict", "screen"]


def screen(manifest: Manifest) -> Verdict:
    """Judge one parsed manifest. The rule set arrives with the screener work (issue 4);
    until then every well-formed manifest is admitted with no reasons."""
    return Verdict(accepted=True, reasons=[])
