"""`labctl bench link` numbers are consistent with the codec and the 9600-bps line model."""

from __future__ import annotations

from labctl.bench import link
from labctl.decisions.messages import encode
from labctl.runtime.transport import SERIAL_OVERHEAD, serial_frame


def test_bench_link_quick_numbers():
    res = link.run(quick=True)
    msgs = res["messages"]
    for name, msg in link.examples().items():
        assert msgs[name]["payload_bytes"] == len(encode(msg))
        assert msgs[name]["serial_bytes"] == len(serial_frame(encode(msg))) == len(encode(msg)) + SERIAL_OVERHEAD
        assert msgs[name]["serial_ms_at_9600"] == round(msgs[name]["serial_bytes"] * 10 / 9600 * 1e3, 2)
        assert msgs[name]["payload_bytes"] < msgs[name]["json_bytes"]
    assert msgs["MarkerPose"]["payload_bytes"] < 50
    for direction in res["typical_run"]["directions"].values():
        # heartbeats at 5 Hz dominate; the whole mix stays a small fraction of the line
        assert 0.05 < direction["utilisation"] < 0.2
        assert direction["heartbeat_share"] > 0.8
    assert res["longest_possible_message"]["serial_ms_at_9600"] < 120
    assert {r["case"] for r in res["rows"]} >= {"codec MarkerPose", "serial frame+deframe MarkerPose"}
