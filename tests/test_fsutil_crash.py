"""fsutil: a process killed (SIGKILL) at every step of a write leaves the old version or the new one.

Each case forks a child that counts its file-system calls and kills itself just before the k-th;
k runs from 1 until the child completes, so every step of the write is a crash instant.
"""

from __future__ import annotations

import os
import shutil
import signal
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from labctl import fsutil

TRAPPED = ("open", "write", "fsync", "replace", "rename", "mkdir", "rmdir", "unlink", "fchmod", "close")


def _crash_at(k: int, job) -> bool:
    """Run ``job()`` in a forked child that SIGKILLs itself before its k-th file-system call.
    True if the child was killed, False if it finished first."""
    pid = os.fork()
    if pid == 0:  # child
        calls = [0]
        real = {n: getattr(os, n) for n in TRAPPED}

        def trap(name):
            def call(*a, **kw):
                calls[0] += 1
                if calls[0] == k:
                    os.kill(os.getpid(), signal.SIGKILL)
                return real[name](*a, **kw)
            return call

        for n in TRAPPED:
            setattr(os, n, trap(n))
        try:
            job()
        except BaseException:
            os._exit(2)
        os._exit(0)
    _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status):
        assert os.WTERMSIG(status) == signal.SIGKILL
        return True
    assert os.WEXITSTATUS(status) == 0, "the write failed without a crash"
    return False


def _read_dir(path: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted(path.iterdir())}


OLD = {"a.txt": "old a", "b.txt": "old b"}
NEW = {"a.txt": "new a" * 50, "b.txt": "new b" * 50, "c.txt": "new c"}


def _write_new(target: Path):
    def job():
        with fsutil.atomic_dir(target) as tmp:
            for name, text in NEW.items():
                (tmp / name).write_text(text)
    return job


def test_folder_replace_survives_a_kill_at_every_step(tmp_path):
    target = tmp_path / "lib" / "obj"
    instants = outcomes_old = outcomes_new = 0
    for k in range(1, 400):
        if target.exists():
            shutil.rmtree(target)
        for leftover in target.parent.glob(".*"):
            shutil.rmtree(leftover) if leftover.is_dir() else leftover.unlink()
        target.mkdir(parents=True)
        for name, text in OLD.items():
            (target / name).write_text(text)
        killed = _crash_at(k, _write_new(target))
        fsutil.recover_dirs(target.parent)  # what a reader does before loading
        got = _read_dir(target)
        assert got in (OLD, NEW), f"crash before call {k}: {got}"
        assert not fsutil.backup_path(target).exists()
        if not killed:
            assert got == NEW
            break
        instants += 1
        outcomes_old += got == OLD
        outcomes_new += got == NEW
    else:
        pytest.fail("the write never completed")
    assert instants >= 8 and outcomes_old and outcomes_new  # the crash instants span both sides of the swap


def test_a_crash_between_the_renames_is_recovered_from_the_backup(tmp_path):
    target = tmp_path / "obj"
    target.mkdir()
    (target / "a.txt").write_text("old")
    os.replace(target, fsutil.backup_path(target))  # step 1 done, step 2 never happened
    assert not target.exists()
    assert fsutil.recover_dirs(tmp_path) == ["obj"]
    assert (target / "a.txt").read_text() == "old"


def test_file_write_survives_a_kill_at_every_step(tmp_path):
    target = tmp_path / "cal.yaml"
    seen = set()
    for k in range(1, 100):
        target.write_text("old")
        killed = _crash_at(k, lambda: fsutil.atomic_write_text(target, "new" * 1000))
        got = target.read_text()
        assert got in ("old", "new" * 1000), f"crash before call {k}: {got[:20]!r}"
        seen.add(got[:3])
        if not killed:
            break
    assert seen == {"old", "new"}


def test_atomic_write_never_touches_the_umask(tmp_path, monkeypatch):
    code = (
        "import os, sys\n"
        "os.umask(0o027)\n"
        "def boom(*a): raise AssertionError('os.umask called')\n"
        "os.umask = boom\n"
        "from labctl import fsutil\n"
        "fsutil.atomic_write_text(sys.argv[1] + '/f.txt', 'x')\n"
        "with fsutil.atomic_dir(sys.argv[1] + '/d') as t:\n"
        "    open(os.path.join(t, 'g'), 'w').write('y')\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, env=env,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    assert stat.S_IMODE((tmp_path / "f.txt").stat().st_mode) == 0o640  # 0o666 under umask 027
    assert stat.S_IMODE((tmp_path / "d").stat().st_mode) == 0o750


def test_an_existing_file_keeps_its_mode(tmp_path):
    p = tmp_path / "key"
    p.write_text("old")
    os.chmod(p, 0o600)
    fsutil.atomic_write_text(p, "new")
    assert p.read_text() == "new" and stat.S_IMODE(p.stat().st_mode) == 0o600
    assert [q.name for q in tmp_path.iterdir()] == ["key"]  # no temporary file left
