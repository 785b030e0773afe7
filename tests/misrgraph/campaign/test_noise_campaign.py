"""A campaign that learns its noise levels on its first passes: the learned file against ``noise
fit`` run on the same pass, and the other passes adjusted with exactly those levels."""

from __future__ import annotations

import json

import pytest

from misrgraph.campaign.plan import CampaignConfig, plan_campaign
from misrgraph.errors import InputError


def _levels_used(result) -> dict:
    from misrgraph.io.h5 import open_h5

    with open_h5(result, "adjustment_result") as f:
        return json.loads(f.attrs["summary_json"])["noise_levels"]


def _same(used: dict, fields: dict) -> bool:
    """The levels a result says it was adjusted with equal a model's graph fields (as JSON)."""
    return {k: used[k] for k in fields} == json.loads(json.dumps(fields))


def test_the_first_passes_teach_the_levels_the_others_use(tmp_path) -> None:
    from misrgraph.campaign.run import run_campaign
    from misrgraph.io.noise import read_noise_model
    from misrgraph.model.noise import NoiseModel
    from misrgraph.runs.noise import run_noise_fit

    cfg = CampaignConfig(paths=(37,), months=1.0, size="reduced", products=False, noise_fit_passes=1)
    plan = plan_campaign(cfg)
    assert plan.fit_pass_ids() == [plan.paths[0].pass_ids[0]] and plan.n_passes == 2
    s = run_campaign(tmp_path / "c", cfg, workers=0)
    assert s["passes"]["failed"] == 0 and s["noise_fit"]["status"] == "done"
    fit_id, other_id = plan.paths[0].pass_ids
    results = {p: next((tmp_path / "c" / "adjusted" / "path_037").glob(f"{p}-*.h5")) for p in (fit_id, other_id)}
    learned, source = read_noise_model(s["noise_fit"]["file"])
    # the same fit by the command a user runs, on the fit pass's result
    again = run_noise_fit([results[fit_id]], out=tmp_path / "again.json")
    assert read_noise_model(tmp_path / "again.json")[0] == learned
    assert again["levels"].keys() == s["noise_fit"]["levels"].keys()
    assert "observations" in [k for k, v in source.items() if v == "learned"]
    # the fit pass was adjusted with the pre-flight levels, the other with the learned ones
    assert _same(_levels_used(results[fit_id]), NoiseModel().graph_fields())
    assert _same(_levels_used(results[other_id]), learned.graph_fields())
    assert learned != NoiseModel()
    assert "Noise levels learned" in (tmp_path / "c" / "report" / "campaign.md").read_text()


def test_the_fit_must_leave_passes_to_use_it(tmp_path) -> None:
    from misrgraph.campaign.run import run_campaign

    cfg = CampaignConfig(paths=(37,), months=1.0, size="reduced", products=False, noise_fit_passes=2)
    with pytest.raises(InputError, match="fewer than the 2 planned passes"):
        run_campaign(tmp_path / "c", cfg, workers=0)
    with pytest.raises(InputError, match="noise_fit_passes"):
        CampaignConfig(noise_fit_passes=-1)
