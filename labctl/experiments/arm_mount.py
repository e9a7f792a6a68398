"""Where to bolt the arm: which base positions reach every view the lab plans.

The views: the robot's home pose, the calibration plan's robot stations and table-registration poses
(:func:`labctl.calibration.run.make_plan` on the lab's target and nominal geometry), and, given run
records, every target the runs commanded (initial and standard views; see
:mod:`labctl.experiments.arm_feasibility`). Each candidate base (upright, on a grid beside the table)
is checked by inverse kinematics from 24 seeds per view. Reaching every view is necessary, not
sufficient: ``labctl robot feasibility`` then checks the paths between them.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import UserInputError
from ..geometry import make_T, rotvec_to_matrix

GRID_MARGIN_MM = 600.0  # the grid reaches this far beyond the table's travel on each side
GRID_STEP_MM = 200.0
CLEARANCE_MM = 100.0  # no base closer than this to the table's travel area (it moves there)
HEIGHTS_MM = (0.0, 350.0, 700.0)


def planned_views(lab, runs_dir: Path | None = None) -> dict[str, list[np.ndarray]]:
    """The flange poses ``T_w_F`` the lab plans, by group: ``home``, ``calibration`` and ``runs``."""
    from ..sim.world import home_flange_pose

    views: dict[str, list[np.ndarray]] = {"home": [home_flange_pose(lab)], "calibration": [], "runs": []}
    from ..calibration.run import lab_target, make_plan, nominal_for
    from ..calibration.target import TargetError

    try:
        plan = make_plan(lab_target(lab.calibration_dir), nominal_for(lab), "all")
    except TargetError as exc:
        raise UserInputError(str(exc)) from None
    views["calibration"] = list(plan.stations) + [T for _, T in plan.registration]
    if runs_dir is not None:
        from .arm_feasibility import find_records, read_events

        seen = set()
        for rec in find_records(runs_dir):
            for e in read_events(rec / "events.jsonl"):
                if e.get("event") == "segment":
                    key = (*e["p"], *e["rotvec"])
                    if key not in seen:
                        seen.add(key)
                        views["runs"].append(make_T(rotvec_to_matrix(np.asarray(e["rotvec"], float)), e["p"]))
    return views


def default_grid(lab) -> list[tuple[float, float, float]]:
    """Upright bases round the table: its travel ± ``GRID_MARGIN_MM`` every ``GRID_STEP_MM``, at ``HEIGHTS_MM``,
    keeping ``CLEARANCE_MM`` off the travel area."""
    o = np.asarray(lab.table.origin_w_mm, float)
    tx, ty = (float(v) for v in lab.table.travel_mm[:2])
    xs = np.arange(o[0] - GRID_MARGIN_MM, o[0] + tx + GRID_MARGIN_MM + 1e-9, GRID_STEP_MM)
    ys = np.arange(o[1] - GRID_MARGIN_MM, o[1] + ty + GRID_MARGIN_MM + 1e-9, GRID_STEP_MM)
    out = []
    for z in HEIGHTS_MM:
        for x in xs:
            for y in ys:
                inside = (o[0] - CLEARANCE_MM < x < o[0] + tx + CLEARANCE_MM
                          and o[1] - CLEARANCE_MM < y < o[1] + ty + CLEARANCE_MM)
                if not inside:
                    out.append((float(x), float(y), float(z)))
    return out


def mount_search(arm_cfg, views: dict[str, list[np.ndarray]], bases, log=None) -> dict:
    """Each base of ``bases`` ((x, y, z) mm, upright) against every view: how many of each group it reaches."""
    from ..planning.arm import ArmModel

    groups = dict(views)
    n_views = sum(len(v) for v in groups.values())
    if n_views == 0:
        raise UserInputError("no views to reach")
    rows: list[dict[str, Any]] = []
    for base in bases:
        arm = ArmModel.from_config(dataclasses.replace(arm_cfg, base_xyz_mm=tuple(base), base_rpy_deg=(0.0, 0.0, 0.0)))
        reached = {k: sum(bool(arm.reachable(T)) for T in v) for k, v in groups.items()}
        rows.append({"base_xyz_mm": list(base), "reached": reached, "all": sum(reached.values()) == n_views,
                     "missed": n_views - sum(reached.values())})
        if log:
            log(f"base {base}: {sum(reached.values())} of {n_views}")
    rows.sort(key=lambda r: (r["missed"], abs(r["base_xyz_mm"][2]), np.hypot(*r["base_xyz_mm"][:2])))
    return {"arm": arm_cfg.name, "views": {k: len(v) for k, v in groups.items()}, "bases": len(rows),
            "reach_all": [r["base_xyz_mm"] for r in rows if r["all"]], "ranked": rows}
