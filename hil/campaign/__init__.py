"""Swing campaigns: a matrix of profiles x controllers x seeds, run as sessions, judged, reported."""

from hil.campaign._faced import CampaignRun, load_campaign_file, prepare_campaign, report_campaign, run_and_report
from hil.campaign.metrics import METRICS, Metric, compute_metrics
from hil.campaign.model import CampaignConfig, CampaignResult, CellResult, RuleResult
from hil.campaign.runner import CampaignError, cell_session, load_campaign, load_results, run_campaign

__all__ = ["METRICS", "CampaignConfig", "CampaignError", "CampaignResult", "CampaignRun", "CellResult", "Metric",
           "RuleResult", "cell_session", "compute_metrics", "load_campaign", "load_campaign_file", "load_results",
           "prepare_campaign", "report_campaign", "run_and_report", "run_campaign"]
