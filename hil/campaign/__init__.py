"""Swing campaigns: a matrix of profiles x controllers x seeds, run as sessions, judged, reported."""

from hil.campaign.metrics import METRICS, Metric, compute_metrics
from hil.campaign.model import CampaignConfig, CampaignResult, CellResult, RuleResult
from hil.campaign.runner import CampaignError, cell_session, load_campaign, load_results, run_campaign

__all__ = ["METRICS", "CampaignConfig", "CampaignError", "CampaignResult", "CellResult", "Metric", "RuleResult",
           "cell_session", "compute_metrics", "load_campaign", "load_results", "run_campaign"]
