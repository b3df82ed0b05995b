"""hil.api's entries: every name it lists resolves, every function is typed, the experiments load on first use, and
the small entries that do what the command line used to do itself (hex text, a frame as JSON, the emulator's
command) keep its behaviour."""

from __future__ import annotations

import inspect
import json
import subprocess
import sys
from pathlib import Path

import pytest

from hil import api

REPO = Path(__file__).resolve().parents[2]


def test_every_listed_name_resolves_and_every_entry_is_typed() -> None:
    untyped = []
    for name in api.__all__:
        value = getattr(api, name)
        if not inspect.isfunction(value) or value.__module__ != api.__name__:  # a re-exported name is typed below
            continue
        signature = inspect.signature(value)
        missing = [p for p, param in signature.parameters.items() if param.annotation in (inspect.Parameter.empty,
                                                                                            "Any")]
        if missing or signature.return_annotation in (inspect.Signature.empty, "Any"):
            untyped.append(f"{name}: {signature}")
    assert untyped == []


def test_the_experiments_load_on_first_use() -> None:
    code = ("import json, sys\nimport hil.api\n"
            "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[:2] in (['hil', 'campaign'], "
            "['hil', 'fit'], ['hil', 'tune'], ['hil', 'replay']))))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO,
                         check=True)
    assert json.loads(run.stdout.strip().splitlines()[-1]) == []
    assert api.FitInputError.__module__.startswith("hil.fit")  # and come when asked for
    assert issubclass(api.CampaignInterrupted, KeyboardInterrupt)
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        api.nothing  # noqa: B018


def test_hex_text_is_read_block_by_block_and_bad_text_names_its_source() -> None:
    assert b"".join(api.hex_bytes([b"aa 5", b"5:0", b"1\n"], "the text")) == bytes.fromhex("aa5501")
    with pytest.raises(ValueError, match=r"^the text: not hex text: 'x' at byte 4$"):
        list(api.hex_bytes([b"aa", b" 5x"], "the text"))
    with pytest.raises(ValueError, match=r"^the text: not hex text: an odd number of hex digits$"):
        list(api.hex_bytes([b"aa5"], "the text"))


def test_a_decoded_frame_as_json_values() -> None:
    from hil.protocol import Board, Ident, encode_frame

    message = Ident(board=Board.SERVO, protocol_version=1, firmware_version="1.4.2", catalogue_fingerprint=0,
                    serial_number=5)
    frames = api.Decoder().feed(encode_frame(message, src=0x10, dst=0x01, seq=7))
    assert len(frames) == 1
    shown = api.frame_json(frames[0])
    assert shown["message"] == "IDENT" and (shown["src"], shown["dst"], shown["seq"]) == (0x10, 0x01, 7)
    assert shown["fields"]["board"] == "SERVO" and shown["fields"]["firmware_version"] == "1.4.2"
    json.dumps(shown)


def test_the_emulator_command_passes_on_what_is_given() -> None:
    assert api.emulator_command() == [sys.executable, "-m", "firmware_stub"]
    assert api.emulator_command(clock="lockstep", seed=3, seconds=1.5)[3:] == ["--clock", "lockstep", "--seed", "3",
                                                                              "--seconds", "1.5"]
