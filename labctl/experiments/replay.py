"""``labctl replay RUN``: re-run the recognizer on a recorded run's images.

The run record holds every capture request (with the camera pose the predictor sent) and the
images the recognizer decided on. Replaying feeds the same requests and images, in order, to a
fresh :class:`~labctl.decisions.recognizer.Recognizer` — e.g. after changing the library or the
matcher — and compares its answers with the recorded ones.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..config import Lab
from ..decisions import messages as m
from ..decisions.context import RunContext
from ..decisions.recognizer import Recognizer
from ..drivers.interfaces import Frame
from ..errors import UserInputError
from ..geometry import matrix_to_rotvec
from ..records import load_run
from ..records.events import spec

CAPTURE = spec("capture_request")
DISCARDED = spec("capture_discarded")


def _image_for(run_dir: Path, view_id: int):
    path = run_dir / f"view_{view_id}.png"
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise UserInputError(f"{run_dir}: the recorded image {path.name} is missing or unreadable")
    return image


def replay_run(lab: Lab, run_dir: Path | str) -> dict:
    """Feed the recorded capture requests and images to a new recognizer; compare identities."""
    run_dir = Path(run_dir)
    run = load_run(run_dir)
    discarded = {int(DISCARDED.get(e, "view_id")) for e in run.of(DISCARDED.name)}
    # an image no @DONE confirmed was forgotten by the recognizer (Discard): it is not fed again
    requests = [e for e in run.of(CAPTURE.name) if int(CAPTURE.get(e, "view_id")) not in discarded]
    if not requests:
        raise UserInputError(f"{run_dir}: no capture requests recorded (the run ended before any image)")
    ctx = RunContext.load(lab)
    queue: list[Frame] = []
    recognizer = Recognizer(ctx, lambda: queue.pop(0), lambda *a, **k: None)
    answers, identity = [], None
    for e in requests:
        kind, view_id, t = CAPTURE.get(e, "kind"), int(CAPTURE.get(e, "view_id")), float(CAPTURE.get(e, "t"))
        T = np.asarray(CAPTURE.get(e, "T_w_c2"), dtype=float)
        queue.append(Frame(_image_for(run_dir, view_id), t, view_id))
        req = m.CaptureRequest(view_id=view_id, kind=kind, t_capture=t,
                               position=tuple(T[:3, 3]), rotvec=tuple(matrix_to_rotvec(T[:3, :3])))
        for reply in recognizer.handle(req):
            answers.append(type(reply).__name__)
            if isinstance(reply, m.Identity):
                identity = ctx.names[reply.object_id]
    recorded = (run.result or {}).get("identity")
    return {"run": str(run_dir), "identity": identity, "recorded_identity": recorded,
            "same": identity == recorded, "answers": answers}
