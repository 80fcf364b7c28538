"""The study commands and job parameters: ``--buy-fraction`` on ``srd auction-study`` and
``srd comparison`` (generated from the configs, like the job parameters)."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from server.cli import cli
from sim.experiment import ConfigError, config_dict
from studies.registry import build_config

SMALL = ["--rarities", "0.25,0.75", "--trials", "1", "--patrons", "8"]


def test_auction_study_takes_the_buy_fraction_rule(tmp_path) -> None:
    for rule in ("all", "staying"):
        out = tmp_path / rule
        args = ["auction-study", *SMALL, "--buy-fraction", rule, "--json", "--out", str(out)]
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 0, result.output
        payload = json.loads(result.stdout)
        assert payload["buy_fraction"] == rule
        summary = json.loads((out / "summary.json").read_text())
        assert summary["config"]["buy_fraction"] == rule


def test_a_bad_rule_exits_2_naming_the_option(tmp_path) -> None:
    args = ["comparison", "--buy-fraction", "buyers", "--json", "--out", str(tmp_path)]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 2
    assert "--buy-fraction" in result.stderr and "'buyers'" in result.stderr
    assert json.loads(result.stdout)["errors"][0]["option"] == "--buy-fraction"


def test_srd_comparison_prints_one_json_object_with_every_configuration(tmp_path) -> None:
    out = tmp_path / "cmp"
    args = ["comparison", *SMALL, "--seed", "3", "--buy-fraction", "staying"]
    result = CliRunner().invoke(cli, [*args, "--json", "--out", str(out)])
    assert result.exit_code == 0, result.output
    (line,) = result.stdout.strip().splitlines()
    payload = json.loads(line)
    assert payload["out_dir"] == str(out) and payload["buy_fraction"] == "staying"
    assert list(payload["configurations"]) == [
        "honest",
        "honest+screened",
        "compromised",
        "compromised+screened",
        "honest-alone",
    ]
    assert len(payload["rows"]) == 10 and len(payload["caption"].splitlines()) == 5
    again = CliRunner().invoke(cli, [*args, "--json", "--out", str(tmp_path / "again")])
    same = json.loads(again.stdout)
    assert same["rows"] == payload["rows"]  # --seed: same seed, same numbers
    assert {p.name for p in out.iterdir()} >= {"comparison.png", "comparison.csv", "result.json"}


def test_srd_comparison_prints_the_table_for_a_person(tmp_path) -> None:
    result = CliRunner().invoke(cli, ["comparison", *SMALL, "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    text = result.stdout
    assert "srd comparison" in text and f"artifacts: {tmp_path}" in text
    assert text.count("honest-alone") == 3 and "mean price" in text  # rows, caption


@pytest.mark.parametrize("kind", ["auction-study", "comparison"])
def test_job_params_take_the_rule_and_refuse_others_by_name(kind) -> None:
    assert build_config(kind, {"buy_fraction": "staying"}).buy_fraction == "staying"
    assert build_config(kind, {}).buy_fraction == "all"
    with pytest.raises(ConfigError) as caught:
        build_config(kind, {"buy_fraction": "buyers"})
    assert [e["field"] for e in caught.value.errors] == ["buy_fraction"]


def test_the_reference_market_options_reach_every_auction(tmp_path) -> None:
    """The reference's --base_price, --min_buy_price, --threshold_sell_price, --increment and
    --decrement: a market at twice the prices sells at twice the prices."""
    prices = {}
    dear = ["--base-price", "10", "--min-buy-price", "9.6", "--threshold-sell-price", "9.6"]
    dear += ["--increment", "0.1", "--decrement", "0.02"]
    for name, extra in {"default": [], "dear": dear}.items():
        out = tmp_path / name
        args = ["auction-study", *SMALL, *extra, "--json", "--out", str(out)]
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 0, result.output
        prices[name] = [row["mean_price"] for row in json.loads(result.stdout)["rows"]]
        config = json.loads((out / "summary.json").read_text())["config"]
    assert config["base_price"] == 10 and config["decrement"] == 0.02
    assert all(4.8 <= p <= 5.5 for p in prices["default"]), prices
    assert all(9.6 <= p <= 11 for p in prices["dear"]), prices


@pytest.mark.parametrize("kind", ["auction-study", "comparison"])
def test_market_options_that_contradict_each_other_are_refused_by_name(kind, tmp_path) -> None:
    params = {"base_price": 5.0, "min_buy_price": 6.0, "increment": 0.04, "decrement": 0.01}
    with pytest.raises(ConfigError) as caught:
        build_config(kind, params)
    assert [e["field"] for e in caught.value.errors] == ["min_buy_price", "increment"]
    args = [kind, "--min-buy-price", "6", "--json", "--out", str(tmp_path)]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 2 and "--min-buy-price: 6 is above base_price 5" in result.stderr
    # A decrement sent as increment / 5 whose five times lands an ulp above the increment is at
    # the bound, not past it (schemathesis found 352.83365215531643 and 70.56673043106329).
    increment = 352.83365215531643
    assert 5 * (increment / 5) > increment
    at_bound = {"base_price": 800.0, "increment": increment, "decrement": increment / 5}
    assert build_config(kind, at_bound).decrement == increment / 5


def test_a_supply_with_no_fish_on_sale_runs_as_the_reference_runs_it(tmp_path) -> None:
    """0.1 of 8 patrons is int(0.8) = 0 fish: the default supplies with a few patrons still give
    one row each; the empty one says so (its auctions stop at once, sold out)."""
    args = ["auction-study", "--trials", "1", "--patrons", "8", "--json", "--out", str(tmp_path)]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    rows = json.loads(result.stdout)["rows"]
    assert [row["rarity"] for row in rows] == [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9]
    empty = rows[0]
    assert empty["n_fish"] == 0 and empty["buyer_fraction"] == 0
    assert empty["purchase_rate"] is None and empty["mean_price"] is None
    assert all(row["n_fish"] > 0 and row["purchase_rate"] is not None for row in rows[1:])
    assert build_config("comparison", {"rarities": [1e-300], "patrons": 8}).rarities == (1e-300,)


@pytest.mark.parametrize(
    ("kind", "params", "field", "words"),
    [
        ("auction-study", {"grid": True, "saboteurs": 0}, "saboteurs", "give a share above 0"),
        ("auction-study", {"freeze_pfc": True}, "freeze_pfc", "without fine-tune nothing"),
        ("comparison", {"fine_tune_rounds": 9}, "fine_tune_rounds", "without fine-tune nothing"),
        (
            "auction-study",
            {"fine_tune": True, "fine_tune_rounds": 0},
            "fine_tune_rounds",
            "0 rounds",
        ),
        ("lavaland", {"train_maps": 0, "lr": 0.5}, "lr", "with train-maps 0 nothing is trained"),
        ("fish", {"srd": False, "lr": 0.5}, "lr", "with srd off nothing is trained"),
        ("fish", {"srd": False, "memory": 4}, "memory", "with srd off nothing is trained"),
    ],
)
def test_an_option_that_would_change_nothing_is_refused_when_given(kind, params, field, words):
    # given, not echoed as if it had mattered (a job's params are stored whole, every field
    # with its value, and read back without this check)
    with pytest.raises(ConfigError) as refused:
        build_config(kind, params)
    (error,) = refused.value.errors
    assert error["field"] == field and words in error["message"]
    # the same run without it, stored whole as a job stores it, reads back as that run
    config = build_config(kind, {k: v for k, v in params.items() if k != field})
    assert build_config(kind, config_dict(config), stored=True) == config


def test_a_stored_job_config_names_every_field_and_reads_back_unchecked() -> None:
    # a default study stored whole holds fine_tune_rounds and freeze_pfc without fine-tuning:
    # as given they would be refused; a job's worker reads them back as stored
    config = build_config("auction-study", {})
    with pytest.raises(ConfigError) as refused:
        build_config("auction-study", config_dict(config))
    assert {e["field"] for e in refused.value.errors} == {"fine_tune_rounds", "freeze_pfc"}
    assert build_config("auction-study", config_dict(config), stored=True) == config


def test_the_command_line_names_only_the_options_it_was_given(tmp_path) -> None:
    # the default's own value, typed: refused as given; left out: the same run, accepted
    typed = CliRunner().invoke(cli, ["cheetah", "--nominal", "--trials", "7", "--json"])
    assert typed.exit_code == 2 and "--trials" in json.loads(typed.stdout)["error"]
    args = ["auction-study", *SMALL, "--grid", "--json", "--out", str(tmp_path / "grid")]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert {row["saboteurs"] for row in json.loads(result.stdout)["rows"]} == {0.0, 0.5}


@pytest.mark.parametrize("kind", ["auction-study", "comparison"])
def test_two_supplies_closer_than_a_millionth_are_one_supply_given_twice(kind) -> None:
    # an auction's random streams are keyed by its supply in millionths: two supplies closer
    # than that would play the very same auctions as two "independent" rows
    with pytest.raises(ConfigError) as refused:
        build_config(kind, {"rarities": "0.1,0.1000004"})
    (error,) = refused.value.errors
    assert error["field"] == "rarities"
    assert error["message"].startswith("0.1 and 0.1000004 are one supply")
    assert build_config(kind, {"rarities": "0.1,0.100001"}).rarities == (0.1, 0.100001)
