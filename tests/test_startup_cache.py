"""The disk cache behind a prompt start (``labctl.fsutil.cached_arrays``): the simulated lab's table texture and
pixel rays and the library's meshes read back bit for bit what the code computes (the oracles: the drawing
code itself, and trimesh's own loader), a changed input is never served stale, a torn or foreign entry is
recomputed, and with a warm cache the simulated world is built without importing trimesh."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh

from labctl import fsutil
from labctl.geometry import CameraModel
from labctl.library.storage import load_library
from labctl.sim import render
from labctl.workspace import init_workspace


@pytest.fixture
def cache(tmp_path, monkeypatch):
    root = tmp_path / "cache"
    monkeypatch.setenv(fsutil.CACHE_ENV, str(root))
    return root


def test_an_entry_is_computed_once_then_read_back_and_a_new_key_or_a_torn_file_recomputes(cache):
    calls = []

    def compute(scale=1.0):
        calls.append(scale)
        rng = np.random.default_rng(3)
        return {"a": rng.standard_normal((7, 5)) * scale, "b": np.arange(12, dtype=np.int64).reshape(3, 4)}

    first = fsutil.cached_arrays("t", ("k", 1), ("a", "b"), compute)
    again = fsutil.cached_arrays("t", ("k", 1), ("a", "b"), compute)
    assert calls == [1.0]
    for k in ("a", "b"):
        assert again[k].dtype == first[k].dtype and np.array_equal(again[k], first[k])
    other = fsutil.cached_arrays("t", ("k", 2), ("a", "b"), lambda: compute(2.0))  # another input: another entry
    assert calls == [1.0, 2.0] and np.array_equal(other["a"], 2.0 * first["a"])
    for p in (cache / "t").iterdir():
        p.write_bytes(p.read_bytes()[:100])  # torn (a crash mid-write without fsync)
    torn = fsutil.cached_arrays("t", ("k", 1), ("a", "b"), compute)
    assert calls == [1.0, 2.0, 1.0] and np.array_equal(torn["a"], first["a"])
    # an entry holding other names (another version of the code) is a miss, not a KeyError
    wrong = fsutil.cached_arrays("t", ("k", 1), ("a", "c"), lambda: {"a": first["a"], "c": first["b"]})
    assert sorted(wrong) == ["a", "c"]


def test_no_cache_when_the_folder_is_set_empty_or_cannot_be_written(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setenv(fsutil.CACHE_ENV, "")
    for _ in range(2):
        fsutil.cached_arrays("t", ("k",), ("a",), lambda: calls.append(1) or {"a": np.zeros(3)})
    assert len(calls) == 2
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv(fsutil.CACHE_ENV, str(blocker / "sub"))
    out = fsutil.cached_arrays("t", ("k",), ("a",), lambda: calls.append(1) or {"a": np.ones(3)})
    assert len(calls) == 3 and np.array_equal(out["a"], np.ones(3))


def test_the_table_texture_from_the_cache_is_the_drawn_one_bit_for_bit(cache):
    seed = 11
    render._table_grey.cache_clear()
    miss = render._table_grey(seed)
    render._table_grey.cache_clear()
    hit = render._table_grey(seed)  # from the disk
    render._table_grey.cache_clear()
    drawn = render._draw_table_grey(seed)  # the oracle: the drawing code, no cache
    assert hit.dtype == drawn.dtype == np.float32 and hit.shape == drawn.shape
    assert np.array_equal(miss, drawn) and np.array_equal(hit, drawn)
    assert not np.array_equal(render._draw_table_grey(seed + 1), drawn)  # the seed is in the key, and matters


def test_the_noise_bank_from_the_cache_is_the_drawn_one_bit_for_bit(cache):
    # the sensor noise every frame takes a window of: from the disk on a second start, the same bytes as drawn
    render._noise_bank.cache_clear()
    miss = render._noise_bank(48, 64, 2.5)
    render._noise_bank.cache_clear()
    hit = render._noise_bank(48, 64, 2.5)  # from the disk
    render._noise_bank.cache_clear()
    drawn = render._draw_noise_bank(48, 64, 2.5)  # the oracle: the drawing code, no cache
    for a, b, c in zip(miss, hit, drawn):
        assert a.dtype == b.dtype == c.dtype == np.uint8 and np.array_equal(a, c) and np.array_equal(b, c)
    assert hit[0].shape == (48 + render._NOISE_MARGIN, 64 + render._NOISE_MARGIN, 3) and hit[0].any()
    other = render._noise_bank(48, 64, 5.0)  # sigma is in the key, and matters
    assert not np.array_equal(other[0], hit[0]) and np.array_equal(other[0], render._draw_noise_bank(48, 64, 5.0)[0])
    render._noise_bank.cache_clear()


def test_pixel_rays_from_the_cache_are_the_computed_ones_and_another_camera_is_another_entry(cache):
    cam = CameraModel(f=8.0, kappa1=2e-3, sx=1.0, cx=33.0, cy=23.0, dx=0.01, dy=0.01, ncx=64, nfx=64,
                      width=64, height=48)
    other = cam.with_(kappa1=-3e-3)
    for c in (cam, other):
        render._full_pixel_rays.cache_clear()
        render._full_pixel_rays(c)
        render._full_pixel_rays.cache_clear()
        hit = render._full_pixel_rays(c)  # from the disk
        ref = render._compute_pixel_rays(c)
        for k in render._RAY_FIELDS:
            a, b = getattr(hit, k), getattr(ref, k)
            assert a.dtype == b.dtype and np.array_equal(a, b), k
    render._full_pixel_rays.cache_clear()
    assert not np.array_equal(render._full_pixel_rays(cam).nx64, render._full_pixel_rays(other).nx64)
    assert len(list((cache / "render").iterdir())) == 2


def test_library_mesh_arrays_are_trimeshs_and_a_changed_model_is_read_again(cache, tmp_path):
    lab = init_workspace(tmp_path / "lab")
    names = sorted(load_library(lab / "object_library"))
    for name in names[:2]:
        for _ in range(2):  # a miss, then a hit
            obj = load_library(lab / "object_library")[name]
            V, F = obj.mesh_arrays()
            direct = trimesh.load(obj.folder / "model.stl", force="mesh")  # the oracle: trimesh's loader
            assert V.dtype == np.float64 and np.array_equal(V, direct.vertices)
            assert np.array_equal(F, direct.faces)
    # the first object's model replaced by the second's: its cached arrays are not served for the new bytes
    a, b = (lab / "object_library" / n / "model.stl" for n in names[:2])
    a.write_bytes(b.read_bytes())
    V, F = load_library(lab / "object_library")[names[0]].mesh_arrays()
    direct = trimesh.load(b, force="mesh")
    assert np.array_equal(V, direct.vertices) and np.array_equal(F, direct.faces)


def test_with_a_warm_cache_the_simulated_world_is_built_without_trimesh(cache, tmp_path):
    from labctl.runtime import live

    assert "trimesh" not in live._PRELOAD  # the process server no longer imports it for every run
    lab = init_workspace(tmp_path / "lab")
    code = (f"import sys; from labctl.library.storage import load_library; from labctl.sim.world import SimObject; "
            f"lib = load_library({str(lab / 'object_library')!r}); "
            f"objs = [SimObject.from_library(lib[n]) for n in sorted(lib)]; "
            f"print(sum(len(o.faces) for o in objs), 'trimesh' in sys.modules)")
    env = {**__import__("os").environ, fsutil.CACHE_ENV: str(cache)}
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
            for _ in range(2)]
    assert all(r.returncode == 0 for r in runs), runs[-1].stderr[-2000:]
    (n1, first), (n2, second) = (r.stdout.split() for r in runs)
    assert n1 == n2 and first == "True" and second == "False"  # the first run read the models with trimesh
