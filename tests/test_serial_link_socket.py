"""SerialLink over pyserial's ``socket://`` (a device behind ser2net): a poll takes everything that
has arrived. pyserial reports ``in_waiting`` as 1 whenever a socket is readable; reading only that
took one byte per poll, and a caller polling once per camera frame (the run's table program) fell
ever further behind GRBL's status reports — its ``ok`` replies never came (found in the HIL
reconnect test: 0 of 5 lines acknowledged after 3 s)."""

from __future__ import annotations

import socket
import time

from labctl.drivers.serial_link import SerialLink


def test_one_poll_reads_every_line_that_arrived_over_socket():
    lines = [f"<Run|MPos:{i:.3f},200.000,0.000|FS:480,0>" for i in range(40)] + ["ok"] * 5
    with socket.create_server(("127.0.0.1", 0)) as srv:
        link = SerialLink(f"socket://127.0.0.1:{srv.getsockname()[1]}", 115200, timeout_s=1.0)
        link.open()
        try:
            conn, _ = srv.accept()
            with conn:
                conn.sendall("".join(line + "\r\n" for line in lines).encode())
                time.sleep(0.2)  # all of it is in the client's socket buffer now
                got = link.lines(0.0)
        finally:
            link.close()
    assert got == lines


def test_a_failed_read_or_write_names_the_failure_once():
    import serial

    from labctl.drivers.serial_link import LinkError, SerialLink

    class Broken:
        is_open, timeout, in_waiting = True, 0, 1

        def read(self, n):
            raise serial.SerialException("read failed: [Errno 5] Input/output error")

        def write(self, data):
            raise serial.SerialException("write failed: [Errno 32] Broken pipe")

    link = SerialLink(port=Broken(), name="table")
    for act, verb in ((lambda: link.write(b"?"), "write"), (lambda: link.poll(0.0), "read")):
        try:
            act()
        except LinkError as exc:
            msg = str(exc)
        assert msg.count(f"{verb} failed") == 1, msg
        assert msg.startswith("table: ") and "Errno" in msg
