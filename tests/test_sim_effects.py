"""The simulated lab's realistic-camera effects (issue 14, Build 7) against independent expectations.

Each effect is checked against something computed without the renderer's own code: the cast
shadow against the convex hull of the box's vertices projected along the light (the renderer
unions light-facing triangles), the highlight against the Blinn-Phong formula, the response
against the IEC 61966-2-1 sRGB curve, Bayer and JPEG against OpenCV applied to the plain frame.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from labctl.config import ConfigError, load_lab
from labctl.geometry import CameraModel, apply, invert, look_at
from labctl.sim.effects import CameraEffects, EffectsError, bayer_mosaic, effects_from_lab
from labctl.sim.render import DEFAULT_LIGHT_DIR_W, MarkerDisc, Mesh, render
from labctl.vision.response import parse_response
from labctl.workspace import init_workspace, sample_lab_path

FIXED = CameraModel(f=25.0, kappa1=0.0, sx=1.0, cx=319.5, cy=239.5, dx=0.013, dy=0.013, ncx=640, nfx=640)
MOBILE = CameraModel(f=25.0, kappa1=-0.0008, sx=1.0, cx=319.5, cy=239.5, dx=0.0098, dy=0.0098, ncx=640, nfx=640)
LIGHT = np.asarray(DEFAULT_LIGHT_DIR_W, float) / np.linalg.norm(DEFAULT_LIGHT_DIR_W)
AMBIENT = 0.55  # the renderer's ambient share (render._AMBIENT), restated: the test's own shading model
SIZE, CENTRE = np.array([40.0, 30.0, 35.0]), np.array([300.0, 200.0, 17.5])


def scene():
    m = trimesh.creation.box(SIZE)
    m.apply_translation(CENTRE)
    top = MarkerDisc(center=CENTRE + [0, 0, SIZE[2] / 2], normal=np.array([0.0, 0, 1]), radius=8.0)
    side = MarkerDisc(center=CENTRE + [SIZE[0] / 2, 0, 0], normal=np.array([1.0, 0, 0]), radius=8.0)
    return [Mesh(m.vertices, m.faces, markers=[top, side])]


T_FIXED = look_at(np.array([300.0, 200.0, 1200.0]), [300.0, 200.0, 0.0], up=(0, 1, 0))
T_MOBILE = look_at(np.array([520.0, 60.0, 500.0]), [300.0, 200.0, 20.0], up=(0, 0, 1))


def draw(camera, T_w_c, effects=None, **kw):
    kw.setdefault("noise_sigma", 0.0)
    return render(camera, T_w_c, scene(), effects=effects, rng=np.random.default_rng(5), **kw)


def test_effects_off_render_exactly_as_before():
    assert not CameraEffects().any and not CameraEffects(response="linear", texture=1.0).any
    for cam, T in ((FIXED, T_FIXED), (MOBILE, T_MOBILE)):
        plain = draw(cam, T, noise_sigma=2.0).image
        assert np.array_equal(plain, draw(cam, T, CameraEffects(), noise_sigma=2.0).image)
        assert np.array_equal(plain, draw(cam, T, CameraEffects(response="linear"), noise_sigma=2.0).image)
    # the sample lab (no sim section) gives its cameras no effects: trials render as they always did
    lab = load_lab(sample_lab_path())
    assert effects_from_lab(lab, lab.fixed_camera) is None and effects_from_lab(lab, lab.mobile_camera) is None


def test_shadow_darkens_the_table_inside_the_independently_computed_polygon():
    res = draw(FIXED, T_FIXED, truth=True)
    shadowed = draw(FIXED, T_FIXED, CameraEffects(shadows=1.0)).image.astype(float)
    plain = res.image.astype(float)
    # oracle: the convex hull of the box's corners projected along the light onto z = 0, into the image
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * SIZE / 2 + CENTRE
    ground = corners[:, :2] - (corners[:, 2:3] / LIGHT[2]) * LIGHT[None, :2]
    hull = cv2.convexHull(ground.astype(np.float32))[:, 0, :]
    px = FIXED.project(apply(invert(T_FIXED), np.column_stack([hull, np.zeros(len(hull))])))
    poly = np.zeros(plain.shape[:2], np.uint8)
    cv2.fillPoly(poly, [np.round(px).astype(np.int32)], 1)
    k = np.ones((7, 7), np.uint8)
    table = ~cv2.dilate(res.mask.astype(np.uint8), k).astype(bool)  # table pixels, 3 px from the object
    inside = cv2.erode(poly, k).astype(bool) & table
    outside = ~cv2.dilate(poly, k).astype(bool) & table
    assert inside.sum() > 150  # a real stretch of shadow is seen beside the box
    f = AMBIENT / (AMBIENT + (1 - AMBIENT) * LIGHT[2])  # only the ambient light left
    ratio = shadowed[inside].sum() / plain[inside].sum()
    assert ratio == pytest.approx(f, abs=0.01)
    assert np.array_equal(shadowed[outside], plain[outside])
    # the object itself is not changed by its shadow (its anti-aliased rim blends in the table behind)
    body = cv2.erode(res.mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert np.array_equal(shadowed[body], plain[body])


def test_specular_highlight_follows_blinn_phong():
    ks, s = 0.2, 30.0
    res = draw(FIXED, T_FIXED, truth=True)
    lit = draw(FIXED, T_FIXED, CameraEffects(specular=ks, shininess=s)).image.astype(float)
    plain = res.image.astype(float)
    # the top face (normal +z) seen from the overhead camera: h between the light and the view
    top_px = FIXED.project(apply(invert(T_FIXED), (CENTRE + [10.0, 8.0, SIZE[2] / 2])[None]))[0]
    u, v = np.round(top_px).astype(int)
    eye = T_FIXED[:3, 3]
    view = eye - (CENTRE + [0, 0, SIZE[2] / 2])
    h = LIGHT + view / np.linalg.norm(view)
    expected = 255 * ks * (h[2] / np.linalg.norm(h)) ** s
    assert expected > 5
    assert lit[v, u] - plain[v, u] == pytest.approx(np.full(3, expected), abs=1.0)
    # the top marker brightens by the same amount (its colour is below full scale)
    mk_px = FIXED.project(apply(invert(T_FIXED), (CENTRE + [0, 0, SIZE[2] / 2])[None]))[0]
    mu, mv = np.round(mk_px).astype(int)
    assert lit[mv, mu] - plain[mv, mu] == pytest.approx(np.full(3, expected), abs=1.0)
    # the table has no specular term (away from the anti-aliased rim, which blends in the face)
    table = ~cv2.dilate(res.mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert np.array_equal(lit[table], plain[table])


def test_response_encodes_linear_values_by_the_srgb_curve():
    plain = draw(MOBILE, T_MOBILE, noise_sigma=2.0).image
    enc = draw(MOBILE, T_MOBILE, CameraEffects(response="srgb"), noise_sigma=2.0).image
    x = np.arange(256) / 255.0
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)  # IEC 61966-2-1
    expected = np.round(255 * srgb)
    assert np.abs(enc.astype(float) - expected[plain]).max() <= 1.0
    # and vision's linearisation of the camera's frames gives back the linear render
    lin = parse_response("srgb").linearise(enc) * 255.0
    bright = plain >= 30  # sRGB codes are coarse in the deep shadows
    assert np.abs(lin[bright] - plain[bright]).max() <= 1.0
    gamma = draw(MOBILE, T_MOBILE, CameraEffects(response="gamma 2.2"), noise_sigma=2.0).image
    assert np.abs(gamma.astype(float) - np.round(255 * x ** (1 / 2.2))[plain]).max() <= 1.0


def test_texture_strength_scales_the_table_contrast():
    res = draw(MOBILE, T_MOBILE, truth=True)
    table = ~res.mask & np.isfinite(res.depth)
    strong = draw(MOBILE, T_MOBILE, CameraEffects(texture=2.0)).image
    flat = draw(MOBILE, T_MOBILE, CameraEffects(texture=0.0)).image
    s1, s2 = res.image[table][:, 1].std(), strong[table][:, 1].std()
    assert s2 / s1 == pytest.approx(2.0, rel=0.1)
    assert flat[table][:, 1].std() < 0.25 * s1  # only shading (and its rounding) is left


def test_bayer_and_jpeg_are_opencvs_pipeline_on_the_plain_frame():
    plain = draw(MOBILE, T_MOBILE, noise_sigma=2.0).image
    bayer = draw(MOBILE, T_MOBILE, CameraEffects(bayer="bilinear"), noise_sigma=2.0).image
    assert np.array_equal(bayer, cv2.cvtColor(bayer_mosaic(plain), cv2.COLOR_BayerBG2BGR))
    assert not np.array_equal(bayer, plain)
    assert np.abs(bayer.astype(int) - plain).mean() < 4  # a demosaic, not a different scene
    jpeg = draw(MOBILE, T_MOBILE, CameraEffects(jpeg_quality=70), noise_sigma=2.0).image
    _, buf = cv2.imencode(".jpg", plain, [cv2.IMWRITE_JPEG_QUALITY, 70])
    assert np.array_equal(jpeg, cv2.imdecode(buf, cv2.IMREAD_COLOR))
    assert not np.array_equal(jpeg, plain)
    # the mosaic keeps one channel per site, RGGB
    raw = bayer_mosaic(plain)
    assert raw[0, 0] == plain[0, 0, 2] and raw[0, 1] == plain[0, 1, 1] and raw[1, 1] == plain[1, 1, 0]


@pytest.mark.parametrize("camera,T", [(FIXED, T_FIXED), (MOBILE, T_MOBILE)], ids=["fixed", "mobile"])
def test_window_with_every_effect_equals_the_full_frame_there(camera, T):
    fx = CameraEffects(response="srgb", shadows=0.8, specular=0.12, shininess=60.0, texture=1.5, bayer="vng",
                       jpeg_quality=80)
    full = draw(camera, T, fx, noise_sigma=2.0, supersample=1).image
    for window in ((283, 173, 360, 251), (5, 7, 61, 50), (600, 430, 640, 480)):
        win = draw(camera, T, fx, noise_sigma=2.0, supersample=1, window=window).image
        x0, y0, x1, y1 = window
        assert np.array_equal(win[y0:y1, x0:x1], full[y0:y1, x0:x1]), window


def test_bad_settings_are_refused(tmp_path):
    with pytest.raises(EffectsError):
        CameraEffects(bayer="rggb")
    with pytest.raises(EffectsError):
        CameraEffects(shadows=1.5)
    with pytest.raises(EffectsError):
        CameraEffects(jpeg_quality=0)
    lab_dir = init_workspace(tmp_path / "lab")
    text = (lab_dir / "lab.yaml").read_text()
    for bad, key in (("preset: shiny", "sim.camera.preset"), ("shadows: 2", "sim.camera.shadows"),
                     ("jpeg_quality: 101", "sim.camera.jpeg_quality"), ("bayer: rggb", "sim.camera.bayer")):
        (lab_dir / "lab.yaml").write_text(text + f"sim:\n  camera:\n    {bad}\n")
        with pytest.raises(ConfigError) as err:
            load_lab(lab_dir)
        assert key in str(err.value)
    # a response the sim could not encode with (nor vision linearise by) is refused at load time
    (lab_dir / "lab.yaml").write_text(text)
    cam = lab_dir / "drivers" / "mobile_camera.yaml"
    for bad in ("gamma 9", "gamma x", "[1.0, 0.5]"):
        cam.write_text(cam.read_text().split("\nresponse:")[0] + f"\nresponse: {bad}\n")
        with pytest.raises(ConfigError, match="response"):
            load_lab(lab_dir)


def test_init_preset_makes_a_consistent_realistic_lab(tmp_path):
    lab = load_lab(init_workspace(tmp_path / "lab", preset="realistic-camera"))
    assert lab.config.sim.camera.preset == "realistic"
    for cam in (lab.fixed_camera, lab.mobile_camera):
        fx = effects_from_lab(lab, cam)
        assert cam.response == "srgb" and fx.response.name == "srgb"  # the sim renders what vision linearises
        assert fx.shadows > 0 and fx.specular > 0 and fx.texture != 1 and fx.bayer and fx.jpeg_quality
    # an override in lab.yaml beats the preset
    path = lab.root / "lab.yaml"
    path.write_text(path.read_text() + "    jpeg_quality: 95\n    bayer: none\n")
    lab = load_lab(lab.root)
    fx = effects_from_lab(lab, lab.fixed_camera)
    assert fx.jpeg_quality == 95 and fx.bayer is None and fx.shadows == 0.8
    path.write_text(path.read_text().replace("jpeg_quality: 95", "jpeg_quality: 0"))
    lab = load_lab(lab.root)
    assert effects_from_lab(lab, lab.fixed_camera).jpeg_quality is None


def test_virtual_run_with_the_realistic_camera_identifies_its_object(tmp_path):
    from labctl.decisions.context import RunContext
    from labctl.runtime.virtual import TrialSpec, simulate_run

    lab = load_lab(init_workspace(tmp_path / "lab", preset="realistic-camera"))
    ctx = RunContext.load(lab)
    res = simulate_run(lab, ctx, TrialSpec("line", 8.0, None, 3))
    assert res["failure"] is None, res
    assert res["correct"] is True and res["identity"] == res["true_identity"]
    assert res["marker_pose_error"]["normal_deg"] < 3.0


def test_realistic_run_falls_back_to_a_suspect_marker_when_the_trusted_one_is_ambiguous(tmp_path):
    # (with the marker-height gate off: the gate alone tells angle_short from tee in this placement)
    # seed 1008 places angle_short so that, in JPEG frames, only its top marker is trusted (the side
    # marker is flagged rough/blurred) and the top's standard view cannot tell it from tee; re-viewing
    # the same marker failed ("still ambiguous after 3 standard views") before the recogniser took
    # the more novel suspect marker as a last resort. (It regressed with vision14b's motion refit, which took
    # the JPEG/Bayer blur of that side marker for a motion smear: its normal σ rose from 0.53° to 0.70°, past
    # the recogniser's 0.6° gate for suspects; the refit now needs the anisotropic part to dominate.)
    import yaml

    from labctl.decisions.context import RunContext
    from labctl.runtime.virtual import TrialSpec, simulate_run

    root = init_workspace(tmp_path / "lab", preset="realistic-camera")
    cfg = yaml.safe_load((root / "lab.yaml").read_text())
    cfg.setdefault("run", {})["height_gate_mm"] = 0.0  # the marker height alone would resolve it at once
    # the robot limits this placement was found with: the viewpoints, and so which markers are seen, follow them
    cfg["run"]["robot_stop_budget_s"] = None
    cfg["run"]["profile"] = "quintic"  # (and the segment profile it was found with)
    # (and the re-plans it was found with: holding an initial view that already has the marker makes the second
    # and third viewpoints arrive seconds earlier, from where the side marker is not seen and the run ends
    # "still ambiguous after 3 standard views"; docs/notes/planning.md, "Ninth round")
    cfg["run"]["initial_view_hold"] = False
    # (and the commit horizon it was found with: 0.8 s commits two frames sooner, from other viewpoints; and its
    # 40-mm commit gate over at least 3 fixes: the sample lab starts on the first fix since issue 33)
    cfg.setdefault("tracking", {})["commit_horizon_s"] = 1.5
    cfg["tracking"]["commit_margin_mm"] = 40.0
    cfg["tracking"]["commit_min_updates"] = 3
    (root / "lab.yaml").write_text(yaml.safe_dump(cfg))
    robot = yaml.safe_load((root / "drivers" / "robot.yaml").read_text())
    robot["a_max_mm_s2"] = 1500.0
    # (and the robot it was found with: a flange in its box; the arm's checked plans and longer STATUS lines
    # move the viewpoints, so that the side marker is not seen)
    robot["arm"] = None
    (root / "drivers" / "robot.yaml").write_text(yaml.safe_dump(robot))
    lab = load_lab(root)
    res = simulate_run(lab, RunContext.load(lab), TrialSpec("line", 8.0, "angle_short", 1008))
    assert res["failure"] is None, res
    # (2 standard views when found; 3 since the start-sooner flow picks another first view, still inside
    # run.max_views: without the fallback this placement ended "still ambiguous after 3 standard views")
    assert res["correct"] is True and res["views"] <= lab.config.run.max_views
    assert res["marker_pose_error"]["normal_deg"] < 3.0
