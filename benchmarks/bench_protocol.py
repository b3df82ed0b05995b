#!/usr/bin/env python3
"""Protocol codec throughput: hil.protocol against pymavlink's pure-Python MAVLink 2 parser.

Run from the repository root (results and targets: docs/performance.md)::

    .venv/bin/python benchmarks/bench_protocol.py [--frames 200000] [--chunk 4096] [--repeat 5] [--json PATH]

What it does, for each codec in the same process:

- builds N frames of similar size carrying varying values: our GYRO_SAMPLE (28-byte payload,
  39-byte frame) and MAVLink 2 ATTITUDE (28-byte payload, 40-byte frame, unsigned);
- times encoding them (message object construction included) and decoding their concatenated
  stream fed in chunks of --chunk bytes to a fresh decoder, --repeat times, codecs interleaved,
  with the garbage collector off while the clock runs (as ``timeit`` does);
- checks every decoded message against what was encoded, and that no decoder saw an error.

pymavlink: its parser (``MAVLink.parse_buffer`` -> ``parse_char`` -> ``decode``) is Python; the
only native code on that path is the CRC, computed by the ``fastcrc`` Rust extension when it is
importable. The benchmark reports what it found, compares against that default configuration
(the faster, stricter baseline) and adds a row with the module's own pure-Python CRC patched in.

Exit status is 1 only on a correctness failure (a frame count or value mismatch, a decoder
error); speed targets are documented in docs/performance.md, never asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib.metadata
import importlib.util
import inspect
import json
import math
import os
import platform
import random
import shlex
import statistics
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from hil.protocol import Board, Decoder, Encoder, GyroSample

DECODE_TARGET_FPS = 250_000  # docs/performance.md, "Protocol codec (issue 2)"
DECODE_RATIO_TARGET = 3.0  # ours / pymavlink's Python parser, same run
MB = 1e6

Values = tuple[int, int, float, float, float, float, float]


# ---------------------------------------------------------------- test data


def make_values(n: int, seed: int = 2) -> list[Values]:
    """N varying gyro samples at 1 kHz: (t_us, tick, rate x/y/z deg/s, az deg, el deg), 1e-6 resolution."""
    rng = random.Random(seed)
    out: list[Values] = []
    t0 = 4_294_000_000  # near the u32 wrap, so t_us wraps inside a long run
    for i in range(n):
        out.append(
            (
                (t0 + 1000 * i) & 0xFFFFFFFF,
                i & 0xFFFFFFFF,
                round(rng.uniform(-2000.0, 2000.0), 6),
                round(rng.uniform(-2000.0, 2000.0), 6),
                round(rng.uniform(-2000.0, 2000.0), 6),
                round(rng.uniform(-180.0, 180.0), 6),
                round(rng.uniform(-30.0, 90.0), 6),
            )
        )
    return out


def to_attitude(v: Values) -> tuple[int, float, float, float, float, float, float]:
    """The same sample as MAVLink ATTITUDE fields: time_boot_ms, roll, pitch, yaw (rad), roll/pitch/yaw speed (rad/s).

    roll takes el, pitch a value derived from the tick, yaw az; the speeds are the three rates. yawspeed is kept
    non-zero so MAVLink 2's trailing-zero payload truncation never shortens a frame (every frame is 40 bytes).
    """
    t_us, tick, rx, ry, rz, az, el = v
    r = math.radians
    yawspeed = r(rz) or 1e-3
    return (t_us // 1000, r(el), r((tick % 3600) / 10 - 180), r(az), r(rx), r(ry), yawspeed)


def split(stream: bytes, chunk: int) -> list[bytes]:
    return [stream[i : i + chunk] for i in range(0, len(stream), chunk)]


# ---------------------------------------------------------------- codecs


@dataclass
class Codec:
    key: str
    label: str
    frame_bytes: int
    encode: Callable[[list[Any]], list[bytes]]
    decode: Callable[[list[bytes]], tuple[list[Any], Any]]
    check: Callable[[list[Any], Any, list[Any]], list[str]]  # (decoded, decoder, inputs) -> problems
    inputs: list[Any]
    context: Callable[[], contextlib.AbstractContextManager[Any]] = contextlib.nullcontext


def hil_encode(values: list[Values]) -> list[bytes]:
    enc = Encoder(Board.SERVO)
    encode = enc.encode
    host = Board.HOST
    return [encode(GyroSample(*v), host) for v in values]


def hil_decode(chunks: list[bytes]) -> tuple[list[Any], Decoder]:
    dec = Decoder()
    feed = dec.feed
    out: list[Any] = []
    for c in chunks:
        out += feed(c)
    return out, dec


def hil_check(frames: list[Any], dec: Decoder, values: list[Values]) -> list[str]:
    c = dec.counters
    problems = []
    if len(frames) != len(values) or c.frames_ok != len(values):
        problems.append(f"hil: decoded {len(frames)} frames (frames_ok {c.frames_ok}), expected {len(values)}")
    if c.errors() or c.bytes_discarded or c.resyncs or dec.pending:
        problems.append(f"hil: decoder errors {c.as_dict()}, pending {dec.pending}")
    for i, (f, v) in enumerate(zip(frames, values, strict=False)):
        m = f.message
        if (
            not isinstance(m, GyroSample)
            or f.src != Board.SERVO
            or f.dst != Board.HOST
            or f.seq != i & 0xFFFF
            or m[:2] != v[:2]
            or any(abs(a - b) > 1e-6 for a, b in zip(m[2:], v[2:], strict=True))
        ):
            problems.append(f"hil: frame {i} decoded as {f!r}, sent {v!r}")
            break
    return problems


def pymavlink_codecs(values: list[Values]) -> tuple[list[Codec], dict[str, Any]]:
    from pymavlink.dialects.v20 import common  # here, not at the top: pymavlink is a test extra

    findings = pymavlink_findings(common)
    att = [to_attitude(v) for v in values]

    def encode(rows: list[Any]) -> list[bytes]:
        mav = common.MAVLink(None, srcSystem=1, srcComponent=1)
        attitude_encode = mav.attitude_encode
        frames = []
        for a in rows:
            frames.append(attitude_encode(*a).pack(mav))
            mav.seq = (mav.seq + 1) & 0xFF  # what MAVLink.send() does after packing
        return frames

    def decode(chunks: list[bytes]) -> tuple[list[Any], Any]:
        mav = common.MAVLink(None)
        parse = mav.parse_buffer
        out: list[Any] = []
        for c in chunks:
            msgs = parse(c)  # None, not [], when the chunk completed no message
            if msgs:
                out += msgs
        return out, mav

    def check(msgs: list[Any], mav: Any, rows: list[Any]) -> list[str]:
        problems = []
        if len(msgs) != len(rows) or mav.total_packets_received != len(rows):
            problems.append(f"pymavlink: parsed {len(msgs)} messages, expected {len(rows)}")
        if mav.total_receive_errors or mav.buf_len():
            problems.append(f"pymavlink: receive errors {mav.total_receive_errors}, {mav.buf_len()} bytes left over")
        names = ("time_boot_ms", "roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed")
        for i, (m, a) in enumerate(zip(msgs, rows, strict=False)):
            got = tuple(getattr(m, k, None) for k in names)
            if (
                m.get_type() != "ATTITUDE"
                or len(m.get_msgbuf()) != 40
                or m.get_seq() != i & 0xFF
                or got[0] != a[0]
                or any(not math.isclose(x, y, rel_tol=1e-6, abs_tol=1e-30) for x, y in zip(got[1:], a[1:], strict=True))
            ):
                problems.append(f"pymavlink: message {i} parsed as {m}, sent {a!r}")
                break
        return problems

    @contextlib.contextmanager
    def python_crc() -> Iterator[None]:
        """Patch the dialect's own pure-Python CRC in for fastcrc (encode and decode look x25crc up per call)."""
        saved = common.x25crc
        common.x25crc = common._x25crc_slow
        try:
            yield
        finally:
            common.x25crc = saved

    crc_name = "fastcrc" if common.mcrf4xx is not None else "Python CRC"
    codecs = [
        Codec("pymavlink", f"pymavlink ATTITUDE ({crc_name})", 40, encode, decode, check, att),
    ]
    if common.mcrf4xx is not None:
        codecs.append(
            Codec("pymavlink_pycrc", "pymavlink ATTITUDE (Python CRC)", 40, encode, decode, check, att, python_crc)
        )
    return codecs, findings


def pymavlink_findings(common: Any) -> dict[str, Any]:
    """How this pymavlink could use native code, and what the benchmark does about each way."""
    pkg = Path(common.__file__).resolve().parents[2]
    notes: list[str] = []
    version = importlib.metadata.version("pymavlink")
    notes.append(
        f"pymavlink {version}: {Path(common.__file__).name} is generated Python source; "
        "MAVLink.parse_buffer -> parse_char -> decode run as Python, one parse_char call per message"
    )
    if common.mcrf4xx is not None:
        notes.append(
            f"CRC: x25crc = {common.x25crc.__name__}, i.e. fastcrc {importlib.metadata.version('fastcrc')} "
            "(compiled Rust extension, a hard dependency of pymavlink); the 'Python CRC' row patches in the "
            "dialect's own _x25crc_slow to show the parser with no native code at all"
        )
    else:
        notes.append("CRC: fastcrc is not importable, so x25crc is the pure-Python _x25crc_slow")
    if importlib.util.find_spec("pymavlink.mavnative") is None:
        notes.append("mavnative (the old C parser) is not shipped")
    else:
        notes.append("mavnative IS present, but this benchmark never passes use_native=True")
    init_src = inspect.getsource(common.MAVLink.__init__)
    if init_src.count("use_native") == 1:
        notes.append("MAVLink(use_native=...) is accepted and ignored (the parameter is never read)")
    ext = sorted(str(p.relative_to(pkg)) for p in pkg.rglob("*") if p.suffix in (".so", ".pyd"))
    only_dfindexer = bool(ext) and all("dfindexer" in e for e in ext)
    notes.append(
        "compiled modules in the package: "
        + (", ".join(ext) if ext else "none")
        + (" (DataFlash log indexer, not on the MAVLink parse path)" if only_dfindexer else "")
    )
    env = {k: os.environ.get(k) for k in ("MAVLINK20", "MAVLINK_DIALECT", "MAV_IGNORE_CRC")}
    notes.append(
        "env MAVLINK20={MAVLINK20!r}, MAVLINK_DIALECT={MAVLINK_DIALECT!r}: read only by pymavlink.mavutil, which is "
        "not imported here (pymavlink.dialects.v20.common is used directly, so MAVLink 2 regardless)".format(**env)
    )
    notes.append(
        f"env MAV_IGNORE_CRC={env['MAV_IGNORE_CRC']!r}: read when the dialect is imported; when set, decode accepts "
        "bad CRCs (it still computes them); forced off for this run"
    )
    common.MAVLINK_IGNORE_CRC = 0
    mavutil_loaded = "pymavlink.mavutil" in sys.modules
    return {"version": version, "env": env, "mavutil_imported": mavutil_loaded, "notes": notes}


# ---------------------------------------------------------------- timing


def timed(fn: Callable[..., Any], *args: Any) -> tuple[float, Any]:
    gc.collect()
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        t0 = time.perf_counter()
        result = fn(*args)
        dt = time.perf_counter() - t0
    finally:
        if was_enabled:
            gc.enable()
    return dt, result


def rates(times: list[float], n: int, nbytes: int) -> dict[str, Any]:
    best, median = min(times), statistics.median(times)
    return {
        "seconds": [round(t, 6) for t in times],
        "fps_best": n / best,
        "fps_median": n / median,
        "mbps_best": nbytes / best / MB,
        "mbps_median": nbytes / median / MB,
    }


def run(codecs: list[Codec], n: int, chunk: int, repeat: int) -> tuple[dict[str, dict[str, Any]], list[str]]:
    enc_times: dict[str, list[float]] = {c.key: [] for c in codecs}
    dec_times: dict[str, list[float]] = {c.key: [] for c in codecs}
    results: dict[str, dict[str, Any]] = {}
    problems: list[str] = []
    for r in range(repeat):
        for c in codecs:  # interleaved, so drift on a shared machine hits every codec alike
            with c.context():
                dt, frames = timed(c.encode, c.inputs)
                enc_times[c.key].append(dt)
                stream = b"".join(frames)
                chunks = split(stream, chunk)
                del frames
                dt, (decoded, decoder) = timed(c.decode, chunks)
                dec_times[c.key].append(dt)
            if r == 0:
                if len(stream) != n * c.frame_bytes:
                    problems.append(f"{c.key}: stream is {len(stream)} bytes, expected {n} x {c.frame_bytes}")
                problems += c.check(decoded, decoder, c.inputs)
                results[c.key] = {
                    "label": c.label,
                    "frame_bytes": len(stream) // n,
                    "frames": n,
                    "frames_decoded": len(decoded),
                    "stream_bytes": len(stream),
                }
            elif len(decoded) != n:
                problems.append(f"{c.key}: repeat {r} decoded {len(decoded)} of {n}")
            del decoded, decoder, chunks
    for c in codecs:
        nbytes = results[c.key]["stream_bytes"]
        results[c.key]["encode"] = rates(enc_times[c.key], n, nbytes)
        results[c.key]["decode"] = rates(dec_times[c.key], n, nbytes)
    return results, problems


# ---------------------------------------------------------------- report


def fmt_rate(x: float) -> str:
    return f"{x / 1000:,.0f}k"


def table(results: dict[str, dict[str, Any]]) -> str:
    ours = results["hil"]["decode"]
    head = (
        f"{'codec':34} {'frame B':>7} {'encode f/s':>17} {'encode MB/s':>11} "
        f"{'decode f/s':>17} {'decode MB/s':>11} {'decode ours/this':>17}"
    )
    lines = [
        head,
        f"{'':34} {'':>7} {'best / median':>17} {'best':>11} {'best / median':>17} {'best':>11} {'best / median':>17}",
        "-" * len(head),
    ]
    for key, r in results.items():
        e, d = r["encode"], r["decode"]
        ratio = (
            "-"
            if key == "hil"
            else f"{ours['fps_best'] / d['fps_best']:.2f}x / {ours['fps_median'] / d['fps_median']:.2f}x"
        )
        lines.append(
            f"{r['label']:34} {r['frame_bytes']:>7} "
            f"{fmt_rate(e['fps_best']) + ' / ' + fmt_rate(e['fps_median']):>17} {e['mbps_best']:>11.2f} "
            f"{fmt_rate(d['fps_best']) + ' / ' + fmt_rate(d['fps_median']):>17} {d['mbps_best']:>11.2f} {ratio:>17}"
        )
    return "\n".join(lines)


def targets(results: dict[str, dict[str, Any]]) -> dict[str, Any]:
    ours = results["hil"]["decode"]
    ref = results["pymavlink"]["decode"]
    out: dict[str, Any] = {}
    for stat in ("best", "median"):
        fps = ours[f"fps_{stat}"]
        ratio = fps / ref[f"fps_{stat}"]
        out[stat] = {
            "decode_fps": fps,
            "decode_fps_met": fps >= DECODE_TARGET_FPS,
            "ratio_vs_pymavlink": ratio,
            "ratio_met": ratio >= DECODE_RATIO_TARGET,
        }
    return out


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=200_000, help="frames per codec (default 200000)")
    p.add_argument("--chunk", type=int, default=4096, help="bytes per decoder feed (default 4096)")
    p.add_argument("--repeat", type=int, default=5, help="timed runs per codec; best and median reported (default 5)")
    p.add_argument("--json", type=Path, metavar="PATH", help="also write the results as JSON to PATH")
    p.add_argument("--no-python-crc", action="store_true", help="skip the pymavlink row with the pure-Python CRC")
    a = p.parse_args(list(argv))
    if a.frames < 1 or a.chunk < 1 or a.repeat < 1:
        p.error("--frames, --chunk and --repeat must be >= 1")
    return a


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; return the results (``result["ok"]`` is False on a correctness failure)."""
    args_list = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(args_list)
    here = Path(__file__)
    with contextlib.suppress(ValueError):
        here = here.resolve().relative_to(Path.cwd())
    command = shlex.join([os.path.relpath(sys.executable), str(here), *args_list])
    cpus = os.cpu_count()
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else cpus
    print(f"command : {command}")
    print(f"python  : {sys.version.split()[0]} ({platform.python_implementation()}, {sys.executable})")
    print(f"platform: {platform.platform()}, {cpus} CPUs ({affinity} usable)")
    print(
        f"run     : {args.frames} frames per codec, {args.chunk}-byte chunks, {args.repeat} repeats, GC off while timed"
    )

    values = make_values(args.frames)
    codecs = [Codec("hil", "hil.protocol GYRO_SAMPLE", 39, hil_encode, hil_decode, hil_check, values)]
    mav_codecs, findings = pymavlink_codecs(values)
    if args.no_python_crc:
        mav_codecs = [c for c in mav_codecs if c.key != "pymavlink_pycrc"]
    codecs += mav_codecs

    print("pymavlink:")
    for note in findings["notes"]:
        print(f"  - {note}")

    results, problems = run(codecs, args.frames, args.chunk, args.repeat)
    tg = targets(results)

    print()
    print(table(results))
    print()
    for stat in ("best", "median"):
        t = tg[stat]
        print(
            f"targets ({stat:6}): decode {t['decode_fps']:,.0f} frames/s >= {DECODE_TARGET_FPS:,}: "
            f"{'met' if t['decode_fps_met'] else 'NOT met'}; "
            f"{t['ratio_vs_pymavlink']:.2f}x pymavlink >= {DECODE_RATIO_TARGET:g}x: "
            f"{'met' if t['ratio_met'] else 'NOT met'}"
        )
    if problems:
        print("\nCORRECTNESS FAILURES:")
        for prob in problems:
            print(f"  - {prob}")
    else:
        print(f"correctness: every codec decoded all {args.frames} frames, values match, no decoder errors")

    result: dict[str, Any] = {
        "benchmark": "protocol codec",
        "command": command,
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "python": sys.version.split()[0],
        "implementation": platform.python_implementation(),
        "platform": platform.platform(),
        "cpu_count": cpus,
        "cpus_usable": affinity,
        "frames": args.frames,
        "chunk": args.chunk,
        "repeat": args.repeat,
        "codecs": results,
        "pymavlink": findings,
        "targets": {"decode_fps": DECODE_TARGET_FPS, "ratio_vs_pymavlink": DECODE_RATIO_TARGET, **tg},
        "ok": not problems,
        "problems": problems,
    }
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {args.json}")
    return result


if __name__ == "__main__":
    sys.exit(0 if main()["ok"] else 1)
