"""What a log says: the plant's frequency response and its fit (identification), and a session's summary metrics.

``identify_log`` and ``fit_plant`` are ``hil ident``'s (docs/ident.md); ``summarize_log`` computes the metrics
every session ends with (rate error, miss distance, drive ripple, board latency; docs/api.md)."""

from hil.analysis._ident import (
    GYRO_CHANNEL,
    Frf,
    PlantFit,
    SweepShapes,
    SweptSine,
    bode_plot,
    estimate_frf,
    estimate_sweep_frf,
    fit_caption,
    fit_plant,
    identify_log,
    plant_response,
    sweep_start,
    welch_layout,
    welch_options,
)
from hil.analysis._summary import NO_BOARD_LATENCY, board_latency, drive_ripple, json_safe, summarize_log

__all__ = [
    "GYRO_CHANNEL",
    "NO_BOARD_LATENCY",
    "Frf",
    "PlantFit",
    "SweepShapes",
    "SweptSine",
    "board_latency",
    "bode_plot",
    "drive_ripple",
    "estimate_frf",
    "estimate_sweep_frf",
    "fit_caption",
    "fit_plant",
    "identify_log",
    "json_safe",
    "plant_response",
    "summarize_log",
    "sweep_start",
    "welch_layout",
    "welch_options",
]
