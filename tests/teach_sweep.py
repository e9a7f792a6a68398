"""Issue 15 sweep (not a test): full teach (placement, checks, sim-renderer standard views) of 50 random
boxes and 30 random extrusions from tests/part_generator.py; the numbers are in docs/notes/library.md.

Usage: python tests/teach_sweep.py [OUT.json]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from part_generator import random_box, random_extrusion  # noqa: E402

from labctl.config import load_lab  # noqa: E402
from labctl.library.placement import viewing_geometry  # noqa: E402
from labctl.library.teach import teach_object  # noqa: E402
from labctl.library.views import mm_per_px  # noqa: E402
from labctl.sim.rigs import standard_view_renderer  # noqa: E402
from labctl.sim.truth import camera_model  # noqa: E402
from labctl.workspace import sample_lab_path  # noqa: E402


def main(out: str) -> None:
    lab = load_lab(sample_lab_path())
    view = viewing_geometry(lab)
    cam = camera_model(lab.mobile_camera)
    standoff = lab.config.viewing.standoff_mm
    rng = np.random.default_rng(2026)
    rows = []
    for k in range(80):
        m = random_box(rng, plate=k % 3 == 0) if k < 50 else random_extrusion(rng, concave=k % 3 != 0)
        t = time.process_time()
        try:
            o = teach_object(f"p{k}", m, radius_mm=lab.config.marker.radius_mm, view=view, standoff_mm=standoff,
                             scale_mm_per_px=mm_per_px(cam, standoff),
                             render_factory=standard_view_renderer(cam, noise_sigma=0.0), sweep=False)
            c = o.info["coverage"]
            rows.append(dict(k=k, ext=np.round(m.extents, 1).tolist(), ok=True, markers=len(o.markers),
                             radii=o.info["marker_radii_mm"], cov=c["probability"], iv=c["initial_view"],
                             tr=c["tracked"], warn=len(o.info["warnings"]),
                             crop=sum("standard view" in w for w in o.info["warnings"]),
                             cpu=time.process_time() - t))
        except Exception as exc:  # a refusal is the result being measured
            rows.append(dict(k=k, ext=np.round(m.extents, 1).tolist(), ok=False, err=repr(exc)))
        print(rows[-1], flush=True)
    Path(out).write_text(json.dumps(rows))


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "teach_sweep.json")
