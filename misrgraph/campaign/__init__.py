"""The calibration campaign on Dask: a GCP month, hundreds of adjusted passes, products per path,
resumable (see :mod:`misrgraph.campaign.run`)."""

from __future__ import annotations

from misrgraph.campaign.plan import CampaignConfig, CampaignPlan, plan_campaign
from misrgraph.campaign.run import campaign_difference, campaign_fingerprint, run_campaign

__all__ = [
    "CampaignConfig",
    "CampaignPlan",
    "plan_campaign",
    "run_campaign",
    "campaign_fingerprint",
    "campaign_difference",
]
