"""Evidence and the review margin: every verdict carries the numbers of the bars it was held to,
and ``review`` turns a verdict into accepted, refused or held for a margin in price."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agents.negotiator import honest_manifest
from screener import Evidence, Reason, Verdict, impact, review, screen, with_hold_reasons
from tests.support.corpus import red_team_corpus

IMPACT_BAR = 5.086


def impact_evidence(measured: float, passed: bool) -> Evidence:
    return Evidence("market-impact", measured, IMPACT_BAR, "price", "at least", passed)


def test_margin_zero_never_holds():
    close = impact_evidence(5.0859, False)
    refused = Verdict(False, [Reason("market-impact", "L", "…")], [close])
    assert review(refused, 0.0) == "refused"
    accepted = Verdict(True, [], [impact_evidence(IMPACT_BAR, True)])
    assert review(accepted, 0.0) == "accepted"


def test_a_refusal_within_the_margin_of_its_bar_is_held():
    refused = Verdict(False, [Reason("market-impact", "L", "…")], [impact_evidence(5.080, False)])
    assert review(refused, 0.01) == "held"
    assert review(refused, 0.005) == "refused"  # 0.006 below the bar


def test_an_admission_within_the_margin_of_its_bar_is_held():
    accepted = Verdict(True, [], [impact_evidence(5.090, True)])
    assert review(accepted, 0.005) == "held"
    assert review(accepted, 0.003) == "accepted"


def test_a_hold_reason_prints_the_measure_and_its_bar_apart():
    """Where four decimals print both alike (5.0860 and 5.0860), more are given, and how far
    it passed."""
    accepted = Verdict(True, [], [impact_evidence(IMPACT_BAR + 0.00003, True)])
    (reason,) = with_hold_reasons(accepted, 0.005).reasons
    assert reason.rule == "review-margin" and reason.neuron == "L"
    assert "measured 5.08603 against its bar 5.08600 (at least the bar)" in reason.message
    assert "passed by 0.00003, within 0.005 of its bar" in reason.message


def test_a_refusal_by_a_rule_without_a_bar_in_price_stands():
    both = Verdict(
        False,
        [Reason("market-impact", "L", "…"), Reason("decision-sign", "B", "…")],
        [impact_evidence(5.085, False)],
    )
    assert review(both, 0.05) == "refused"
    drift = Evidence("fine-tuning-drift", None, None, "check", "at most", False)
    drifted = Verdict(False, [Reason("fine-tuning-drift", "T", "…")], [drift])
    assert review(drifted, 1.0) == "refused"


def test_every_failed_bar_of_a_reason_must_be_close():
    far = Evidence("market-impact", 5.00, IMPACT_BAR, "price", "at least", False)
    verdict = Verdict(
        False, [Reason("market-impact", "L", "…")], [impact_evidence(5.084, False), far]
    )
    assert review(verdict, 0.01) == "refused"


def test_a_negative_margin_is_an_error():
    with pytest.raises(ValueError, match="margin must be ≥ 0"):
        review(Verdict(True), -0.01)


def test_the_opening_price_holder_is_held_within_a_cent():
    (entry,) = [e for e in red_team_corpus() if e.construction == "red-team:opening-price-holder"]
    verdict = screen(entry.manifest)
    impact_items = [e for e in verdict.evidence if e.test == "market-impact"]
    bars = {impact.references().lowest_price, impact.wide_references().lowest_price}
    assert impact_items and all(any(e.bar == pytest.approx(b) for b in bars) for e in impact_items)
    failed = [e for e in impact_items if not e.passed]
    assert failed and all(e.measured is not None and e.measured < e.bar for e in failed)
    gap = max(e.bar - e.measured for e in failed if e.measured is not None)
    rules = {r.rule for r in verdict.reasons}
    if rules == {"market-impact"}:
        assert review(verdict, gap + 0.001) == "held"
    else:  # its own fine-tuning also drifts it out of the rules: no margin holds it
        assert review(verdict, 1.0) == "refused"
    assert review(verdict, gap / 2) == "refused"


def test_evidence_is_in_the_json_and_the_old_fields_stay():
    verdict = screen(honest_manifest(np.random.default_rng(7), "honest-7"))
    data = json.loads(json.dumps(verdict.to_dict()))
    assert data["accepted"] is True and data["reasons"] == []
    tests = [e["test"] for e in data["evidence"]]
    assert "noise-flip" in tests
    flip = data["evidence"][tests.index("noise-flip")]
    assert set(flip) == {"test", "measured", "bar", "units", "side", "passed", "detail"}
    assert flip["measured"] == 0.0 and flip["bar"] == 0.05 and flip["units"] == "price"
    assert flip["detail"]["clean"] == flip["detail"]["noisy"]
    assert flip["detail"]["clean"].startswith("buys 4.75-")
    assert review(verdict, 0.0) == "accepted"
