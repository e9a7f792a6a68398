"""A fixed robot-controller session on a virtual clock (requests, clock steps), replayed by the
byte-for-byte tests of older dialect sessions (tests/test_robot_arm_dialect.py). Its transcripts in
tests/data/robot/ were recorded from the controller before the arm was added."""

from __future__ import annotations

# (seconds to advance the clock before the line, request line); the session never needs the arm's
# new refusals: every move is one the sample lab's arm flies from its start pose.
SESSION_12 = [
    (0.0, "#1 HELLO 1.2"),
    (0.0, "#2 LIMITS"),
    (0.0, "#3 STATUS"),
    (0.0, "#4 SEG 1 260 -470 930 -1.9 -1.85 -0.55 1.5"),
    (0.2, "#5 HB"),
    (0.2, "#6 STATUS"),
    (0.2, "#7 SEG 2 280 -430 900 -1.95 -1.8 -0.6 1.0 20 0 0 0 0 0"),
    (0.2, "#8 SEGNOW 3 250 -460 920 -1.85 -1.9 -0.6 0 profile=ruckig vmax=200"),
    (0.2, "#9 STATUS"),
    (0.2, "#10 SEG 4 9000 0 0 3.0 0 0 1"),
    (0.2, "#11 HB"),
    (0.2, "#12 STATUS"),
    (0.2, "#13 HB"),
    (0.2, "#14 STOP"),
    (0.2, "#15 SEG 5 300 -450 900 -1.9 -1.85 -0.55 1"),
    (0.2, "#16 CLEAR"),
    (0.2, "#17 HOME"),
    (0.2, "#18 STATUS 1"),
    (0.2, "#19 HB*00"),
    (0.2, "#20 HB"),
    (0.2, "#21 STATUS"),
    (0.2, "#22 HB"),
    (0.2, "#23 HB"),
    (0.2, "#24 HB"),
    (0.2, "#25 HB"),
    (0.2, "#26 HB"),
    (0.2, "#27 STATUS"),
    (0.0, "#28 LIMITS"),
]

SESSION_10 = [
    (0.0, "#1 HELLO"),
    (0.0, "#2 LIMITS"),
    (0.0, "#3 SEG 0 260 -470 930 -1.9 -1.85 -0.55 1.5"),
    (0.2, "#4 STOP"),
    (0.2, "#5 STATUS"),
    (0.0, "#6 SEG 1 260 -470 930 -1.9 -1.85 -0.55 1.5"),
]


def run_session(emu, clock, session) -> str:
    """Every byte the controller writes over ``session`` after its boot line, as text."""
    emu.read_output()
    out = []
    for dt, line in session:
        clock.advance(dt)
        emu.receive((line + "\n").encode())
        out.append(emu.read_output().decode())
    return "".join(out)
