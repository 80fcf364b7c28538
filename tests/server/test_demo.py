"""``make demo``'s program (``python -m server.cli.demo``) end to end: it serves SQLite, turns
the saboteurs away, runs an auction and the honest vs malicious comparison, says what each row
is, and leaves the artifacts where it says."""

from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_demo_runs_the_comparison_and_says_where_to_look(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "server.cli.demo"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        env={"PATH": "/usr/bin:/bin", "COLUMNS": "200", "HOME": str(tmp_path)},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    out = done.stdout
    assert "POST /auctions {" in out and "fish sold, revenue" in out
    # an auction's bidding steps are iterations, as the API calls them ("round" is fine-tuning)
    assert "  iteration  0: price " in out and "  round " not in out, out
    for name in ("honest", "honest+screened", "compromised", "compromised+screened"):
        assert f"{name}: " in out  # the configuration explained, not only named
    files = [Path(line.strip()) for line in out.splitlines() if "/jobs/1/" in line]
    assert {f.name for f in files} >= {"comparison.png", "comparison.csv", "result.json"}
    for file in files:
        assert (tmp_path / file).is_file(), file
    rows = list(csv.DictReader((tmp_path / files[0].parent / "comparison.csv").open()))
    screened = [r for r in rows if r["setting"] == "compromised+screened"]
    assert screened and {float(r["refused"]) for r in screened} == {16.0}  # per auction
    table_refused = {
        int(m.group(1)) for m in re.finditer(r"compromised\+screened\s*│\s*(\d+)\s*│", out)
    }
    assert table_refused == {16}, out  # as the CSV says, not the setting's total
    result = json.loads((tmp_path / files[0].parent / "result.json").read_text())
    assert set(result["configurations"]) >= {"honest", "compromised", "compromised+screened"}
    assert "serve it again" in out and "/ui/#/jobs/1" in out
