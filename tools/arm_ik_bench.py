"""Kinematics libraries compared on a UR10e: IK solve time and robustness (docs/notes/robot.md, "Choosing the
kinematics library").

    python tools/arm_ik_bench.py [--n 200] [--paths 20] [--libs pinocchio,ikpy,rtb,labctl]

Each library gets the same UR10e (Universal Robots' published standard DH table, metres inside this
script because that is what the libraries expect) and the same problems:

* **random**: a random configuration's flange pose, solved from an unrelated random seed;
* **path**: 301 flange poses along a smooth joint-space sweep of up to ±20° per joint (a path the arm can
  follow, about 1 mm apart), each solved from the previous solution (the way a Cartesian servo follows a
  path); it fails on a pose error or on a joint step over 5° between samples (a jump to another
  configuration).

A solve succeeds when the position error is under 1e-3 mm and the rotation error under 1e-5 rad, checked
with the plain-numpy DH forward kinematics below, not the library's own.
``labctl`` is labctl's own :class:`labctl.planning.arm.ArmModel` on the sample lab's UR10e file.
ikpy and roboticstoolbox-python are not labctl dependencies: install them to compare.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np

D = [0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655]
A = [0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0]
ALPHA = [math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0]
POS_TOL_M = 1e-6
ROT_TOL = 1e-5
STEP_TOL = math.radians(5.0)


def dh(theta, d, a, alpha):
    """Standard DH link transform Rz(θ)·Tz(d)·Tx(a)·Rx(α)."""
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]])


def fk(q):
    """Flange pose in the base frame (4×4, m)."""
    T = np.eye(4)
    for i in range(6):
        T = T @ dh(q[i], D[i], A[i], ALPHA[i])
    return T


def pose_error(T, T_goal):
    """(position error m, rotation angle rad)."""
    dR = T[:3, :3].T @ T_goal[:3, :3]
    ang = math.acos(max(-1.0, min(1.0, (np.trace(dR) - 1) / 2)))
    return float(np.linalg.norm(T[:3, 3] - T_goal[:3, 3])), ang


def ok(q, T_goal):
    """The solution reaches the goal (checked with this script's own FK)."""
    if q is None:
        return False
    e, r = pose_error(fk(q), T_goal)
    return e < POS_TOL_M and r < ROT_TOL


def solver_pinocchio():
    """DLS IK on a Pinocchio model built from the DH table (Pinocchio has no IK solver of its own)."""
    import pinocchio as pin

    model = pin.Model()
    parent, M = 0, pin.SE3.Identity()
    for i in range(6):
        parent = model.addJoint(parent, pin.JointModelRZ(), M, f"j{i + 1}")
        M = pin.SE3(pin.utils.rotate("x", ALPHA[i]), np.array([A[i], 0.0, D[i]]))  # Tz(d)·Tx(a)·Rx(α)
    fid = model.addFrame(pin.Frame("flange", parent, 0, M, pin.FrameType.OP_FRAME))
    data = model.createData()

    def solve(T_goal, q0, iters=100):
        goal = pin.SE3(T_goal[:3, :3], T_goal[:3, 3])
        q = np.array(q0, float)
        for _ in range(iters):
            pin.framesForwardKinematics(model, data, q)
            cur = data.oMf[fid]
            err = pin.log6(cur.actInv(goal)).vector
            if np.linalg.norm(err[:3]) < POS_TOL_M * 0.1 and np.linalg.norm(err[3:]) < ROT_TOL * 0.1:
                return q
            J = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL)
            J = pin.Jlog6(cur.actInv(goal)) @ J
            dq = J.T @ np.linalg.solve(J @ J.T + 1e-10 * np.eye(6), err)
            q = pin.integrate(model, q, dq)
        return q

    return solve


def solver_ikpy():
    """ikpy's chain (scipy least squares) with URDF-style links from the DH table."""
    from ikpy.chain import Chain
    from ikpy.link import OriginLink, URDFLink

    links = [OriginLink()]
    for i in range(6):
        prev_d, prev_a, prev_alpha = (0.0, 0.0, 0.0) if i == 0 else (D[i - 1], A[i - 1], ALPHA[i - 1])
        links.append(URDFLink(name=f"j{i + 1}", origin_translation=[prev_a, 0, prev_d],
                              origin_orientation=[prev_alpha, 0, 0], rotation=[0, 0, 1], bounds=(-2 * math.pi,
                                                                                                  2 * math.pi)))
    links.append(URDFLink(name="flange", origin_translation=[A[5], 0, D[5]], origin_orientation=[ALPHA[5], 0, 0],
                          joint_type="fixed"))
    chain = Chain(links, active_links_mask=[False] + [True] * 6 + [False])

    def solve(T_goal, q0):
        q = chain.inverse_kinematics(T_goal[:3, 3], T_goal[:3, :3], orientation_mode="all",
                                     initial_position=[0.0, *q0, 0.0])
        return np.asarray(q[1:7])

    return solve


def solver_rtb():
    """roboticstoolbox-python's DHRobot and its C++ Levenberg–Marquardt (``ik_LM``)."""
    import roboticstoolbox as rtb

    robot = rtb.DHRobot([rtb.RevoluteDH(d=D[i], a=A[i], alpha=ALPHA[i]) for i in range(6)], name="UR10e")
    ets = robot.ets()

    def solve(T_goal, q0):
        sol = ets.ik_LM(T_goal, q0=np.asarray(q0, float), ilimit=100, slimit=1, tol=1e-14, joint_limits=False)
        return np.asarray(sol[0])

    return solve


def solver_labctl():
    """labctl's own :class:`labctl.planning.arm.ArmModel` (Pinocchio underneath), on the sample lab's UR10e file."""
    from pathlib import Path

    from labctl.config.arm import load_arm
    from labctl.planning.arm import ArmModel

    arm = ArmModel.from_config(load_arm(Path(__file__).resolve().parents[1] / "drivers" / "arms" / "ur10e.yaml"))

    def solve(T_goal, q0):
        T = np.array(T_goal, float)
        T[:3, 3] *= 1000.0
        return arm.ik(T, q0).q

    return solve


SOLVERS = {"pinocchio": solver_pinocchio, "ikpy": solver_ikpy, "rtb": solver_rtb, "labctl": solver_labctl}


def path_goals(q_start, rng):
    """301 flange poses of a smooth joint-space sweep from q_start (up to ±20° per joint, kept away from
    singularities), so every path is followable and a failure is the solver's."""
    while True:
        dq = rng.uniform(-math.radians(20), math.radians(20), 6)
        qs = [q_start + s * dq for s in np.linspace(0, 1, 301)]
        if all(well_conditioned(q) for q in qs[::10]):
            return [fk(q) for q in qs]


def well_conditioned(q):
    """Away from the UR's singularities (wrist, elbow, shoulder) so random problems are solvable."""
    if abs(math.sin(q[4])) < 0.2 or abs(math.sin(q[2])) < 0.2:
        return False
    p = fk(q)[:3, 3]
    return math.hypot(p[0], p[1]) > 0.3


def random_q(rng):
    """A well-conditioned random configuration in [−π, π]^6."""
    while True:
        q = rng.uniform(-math.pi, math.pi, 6)
        if well_conditioned(q):
            return q


def bench(name, n, n_paths, rng_seed=1):
    """Success rates and median solve times of one library."""
    solve = SOLVERS[name]()
    rng = np.random.default_rng(rng_seed)
    times, wins = [], 0
    for _ in range(n):
        goal = fk(random_q(rng))
        seed = rng.uniform(-math.pi, math.pi, 6)
        t = time.perf_counter()
        q = solve(goal, seed)
        times.append(time.perf_counter() - t)
        wins += ok(q, goal)
    path_ok, path_times = 0, []
    for _ in range(n_paths):
        q = random_q(rng)
        good = True
        for goal in path_goals(q, rng):
            t = time.perf_counter()
            q1 = solve(goal, q)
            path_times.append(time.perf_counter() - t)
            if not ok(q1, goal) or np.max(np.abs(np.asarray(q1) - q)) > STEP_TOL:
                good = False
                break
            q = np.asarray(q1)
        path_ok += good
    return {"random_success": wins / n, "random_median_ms": 1e3 * statistics.median(times),
            "path_success": path_ok / n_paths, "path_step_median_ms": 1e3 * statistics.median(path_times)}


def main() -> None:
    """Print one line per library."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--paths", type=int, default=20)
    ap.add_argument("--libs", default="pinocchio,ikpy,rtb,labctl")
    args = ap.parse_args()
    for name in args.libs.split(","):
        try:
            r = bench(name, args.n, args.paths)
        except ImportError as exc:
            print(f"{name}: not installed ({exc})")
            continue
        print(f"{name}: random seeds {100 * r['random_success']:.1f} % in {r['random_median_ms']:.2f} ms median; "
              f"paths {100 * r['path_success']:.0f} % followed, {r['path_step_median_ms']:.3f} ms per step")


if __name__ == "__main__":
    main()
