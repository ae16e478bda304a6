"""The per-scene stage cache (DESIGN §6): declared stages, keys, reasons, the manifest and the lock.

A stage declares (`Stage`) its name, an explicit version, the parameters that change its result,
its input files, the keys of the stages it reads from (a Merkle chain) and, apart, the display
options that only change how its previews look. Its key hashes all but the display options.
`run_stage` does the rest, the same way for every stage: it says why the stage runs or is
skipped, runs it inside one atomic output set (`pipelines.io.files.output_set`: every file
replaces its old version together, or none does), records the outputs' SHA-256 and the summary
in `.wavelight/manifest.json` last (a crash leaves a stage stale, never corrupt), and when only a
display option changed, redraws the previews without rerunning the stage.

File digests are remembered by (size, mtime): an unchanged file is not read again. A damaged
manifest is rebuilt from what the files themselves prove: camera.json and pose.json carry the
record of the calibrate / register run that wrote them (with the hash of their own content), a
visibility file carries its stage's record.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from pipelines.errors import InputError
from pipelines.io.files import atomic_output, is_temporary, output_set

CACHE_DIR = ".wavelight"
MANIFEST = "manifest.json"
MANIFEST_FORMAT = 2
RECORD_FIELD = "wavelight_record"  # the key camera.json / pose.json keep their writer's record under
_HELD: dict[str, int] = {}  # scene locks this process holds -> depth


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def content_digest(data: dict) -> str:
    """SHA-256 of a JSON document without its embedded record (what the record proves)."""
    body = {k: v for k, v in data.items() if k != RECORD_FIELD}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def _package_version() -> str:
    try:
        from importlib.metadata import version

        return version("wavelight")
    except Exception:  # not installed (running from a source tree)
        return "unknown"


def _fmt(value) -> str:
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= 40 else text[:37] + "..."


def write_json_atomic(path: Path, data) -> None:
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1, sort_keys=False) + "\n")


@dataclass(frozen=True)
class Stage:
    """What a stage run depends on.

    name : its manifest entry (e.g. "solve", "visibility/photo/R32", "relight-evening").
    params : the options that change its result; display : the options that only change its
    previews (a change reruns `redisplay`, not the stage).
    inputs : name -> file (None: absent); upstream : stage name -> key of the run it reads.
    """

    name: str
    version: int
    params: dict
    inputs: dict = field(default_factory=dict)
    upstream: dict = field(default_factory=dict)
    display: dict = field(default_factory=dict)

    def __post_init__(self):
        # as the manifest will hold them (tuples become lists): a rerun compares like with like
        object.__setattr__(self, "params", json.loads(json.dumps(self.params, default=str)))
        object.__setattr__(self, "display", json.loads(json.dumps(self.display, default=str)))


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
    display: dict = field(default_factory=dict)
    redisplay: bool = False  # only a display option changed


class SceneCache:
    """The cache of one scene folder."""

    def __init__(self, scene_dir: Path):
        self.scene_dir = Path(scene_dir)
        self.dir = self.scene_dir / CACHE_DIR
        self.manifest_path = self.dir / MANIFEST
        self._digests: dict | None = None

    # -- digests --------------------------------------------------------------------------------
    def digest(self, path: Path) -> str:
        """SHA-256 of a file, remembered by (size, mtime): an unchanged file is read once."""
        path = Path(path)
        st = path.stat()
        memo = self._digest_memo()
        key = self.relative(path)
        seen = memo.get(key)
        if seen and seen[0] == st.st_size and seen[1] == st.st_mtime_ns:
            return seen[2]
        value = sha256_file(path)
        memo[key] = [st.st_size, st.st_mtime_ns, value]
        return value

    def _digest_memo(self) -> dict:
        if self._digests is None:
            self._digests = dict(self.manifest().get("digests", {}))
        return self._digests

    # -- manifest -------------------------------------------------------------------------------
    def manifest(self) -> dict:
        empty = {"format": MANIFEST_FORMAT, "stages": {}, "digests": {}}
        if not self.manifest_path.is_file():
            return {**empty, "stages": self._proven_records()}
        try:
            data = json.loads(self.manifest_path.read_text())
            if (not isinstance(data, dict) or data.get("format") not in (1, MANIFEST_FORMAT)
                    or not isinstance(data.get("stages"), dict)
                    or not all(isinstance(r, dict) and isinstance(r.get("key"), str) for r in data["stages"].values())):
                raise ValueError("unknown format")
            data.setdefault("digests", {})
            if not isinstance(data["digests"], dict):
                data["digests"] = {}
            return data
        except (ValueError, UnicodeDecodeError):
            # A damaged manifest costs a rerun of what the files cannot prove
            return {**empty, "stages": self._proven_records(), "damaged": True}

    def _proven_records(self) -> dict:
        """Stage records the scene's files carry and still match (camera.json, pose.json)."""
        found = {}
        for name in ("camera.json", "pose.json"):
            path = self.scene_dir / name
            if not path.is_file():
                continue
            try:
                data = json.loads(path.read_text())
            except (OSError, ValueError, UnicodeDecodeError):
                continue
            rec = data.get(RECORD_FIELD) if isinstance(data, dict) else None
            if isinstance(rec, dict) and isinstance(rec.get("record"), dict) and \
                    rec.get("content_sha256") == content_digest(data):
                record = dict(rec["record"])
                record["outputs"] = {**record.get("outputs", {}), name: sha256_file(path)}
                found[rec.get("stage", name)] = record
        return found

    def record_of(self, stage: str) -> dict | None:
        return self.manifest()["stages"].get(stage)

    def key_of(self, stage: str) -> str | None:
        rec = self.record_of(stage)
        return rec["key"] if rec else None

    def relative(self, path: Path) -> str:
        path = Path(path)
        try:
            return str(path.resolve().relative_to(self.scene_dir.resolve()))
        except ValueError:
            return str(path.resolve())

    def status(self, versions: dict[str, int] | None = None) -> list[dict]:
        """Every recorded stage checked against the current files: fresh or stale, and why.
        A stage whose upstream is stale is stale too (its next run will rerun it). `versions`: the
        current version of each stage kind (the name up to its first '/' or '-'), so that a stage
        recorded by another version of wavelight shows as stale."""
        stages = self.manifest()["stages"]
        versions = versions or {}
        reasons: dict[str, str | None] = {}

        def kind(stage: str) -> str:
            return stage.split("/")[0].split("-")[0]

        def check(stage: str) -> str | None:
            if stage in reasons:
                return reasons[stage]
            reasons[stage] = None  # guards against cycles in a hand-edited manifest
            rec = stages[stage]
            reason = None
            current = versions.get(stage, versions.get(kind(stage)))
            if current is not None and rec.get("version") != current:
                reason = f"stage version changed: {rec.get('version')} -> {current}"
            for name, digest in rec.get("inputs", {}).items():
                if reason is not None:
                    break
                rel = rec.get("input_paths", {}).get(name)
                path = None if rel is None else self.scene_dir / rel
                now = self.digest(path) if path is not None and path.is_file() else None
                if now != digest:
                    reason = f"input changed: {name}"
            for up, key in rec.get("upstream", {}).items():
                if reason is None and (up not in stages or stages[up]["key"] != key):
                    reason = f"upstream changed: {up}"
                elif reason is None and check(up) is not None:
                    reason = f"upstream stale: {up}"
            for rel, digest in rec.get("outputs", {}).items():
                p = self.scene_dir / rel
                if reason is None and (not p.is_file() or self.digest(p) != digest):
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

    # -- planning -------------------------------------------------------------------------------
    def plan(self, stage: Stage, force: bool = False) -> Decision:
        """Decide whether `stage` must run, and say why."""
        digests = {name: (self.digest(p) if p is not None else None) for name, p in stage.inputs.items()}
        key = hashlib.sha256(json.dumps(
            {"stage": stage.name, "version": stage.version, "params": stage.params, "inputs": digests,
             "upstream": stage.upstream}, sort_keys=True).encode()).hexdigest()
        manifest = self.manifest()
        prev = manifest["stages"].get(stage.name)
        reason = None
        if force:
            reason = "--force"
        elif prev is None:
            reason = "manifest damaged, rebuilding" if manifest.get("damaged") else "no previous run"
        elif prev.get("version") != stage.version:
            reason = f"stage version changed: {prev.get('version')} -> {stage.version}"
        elif prev.get("params") != stage.params:
            old = prev.get("params", {})
            changed = [f"{k} {_fmt(old.get(k))} -> {_fmt(stage.params.get(k))}"
                       for k in sorted(set(old) | set(stage.params)) if old.get(k) != stage.params.get(k)]
            reason = "params changed: " + ", ".join(changed)
        elif prev.get("inputs") != digests:
            old = prev.get("inputs", {})
            changed = [k for k in sorted(set(old) | set(digests)) if old.get(k) != digests.get(k)]
            reason = "input changed: " + ", ".join(changed)
        elif prev.get("upstream") != stage.upstream:
            old = prev.get("upstream", {})
            changed = [k for k in sorted(set(old) | set(stage.upstream)) if old.get(k) != stage.upstream.get(k)]
            reason = "upstream changed: " + ", ".join(changed)
        else:
            for rel, digest in prev.get("outputs", {}).items():
                path = self.scene_dir / rel
                if not path.is_file():
                    reason = f"output missing: {rel}"
                    break
                if self.digest(path) != digest:
                    reason = f"output damaged or edited: {rel} (hash mismatch)"
                    break
        run = reason is not None
        redisplay = not run and prev.get("display", {}) != stage.display
        if redisplay:
            old = prev.get("display", {})
            reason = "display options changed: " + ", ".join(
                f"{k} {_fmt(old.get(k))} -> {_fmt(stage.display.get(k))}"
                for k in sorted(set(old) | set(stage.display)) if old.get(k) != stage.display.get(k))
        paths = {name: (self.relative(p) if p is not None else None) for name, p in stage.inputs.items()}
        return Decision(stage.name, stage.version, key, run,
                        reason if run or redisplay else f"up to date (key {key[:12]})", stage.params, digests,
                        dict(stage.upstream), paths, dict(stage.display), redisplay)

    def record(self, decision: Decision, outputs: list[Path], seconds: float, summary: dict | None = None) -> dict:
        """Record a finished stage (call after its outputs are in place); returns the record."""
        data = self.manifest()
        data.pop("damaged", None)
        rec = {
            "key": decision.key, "version": decision.version, "params": decision.params, "inputs": decision.inputs,
            "input_paths": decision.input_paths, "upstream": decision.upstream,
            "outputs": {self.relative(p): self.digest(p) for p in outputs}, "display": decision.display,
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "seconds": round(seconds, 3),
            "wavelight": _package_version(), "summary": summary or {},
        }
        data["stages"][decision.stage] = rec
        self._save(data)
        return rec

    def forget(self, stage: str, files: list[Path]) -> None:
        """Drop a stage's record and delete its files (pruning)."""
        data = self.manifest()
        data["stages"].pop(stage, None)
        self._save(data)
        for p in files:
            with contextlib.suppress(FileNotFoundError):
                Path(p).unlink()

    def _save(self, data: dict) -> None:
        data["format"] = MANIFEST_FORMAT
        digests = self._digest_memo()
        # keep the digests of files that still exist, so the memo does not grow without bound
        data["digests"] = {k: v for k, v in digests.items() if (self.scene_dir / k).exists() or Path(k).exists()}
        self.dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.manifest_path, data)

    def embedded_record(self, decision: Decision, summary: dict, data: dict) -> dict:
        """The record a JSON output (camera.json, pose.json) carries of the run that wrote it, with
        the digest of its own content: it proves the file's origin when the manifest is lost."""
        record = {"key": decision.key, "version": decision.version, "params": decision.params,
                  "inputs": decision.inputs, "input_paths": decision.input_paths, "upstream": decision.upstream,
                  "outputs": {}, "display": decision.display, "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                  "wavelight": _package_version(), "summary": summary}
        return {"stage": decision.stage, "record": record, "content_sha256": content_digest(data)}

    def guard_user_file(self, stage: str, path: Path, force: bool, option: str = "--force") -> None:
        """Refuse to overwrite a scene file (camera.json, pose.json) that `stage` did not write as it
        is now (the user wrote or edited it by hand), unless forced."""
        path = Path(path)
        if force or not path.is_file():
            return
        rec = self.record_of(stage) or {}
        if rec.get("outputs", {}).get(self.relative(path)) == self.digest(path):
            return
        raise InputError(f"exists and was not written by wavelight {stage} as it is now (written or edited by hand)",
                         path, f"move it away, or pass {option} to replace it")

    def sweep_temporaries(self) -> list[Path]:
        """Delete the temp files a killed run left (`files.is_temporary` names) in the scene folder,
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


@dataclass
class Ran:
    """What a stage's work returns: its outputs (paths written inside the output set) and summary."""

    outputs: list
    summary: dict = field(default_factory=dict)


def run_stage(cache: SceneCache, stage: Stage, console, force: bool, work: Callable[[Decision], Ran],
              redisplay: Callable[[], list] | None = None) -> Decision:
    """Plan `stage`, print why it runs or is skipped, run `work(decision)` with every output replaced
    together (one output set) and record it. When only display options changed, `redisplay()`
    rewrites the previews (also atomically) and the record takes the new display options."""
    d = cache.plan(stage, force)
    if d.redisplay and redisplay is None:
        d = Decision(d.stage, d.version, d.key, False, f"up to date (key {d.key[:12]})", d.params, d.inputs,
                     d.upstream, d.input_paths, d.display, False)
    console.decision(d)
    if not d.run and not d.redisplay:
        return d
    t0 = time.monotonic()
    if d.redisplay:
        prev = cache.record_of(stage.name)
        with output_set():
            redisplay()
        outputs = [cache.scene_dir / rel for rel in prev.get("outputs", {})]
        cache.record(d, outputs, prev.get("seconds", 0.0), prev.get("summary", {}))
        return d
    with output_set():
        ran = work(d)
    cache.record(d, ran.outputs, time.monotonic() - t0, ran.summary)
    return d
