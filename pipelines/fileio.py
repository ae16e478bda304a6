"""Atomic file output: write to a temp file beside the target, rename into place on success.

`atomic_output` makes one file atomic. `output_set` makes a stage's files replace their old
versions together: inside it every `atomic_output` keeps its finished temp file, and the renames
happen only when the whole block succeeds (an error, a full disk or Ctrl-C halfway through the
writes leaves every old result as it was). A process killed outright leaves temp files behind
(`.<name>.<random>.tmp<suffix>`, `is_temporary`); the next run on the scene removes them.
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from pathlib import Path

_TEMP_NAME = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?$")
_pending: list[tuple[Path, Path]] | None = None  # finished temp files of the open output_set


def is_temporary(name: str) -> bool:
    """True for the names `atomic_output` gives its temp files."""
    return bool(_TEMP_NAME.match(name))


@contextlib.contextmanager
def output_set():
    """Files written with `atomic_output` inside this block replace their targets together, at
    its end, and only if it succeeds. Nested blocks join the outermost one."""
    global _pending
    if _pending is not None:
        yield
        return
    _pending = pending = []
    try:
        yield
        for tmp, path in pending:
            os.replace(tmp, path)
    finally:
        _pending = None
        for tmp, _ in pending:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)


@contextlib.contextmanager
def atomic_output(path: str | Path):
    """Yield a temp path next to `path` (same suffix, so format-sniffing writers work); rename it
    into place only if the block succeeds (inside `output_set`: when the set succeeds), otherwise
    delete it. A crash never leaves a half file under the final name."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would make results private to one user
    deferred = False
    try:
        try:
            yield Path(tmp)
        except OSError as exc:  # name the file the user knows (a full disk, say), not the temp file
            if exc.errno is not None and exc.filename in (None, tmp):
                raise OSError(exc.errno, exc.strerror, str(path)) from exc
            raise
        if _pending is not None:
            _pending.append((Path(tmp), path))
            deferred = True
        else:
            os.replace(tmp, path)
    finally:
        if not deferred:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)


@contextlib.contextmanager
def h5_file(path: str | Path, **kwargs):
    """Yield a new HDF5 file (h5py.File, opened "w") that is built in memory and written to `path`
    in one plain write when the block succeeds. A full disk then raises OSError (ENOSPC) from
    Python's write: when the HDF5 library's own writes fail, h5py reports errors from its
    destructors and can crash the process."""
    import io

    import h5py

    buf = io.BytesIO()
    with h5py.File(buf, "w", **kwargs) as f:
        yield f
    with open(path, "wb") as out:
        out.write(buf.getbuffer())
