"""Marker availability on two independent renderers: how often the true marker is found *and trusted*.

The degradation suite (:mod:`._vision_suite`) asks how accurate a found marker is; this asks how
often it is usable at all, under blur, a thin occluder and a camera response the lab did not
declare — conditions where refusing a marker costs the run a view. Per condition and method:

* ``available``: share of images in which the true disc is detected and trusted (ours: a marker
  within half its image radius + 3 px of the truth whose ``marker_poses`` carry no flag and whose
  pair passes :func:`labctl.vision.pose_pair_consistency`; plain OpenCV (``vision.baseline``): the
  largest red contour's ellipse there — it has no notion of trust);
* ``gross_trusted``: share of trusted answers with normal error > 3° or centre error > 2 % of range
  (the candidate nearer the truth), i.e. confident wrong answers;
* ``duality``: pairs resolved right / ambiguous / wrong (both images trusted; ≥ 3° between the
  chosen and the true normal counts as wrong only when the other candidate was nearer);
* ``z95``: 95th percentile of the normal error ÷ its σ (ours, trusted answers): calibration;
* ``available_centre`` (ours): share of images whose marker is *fit for its use*
  (``MarkerPoses.fit_for``: at least tracking — no flag but ``uncertain_normal``, a near-frontal
  marker's tilt is ill-defined, its centre is not) and whose pair passes the two-view check;
  ``n_gross_kept``: those with a centre > 2 % of range off, or (pose-grade ones) a normal > 3° off;
  ``z95_kept``: the normal z of all kept answers (a tracking-only marker's large σ included);
  ``z95_centre_kept``: their centre error (mm) ÷ √trace of the centre covariance (a 3-D Gaussian: 1.6).

Renderers: ``"mitsuba"`` (:mod:`._vision_mitsuba`, Mitsuba 3, the lab's mobile camera intrinsics)
and ``"oracle"`` (:mod:`._vision_oracle`, the project's exact-coverage renderer, f 1200–2500 px).
Images are rendered once per (renderer, condition, seed) and kept in ``cache_dir`` (npz), so the
code before and after a change is judged on the same pixels.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..records.sweep_report import wilson_interval
from . import _vision_oracle as oracle
from ._vision_suite import GROSS_CENTRE_PCT, GROSS_NORMAL_DEG, _angle_deg, _errors, _labctl_camera

CALIBRATION = Path(__file__).resolve().parents[2] / "calibration" / "mobile_camera.yaml"


def mitsuba_conditions() -> list[tuple[str, Any, str]]:
    """(name, Mitsuba ``Shot``, declared response) of each condition."""
    from ._vision_mitsuba import Shot

    webcam: dict[str, Any] = dict(response="srgb", defocus_px=1.0, bayer=True, jpeg_quality=70, noise_std=3.0,
                                  photons=2000.0)
    mild: dict[str, Any] = dict(response="gamma 2.2", defocus_px=1.0, motion_mm_s=40.0, jpeg_quality=85, noise_std=2.0)
    return [
        ("clean", Shot(), "linear"),
        ("defocus r 2 px", Shot(defocus_px=2.0), "linear"),
        ("defocus r 3 px", Shot(defocus_px=3.0), "linear"),
        ("gamma 2.2 + defocus r 2 px", Shot(response="gamma 2.2", defocus_px=2.0), "gamma 2.2"),
        ("motion 100 mm/s × 30 ms", Shot(motion_mm_s=100.0, exposure_s=0.030), "linear"),
        ("3-px dark wire", Shot(wire_px=3.0), "linear"),
        ("webcam-like", Shot(**webcam), "srgb"),
        ("mild combination", Shot(**mild), "gamma 2.2"),
        ("undeclared: gamma 2.2 + defocus 2 as linear", Shot(response="gamma 2.2", defocus_px=2.0), "linear"),
        ("undeclared: webcam-like as linear", Shot(**webcam), "linear"),
        ("undeclared: mild combination as linear", Shot(**mild), "linear"),
    ]


def oracle_conditions() -> list[tuple[str, Any, str]]:
    """(name, oracle ``Conditions``, declared response) of each condition (the same kinds as Mitsuba's)."""
    C = oracle.Conditions
    webcam: dict[str, Any] = dict(response="srgb", defocus_px=1.0, bayer="bilinear", jpeg_quality=70, noise_std=3.0,
                                  photons=2000.0)
    mild: dict[str, Any] = dict(response="gamma 2.2", defocus_px=1.0, motion_px=4.0, jpeg_quality=85, noise_std=2.0)
    return [
        ("clean", C(), "linear"),
        ("defocus r 2 px", C(defocus_px=2.0), "linear"),
        ("defocus r 3 px", C(defocus_px=3.0), "linear"),
        ("gamma 2.2 + defocus r 2 px", C(response="gamma 2.2", defocus_px=2.0), "gamma 2.2"),
        ("motion 8 px", C(motion_px=8.0), "linear"),
        ("3-px dark wire", C(wire_px=3.0), "linear"),
        ("webcam-like", C(**webcam), "srgb"),
        ("mild combination", C(**mild), "gamma 2.2"),
        ("undeclared: gamma 2.2 + defocus 2 as linear", C(response="gamma 2.2", defocus_px=2.0), "linear"),
        ("undeclared: webcam-like as linear", C(**webcam), "linear"),
        ("undeclared: mild combination as linear", C(**mild), "linear"),
    ]


def _render_pairs(renderer: str, cond, n_pairs: int, seed: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    render: Any
    if renderer == "mitsuba":
        from . import _vision_mitsuba as mits

        base = mits.lab_camera(CALIBRATION)
        render = mits.render
    else:
        base, render = None, oracle.render
    out = []
    for _ in range(n_pairs):
        cam = base if base is not None else oracle.Cam(f=float(rng.uniform(1200, 2500)))
        d1 = oracle.random_pose(rng, cam)
        d2 = d1
        for _ in range(50):
            v = rng.standard_normal(3)
            d2 = oracle.translated(d1, v / np.linalg.norm(v) * rng.uniform(10, 50))
            rim = oracle.rim_pixels(cam, d2, 64)
            if (rim.min(axis=0) > 30).all() and (rim[:, 0] < cam.width - 30).all() \
                    and (rim[:, 1] < cam.height - 30).all():
                break
        ps = int(rng.integers(2**31))
        imgs = [render(cam, d, cond, np.random.default_rng(ps + k))[0] for k, d in enumerate((d1, d2))]
        out.append({"f": cam.f, "discs": (d1, d2), "images": imgs})
    return out


def _cache_key(renderer: str, name: str, n_pairs: int, seed: int) -> str:
    safe = "".join(ch if ch.isalnum() else "_" for ch in name)
    return f"{renderer}_{safe}_{n_pairs}_{seed}.npz"


def pairs(renderer: str, name: str, cond, n_pairs: int, seed: int, cache_dir: str | None) -> list[dict]:
    """The rendered pairs of one condition (from ``cache_dir`` when already rendered)."""
    path = Path(cache_dir) / _cache_key(renderer, name, n_pairs, seed) if cache_dir else None
    if path is not None and path.exists():
        # each z[key] decompresses the whole array again: read every one once (100 pairs of images is 180 MB)
        with np.load(path) as z:
            f, c, n, r, img = (z[k] for k in ("f", "c", "n", "r", "img"))
        out: list[dict[str, Any]] = []
        for i in range(n_pairs):
            discs = tuple(oracle.Disc(tuple(c[i, k]), tuple(n[i, k]), float(r[i])) for k in (0, 1))
            out.append({"f": float(f[i]), "discs": discs, "images": [img[i, 0], img[i, 1]]})
        return out
    out = _render_pairs(renderer, cond, n_pairs, seed)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, f=np.array([p["f"] for p in out]),
                            c=np.array([[d.center for d in p["discs"]] for p in out]),
                            n=np.array([[d.normal for d in p["discs"]] for p in out]),
                            r=np.array([p["discs"][0].radius for p in out]),
                            img=np.array([p["images"] for p in out]))
    return out


def _ours(img, cam, disc, truth_px, tol, declared, response_declared=True):
    from ..vision import find_markers, marker_poses

    # an undeclared row is a camera whose response nobody stated (read as linear): pose is conservative there
    res = find_markers(img, response=declared, response_declared=response_declared)
    for mk in res.markers:
        if np.hypot(*(np.asarray(mk.ellipse.center) - truth_px)) < tol:
            try:
                return marker_poses(mk, _labctl_camera(cam, False), disc.radius, lens_sigma_px=0.0)
            except ValueError:
                return None
    return None


def _opencv(img, cam, disc, truth_px, tol):
    from ..vision import CirclePoseError, circle_poses
    from .vision_baselines import opencv_marker_ellipse

    ell = opencv_marker_ellipse(img)
    if ell is None or np.hypot(*(np.asarray(ell.center) - truth_px)) >= tol:
        return None
    try:
        return circle_poses(ell, disc.radius, cam.K)
    except CirclePoseError:
        return None


def evaluate(prs: list[dict], declared: str, response_declared: bool = True) -> dict:
    """Both methods on rendered pairs: the statistics of the module doc. ``response_declared`` False: the
    camera's response (``declared``, linear) was stated by nobody, as a lab that kept the default."""
    from ..vision import pose_pair_consistency, resolve_duality_detailed, resolve_duality_noise_aware

    acc: dict[str, dict[str, Any]] = {m: {"n": 0, "avail": 0, "gross": 0, "dual": [0, 0, 0], "z": [],
                                          "flags": {}, "centre": 0, "gross_kept": 0, "z_kept": [], "zc_kept": []}
                                   for m in ("labctl", "opencv")}
    for p in prs:
        cam = oracle.Cam(f=p["f"])
        got: dict[str, list] = {"labctl": [], "opencv": []}
        for disc, img in zip(p["discs"], p["images"]):
            rim = oracle.rim_pixels(cam, disc)
            truth = rim.mean(axis=0)
            tol = 0.5 * float(np.sqrt(np.mean(np.sum((rim - truth) ** 2, axis=1)))) + 3.0
            got["labctl"].append(_ours(img, cam, disc, truth, tol, declared, response_declared))
            got["opencv"].append(_opencv(img, cam, disc, truth, tol))
        mp = got["labctl"]
        trusted = [m is not None and m.trusted for m in mp]
        kept = [m is not None and "tracking" in m.fit_for for m in mp]
        for m in mp:
            if m is not None:
                for f in m.flags:
                    acc["labctl"]["flags"][f] = acc["labctl"]["flags"].get(f, 0) + 1
        if all(kept):
            # the two-view check (noise-aware: a near-frontal marker's large normal σ is in it) on every kept pair
            chk = pose_pair_consistency(mp[0], mp[1], displacement_mm=np.subtract(p["discs"][1].center,
                                                                                   p["discs"][0].center))
            if not chk.consistent:
                trusted, kept = [False, False], [False, False]
                acc["labctl"]["flags"]["inconsistent"] = acc["labctl"]["flags"].get("inconsistent", 0) + 2
        a_ = acc["labctl"]
        for k, (m, disc) in enumerate(zip(mp, p["discs"])):
            if not kept[k]:
                continue
            ne, ce, j = _errors(m.candidates, disc)
            a_["centre"] += 1
            # gross for its use: the centre for a tracking-only marker, centre and normal for a pose-grade one
            a_["gross_kept"] += ce > GROSS_CENTRE_PCT or (trusted[k] and ne > GROSS_NORMAL_DEG)
            a_["z_kept"].append(ne / max(math.degrees(float(m.normal_sigma_rad[j])), 1e-9))
            rng_mm = float(np.linalg.norm(disc.center))
            a_["zc_kept"].append(ce / 100.0 * rng_mm / max(math.sqrt(max(float(np.trace(m.center_cov[j])), 0.0)), 1e-9))
        for name in ("labctl", "opencv"):
            a = acc[name]
            cands: list[Any] = []
            for k, disc in enumerate(p["discs"]):
                a["n"] += 1
                r = got[name][k]
                ok = r is not None and (trusted[k] if name == "labctl" else True)
                if not ok:
                    cands.append(None)
                    continue
                c = r.candidates if name == "labctl" else r
                ne, ce, j = _errors(c, disc)
                a["avail"] += 1
                a["gross"] += ne > GROSS_NORMAL_DEG or ce > GROSS_CENTRE_PCT
                if name == "labctl":
                    a["z"].append(ne / max(math.degrees(float(r.normal_sigma_rad[j])), 1e-9))
                cands.append(r)
            if cands[0] is None or cands[1] is None:
                continue
            if name == "labctl":
                res = resolve_duality_noise_aware(cands[0], cands[1], motion="translation")
                c2 = cands[1].candidates
            else:
                res = resolve_duality_detailed(cands[0], cands[1], motion="translation")
                c2 = cands[1]
            d2 = p["discs"][1]
            err = _angle_deg(c2[res.index].normal, d2.normal)
            right = err <= _angle_deg(c2[1 - res.index].normal, d2.normal) or err <= GROSS_NORMAL_DEG
            a["dual"][1 if res.ambiguous else (0 if right else 2)] += 1
    out = {}
    for name, a in acc.items():
        out[name] = {"available": a["avail"] / max(a["n"], 1), "n_images": a["n"],
                     "gross_trusted": a["gross"] / a["avail"] if a["avail"] else 0.0,
                     "n_gross_trusted": a["gross"], "duality_right_ambiguous_wrong": a["dual"]}
        if name == "labctl":
            out[name]["z95"] = float(np.percentile(a["z"], 95)) if a["z"] else None
            out[name]["available_centre"] = a["centre"] / max(a["n"], 1)
            out[name]["n_kept"] = a["centre"]
            out[name]["n_gross_kept"] = a["gross_kept"]
            out[name]["z95_kept"] = float(np.percentile(a["z_kept"], 95)) if a["z_kept"] else None
            out[name]["z95_centre_kept"] = float(np.percentile(a["zc_kept"], 95)) if a["zc_kept"] else None
            out[name]["flags"] = a["flags"]
    return out


def run(renderer: str, n_pairs: int = 100, seed: int = 32, cache_dir: str | None = None,
        only: str | None = None, n_eval: int | None = None) -> list[dict]:
    """Every condition of ``renderer`` ("mitsuba" or "oracle"): rows {condition, declared, labctl, opencv}.
    ``n_eval``: judge only the first that many of the ``n_pairs`` rendered (cached) pairs."""
    conds = mitsuba_conditions() if renderer == "mitsuba" else oracle_conditions()
    cache_dir = cache_dir or os.environ.get("LABCTL_VISION_AVAIL_CACHE")
    rows = []
    for i, (name, cond, declared) in enumerate(conds):
        if only and only not in name:
            continue
        # the undeclared rows reuse their declared twin's images (same condition, same seed)
        twin = next((j for j, (_, c2, _) in enumerate(conds) if c2 == cond), i)
        prs = pairs(renderer, conds[twin][0], cond, n_pairs, seed + 100 * twin, cache_dir)
        rows.append({"condition": name, "declared": declared,
                     **evaluate(prs[:n_eval], declared, response_declared=not name.startswith("undeclared"))})
    return rows


def _pct_ci(frac: float, n: int) -> str:
    k = int(round(frac * n))
    lo, hi = wilson_interval(k, n)
    return f"{100 * frac:.0f} ({100 * lo:.0f}–{100 * hi:.0f})"


def table(rows: list[dict]) -> str:
    """Markdown table of :func:`run`'s rows: shares in % with 95 % Wilson intervals; gross as counts."""
    lines = ["| condition | pose-grade (trusted) | fit for its use (kept) | OpenCV | gross trusted / kept; OpenCV"
             " | duality R/A/W labctl; OpenCV | normal z95 trusted / kept; centre z95 kept | labctl flags |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        o, b = r["labctl"], r["opencv"]
        n = o["n_images"]
        z = f"{o['z95']:.2f}" if o.get("z95") is not None else "–"
        zk = f"{o['z95_kept']:.2f}" if o.get("z95_kept") is not None else "–"
        zc = f"{o['z95_centre_kept']:.2f}" if o.get("z95_centre_kept") is not None else "–"
        n_tr = int(round(o["available"] * n))
        fl = ", ".join(f"{k} {v}" for k, v in sorted(o["flags"].items(), key=lambda kv: -kv[1])[:4])
        lines.append(f"| {r['condition']} | {_pct_ci(o['available'], n)} | {_pct_ci(o['available_centre'], n)} | "
                     f"{_pct_ci(b['available'], b['n_images'])} | "
                     f"{o['n_gross_trusted']}/{n_tr} / {o['n_gross_kept']}/{o['n_kept']}; "
                     f"{b['n_gross_trusted']}/{int(round(b['available'] * b['n_images']))} | "
                     f"{'/'.join(map(str, o['duality_right_ambiguous_wrong']))}; "
                     f"{'/'.join(map(str, b['duality_right_ambiguous_wrong']))} | {z} / {zk}; {zc} | {fl} |")
    return "\n".join(lines)
