"""Replays: a session log through another controller offline (``replay_log``), and a capture played back at a
board or the emulator byte for byte at its recorded times (``replay_capture``, ``play_capture``; docs/capture.md)."""

from hil.replay._controller import ReplayError, ReplayResult, replay_log, write_outputs, xcorr_lag
from hil.replay._playback import (
    FIRST_SAMPLE_WAIT_S,
    SAMPLE_TIMES_KEPT,
    CapturePlayer,
    PlaybackResult,
    Quantiles,
    play_capture,
)
from hil.replay._replay_capture import emulator_settings, replay_capture, resolve_ports, write_playback_json

__all__ = [
    "FIRST_SAMPLE_WAIT_S",
    "SAMPLE_TIMES_KEPT",
    "CapturePlayer",
    "PlaybackResult",
    "Quantiles",
    "ReplayError",
    "ReplayResult",
    "emulator_settings",
    "play_capture",
    "replay_capture",
    "replay_log",
    "resolve_ports",
    "write_outputs",
    "write_playback_json",
    "xcorr_lag",
]
