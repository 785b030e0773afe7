"""The campaign's plan: repeat passes in the period, the chosen ones, path lists, config checks."""

from __future__ import annotations

import pytest

from misrgraph.campaign.plan import CampaignConfig, choose, digest, parse_paths, plan_campaign
from misrgraph.errors import InputError


def test_six_months_hold_twelve_repeats_of_which_thirty_percent_is_four() -> None:
    # 6 months = 182.6 days: cycles start on days 0, 16, ..., 176 -> 12; 30 % of 12 = 3.6 -> 4
    plan = plan_campaign(CampaignConfig(paths=(37,)))
    (pp,) = plan.paths
    assert pp.available == 12
    assert pp.cycles == (0, 4, 7, 11)  # spread evenly, first and last included
    assert pp.pass_ids == ("P037_O0000", "P037_O0932", "P037_O1631", "P037_O2563")  # orbit 233 k of cycle k


def test_the_fraction_wins_when_it_asks_for_more_than_the_minimum() -> None:
    cfg = CampaignConfig(months=6.0, fraction=0.5, passes_per_path=4)
    assert len(choose(12, cfg)) == 6
    assert len(choose(2, cfg)) == 2  # never more than the period holds
    assert choose(1, cfg) == (0,)


def test_default_paths_are_the_whole_repeat_cycle() -> None:
    plan = plan_campaign(CampaignConfig())
    assert [p.path for p in plan.paths] == list(range(1, 234))
    assert plan.n_passes == 233 * 4


def test_parse_paths() -> None:
    assert parse_paths("37,38") == (37, 38)
    assert parse_paths("30-32, 40") == (30, 31, 32, 40)
    with pytest.raises(InputError, match="--paths"):
        parse_paths("3x")


@pytest.mark.parametrize(
    "field,value",
    [
        ("paths", (0,)),
        ("paths", (37, 37)),
        ("months", 0.0),
        ("fraction", 1.5),
        ("size", "huge"),
        ("passes_per_path", 0),
        ("pp_blocks", 200),
    ],
)
def test_bad_config_names_the_field(field: str, value: object) -> None:
    with pytest.raises(InputError, match=field):
        CampaignConfig.from_dict({field: value})


def test_digest_depends_on_every_part() -> None:
    assert digest({"a": 1}, "x") == digest({"a": 1}, "x")
    assert digest({"a": 1}, "x") != digest({"a": 2}, "x") != digest({"a": 1}, "y")
