"""The per-scene stage cache (DESIGN §5): keys, reasons, atomic writes, the manifest and the lock.

A stage's key hashes its name, an explicit stage version, its result-affecting parameters, the
contents of its input files and the keys of the stages it reads from (a Merkle chain). The manifest
(`.wavelight/manifest.json`) records, per stage, the key and everything that went into it plus the
SHA-256 of each output, so a later run can say *why* a stage reruns, and a damaged output file is
caught by its hash. Outputs are written to temp files and renamed into place; the manifest is
written last, so a crash leaves a stage stale, never corrupt.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

from pipelines.errors import InputError
from pipelines.fileio import atomic_output, is_temporary, output_set  # noqa: F401 (output_set: for the stages)

CACHE_DIR = ".wavelight"
MANIFEST = "manifest.json"
MANIFEST_FORMAT = 1
_HELD: dict[str, int] = {}  # scene locks this process holds -> depth


def file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _package_version() -> str:
    try:
        from importlib.metadata import version

        return version("wavelight")
    except Exception:  # not installed (running from a source tree)
        return "unknown"


def _fmt(value) -> str:
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= 40 else text[:37] + "..."


@dataclass(frozen=True)
class Decision:
    stage: str
    version: int
    key: str
    run: bool
    reason: str
    params: dict
    inputs: dict  # name -> digest
    upstream: dict  # stage -> key
    input_paths: dict  # name -> path (relative to the scene when inside it)


def write_json_atomic(path: Path, data) -> None:
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1, sort_keys=False) + "\n")


class SceneCache:
    """The cache of one scene folder."""

    def __init__(self, scene_dir: Path):
        self.scene_dir = Path(scene_dir)
        self.dir = self.scene_dir / CACHE_DIR
        self.manifest_path = self.dir / MANIFEST

    # -- manifest -------------------------------------------------------------------------------
    def manifest(self) -> dict:
        if not self.manifest_path.is_file():
            return {"format": MANIFEST_FORMAT, "stages": {}}
        try:
            data = json.loads(self.manifest_path.read_text())
            if (not isinstance(data, dict) or data.get("format") != MANIFEST_FORMAT
                    or not isinstance(data.get("stages"), dict)
                    or not all(isinstance(r, dict) and isinstance(r.get("key"), str) for r in data["stages"].values())):
                raise ValueError("unknown format")
            return data
        except (ValueError, UnicodeDecodeError):
            # A damaged manifest only costs a rerun: every stage is treated as never run.
            return {"format": MANIFEST_FORMAT, "stages": {}, "damaged": True}

    def record_of(self, stage: str) -> dict | None:
        return self.manifest()["stages"].get(stage)

    def status(self, versions: dict[str, int] | None = None) -> list[dict]:
        """Every recorded stage checked against the current files: fresh or stale, and why.
        A stage whose upstream is stale is stale too (its next run will rerun it). `versions`: the
        current version of each stage kind (`visibility` covers `visibility-view-...`), so that a
        stage recorded by another version of wavelight shows as stale."""
        stages = self.manifest()["stages"]
        versions = versions or {}
        reasons: dict[str, str | None] = {}

        def check(stage: str) -> str | None:
            if stage in reasons:
                return reasons[stage]
            reasons[stage] = None  # guards against cycles in a hand-edited manifest
            rec = stages[stage]
            reason = None
            current = versions.get(stage, versions.get(stage.split("-")[0]))
            if current is not None and rec.get("version") != current:
                reason = f"stage version changed: {rec.get('version')} -> {current}"
            for name, digest in rec.get("inputs", {}).items():
                if reason is not None:
                    break
                rel = rec.get("input_paths", {}).get(name)
                path = None if rel is None else self.scene_dir / rel
                now = file_digest(path) if path is not None and path.is_file() else None
                if now != digest:
                    reason = f"input changed: {name}"
                    break
            for up, key in rec.get("upstream", {}).items():
                if reason is None and (up not in stages or stages[up]["key"] != key):
                    reason = f"upstream changed: {up}"
                elif reason is None and check(up) is not None:
                    reason = f"upstream stale: {up}"
            for rel, digest in rec.get("outputs", {}).items():
                p = self.scene_dir / rel
                if reason is None and (not p.is_file() or file_digest(p) != digest):
                    reason = f"output missing or damaged: {rel}"
            reasons[stage] = reason
            return reason

        rows = []
        for stage, rec in stages.items():
            reason = check(stage)
            rows.append({"stage": stage, "state": "stale" if reason else "fresh", "reason": reason or "up to date",
                         "key": rec["key"][:12], "finished": rec.get("finished"), "seconds": rec.get("seconds"),
                         "params": rec.get("params"), "summary": rec.get("summary", {})})
        return rows

    def key_of(self, stage: str) -> str | None:
        rec = self.record_of(stage)
        return rec["key"] if rec else None

    def relative(self, path: Path) -> str:
        path = Path(path)
        try:
            return str(path.resolve().relative_to(self.scene_dir.resolve()))
        except ValueError:
            return str(path.resolve())

    # -- planning -------------------------------------------------------------------------------
    def plan(self, stage: str, version: int, params: dict, inputs: dict[str, Path | None],
             upstream: dict[str, str], force: bool = False) -> Decision:
        """Decide whether `stage` must run, and say why."""
        digests = {name: (file_digest(p) if p is not None else None) for name, p in inputs.items()}
        key = hashlib.sha256(json.dumps(
            {"stage": stage, "version": version, "params": params, "inputs": digests, "upstream": upstream},
            sort_keys=True).encode()).hexdigest()
        prev = self.record_of(stage)
        reason = None
        if force:
            reason = "--force"
        elif prev is None:
            reason = "manifest damaged, rebuilding" if self.manifest().get("damaged") else "no previous run"
        elif prev.get("version") != version:
            reason = f"stage version changed: {prev.get('version')} -> {version}"
        elif prev.get("params") != params:
            old = prev.get("params", {})
            changed = [f"{k} {_fmt(old.get(k))} -> {_fmt(params.get(k))}"
                       for k in sorted(set(old) | set(params)) if old.get(k) != params.get(k)]
            reason = "params changed: " + ", ".join(changed)
        elif prev.get("inputs") != digests:
            old = prev.get("inputs", {})
            changed = [k for k in sorted(set(old) | set(digests)) if old.get(k) != digests.get(k)]
            reason = "input changed: " + ", ".join(changed)
        elif prev.get("upstream") != upstream:
            old = prev.get("upstream", {})
            changed = [k for k in sorted(set(old) | set(upstream)) if old.get(k) != upstream.get(k)]
            reason = "upstream changed: " + ", ".join(changed)
        else:
            for rel, digest in prev.get("outputs", {}).items():
                path = self.scene_dir / rel
                if not path.is_file():
                    reason = f"output missing: {rel}"
                    break
                if file_digest(path) != digest:
                    reason = f"output damaged or edited: {rel} (hash mismatch)"
                    break
        run = reason is not None
        paths = {name: (self.relative(p) if p is not None else None) for name, p in inputs.items()}
        return Decision(stage, version, key, run, reason if run else f"up to date (key {key[:12]})", params, digests,
                        dict(upstream), paths)

    def record(self, decision: Decision, outputs: list[Path], seconds: float, summary: dict | None = None) -> None:
        """Record a finished stage (call after its outputs are in place)."""
        data = self.manifest()
        data.pop("damaged", None)
        data["stages"][decision.stage] = {
            "key": decision.key, "version": decision.version, "params": decision.params, "inputs": decision.inputs,
            "input_paths": decision.input_paths, "upstream": decision.upstream,
            "outputs": {self.relative(p): file_digest(p) for p in outputs},
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "seconds": round(seconds, 3),
            "wavelight": _package_version(),
            "summary": summary or {},
        }
        self.dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.manifest_path, data)

    def guard_user_file(self, stage: str, path: Path, force: bool, option: str = "--force") -> None:
        """Refuse to overwrite a scene file (camera.json, pose.json) that `stage` did not write as it
        is now (the user wrote or edited it by hand), unless forced."""
        path = Path(path)
        if force or not path.is_file():
            return
        rec = self.record_of(stage) or {}
        if rec.get("outputs", {}).get(self.relative(path)) == file_digest(path):
            return
        raise InputError(f"exists and was not written by wavelight {stage} as it is now (written or edited by hand)",
                         path, f"move it away, or pass {option} to replace it")

    def sweep_temporaries(self) -> list[Path]:
        """Delete the temp files a killed run left (`fileio.is_temporary` names) in the scene folder,
        its out/ tree and the cache. Only called under the scene lock, when no other run writes."""
        found = [p for p in self.scene_dir.glob(".*") if p.is_file() and is_temporary(p.name)]
        for d in (self.scene_dir / "out", self.dir):
            if d.is_dir():
                found += [p for p in d.rglob(".*") if p.is_file() and is_temporary(p.name)]
        for p in found:
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
        return found

    # -- locking --------------------------------------------------------------------------------
    @contextlib.contextmanager
    def lock(self, wait_seconds: float = 600.0, say=print):
        """Exclusive per-scene lock: a second run waits for the first (or fails after a timeout).
        Re-entrant within a process, so a stage can hold it across the upstream stages it runs."""
        self.dir.mkdir(parents=True, exist_ok=True)
        path = self.dir / "lock"
        held = str(path.resolve())
        if _HELD.get(held):
            _HELD[held] += 1
            try:
                yield
            finally:
                _HELD[held] -= 1
            return
        with open(path, "a+") as f:
            deadline = time.monotonic() + wait_seconds
            announced = False
            while True:
                try:
                    fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError as exc:
                    if exc.errno not in (errno.EAGAIN, errno.EACCES):
                        raise
                    if not announced:
                        say(f"waiting: another wavelight run holds {path}")
                        announced = True
                    if time.monotonic() > deadline:
                        raise InputError(f"another wavelight run has held the scene lock for {wait_seconds:.0f} s",
                                         path, "wait for it to finish, or raise --lock-wait") from None
                    time.sleep(0.2)
            try:
                f.seek(0)
                f.truncate()
                f.write(f"{os.getpid()}\n")
                f.flush()
                _HELD[held] = 1
                self.sweep_temporaries()
                yield
            finally:
                _HELD.pop(held, None)
                fcntl.flock(f, fcntl.LOCK_UN)
