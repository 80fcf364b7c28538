"""The ``srd`` command line: commands generated from the experiment configs, lazy imports,
human and JSON output, option errors."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
from click.testing import CliRunner
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect as ws_connect

from agents.negotiator import honest_manifest, saboteur_manifest
from server.cli import HAND_WRITTEN, cli
from server.cli.experiment import experiment_command
from server.cli.launch import ServerProcess, settings_environment
from sim.experiment import config_fields
from studies.registry import KINDS
from tests.server.test_remote_protocol import start_remote
from tests.support.server import ADMIN_TOKEN, QUOTAS_OFF

SRD = (sys.executable, "-c", "from server.cli import main; main()")
COMMANDS = [kind for kind in KINDS.values() if kind.command]


def invoke(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*SRD, *args], capture_output=True, text=True, timeout=300)


def test_help_lists_every_command_without_importing_torch() -> None:
    probe = (
        "import sys\nfrom click.testing import CliRunner\nfrom server.cli import cli\n"
        "out = CliRunner().invoke(cli, ['--help']).output\n"
        "print(out)\nprint('torch' in sys.modules, 'numpy' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    for name in [*HAND_WRITTEN, *(k.name for k in COMMANDS)]:
        assert f"  {name} " in done.stdout
    assert done.stdout.strip().endswith("False False")


@pytest.mark.parametrize("kind", COMMANDS, ids=lambda k: k.name)
def test_summary_is_the_config_docstring_and_every_field_is_an_option(kind) -> None:
    config = kind.config_class()
    assert (config.__doc__ or "").strip().splitlines()[0] == kind.summary
    options = {opt for p in experiment_command(kind).params for opt in p.opts}
    for field in config_fields(config):
        assert f"--{field.name.replace('_', '-')}" in options
        assert field.help  # every option explains itself
    assert {"--out", "--json"} <= options


def test_json_output_is_one_object_with_the_artifact_folder(tmp_path) -> None:
    out = tmp_path / "fish"
    result = CliRunner().invoke(
        cli, ["fish", "--steps", "120", "--no-srd", "--json", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1
    payload = json.loads(lines[0])
    assert payload["out_dir"] == str(out)
    assert payload["steps"] == 120 and payload["srd"] is False and payload["died"] is False
    saved = json.loads((out / "result.json").read_text())
    assert saved == {k: v for k, v in payload.items() if k != "out_dir"}
    assert {p.name for p in out.iterdir()} == {"energy.csv", "fish.png", "result.json"}


def test_a_list_option_given_again_adds_its_values(tmp_path) -> None:
    # a list's items are numbers as a single-value option takes them: ".5" and "+0.75" too
    args = ["auction-study", "--rarities", ".25", "--rarities", "0.5,+0.75", "--trials", "1"]
    result = CliRunner().invoke(cli, [*args, "--patrons", "8", "--json", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert [row["rarity"] for row in json.loads(result.stdout)["rows"]] == [0.25, 0.5, 0.75]


def test_a_run_that_cannot_write_says_so_in_one_line_and_leaves_none_of_its_files(
    tmp_path,
) -> None:
    """An --out folder that was there, with a folder where the figure should go: the run fails
    writing it, exit 1, one line (no traceback), and the energy.csv it wrote before is gone; what
    was there stays."""
    out = tmp_path / "fish"
    (out / "fish.png").mkdir(parents=True)
    done = invoke("fish", "--steps", "120", "--json", "--out", str(out))
    assert done.returncode == 1, done.stderr
    error = f"cannot write the run's files ({out / 'fish.png'}): Is a directory"
    assert json.loads(done.stdout) == {"error": error}
    assert done.stderr.strip() == f"error: {error}"
    assert [p.name for p in out.iterdir()] == ["fish.png"] and (out / "fish.png").is_dir()


def test_a_closed_stdout_refuses_json_before_the_run_and_discards_a_summary(tmp_path) -> None:
    """`>&-`: a --json run has nowhere to print its object, so nothing runs (exit 2, one line);
    without --json the run writes its files and exits 0, its printed summary discarded."""

    def closed(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [*SRD, *args],
            stdout=None,
            stderr=subprocess.PIPE,
            text=True,
            timeout=300,
            pass_fds=(),
            preexec_fn=lambda: os.close(1),
        )

    refused = closed("fish", "--steps", "120", "--json", "--out", str(tmp_path / "a"))
    assert refused.returncode == 2
    assert refused.stderr.strip() == "error: --json: standard output is closed; nothing was run"
    assert not (tmp_path / "a").exists()
    done = closed("fish", "--steps", "120", "--out", str(tmp_path / "b"))
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr and (tmp_path / "b" / "result.json").is_file()


@pytest.mark.parametrize(
    "json_flag",
    [[], pytest.param(["--json"], marks=pytest.mark.slow)],  # one output path
)
def test_a_result_standard_output_does_not_take_is_one_line_and_exit_74(json_flag) -> None:
    """A full disk (``/dev/full``) or a reader gone (a pipe closed): the verdict never reaches
    anyone, so no verdict's exit code (0 accepted) and no traceback: one line, exit 74."""
    manifest = str(Path(__file__).parents[2] / "examples" / "honest.json")

    def screen_into(stdout: object) -> subprocess.CompletedProcess[str]:
        command = [*SRD, "screen", manifest, *json_flag]
        return subprocess.run(
            command, stdout=stdout, stderr=subprocess.PIPE, text=True, timeout=120
        )

    with open("/dev/full", "w") as full:
        lost = screen_into(full)
    assert lost.returncode == 74, lost.stderr
    assert lost.stderr.strip() == (
        "error: cannot write to standard output: No space left on device; the result is lost"
    )
    read, write = os.pipe()
    os.close(read)  # the reader is gone before anything is written
    try:
        gone = screen_into(write)
    finally:
        os.close(write)
    assert gone.returncode == 74 and "Broken pipe" in gone.stderr, gone.stderr
    assert "Traceback" not in gone.stderr


def test_human_output_is_a_short_summary_on_stdout(tmp_path) -> None:
    out = tmp_path / "study"
    args = ["auction-study", "--rarities", "0.25,0.75", "--trials", "1", "--patrons", "8"]
    result = CliRunner().invoke(cli, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    text = result.stdout
    assert "srd auction-study" in text and f"artifacts: {out}" in text
    assert "mean price" in text and "0.25" in text and "0.75" in text
    assert len(text.splitlines()) < 20
    assert (out / "results.csv").exists()


@pytest.mark.parametrize(
    ("args", "option", "message"),
    [
        (["fish", "--steps", "0"], "--steps", "greater than or equal to 1"),
        (["auction-study", "--saboteurs", "2"], "--saboteurs", "less than or equal to 1"),
        (["auction-study", "--rarities", "0.1,x"], "--rarities", "'x' is not a number"),
        (["cheetah", "--backswing", "9" * 5000], "--backswing", "5000 characters, too long"),
        (["auction-study", "--rarities", "0.5," + "[" * 30], "--rarities", "is not a number"),
        (["auction-study", "--rarities", "0.5," + "[" * 100_000], "--rarities", "too long for a"),
        (["auction-study", "--rarities", "0.5,1e400"], "--rarities", "must be a finite number"),
        (["auction-study", "--rarities", "0.5,1_0"], "--rarities", "'1_0' is not a number"),
        (["auction-study", "--rarities", "0.5,inf"], "--rarities", "'inf' is not a number"),
        (["fish", "--lr", "nan"], "--lr", "finite"),
        (["cheetah", "--stage", "1", "--backswing", "9"], "--backswing", "does not take backswing"),
        (["cheetah", "--stage", "4", "--srd", "off"], "--srd", "does not take srd"),
        (["auction-study", "--rarities", "1.5"], "--rarities", "less than or equal to 1"),
        (["auction-study", "--rows", "0"], "--rows", "greater than or equal to 1"),
        (["cheetah", "--inhibitor", "-1"], "--inhibitor", "greater than or equal to 0"),
    ],
)
def test_bad_options_exit_2_naming_the_option(tmp_path, args, option, message) -> None:
    result = CliRunner().invoke(cli, [*args, "--json", "--out", str(tmp_path / "x")])
    assert result.exit_code == 2
    assert option in result.stderr and message in result.stderr
    assert result.stderr.count("error:") == 1, result.stderr  # the cause alone
    failure = json.loads(result.stdout)  # --json: still exactly one object on stdout
    assert [e["option"] for e in failure["errors"]] == [option]
    assert message in failure["error"] and "out_dir" not in failure
    assert not (tmp_path / "x").exists()


def test_a_run_over_its_compute_budget_is_refused_naming_the_option_to_lower(tmp_path) -> None:
    """A grid that would keep the machine busy for days (a typo in ``--trials``) is refused
    before it runs, naming the option and how far to lower it; ``--budget-s`` moves the bar."""
    out = tmp_path / "never"
    days = ["cheetah", "--backswing", "1,2,3,4,5,6,7,8", "--inhibitor", "0,1,2,3,4,5,6,7"]
    days += ["--srd", "off", "--trials", "64", "--steps", "1000000", "--out", str(out), "--json"]
    refused = CliRunner().invoke(cli, days)
    assert refused.exit_code == 2, refused.output
    (error,) = json.loads(refused.stdout)["errors"]
    assert error["option"] == "--trials"
    assert "over the budget of 86400 s (--budget-s): lower trials to at most" in error["message"]
    assert not out.exists()  # nothing ran, nothing made
    small = ["auction-study", "--rarities", "0.5", "--trials", "1000", "--patrons", "8"]
    tight = CliRunner().invoke(cli, [*small, "--budget-s", "1", "--out", str(out), "--json"])
    assert tight.exit_code == 2, tight.output  # about 1.25 s, estimated
    assert "over the budget of 1 s (--budget-s): lower trials to at most 800" in tight.stdout
    done = CliRunner().invoke(cli, [*small, "--out", str(tmp_path / "ok"), "--json"])
    assert done.exit_code == 0, done.output


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["fish", "--steps", "nan"], "Invalid value for '--steps': 'nan' is not a valid integer."),
        (["fish", "--bogus", "1"], "No such option '--bogus'."),
        (["screen"], "Missing argument 'FILE'."),
        (["lavaland", "--project", "B"], "Invalid value for '--project': 'B' is not one of"),
    ],
)
def test_a_usage_error_is_one_line_naming_the_option(args, line) -> None:
    """As the commands' own checks say theirs: `error: ...` on one line, exit 2, no usage
    block; with --json the one object on stdout as well."""
    for json_flag in ([], ["--json"]):
        done = invoke(*args, *json_flag)
        assert done.returncode == 2, done.stderr
        [said] = done.stderr.splitlines()
        assert said.startswith(f"error: {line}") and said.endswith(f"(see 'srd {args[0]} --help')")
        assert bool(json_flag) == bool(done.stdout) and "Usage:" not in done.stderr


def test_an_out_folder_that_cannot_be_made_exits_2_naming_it(tmp_path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    out = blocker / "results"  # a folder inside a file
    result = CliRunner().invoke(cli, ["fish", "--steps", "10", "--json", "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert result.stderr.count("error:") == 1 and "--out" in result.stderr
    assert "Traceback" not in result.stderr
    failure = json.loads(result.stdout)
    assert [e["option"] for e in failure["errors"]] == ["--out"]
    assert str(out) in failure["error"]


def test_a_default_out_folder_that_cannot_be_made_exits_2_naming_it(tmp_path, monkeypatch) -> None:
    """No --out, and ./runs is a file: the same one line as for a given folder, no traceback."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runs").write_text("")
    result = CliRunner().invoke(cli, ["fish", "--steps", "10", "--json"])
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.stderr
    failure = json.loads(result.stdout)
    assert failure["errors"] == [
        {"option": "--out", "message": "cannot create the folder runs: File exists"}
    ]


@pytest.mark.parametrize(
    ("out", "words"), [("", "must name a folder"), ("/proc", "cannot write into the folder /proc")]
)
def test_an_out_folder_that_cannot_be_written_is_refused_before_the_run(out, words) -> None:
    """An empty --out had written into the current folder; a folder that exists but takes no
    files had failed with a traceback after the whole run."""
    result = CliRunner().invoke(cli, ["fish", "--steps", "10", "--json", "--out", out])
    assert result.exit_code == 2, result.output
    assert "--out" in result.stderr and words in result.stderr
    assert "Traceback" not in result.stderr
    assert [e["option"] for e in json.loads(result.stdout)["errors"]] == ["--out"]


@pytest.mark.parametrize(
    ("args", "code", "option", "words"),
    [
        (["lavaland", "--project", "nope"], 2, "--project", "is not one of"),
        (["fish", "--no-such-option"], 2, "--no-such-option", "No such option"),
        (["agents", "--honest", "-1"], 2, "--honest", "not in the range"),
        (["agents", "--server", "http://127.0.0.1:9", "--honest", "0"], 2, "--honest", "between 1"),
        (["agents", "--server", "http://127.0.0.1:9", "--give-up", "1"], 1, None, "gave up"),
        (
            ["agents", "--server", "http://127.0.0.1:9", "--give-up", "nan"],
            2,
            "--give-up",
            "finite",
        ),
        (["agents", "--server", "http://127.0.0.1:9", "--wait", "inf"], 2, "--wait", "finite"),
        (
            ["agents", "--server", "http://127.0.0.1:9", "--auction", "99999999999"],
            2,
            "--auction",
            "not in the range",
        ),
        (["agents", "--server", "http://[::1", "--honest", "1"], 2, "--server", "not an http"),
        (
            ["agents", "--server", "http://127.0.0.1:9", "--honest", "2", "--admin-token", "a b"],
            2,
            "--admin-token",
            "without white space",
        ),
        (
            [
                "agents",
                "--server",
                "http://127.0.0.1:9",
                "--honest",
                "1",
                "--admin-token",
                "x" * 32,
                "--rarity",
                "0.5",
            ],
            2,
            "--rarity",
            "at least one fish",
        ),
        (["watch", "1", "--server", "http://127.0.0.1:9"], 3, None, "ConnectError"),
        (["watch", "abc"], 2, None, "'AUCTION_ID': 'abc' is not a valid integer."),
        (["agents", "--auction", "x"], 2, "--auction", "'x' is not a valid integer."),
    ],
)
def test_every_failure_under_json_is_one_object_on_stdout(args, code, option, words) -> None:
    """Options click itself refuses, and a server that never answers, as a script reads them:
    the exit code, and one JSON object saying what failed (the person's words on stderr)."""
    done = invoke(*args, "--json")
    assert done.returncode == code, done.stderr
    failure = json.loads(done.stdout)
    assert words in failure["error"] and words in done.stderr
    assert [e["option"] for e in failure.get("errors", [])] == ([option] if option else [])


def test_the_item_rows_are_an_option(tmp_path) -> None:
    """64 rows (the reference's) by default; the paper's text says 16."""
    base = ["auction-study", "--rarities", "0.5", "--trials", "2", "--patrons", "16", "--json"]
    found = {}
    for rows in ("16", "64", None):
        extra = [] if rows is None else ["--rows", rows]
        result = CliRunner().invoke(cli, [*base, *extra, "--out", str(tmp_path / f"r{rows}")])
        assert result.exit_code == 0, result.output
        found[rows] = json.loads(result.stdout)["rows"][0]
    assert found[None] == found["64"]
    assert found["16"]["mean_price"] != found["64"]["mean_price"]


def test_unknown_command_is_a_usage_error() -> None:
    done = invoke("no-such-command")
    assert done.returncode == 2 and "No such command" in done.stderr


# --- srd screen FILE [--json]: exit 0 accepted, 1 rejected, 2 unreadable or malformed ---------


EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def screen(*args: str):
    return CliRunner().invoke(cli, ["screen", *args])


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_screen_accepted_exits_0_with_one_json_object(tmp_path) -> None:
    manifest = honest_manifest(np.random.default_rng(0), "alice")
    outcome = screen(write(tmp_path, "a.json", manifest.model_dump_json()), "--json")
    assert outcome.exit_code == 0, outcome.output
    (line,) = outcome.stdout.strip().splitlines()
    result = json.loads(line)
    assert result["accepted"] is True and result["reasons"] == []
    assert "noise-flip" in {e["test"] for e in result["evidence"]}  # the screener's numbers


def test_screen_says_a_server_would_hold_a_borderline_model() -> None:
    """The screener refuses the window holder, by less than the server's review margin of its
    bar: status "held", what /submit would answer, and not accepted (exit 1), as /submit
    says; the screener's own verdict is there too."""
    holder = str(EXAMPLES / "red_team" / "opening-window-holder-a.json")
    outcome = screen(holder, "--json")
    assert outcome.exit_code == 1
    result = json.loads(outcome.stdout)
    assert result["accepted"] is False and result["status"] == "held"
    assert result["screener_accepted"] is False
    assert json.loads(screen(holder, "--json", "--margin", "0").stdout)["status"] == "refused"
    assert "held (a server would hold it for an inspector" in screen(holder).stdout
    assert "within 0.005 of a bar" in screen(holder).stdout
    honest_one = screen(str(EXAMPLES / "honest.json"), "--json")
    assert json.loads(honest_one.stdout)["status"] == "accepted"
    # A keen buyer passes the screener's refusing bars and is held for an inspector by its
    # own: one answer, whichever side of a bar held it (before, this one exited 0).
    keen = str(EXAMPLES.parent / "tests" / "screener" / "inspection" / "any-price-buyer.json")
    outcome = screen(keen)
    assert outcome.exit_code == 1
    assert "held (a server would hold it for an inspector: its reason below)" in outcome.stdout
    assert "keen-far-too-expensive" in outcome.stdout
    result = json.loads(screen(keen, "--json").stdout)
    assert (result["accepted"], result["status"], result["screener_accepted"]) == (
        False,
        "held",
        True,
    )


def test_screen_rejected_exits_1_with_reasons(tmp_path) -> None:
    manifest = saboteur_manifest(np.random.default_rng(0), "mallory")
    path = write(tmp_path, "s.json", manifest.model_dump_json())
    outcome = screen(path, "--json")
    assert outcome.exit_code == 1
    result = json.loads(outcome.stdout)
    assert result["accepted"] is False and result["reasons"]
    assert all(set(r) == {"rule", "neuron", "message"} for r in result["reasons"])
    human = screen(path)
    assert human.exit_code == 1
    assert human.stdout.startswith("mallory: rejected")
    first = result["reasons"][0]
    assert f"{first['neuron']} ({first['rule']}): " in human.stdout


def test_screen_non_finite_number_is_malformed_and_names_its_path(tmp_path) -> None:
    data = json.loads(honest_manifest(np.random.default_rng(0), "nan").model_dump_json())
    data["external_sensor"]["PG"]["weights"]["price"] = float("nan")
    outcome = screen(write(tmp_path, "nan.json", json.dumps(data)), "--json")  # writes NaN
    assert outcome.exit_code == 2
    assert "external_sensor.PG.weights.price" in outcome.stderr
    result = json.loads(outcome.stdout)
    assert result["accepted"] is False and result["reasons"] == []
    assert [e["path"] for e in result["errors"]] == ["external_sensor.PG.weights.price"]


def test_screen_missing_fields_and_broken_json_are_malformed(tmp_path) -> None:
    data = json.loads(honest_manifest(np.random.default_rng(0), "x").model_dump_json())
    del data["decision"]["L"]
    outcome = screen(write(tmp_path, "m.json", json.dumps(data)))
    assert outcome.exit_code == 2
    assert "decision.L: Field required" in outcome.stderr
    broken = screen(write(tmp_path, "b.json", '{"participant": '))
    assert broken.exit_code == 2
    assert "error: Invalid JSON" in broken.stderr  # the whole file: no path said
    assert "$" not in broken.stderr


def test_screen_unreadable_file_exits_2(tmp_path) -> None:
    outcome = screen(str(tmp_path / "missing.json"), "--json")
    assert outcome.exit_code == 2
    assert "cannot read" in json.loads(outcome.stdout)["errors"][0]["message"]
    empty = screen("")  # not the working folder, "."
    assert empty.exit_code == 2 and "error: cannot read '': no file named" in empty.stderr


def test_screen_usage_errors_keep_the_verdicts_keys() -> None:
    for args in (["screen", "--json"], ["screen", "--json", "--margin", "7", "x.json"]):
        outcome = CliRunner().invoke(cli, args)
        assert outcome.exit_code == 2
        answer = json.loads(outcome.stdout)
        assert answer["accepted"] is False and answer["reasons"] == [] and answer["error"]


# --- the other worlds' commands, at a tiny budget ------------------------------------------------


def test_cheetah_and_lavaland_commands_run_and_refuse_bad_choices(tmp_path) -> None:
    args = ["cheetah", "--backswing", "3,4", "--inhibitor", "2", "--srd", "on", "--trials", "2"]
    args += ["--steps", "300", "--no-video", "--seed", "3", "--json"]
    outcome = CliRunner().invoke(cli, [*args, "--out", str(tmp_path / "c")])
    assert outcome.exit_code == 0, outcome.output
    (line,) = outcome.stdout.strip().splitlines()
    runs = json.loads(line)["runs"]
    assert [(r["backswing"], r["trial"]) for r in runs] == [(3.0, 1), (3.0, 2), (4.0, 1), (4.0, 2)]
    bad = CliRunner().invoke(cli, ["cheetah", "--srd", "sometimes", "--out", str(tmp_path)])
    assert bad.exit_code == 2 and "--srd" in bad.stderr
    args = ["lavaland", "--project", "compare-A", "--eval-maps", "16", "--train-maps", "4"]
    outcome = CliRunner().invoke(cli, [*args, "--json", "--out", str(tmp_path / "l")])
    assert outcome.exit_code == 0, outcome.output
    result = json.loads(outcome.stdout)
    assert result["project"] == "compare-A" and result["eval_maps"] == 16
    assert 0 <= result["accuracy_untrained"] <= 1 and 0 <= result["accuracy_srd"] <= 1


@pytest.mark.parametrize(("value", "logged"), [(None, True), ("false", False), ("true", True)])
def test_serve_logs_each_request_unless_told_not_to(monkeypatch, value, logged) -> None:
    import uvicorn

    from server.config import get_settings

    seen: dict[str, object] = {}

    def run(server: uvicorn.Server) -> None:  # instead of serving: what it would serve
        seen.update(access_log=server.config.access_log, port=server.config.port)
        server.started = True

    monkeypatch.setattr(uvicorn.Server, "run", run)
    if value is None:
        monkeypatch.delenv("SRD_ACCESS_LOG", raising=False)
    else:
        monkeypatch.setenv("SRD_ACCESS_LOG", value)
    get_settings.cache_clear()
    try:
        result = CliRunner().invoke(cli, ["serve", "--port", "0"])
    finally:
        get_settings.cache_clear()
    assert result.exit_code == 0, result.output
    assert seen["access_log"] is logged and seen["port"] == 0


# --- what a person reads: help in plain words, headers, rounding, run folders -------------------


@pytest.mark.parametrize("command", ["", *HAND_WRITTEN, *(k.name for k in COMMANDS)])
def test_help_has_no_restructuredtext_literals(command) -> None:
    result = CliRunner().invoke(cli, [*command.split(), "--help"])
    assert result.exit_code == 0, result.output
    assert "`" not in result.output


def test_rarities_are_explained_as_supply() -> None:
    text = CliRunner().invoke(cli, ["auction-study", "--help"]).output
    assert "Supply: fish on sale per patron" in " ".join(text.split())


def test_summary_headers_are_words_and_floats_have_three_significant_digits(tmp_path) -> None:
    args = ["auction-study", "--rarities", "0.25", "--trials", "1", "--patrons", "8"]
    result = CliRunner().invoke(cli, [*args, "--out", str(tmp_path / "s")])
    assert result.exit_code == 0, result.output
    assert "supply: fish on sale per patron" in result.stdout and "mean price" in result.stdout
    assert "_" not in result.stdout.replace(str(tmp_path), "")
    saved = json.loads((tmp_path / "s" / "result.json").read_text())
    price = saved["rows"][0]["mean_price"]
    assert f"{price:.3g}" in result.stdout and f"{price:.4g}" not in result.stdout


@pytest.mark.parametrize(
    ("value", "shown"),
    [(5.1913, "5.19"), (0.012345, "0.0123"), (1234.5, "1230"), (0.5, "0.5"), (2e-05, "2e-05")],
)
def test_floats_are_shown_to_three_significant_digits(value, shown) -> None:
    from server.cli.words import rounded

    assert rounded(value) == shown


def test_a_run_folder_is_named_by_command_seed_and_readable_time(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(cli, ["fish", "--steps", "50", "--seed", "4", "--json"])
    assert result.exit_code == 0, result.output
    out_dir = Path(json.loads(result.stdout)["out_dir"])
    assert out_dir.parent == Path("runs")
    assert re.fullmatch(r"fish__4__\d{8}-\d{6}", out_dir.name)


@pytest.mark.parametrize("command", [["agents", "--honest", "1"], ["watch", "1"]])
@pytest.mark.parametrize("url", ["not-a-url", "ftp://127.0.0.1", "http://"])
def test_a_server_that_is_not_a_url_is_a_usage_error(command: list[str], url: str) -> None:
    result = CliRunner().invoke(cli, [*command, "--server", url])
    assert result.exit_code == 2
    assert "--server" in result.stderr and "not an http:// or https:// URL" in result.stderr


def test_a_supply_given_twice_is_refused() -> None:
    result = CliRunner().invoke(cli, ["auction-study", "--rarities", "0.5,0.1,0.5", "--json"])
    assert result.exit_code == 2 and "--rarities" in result.stderr
    assert "0.5 is given twice" in result.stderr


@pytest.mark.parametrize("rarities", ["0.1,,0.5", "0.1,", ","])
def test_an_empty_item_of_a_list_option_is_refused(rarities: str) -> None:
    """ "0.1,,0.5" is a typo, not the list 0.1, 0.5 (its empty item had been dropped)."""
    result = CliRunner().invoke(cli, ["auction-study", "--rarities", rarities, "--json"])
    assert result.exit_code == 2 and "--rarities" in result.stderr
    assert json.loads(result.stdout)["error"].startswith("--rarities")


def test_screen_reads_the_file_as_strictly_as_submit_reads_a_body(tmp_path) -> None:
    """A key given twice is malformed (POST /submit answers 422): never judged as one of the
    two manifests it could be. A directory is unreadable, and --json still prints one object."""
    text = honest_manifest(np.random.default_rng(0), "twice").model_dump_json()
    doubled = text[:-1] + ', "participant": "other"}'
    outcome = screen(write(tmp_path, "d.json", doubled), "--json")
    assert outcome.exit_code == 2
    (error,) = json.loads(outcome.stdout)["errors"]
    assert error["path"] == "participant" and "twice" in error["message"]
    folder = screen(str(tmp_path), "--json")
    assert folder.exit_code == 2
    assert "cannot read" in json.loads(folder.stdout)["errors"][0]["message"]


def test_serve_without_the_access_log_logs_no_line_per_socket(tmp_path) -> None:
    """With the access log off, a round socket is a request like any other: no line for its
    handshake (accepted or refused), none for its connection; an auction's agents reconnecting
    had written two lines each (100,800 in one audit)."""
    env = settings_environment({**QUOTAS_OFF, "access_log": False})
    with (
        ServerProcess(
            database_url=f"sqlite:///{tmp_path / 'srd.db'}",
            data_dir=tmp_path / "data",
            admin_token=ADMIN_TOKEN,
            extra_env=env,
        ) as server,
        httpx.Client(base_url=server.url, timeout=30) as client,
    ):
        auction_id, _, _ = start_remote(client, "quiet", 730, 2, round_deadline_s=120, seed=3)
        base = server.url.replace("http://", "ws://")
        for _ in range(3):
            with ws_connect(f"{base}/auctions/{auction_id}/rounds/socket") as socket:
                assert json.loads(socket.recv(timeout=30))["type"] == "round"
        with pytest.raises(InvalidStatus):
            ws_connect(f"{base}/auctions/999999/rounds/socket").close()
        assert client.get("/healthz").status_code == 200
    log = server.log_path.read_text()
    assert "srd server ready" in log  # the log is there ...
    for line in ("WebSocket", "connection open", "connection closed", "GET /healthz"):
        assert line not in log, line  # ... and no request's line
