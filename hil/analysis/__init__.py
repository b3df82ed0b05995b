"""What a log says: the plant's frequency response and its fit (identification), and a session's summary metrics.

``identify_log`` and ``fit_plant`` are ``hil ident``'s (docs/ident.md); ``summarize_log`` computes the metrics
every session ends with (rate error, miss distance, drive ripple, board latency; docs/api.md).

The identification's modules: ``_frf`` (the Welch estimate), ``_plant`` (the model, its fit, the resonance over it),
``_bode`` (the plot), ``_logs`` (a session log's columns, the host's disturbances, the FRF of a logged sweep) and
``_levels`` (the levelling's checks). ``SweptSine`` and ``IDENT_SWEEP`` are ``hil.config``'s (the sweep is a
session's excitation), exported here too."""

from hil.analysis._bode import bode_plot
from hil.analysis._frf import Frf, estimate_frf, estimate_sweep_frf, welch_layout, welch_options
from hil.analysis._levels import (
    REVERSAL_SMOOTH_S,
    LevelCheck,
    check_levels,
    coherent_band,
    level_frequencies,
    next_level,
)
from hil.analysis._logs import GYRO_CHANNEL, axis_columns, host_disturbed, identify_log, log_frf, sweep_start
from hil.analysis._plant import PlantFit, SweepShapes, fit_caption, fit_plant, plant_response, resonance_hz
from hil.analysis._summary import NO_BOARD_LATENCY, board_latency, drive_ripple, json_safe, summarize_log
from hil.config import IDENT_SWEEP, SweptSine

__all__ = [
    "GYRO_CHANNEL",
    "IDENT_SWEEP",
    "NO_BOARD_LATENCY",
    "REVERSAL_SMOOTH_S",
    "Frf",
    "LevelCheck",
    "PlantFit",
    "SweepShapes",
    "SweptSine",
    "axis_columns",
    "board_latency",
    "bode_plot",
    "check_levels",
    "coherent_band",
    "drive_ripple",
    "estimate_frf",
    "estimate_sweep_frf",
    "fit_caption",
    "fit_plant",
    "host_disturbed",
    "identify_log",
    "json_safe",
    "level_frequencies",
    "log_frf",
    "next_level",
    "plant_response",
    "resonance_hz",
    "summarize_log",
    "sweep_start",
    "welch_layout",
    "welch_options",
]
