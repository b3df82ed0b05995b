"""A stand-in bench for the host-death test, run as its own process (the test SIGKILLs it):

    python -m tests.firmware_stub.alive_host PORTS_JSON SENT_LOG

Identifies every board, enables the driver, turns tracking on, loads and starts a 120 s hexapod swing,
starts the stream, then serves until killed: DRIVE_CMD for every GYRO_SAMPLE, HOST_ALIVE every 100 ms
on the servo, image and hexapod links. Prints "ready" once 300 samples have been answered. Before each
frame it sends, appends "<link> <time.time()>" to SENT_LOG (flushed), so the test knows a moment no
later than the last frame each board heard.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import IO, Any

from hil.protocol import (
    Ack,
    AxisMask,
    DriveCmd,
    DriveEnable,
    GyroSample,
    HexapodStart,
    HexAxis,
    HostAlive,
    Ident,
    IdentRequest,
    ServoMode,
    StreamMode,
    TrackCmd,
    TrackMode,
)
from hil.protocol.swing import Segment, segments_to_messages
from tests.firmware_stub.host import Host

ALIVE_PERIOD_S = 0.1
QUIET_LINKS = ("servo", "image", "hexapod")
SWING = Segment(HexAxis.PITCH, 0.0, 120.0, 1.0, 1.0, 0.0, 0.2)


def main(ports_file: Path, sent_log: Path) -> None:
    host = Host(json.loads(ports_file.read_text()))
    log: IO[str] = sent_log.open("w")

    def note(link: str) -> None:
        log.write(f"{link} {time.time():.6f}\n")
        log.flush()

    def send(link: str, message: Any) -> None:
        note(link)
        host[link].send(message)

    def command(link: str, message: Any) -> None:
        note(link)
        reply = host.request(link, message)
        if not isinstance(reply, Ack):
            raise SystemExit(f"{link}: {message!r} refused: {reply!r}")

    for link in ("servo", "driver", "image", "hexapod"):
        since = len(host[link].frames)
        send(link, IdentRequest())
        host.wait(link, lambda f: isinstance(f.message, Ident), since=since)
    command("driver", DriveEnable(AxisMask.BOTH, True))
    command("image", TrackCmd(TrackMode.TRACK, 0))
    for msg in segments_to_messages([SWING]):
        command("hexapod", msg)
    command("hexapod", HexapodStart())
    command("servo", ServoMode(StreamMode.STREAM))
    servo, seen, answered = host["servo"], len(host["servo"].frames), 0
    t0 = time.monotonic()
    next_alive = t0 + ALIVE_PERIOD_S
    while True:
        host.pump_all(0.002)
        for frame in servo.frames[seen:]:
            if isinstance(frame.message, GyroSample):
                send("driver", DriveCmd(frame.message.tick, 0, 0))
                answered += 1
                if answered == 300:
                    print("ready", flush=True)
        seen = len(servo.frames)
        if time.monotonic() >= next_alive:
            next_alive += ALIVE_PERIOD_S
            for link in QUIET_LINKS:
                send(link, HostAlive(round((time.monotonic() - t0) * 1000)))


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
