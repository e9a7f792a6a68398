"""The marker-vision degradation suite: ours vs the plain OpenCV pipeline on images of
the independent renderer :mod:`labctl.bench._vision_oracle`, with exact ground truth.

Each case renders ``n_pairs`` pairs of images of a 10 mm disc (640×480, f 1200–2500 px, range
600–1200 mm, obliquity 0–70°); the second image of a pair shows the disc translated by
10–50 mm (any direction), which resolves the pose duality (paper §3.3). Per case and method:

* ``detected``: fraction of images with a marker found at the disc (ellipse centre within half
  the disc's image radius + 3 px of the truth);
* ``normal_deg`` / ``centre_pct`` median and p95 over detected markers (the candidate nearer
  the truth; centre error in % of the range);
* ``gross``: fraction of detections with normal error > 3° or centre error > 2 % of range;
* ``confident_wrong``: fraction of images with a gross error (or a marker where there is
  none) that carries no flag, plus fraction of pairs whose duality was decided wrongly with
  neither marker flagged (the baseline has no flags: every answer is confident);
* ``duality``: pairs right / ambiguous / wrong (both images detected);
* ``paired``: for normal p95 and centre median, ours − OpenCV on the same images with a paired
  bootstrap 95 % interval (:func:`labctl.bench._vision_paired.paired_p95`, pose pairs resampled).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from . import _vision_oracle as oracle
from ._vision_paired import paired_p95

if TYPE_CHECKING:
    from ..vision.markers import MarkerQuality

C = oracle.Conditions
GROSS_NORMAL_DEG = 3.0
GROSS_CENTRE_PCT = 2.0


def _k(shift_px: float) -> float:
    """Radial distortion k (px⁻²) that moves an image corner (r = 400 px) by ``shift_px``."""
    return shift_px / 400.0**3


# (condition, [(strength label, Conditions, {camera overrides}, {options})])
SUITE: list[tuple[str, list]] = [
    ("clean", [("-", C(), {}, {})]),
    ("shadow edge", [(f"depth {d}", C(shadow=d), {}, {}) for d in (0.3, 0.5, 0.7)]),
    ("background texture", [(f"std {s}", C(texture_std=s), {}, {}) for s in (15, 25, 45)]),
    ("camera response", [("srgb", C(response="srgb"), {}, {}), ("gamma 2.2", C(response="gamma 2.2"), {}, {}),
                         ("gamma 2.2 + defocus 2", C(response="gamma 2.2", defocus_px=2.0), {}, {})]),
    ("specular highlight", [(f"{h} grey", C(highlight=h), {}, {}) for h in (80, 150, 300)]),
    ("occlusion", [(f"{int(o * 100)} % of rim", C(occlusion=o), {}, {}) for o in (0.1, 0.2, 0.3)]),
    ("red bar beside", [(f"gap {g} px", C(bar_gap_px=g), {}, {}) for g in (2.0, 4.0, 8.0)]),
    ("lone red bar", [(f"{w}×{h} px", C(lone_bar=(w, h)), {}, {}) for w, h in ((5, 40), (8, 30), (12, 24))]),
    ("hue shift", [(f"{h:+d}°", C(hue_shift_deg=h), {}, {}) for h in (10, 20, -20)]),
    ("white balance", [(f"R×{r} B×{b}", C(wb_gain_rgb=(r, 1.0, b)), {}, {})
                       for r, b in ((0.85, 1.2), (0.7, 1.45), (0.55, 1.8))]),
    ("exposure", [(f"×{e}", C(exposure=e), {}, {}) for e in (0.5, 0.25, 0.12)]),
    ("contrast", [(f"×{c}", C(contrast=c), {}, {}) for c in (0.8, 0.6, 0.45)]),
    ("gaussian noise", [(f"σ {s}", C(noise_std=s), {}, {}) for s in (4, 8, 16)]),
    ("poisson noise", [(f"{p} e⁻", C(photons=p, noise_std=0.0), {}, {}) for p in (2000, 500, 150)]),
    ("salt and pepper", [(f"{p * 100:.1f} %", C(salt_pepper=p), {}, {}) for p in (0.005, 0.01, 0.02)]),
    ("defocus", [(f"r {r} px", C(defocus_px=r), {}, {}) for r in (1.0, 2.0, 3.0)]),
    ("motion blur", [(f"{m} px", C(motion_px=m), {}, {}) for m in (3.0, 6.0, 10.0)]),
    ("jpeg", [(f"q {q}", C(jpeg_quality=q), {}, {}) for q in (90, 70, 50)]),
    ("bayer + demosaic", [(d, C(bayer=d, noise_std=2.0), {}, {}) for d in ("bilinear", "vng", "ea")]),
    ("vignetting", [(f"{v}", C(vignetting=v), {}, {}) for v in (0.3, 0.5, 0.7)]),
    ("illumination gradient", [(f"{g}", C(gradient=g), {}, {}) for g in (0.3, 0.6, 0.8)]),
    ("lens distortion, modelled", [(f"corner {s} px", C(), {"k_px": _k(s)}, {"model": True}) for s in (2, 5, 10)]),
    ("lens distortion, unmodelled", [(f"corner {s} px", C(), {"k_px": _k(s)}, {}) for s in (2, 5, 10)]),
    ("combination", [
        ("webcam", C(response="srgb", jpeg_quality=70, noise_std=4.0, bayer="bilinear", vignetting=0.3,
                     wb_gain_rgb=(0.9, 1.0, 1.15)), {}, {}),
        ("moving part, industrial light", C(motion_px=6.0, exposure=0.5, noise_std=6.0, highlight=150), {}, {}),
        ("dim workcell", C(response="gamma 2.2", exposure=0.15, photons=300, noise_std=3.0), {}, {}),
        ("cluttered bench", C(texture_std=35, bar_gap_px=4.0, shadow=0.5), {}, {}),
    ]),
]


def _labctl_camera(cam: oracle.Cam, model: bool):
    from ..geometry.camera import CameraModel

    dx = 0.01
    cx, cy = cam.c
    return CameraModel(f=cam.f * dx, kappa1=(cam.k_px / dx**2) if model else 0.0, sx=1.0, cx=cx, cy=cy, dx=dx,
                       dy=dx, ncx=cam.width, nfx=cam.width, width=cam.width, height=cam.height)


def _angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(a, b))), float(a @ b)))


def _errors(cands, disc: oracle.Disc) -> tuple[float, float, int]:
    """(normal error °, centre error % of range, index) of the candidate nearer the truth."""
    errs = [_angle_deg(c.normal, disc.normal) for c in cands]
    j = int(np.argmin(errs))
    rng_mm = float(np.linalg.norm(disc.center))
    return errs[j], 100.0 * float(np.linalg.norm(np.asarray(cands[j].center) - disc.center)) / rng_mm, j


def _ours(img, cam, disc, truth_px, tol_px, cond, opts):
    """(found, cands or None, trusted, false_positive_trusted, pose_sigma) for our pipeline."""
    from ..vision import find_markers, marker_poses

    res = find_markers(img, response=cond.response)
    camera = _labctl_camera(cam, opts.get("model", False))
    hit, fp = None, False
    for mk in res.markers:
        if hit is None and np.hypot(*(np.asarray(mk.ellipse.center) - truth_px)) < tol_px:
            hit = mk
        elif cast("MarkerQuality", mk.quality).trusted:  # find_markers measures every marker's quality
            fp = True
    if hit is None:
        return False, None, False, fp, None
    try:
        poses = marker_poses(hit, camera, disc.radius)
    except ValueError:
        return True, None, False, fp, None
    return True, poses.candidates, poses.trusted, fp, poses


def _baseline(img, cam, disc, truth_px, tol_px, cond, opts):
    from ..vision import CirclePoseError, circle_poses
    from .vision_baselines import opencv_marker_ellipse

    ell = opencv_marker_ellipse(img)
    if ell is None:
        return False, None, False, False, None
    if np.hypot(*(np.asarray(ell.center) - truth_px)) >= tol_px:
        return False, None, False, True, None  # the largest red blob is not the marker: a confident wrong answer
    try:
        cands = circle_poses(ell, disc.radius, cam.K)
    except CirclePoseError:
        return True, None, True, False, None
    return True, cands, True, False, None


def _pct(v, q):
    """Percentile, or None when nothing was measured (JSON has no NaN)."""
    return float(np.percentile(v, q)) if len(v) else None


def run_case(cond: oracle.Conditions, cam_over: dict, opts: dict, n_pairs: int, seed: int,
             per_image: bool = False) -> dict:
    """Both methods on ``n_pairs`` image pairs of one condition; the statistics of the module doc.

    With ``per_image``, ``out["per_image"][method]`` also holds the normal error (°) and centre
    error (% of range) of every image in render order (image 2i and 2i + 1 are pair i; NaN where
    the method found no marker or no pose), for paired comparisons of the two methods on the same
    images (:func:`labctl.bench._vision_paired.paired_p95`)."""
    from ..vision import pose_pair_consistency, resolve_duality_detailed, resolve_duality_noise_aware

    rng = np.random.default_rng(seed)
    methods = {"labctl": _ours, "opencv": _baseline}
    acc: dict[str, dict[str, Any]] = {m: {"n": 0, "found": 0, "normal": [], "centre": [], "gross": 0, "cw_img": 0,
               "dual": [0, 0, 0], "cw_pair": 0, "n_pairs": 0,
               "inconsistent": 0, "img_normal": [], "img_centre": []} for m in methods}
    for _ in range(n_pairs):
        cam = oracle.Cam(f=float(rng.uniform(1200, 2500)), **cam_over)
        d1 = oracle.random_pose(rng, cam)
        for _ in range(50):
            v = rng.standard_normal(3)
            d2 = oracle.translated(d1, v / np.linalg.norm(v) * rng.uniform(10, 50))
            rim = oracle.rim_pixels(cam, d2, 64)
            if (rim.min(axis=0) > 30).all() and (rim[:, 0] < cam.width - 30).all() \
                    and (rim[:, 1] < cam.height - 30).all():
                break
        pair_seed = int(rng.integers(2**31))
        results: dict[str, list[Any]] = {m: [] for m in methods}
        for k, disc in enumerate((d1, d2)):
            img, info = oracle.render(cam, disc, cond, np.random.default_rng(pair_seed + k))
            rim = oracle.rim_pixels(cam, disc)
            truth_px = rim.mean(axis=0)
            r_px = float(np.sqrt(np.mean(np.sum((rim - truth_px) ** 2, axis=1))))
            tol = 0.5 * r_px + 3.0
            for name, fn in methods.items():
                a = acc[name]
                a["n"] += 1
                found, cands, trusted, fp, poses = fn(img, cam, disc, truth_px, tol, cond, opts)
                if not info["marker"]:
                    found, cands = False, None
                    fp = fp or trusted
                if fp:
                    a["cw_img"] += 1
                a["found"] += found
                if cands is None:
                    results[name].append(None)
                    a["img_normal"].append(math.nan)
                    a["img_centre"].append(math.nan)
                    continue
                ne, ce, j = _errors(cands, disc)
                a["img_normal"].append(ne)
                a["img_centre"].append(ce)
                a["normal"].append(ne)
                a["centre"].append(ce)
                gross = ne > GROSS_NORMAL_DEG or ce > GROSS_CENTRE_PCT
                a["gross"] += gross
                results[name].append([cands, trusted, poses, gross and not fp])  # fp: counted above
        for name in methods:
            r1, r2 = results[name]
            a = acc[name]
            if name == "labctl" and r1 is not None and r2 is not None:
                # the two images must agree with the known motion (the disc's shift): a pose pair
                # that does not is flagged ``inconsistent`` (both markers)
                chk = pose_pair_consistency(r1[2], r2[2], displacement_mm=np.subtract(d2.center, d1.center))
                a["inconsistent"] += not chk.consistent
                if not chk.consistent:
                    r1[1] = r2[1] = False
            for r in (r1, r2):
                if r is not None and r[3] and r[1]:
                    a["cw_img"] += 1
            if r1 is None or r2 is None:
                continue
            a["n_pairs"] += 1
            if name == "labctl":
                res = resolve_duality_noise_aware(r1[2], r2[2], motion="translation")
            else:
                res = resolve_duality_detailed(r1[0], r2[0], motion="translation")
            right = _angle_deg(r2[0][res.index].normal, d2.normal) <= _angle_deg(r2[0][1 - res.index].normal,
                                                                                  d2.normal)
            if res.ambiguous:
                a["dual"][1] += 1
            elif right:
                a["dual"][0] += 1
            else:
                a["dual"][2] += 1
                if r1[1] and r2[1]:
                    a["cw_pair"] += 1
    out = {}
    for name, a in acc.items():
        nd = len(a["normal"])
        out[name] = {
            "detected": a["found"] / a["n"],
            "normal_deg_median": _pct(a["normal"], 50), "normal_deg_p95": _pct(a["normal"], 95),
            "centre_pct_median": _pct(a["centre"], 50), "centre_pct_p95": _pct(a["centre"], 95),
            "gross": a["gross"] / nd if nd else 0.0,
            "confident_wrong": a["cw_img"] / a["n"] + (a["cw_pair"] / a["n_pairs"] if a["n_pairs"] else 0.0),
            "duality_right_ambiguous_wrong": list(a["dual"]),
            "inconsistent_pairs": a["inconsistent"],
        }
    o, b = acc["labctl"], acc["opencv"]
    out["paired"] = {key: paired_p95(o[img], b[img], n_boot=1000, seed=seed, q=q)
                     for key, img, q in (("normal_deg_p95", "img_normal", 95.0),
                                         ("centre_pct_median", "img_centre", 50.0))}
    if per_image:
        out["per_image"] = {name: {"normal_deg": a["img_normal"], "centre_pct": a["img_centre"]}
                            for name, a in acc.items()}
    return out


def run_suite(n_pairs: int = 40, seed: int = 14, only: str | None = None) -> list[dict]:
    """Every case of :data:`SUITE` (or those whose condition contains ``only``): rows of
    {condition, strength, visible, labctl: stats, opencv: stats}."""
    rows = []
    for ci, (name, cases) in enumerate(SUITE):
        if only and only not in name:
            continue
        for si, (label, cond, cam_over, opts) in enumerate(cases):
            stats = run_case(cond, cam_over, opts, n_pairs, seed + 1000 * ci + si)
            visible = 0.0 if cond.lone_bar else 1.0 - cond.occlusion
            rows.append({"condition": name, "strength": label, "visible": visible, **stats})
    return rows


def acceptance(rows: list[dict]) -> dict:
    """The issue's acceptance checks per row: confident wrong ≤ 1 %, detection within 1 point of
    the baseline's where ≥ 80 % of the marker is visible, normal p95 and centre median no worse
    than the baseline's (NaN-free rows only), clean accuracy.

    A normal p95 or centre median above the baseline's is a failure when the paired bootstrap
    interval of ours − OpenCV lies wholly above 0 (worse with 95 % confidence); when the interval
    contains 0 the row goes to ``inconclusive`` instead (the difference is within the sampling
    noise of this many pairs: re-run that case with more pairs, as docs/notes/vision.md does)."""
    fails, unsure = [], []
    for r in rows:
        o, b = r["labctl"], r["opencv"]
        tag = f"{r['condition']} / {r['strength']}"
        if o["confident_wrong"] > 0.01:
            fails.append(f"{tag}: confident wrong {100 * o['confident_wrong']:.1f} %")
        if r["visible"] >= 0.8 and o["detected"] < b["detected"] - 0.01:
            fails.append(f"{tag}: detected {100 * o['detected']:.1f} % vs baseline {100 * b['detected']:.1f} %")
        for key in ("normal_deg_p95", "centre_pct_median"):
            if b[key] is not None and o[key] is not None and o[key] > b[key]:
                pr = r.get("paired", {}).get(key)
                msg = f"{tag}: {key} {o[key]:.3g} vs baseline {b[key]:.3g}"
                if pr is not None and (pr["lo"] is None or not pr["lo"] > 0):
                    unsure.append(f"{msg} (paired difference {pr['diff']:+.3g}, 95 % interval "
                                  f"[{pr['lo']:+.3g}, {pr['hi']:+.3g}])")
                else:
                    fails.append(msg + (f" (95 % interval [{pr['lo']:+.3g}, {pr['hi']:+.3g}])" if pr else ""))
        if r["condition"] == "clean" and not (o["normal_deg_median"] is not None and o["normal_deg_median"] <= 0.05
                                              and o["centre_pct_median"] <= 0.05):
            fails.append(f"{tag}: clean accuracy {o['normal_deg_median']:.3f}° / {o['centre_pct_median']:.3f} %")
    return {"ok": not fails, "failures": fails, "inconclusive": unsure}


def replace_cond(cond: oracle.Conditions, **kw) -> oracle.Conditions:
    """A copy of ``cond`` with the given fields replaced."""
    return replace(cond, **kw)
