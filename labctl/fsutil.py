"""Atomic file and folder writes: nothing the user made is ever half-written, at any crash instant.

Files: write a temporary sibling, fsync it, ``os.replace`` it over the target, fsync the folder —
a crash leaves the old file or the new one, never a mix. The temporary file is created with mode
``0o666`` so the kernel applies the process umask; the umask itself is never read or changed
(``os.umask`` is process-wide: changing it, even for a moment, races every other thread that
creates a file). An existing target keeps its mode.

Folders (:func:`atomic_dir`): the new version is built in a temporary sibling, then

1. the old folder is renamed aside to its backup name ``.NAME.bak``,
2. the new folder is renamed into place,
3. the backup is removed.

A crash before 1 leaves the old folder (and a stray temporary one); between 1 and 2, only the
backup — :func:`recover_dir` renames it back; after 2, the new folder (and perhaps a backup,
which :func:`recover_dir` removes). Readers call :func:`recover_dir` (or :func:`recover_dirs` for a
folder of folders) before loading, so at every instant they see the old version or the new one.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from collections.abc import Iterator
from pathlib import Path

BACKUP_SUFFIX = ".bak"


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")


def fsync_dir(path: Path | str) -> None:
    """fsync a folder, so that renames inside it survive a power cut (no-op where unsupported)."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    """Replace ``path`` with ``data`` atomically and durably (see the module docstring)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_name(path)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
    try:
        with contextlib.suppress(FileNotFoundError):
            os.fchmod(fd, os.stat(path).st_mode & 0o7777)  # an existing file keeps its mode
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


def atomic_write_text(path: Path | str, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically, as :func:`atomic_write_bytes`."""
    atomic_write_bytes(path, text.encode("utf-8"))


def backup_path(path: Path | str) -> Path:
    """Where :func:`atomic_dir` keeps the old folder during a swap: ``.NAME.bak`` beside it."""
    path = Path(path)
    return path.with_name(f".{path.name}{BACKUP_SUFFIX}")


def recover_dir(path: Path | str) -> bool:
    """Finish or undo a folder swap that a crash interrupted; True if anything was done.

    Only a backup left: it is the old version, renamed back. Both there: the swap had completed,
    the backup goes."""
    path = Path(path)
    bak = backup_path(path)
    if not bak.exists():
        return False
    if path.exists():
        shutil.rmtree(bak, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):  # another reader recovered it first
            os.replace(bak, path)
    fsync_dir(path.parent)
    return True


def recover_dirs(parent: Path | str) -> list[str]:
    """:func:`recover_dir` for every interrupted swap in ``parent``; returns the names recovered."""
    parent = Path(parent)
    out: list[str] = []
    if not parent.is_dir():
        return out
    for bak in sorted(parent.glob(f".*{BACKUP_SUFFIX}")):
        name = bak.name[1:-len(BACKUP_SUFFIX)]
        if name and recover_dir(parent / name):
            out.append(name)
    return out


def _fsync_tree(root: Path) -> None:
    for dirpath, _dirs, files in os.walk(root):
        for f in files:
            with contextlib.suppress(OSError):
                fd = os.open(os.path.join(dirpath, f), os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
        fsync_dir(dirpath)


@contextlib.contextmanager
def atomic_dir(path: Path | str) -> Iterator[Path]:
    """Yield a temporary folder; on success it replaces ``path`` whole, on error it vanishes.

    At every instant of the swap ``path`` holds the old version or the new one, or (between the two
    renames) only the backup does, which :func:`recover_dir` restores."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    recover_dir(path)  # an earlier swap that crashed half-way
    tmp = _tmp_name(path)
    os.mkdir(tmp, 0o777)  # the kernel applies the umask
    try:
        yield tmp
        _fsync_tree(tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    bak = backup_path(path)
    had_old = path.exists()
    if had_old:
        os.replace(path, bak)  # 1: old aside
    os.replace(tmp, path)  # 2: new in
    fsync_dir(path.parent)
    if had_old:
        shutil.rmtree(bak, ignore_errors=True)  # 3: old gone


# ---------------------------------------------------------------------------------------------------------
# A cache of computed arrays on disk (the simulated lab's table texture and pixel rays, the library's meshes
# as trimesh reads them): what a fresh process would otherwise recompute for seconds on every start, read
# back bit for bit. Keyed by everything the arrays are a function of (the inputs and the source files that
# compute them), so a stale entry is never read; a cache that cannot be read or written is recomputed.
# ---------------------------------------------------------------------------------------------------------
CACHE_ENV = "LABCTL_CACHE_DIR"  # the cache's folder; set empty to compute everything afresh


def cache_root() -> Path | None:
    """The cache's folder: ``$LABCTL_CACHE_DIR``, else ``$XDG_CACHE_HOME/labctl`` (``~/.cache/labctl``);
    None when ``$LABCTL_CACHE_DIR`` is set empty (no cache)."""
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        return Path(env) if env else None
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "labctl"


def file_digest(*paths: Path | str) -> str:
    """SHA-256 (hex) of the files' bytes in turn: a cache key part that changes whenever the code or the
    data that computes an entry does."""
    import hashlib

    h = hashlib.sha256()
    for p in paths:
        h.update(Path(p).read_bytes())
        h.update(b"\0")
    return h.hexdigest()


def cached_arrays(kind: str, key: tuple, names: tuple[str, ...], compute) -> dict:
    """The arrays ``compute()`` returns (a dict holding exactly ``names``), read from the cache when an
    entry for ``key`` (a tuple of reprs that pins every input: values, versions, :func:`file_digest`\\ s)
    exists, else computed and stored. Stored as an uncompressed ``.npz`` with no pickles, written to a
    temporary sibling and renamed into place (no fsync: a torn entry only reads as a miss)."""
    import hashlib
    import zipfile

    import numpy as np

    root = cache_root()
    if root is None:
        return compute()
    path = root / kind / f"{hashlib.sha256(repr(key).encode()).hexdigest()[:40]}.npz"
    try:
        with np.load(path, allow_pickle=False) as z:
            if sorted(z.files) == sorted(names):
                return {k: z[k] for k in names}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        pass
    out = compute()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = _tmp_name(path)
        with open(tmp, "wb") as fh:
            np.savez(fh, **{k: out[k] for k in names})
        os.replace(tmp, path)
    except OSError:
        with contextlib.suppress(OSError, UnboundLocalError):
            os.unlink(tmp)
    return out
