"""``labctl bench link``: bytes per message, time on a 9600-bps line, utilisation of a typical run.

The paper's hosts share one 9600-bps RS-232 line (He et al. 1996, §5.1). For each message type
this reports its encoded size, its size on each transport (serial: COBS + CRC-16 framing; TCP:
2-byte length), the time to clock it over 9600 bps at 10 bits per byte, and, for comparison,
the size of the same fields as JSON. It then sums a typical run's message mix (heartbeats at
``1/heartbeat_s`` both ways, the capture requests, frame notices, a marker pose, standard-view
requests, one ambiguous match and the identity) into per-direction utilisation, and measures
the real carrying time of a message through a pty null modem paced at 9600 bps.

Rows time the codec (encode+decode) against ``json.dumps``/``json.loads`` of the same fields,
and serial framing+deframing.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import time

from ..config.devices import HostLinkConfig
from ..decisions.messages import (
    Ambiguous,
    CaptureRequest,
    Failure,
    FailureCode,
    FrameTaken,
    Heartbeat,
    Hello,
    Identity,
    MarkerPose,
    Message,
    StandardViewRequest,
    Stop,
    decode,
    encode,
)
from ..runtime.transport import SERIAL_OVERHEAD, TCP_HEADER, SerialDeframer, serial_frame, wire_time_s
from ._timing import median_time, row

BAUD = 9600
RUN_S = 30.0  # a typical run to identity at the paper's 4-12 mm/s over a 600 mm field of view


def examples() -> dict[str, Message]:
    """One realistic instance of each message type."""
    return {
        "Hello": Hello("predictor", 31337),
        "Heartbeat": Heartbeat("predictor", 1234, 10234.56),
        "CaptureRequest": CaptureRequest(2, "initial2", 10234.9, (412.5, -120.25, 380.0), (2.9, 0.31, -0.12)),
        "FrameTaken": FrameTaken(2, 10234.9),
        "MarkerPose": MarkerPose(2, (412.5, -120.25, 35.0), (0.0, 0.6, 0.8), False, 3.2),
        "StandardViewRequest": StandardViewRequest(3, 1),
        "Identity": Identity(5, 0.93, 7, (5, 2)),
        "Ambiguous": Ambiguous((5, 2, 6), 2),
        "Failure": Failure(FailureCode.MARKER_LOST, "marker lost in fixed camera for 0.5 s"),
        "Stop": Stop("identity reported"),
    }


def typical_mix(heartbeat_s: float, run_s: float = RUN_S) -> dict[str, dict[str, int]]:
    """Message counts per direction for one run with one ambiguous standard view (two views)."""
    hb = int(run_s / heartbeat_s)
    return {
        "predictor->recognizer": {"Hello": 1, "Heartbeat": hb, "CaptureRequest": 4, "StandardViewRequest": 2,
                                  "Stop": 1},
        "recognizer->predictor": {"Hello": 1, "Heartbeat": hb, "FrameTaken": 4, "MarkerPose": 1, "Ambiguous": 1,
                                  "Identity": 1},
    }


def _json_bytes(msg) -> int:
    return len(json.dumps({"type": type(msg).__name__, **dataclasses.asdict(msg)}, separators=(",", ":")))


def _paced_carry_s(msg, repeat: int) -> float | None:
    """Median send->recv time of ``msg`` through a pty null modem paced at BAUD (None without ptys)."""
    try:
        from ..runtime.transport import SerialHostLink, pty_null_modem

        with pty_null_modem(baud=BAUD) as modem:
            a, b = SerialHostLink.open(modem.port_a, BAUD), SerialHostLink.open(modem.port_b, BAUD)
            with a, b:
                samples = []
                for _ in range(repeat):
                    t0 = time.perf_counter()
                    a.send(msg)
                    got = b.recv(timeout=2.0)
                    if got != msg:
                        return None
                    samples.append(time.perf_counter() - t0)
                return statistics.median(samples)
    except OSError:
        return None


def run(quick: bool = False) -> dict:
    """Host-link message sizes and 9600-bps wire times per type, a typical run's utilisation, codec speed vs JSON."""
    cfg = HostLinkConfig()
    msgs = examples()
    rep = 200 if quick else 2000
    per_type = {}
    rows = []
    for name, msg in msgs.items():
        payload = len(encode(msg))
        serial = payload + SERIAL_OVERHEAD
        per_type[name] = {"payload_bytes": payload, "serial_bytes": serial, "tcp_bytes": payload + TCP_HEADER.size,
                          "json_bytes": _json_bytes(msg),
                          "serial_ms_at_9600": round(wire_time_s(serial, BAUD) * 1e3, 2)}
        as_json = {"type": name, **dataclasses.asdict(msg)}
        def binary(m=msg):
            return decode(encode(m))

        def as_text(d=as_json):
            return json.loads(json.dumps(d))

        t_bin = median_time(binary, repeat=rep)
        t_json = median_time(as_text, repeat=rep)
        rows.append(row(f"codec {name}", t_bin, baseline="json dumps+loads", baseline_s=t_json,
                        payload_bytes=payload, json_bytes=per_type[name]["json_bytes"]))
    pose = encode(msgs["MarkerPose"])
    deframer = SerialDeframer()
    t_frame = median_time(lambda: deframer.feed(serial_frame(pose)), repeat=rep)
    rows.append(row("serial frame+deframe MarkerPose", t_frame))

    mix = typical_mix(cfg.heartbeat_s)
    utilisation = {}
    for direction, counts in mix.items():
        nbytes = sum(per_type[k]["serial_bytes"] * n for k, n in counts.items())
        hb_bytes = per_type["Heartbeat"]["serial_bytes"] * counts["Heartbeat"]
        utilisation[direction] = {
            "messages": sum(counts.values()), "bytes": nbytes,
            "utilisation": round(nbytes * 10 / (BAUD * RUN_S), 4),
            "heartbeat_share": round(hb_bytes / nbytes, 3),
        }
    largest = max(per_type, key=lambda k: per_type[k]["serial_bytes"])
    # the longest any message can be: a Failure with a full-length text (Identity tops out at 74 bytes)
    bound = len(encode(Failure.short(FailureCode.INTERNAL, "x" * 500))) + SERIAL_OVERHEAD
    hb_ms = per_type["Heartbeat"]["serial_ms_at_9600"]
    worst_latency_ms = {k: round(v["serial_ms_at_9600"] + hb_ms, 2) for k, v in per_type.items()}

    measured = {}
    for name in ("Heartbeat", "MarkerPose", "CaptureRequest"):
        carry = _paced_carry_s(msgs[name], 5 if quick else 15)
        measured[name] = {"computed_ms": per_type[name]["serial_ms_at_9600"],
                          "measured_ms": None if carry is None else round(carry * 1e3, 2)}
        if carry is not None:
            rows.append(row(f"pty @9600 carry {name}", carry))

    return {
        "rows": rows,
        "baud": BAUD,
        "bits_per_byte": 10,
        "serial_overhead_bytes": SERIAL_OVERHEAD,
        "messages": per_type,
        "typical_run": {"duration_s": RUN_S, "heartbeat_hz": 1 / cfg.heartbeat_s, "directions": utilisation},
        "largest_message": {"type": largest, **per_type[largest]},
        "longest_possible_message": {"serial_bytes": bound,
                                     "serial_ms_at_9600": round(wire_time_s(bound, BAUD) * 1e3, 2)},
        "worst_latency_behind_heartbeat_ms": worst_latency_ms,
        "paced_pty_check": measured,
    }
