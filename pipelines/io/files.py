"""Atomic file output, the one way wavelight writes files: a temp file beside the target, renamed
into place on success.

`atomic_output` makes one file atomic. Inside an `output_set` (a stage's run) every
`atomic_output` keeps its finished temp file, and the renames happen only when the whole block
succeeds: an error, a full disk or Ctrl-C halfway through the writes leaves every old result as it
was. `output_set().discard(path)` removes an old file of the set when it commits (a result that no
longer exists). Files that must survive a failed stage (resumable chunks) are written with
`atomic_output(path, now=True)`. HDF5 files are built in memory and written through
`atomic_output` (`h5_file`). A process killed outright leaves temp files behind
(`.<name>.<random>.tmp<suffix>`, `is_temporary`); the next run on the scene removes them.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import re
import tempfile
from pathlib import Path

_TEMP_NAME = re.compile(r"^\.(.+)\.[A-Za-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?$")


def is_temporary(name: str) -> bool:
    """True for the names `atomic_output` gives its temp files."""
    return bool(_TEMP_NAME.match(name))


def final_path(path: str | Path) -> Path:
    """The file a temp file of `atomic_output` stands for (`out/.relit.exr.x1y2z3w4.tmp.exr` ->
    `out/relit.exr`: what an error names); any other path as it is."""
    path = Path(path)
    m = _TEMP_NAME.match(path.name)
    return path.with_name(m.group(1)) if m else path


class OutputSet:
    """Finished temp files waiting to replace their targets together (see `output_set`)."""

    def __init__(self):
        self.pending: list[tuple[Path, Path]] = []
        self.discarded: list[Path] = []

    def discard(self, path: str | Path) -> None:
        """Remove `path` (if it exists) when the set commits."""
        self.discarded.append(Path(path))

    def _commit(self) -> None:
        for tmp, path in self.pending:
            os.replace(tmp, path)
        written = {p for _, p in self.pending}
        for path in self.discarded:
            if path not in written:
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()

    def _abort(self) -> None:
        for tmp, _ in self.pending:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)


_current: contextvars.ContextVar[OutputSet | None] = contextvars.ContextVar("wavelight_output_set", default=None)


@contextlib.contextmanager
def output_set():
    """Files written with `atomic_output` inside this block replace their targets together, at
    its end, and only if it succeeds. Nested blocks join the outermost one."""
    outer = _current.get()
    if outer is not None:
        yield outer
        return
    current = OutputSet()
    token = _current.set(current)
    try:
        yield current
        current._commit()
    finally:
        _current.reset(token)
        current._abort()


def discard(path: str | Path) -> None:
    """Remove `path`: when the enclosing `output_set` commits, or now outside one."""
    current = _current.get()
    if current is not None:
        current.discard(path)
    else:
        with contextlib.suppress(FileNotFoundError):
            Path(path).unlink()


@contextlib.contextmanager
def atomic_output(path: str | Path, now: bool = False):
    """Yield a temp path next to `path` (same suffix, so format-sniffing writers work); rename it
    into place only if the block succeeds (inside `output_set`: when the set succeeds, unless
    `now`), otherwise delete it. A crash never leaves a half file under the final name."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would make results private to one user
    deferred = False
    current = None if now else _current.get()
    try:
        try:
            yield Path(tmp)
        except OSError as exc:  # name the file the user knows (a full disk, say), not the temp file
            if exc.filename in (None, tmp):
                # a library's OSError may carry no errno (nor strerror): keep what it says
                why = exc.strerror if exc.errno is not None else exc.strerror or str(exc) or "the write failed"
                raise OSError(exc.errno, why, str(path)) from exc
            raise
        if current is not None:
            current.pending.append((Path(tmp), path))
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
    through `atomic_output` when the block succeeds. A full disk then raises OSError (ENOSPC) from
    Python's write: when the HDF5 library's own writes fail, h5py reports errors from its
    destructors and can crash the process."""
    import io

    import h5py

    buf = io.BytesIO()
    with h5py.File(buf, "w", **kwargs) as f:
        yield f
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as out:
            out.write(buf.getbuffer())
