"""The live view: its JSON endpoint on a record folder, the fixed camera's snapshots, and a real run in Chromium."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.request

import numpy as np
import pytest

from labctl.drivers.interfaces import Frame
from labctl.records import RunRecord, load_run
from labctl.records.events import validate
from labctl.records.liveview import LiveViewServer, RecordTail
from labctl.runtime.snapshot import LIVE_DIR, SnapshotCamera, maybe_snapshots
from labctl.runtime.stopping import still_after

# ---- the endpoint, on a record folder written here -------------------------------------------------------


def _record(tmp_path) -> RunRecord:
    rec = RunRecord.create(tmp_path / "runs", {"command": "run"})
    rec.event("worker_started", role="predictor", pid=11)
    rec.event("stage", t=0.0, stage="wait")
    rec.event("stage", t=1.0, stage="track")
    for i in range(5):
        rec.event("track", t=1.0 + 0.1 * i, x=100.0 + i, y=50.0 - i, px=[320.0 + i, 240.0])
    rec.event("predict", t=1.4, path=[[104.0, 46.0], [110.0, 40.0], [120.0, 30.0]])
    rec.event("stage", t=1.5, stage="intercept")
    rec.event("segment", t=1.5, id=1, kind="initial1", t_end=2.5, t0c=None, t1c=None, p=[110.0, 40.0, 300.0],
              rotvec=[0.0, 3.1, 0.0])
    rec.event("robot", t=1.6, p=[200.0, 0.0, 400.0])
    rec.event("capture_request", t=2.5, view_id=1, kind="initial1", T_w_c2=np.eye(4).tolist())
    rec.event("marker_candidates", t=2.5, view_id=1,
              ellipse={"center": [300.0, 200.0], "axes": [40.0, 25.0], "angle_rad": 0.3, "conic": [0.0] * 6},
              candidates=[], markers=1)
    rec.event("sim_truth", t=2.6, robot_moving=True, table_moving=False, table_state="Idle", robot_stop=None)
    rec.save_image("view_1", np.zeros((48, 64, 3), np.uint8))
    return rec


def _get(url: str, headers=None):
    with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}), timeout=5) as r:
        return r.status, r.headers.get("Content-Type"), r.read()


def test_state_endpoint_folds_the_record_through_the_schema(tmp_path):
    rec = _record(tmp_path)
    stops = []
    with LiveViewServer(rec.path, port=0, on_stop=lambda: stops.append(time.monotonic())) as view:
        base = view.url.split("/?")[0]
        with pytest.raises(urllib.error.HTTPError) as no_key:  # another page in the browser cannot read or stop
            _get(f"{base}/api/state")
        assert no_key.value.code == 403
        status, ctype, body = _get(f"{base}/api/state", {"X-Labctl-Key": view.key})
        assert status == 200 and ctype == "application/json"
        s = json.loads(body)
        assert [x["stage"] for x in s["stages"]] == ["wait", "track", "intercept"]
        assert [p[1:3] for p in s["track"]] == [[100.0 + i, 50.0 - i] for i in range(5)]
        assert s["track"][-1][3:] == [324.0, 240.0]
        assert s["predict"]["path"][-1] == [120.0, 30.0]
        assert s["segments"][0]["p"] == [110.0, 40.0, 300.0] and s["robot"][0][1:] == [200.0, 0.0, 400.0]
        assert s["ellipses"]["view_1"] == [300.0, 200.0, 40.0, 25.0, 0.3]
        assert s["captures"]["view_1"]["kind"] == "initial1"
        assert s["truth"]["robot_moving"] is True and s["fixed"] is None and s["result"] is None
        assert [i["name"] for i in s["images"]] == ["view_1.png"]
        _, ctype, png = _get(f"{base}/img/view_1.png?key={view.key}")
        assert ctype == "image/png" and png[:4] == b"\x89PNG"
        with pytest.raises(urllib.error.HTTPError) as outside:  # only the run's own images
            _get(f"{base}/img/meta.json?key={view.key}")
        assert outside.value.code == 404
        # incremental: only the new lines are read, and a half-written line waits for its end
        rec.event("stage", t=3.0, stage="initial")
        line = json.dumps({"event": "identity", "wall": 0.0, "t": 3.5, "object": "bracket", "score": 0.1,
                           "candidates": ["bracket"]}) + "\n"
        with (rec.path / "events.jsonl").open("a") as f:
            f.write(line[:20])
        s = json.loads(_get(f"{base}/api/state", {"X-Labctl-Key": view.key})[2])
        assert s["stages"][-1]["stage"] == "initial" and s["identity"] is None
        with (rec.path / "events.jsonl").open("a") as f:
            f.write(line[20:])
        s = json.loads(_get(f"{base}/api/state", {"X-Labctl-Key": view.key})[2])
        assert s["identity"]["object"] == "bracket" and len(s["stages"]) == 4
        page = _get(f"{base}/?key={view.key}")[2].decode()
        assert 'id="stop"' in page and "/api/state" in page
        req = urllib.request.Request(f"{base}/api/stop", method="POST", headers={"X-Labctl-Key": view.key})
        assert json.loads(urllib.request.urlopen(req, timeout=5).read())["first"] is True
        assert json.loads(urllib.request.urlopen(req, timeout=5).read())["first"] is False  # once only
        assert len(stops) == 1
    rec.close()


def test_a_mistyped_field_reads_as_absent(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "events.jsonl").write_text(
        json.dumps({"event": "track", "wall": 0, "t": 1.0, "x": "left", "y": 2.0, "px": [1, 2]}) + "\n"
        + json.dumps({"event": "stage", "wall": 0, "t": 1.0, "stage": "track"}) + "\n")
    tail = RecordTail(folder)
    assert tail.poll() == 2
    assert tail.state["track"] == [] and tail.state["stages"] == [{"t": 1.0, "stage": "track"}]


# ---- the fixed camera's snapshots ---------------------------------------------------------------------------


class _Camera:
    def __init__(self):
        self.seq, self.closed = 0, False

    def grab_recent(self, n):
        self.seq += 1
        img = np.zeros((480, 640, 3), np.uint8)
        img[:, : self.seq % 640] = 255
        return [Frame(img, t=self.seq / 30, seq=self.seq)]

    def close(self):
        self.closed = True


def test_snapshots_are_low_rate_downscaled_and_never_block(tmp_path):
    import cv2

    cam = _Camera()
    assert maybe_snapshots(cam, tmp_path, 0.5, 320) is cam  # no live/ folder: nothing more is written
    assert maybe_snapshots(cam, None, 0.5, 320) is cam
    (tmp_path / LIVE_DIR).mkdir()
    clock = [0.0]
    snap = maybe_snapshots(cam, tmp_path, 0.5, 320)
    assert isinstance(snap, SnapshotCamera)
    snap._clock = lambda: clock[0]
    worst = 0.0
    for _ in range(90):  # 2.8 s of frames at 32 Hz (exact steps) on a fake clock: 6 snapshots are due
        t0 = time.perf_counter()
        frames = snap.grab_recent(8)
        worst = max(worst, time.perf_counter() - t0)
        assert frames[-1].seq == cam.seq  # the run gets every frame, unchanged
        clock[0] += 1 / 32
    snap.close()
    assert cam.closed and 1 <= snap.written <= 6
    meta = json.loads((tmp_path / LIVE_DIR / "fixed.json").read_text())
    img = cv2.imread(str(tmp_path / LIVE_DIR / "fixed.jpg"))
    assert img.shape == (240, 320, 3) and meta["scale"] == 0.5 and meta["width"] == 320
    assert meta["seq"] == 81  # the last one offered (frames 1, 17, 33, 49, 65, 81 were due)
    assert worst < 0.05, worst  # the caller only hands a copy over


# ---- a real run, in a real headless browser ----------------------------------------------------------------


def _chromium() -> tuple[str, str]:
    """Paths of Debian's chromium and chromedriver, installed here if missing and we may (root)."""
    found = shutil.which("chromium"), shutil.which("chromedriver")
    if None in found and hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        cmd = ["apt-get", "install", "-y", "-q", "chromium", "chromium-driver"]
        if subprocess.run(cmd, env=env, capture_output=True).returncode != 0:
            subprocess.run(["apt-get", "update", "-q"], env=env, capture_output=True)
            subprocess.run(cmd, env=env, capture_output=True)
        found = shutil.which("chromium"), shutil.which("chromedriver")
    if None in found:
        pytest.skip("needs Debian's chromium and chromium-driver (apt-get install chromium chromium-driver, as root)")
    return found  # type: ignore[return-value]


def _browser(tmp_path):
    webdriver = pytest.importorskip("selenium.webdriver", reason="needs selenium (pip install -e '.[test]')")
    from selenium.webdriver.chrome.service import Service

    chromium, driver = _chromium()
    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--window-size=1200,1050", f"--user-data-dir={tmp_path / 'chromium-profile'}"):
        opts.add_argument(flag)
    return webdriver.Chrome(service=Service(executable_path=driver), options=opts)


def _until(what: str, check, timeout_s: float, poll_s: float = 0.05):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(poll_s)
    raise AssertionError(f"the page never showed {what} within {timeout_s:g} s")


@pytest.mark.timeout(240)
def test_live_view_in_chromium_follows_the_run_and_stop_stops_it(tmp_path):
    from labctl.workspace import init_workspace

    browser = _browser(tmp_path)
    lab = init_workspace(tmp_path / "lab")
    p = subprocess.Popen([sys.executable, "-m", "labctl", "--lab", str(lab), "run", "--view", "--view-port", "0",
                          "--trajectory", "line", "--seed", "2", "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = p.stderr.readline()
        assert line.startswith("live view: http://127.0.0.1:"), line
        browser.get(line.split(": ", 1)[1].strip())
        js = browser.execute_script
        _until("a first answer", lambda: js("return +document.body.dataset.polls || 0") >= 1, 30)
        assert browser.title == "labctl live view"
        stages = set()

        def seen(check):
            stages.add(browser.find_element("id", "stage").text)
            return check()

        track = _until("tracked points in the plan view",
                       lambda: seen(lambda: int(browser.find_element("id", "track-count").text)), 90)
        first = _until("a fixed-camera snapshot", lambda: seen(lambda: js("return $('fixed').dataset.seq")), 30)
        _until("a newer fixed-camera snapshot",
               lambda: seen(lambda: js("return $('fixed').dataset.seq") not in (None, first)), 10)
        _until("more tracked points", lambda: seen(lambda: int(browser.find_element("id", "track-count").text)
                                                   > track), 10)
        # the first mobile-camera image, with its ellipse: the robot then moves on to the second image
        _until("a mobile-camera image", lambda: seen(lambda: js("return $('mobile').dataset.name")), 60, 0.02)
        assert browser.find_element("id", "stage").text not in ("done", "failed"), "the run ended before Stop"
        assert len(stages - {"starting"}) >= 2, stages  # the stage changed on the page (track → ... → initial)
        assert int(browser.find_element("id", "segment-count").text) >= 1
        shot = os.environ.get("LABCTL_LIVE_VIEW_SCREENSHOT")
        if shot:  # the notes' picture (docs/notes/img/live_view.png), 256 colours to stay small
            from PIL import Image

            time.sleep(0.3)
            browser.save_screenshot(str(tmp_path / "shot.png"))
            Image.open(tmp_path / "shot.png").convert("RGB").quantize(256).save(shot, optimize=True)
        browser.find_element("id", "stop").click()
        _until("the stop requested", lambda: browser.find_element("id", "stop").text in ("Stopping…", "Ended"), 5)
        out, err = p.communicate(timeout=60)
    finally:
        browser.quit()
        if p.poll() is None:
            p.kill()
            p.communicate()
    assert p.returncode == 130, err  # Ctrl-C's exit status (README "Exit status")
    assert "interrupted" in err and "record kept" in err, err
    run_dir = next((lab / "runs").iterdir())
    run = load_run(run_dir)
    for e in run.events:
        validate(e)
    a = run.of("run_aborted")[-1]
    assert a["cause"] == "interrupted" and a["exit_code"] == 130, a
    assert set(a["devices_stopped"]) == {"robot", "table"}
    assert all(o["confirmed"] for o in a["stop_outcomes"])
    # the simulator's ground truth: both devices still within 0.5 s of the stop command
    lag = still_after(run.events, a["t_stop_sent"])
    assert lag["robot"] < 0.5 and lag["table"] < 0.5, lag
    assert (run_dir / LIVE_DIR / "fixed.jpg").is_file()
    assert run.result["identity"] is None and "interrupted" in run.result["failure"]


def test_a_taken_port_is_refused_before_the_record_is_made(tmp_path):
    import socket

    from labctl.workspace import init_workspace

    lab = init_workspace(tmp_path / "lab")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        p = subprocess.run([sys.executable, "-m", "labctl", "--lab", str(lab), "run", "--virtual", "--view",
                            "--view-port", str(port), "--seed", "1"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines() == [
        f"labctl: error: the live view cannot listen on 127.0.0.1:{port}: Address already in use "
        "(another port: --view-port, 0 for any)"]
    assert not (lab / "runs").is_dir() or not any((lab / "runs").iterdir())
