"""Exploration sessions on disk: every executed interaction is appended to a log before it is
learned from, so an interrupted exploration resumes where it stopped and a crash loses none.

Layout under a root directory (the planner node's ``exploration_log_dir``/``<state scope>``,
see ``w2e_ros.ros.state``)::

    <root>/<session>/<category>_<primitive>/run-0001/
        events.jsonl          one JSON object per line: "run" (a call started or resumed the
                              run), "interaction", "update" (a model update and its checkpoint),
                              "end" (how a call ended)
        clouds/000001.npz     the cloud interaction 1 was chosen on (points, normals)

A session is (session name, category, primitive). Its latest run is resumed until it ends
complete (budget spent, bar reached); the call after a complete run starts ``run-0002``. A cloud
file is complete (temporary name, fsync, rename) before the line that names it, and every line
is flushed and fsynced before the interaction is used. A line torn by a crash mid-write is cut
off when the run is opened again; a write that fails (a full disk) is undone at once (the file
cut back to where it was, the temporary cloud removed) and raises :class:`LogWriteError`, so the
log goes on cleanly once it can be written again. One explore runs at a time per planner, so the
files are not locked: give two planners two directories.
"""

from __future__ import annotations

import json
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from w2e_ros.core.robot.primitives import Action, TrialResult

EVENTS = "events.jsonl"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
DEFAULT_SESSION = "default"


class LogWriteError(OSError):
    """The session's log could not be written (a full disk, a read-only or vanished
    directory); nothing half-written was left, what was logged before is unchanged."""

    def __str__(self) -> str:
        return str(self.strerror)


def _cannot_write(run_dir: Path, exc: OSError) -> LogWriteError:
    return LogWriteError(exc.errno, f"exploration log {run_dir}: cannot write "
                         f"({exc.strerror or exc})")


def _write_whole(path: Path, data: bytes) -> None:
    """Append ``data`` to ``path`` and fsync, or leave the file as it was and raise: a disk
    that fills mid-write takes part of a line (a short write, then ENOSPC), and a later
    line appended after the torn one would make one undecodable line of the two."""
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        size = os.fstat(fd).st_size
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        except OSError:
            os.ftruncate(fd, size)  # giving space back needs none
            raise
    finally:
        os.close(fd)


def check_name(name: str, what: str) -> str:
    """A session / category / primitive name usable as a directory name, else ValueError."""
    if not _NAME.fullmatch(name):
        raise ValueError(f"{what} {name!r}: use letters, digits, '_', '.', '-' (at most 64, "
                         "not starting with '.', '_' or '-')")
    return name


def action_to_dict(a: Action) -> dict[str, Any]:
    return {"point": np.asarray(a.point, float).tolist(), "up": np.asarray(a.up, float).tolist(),
            "forward": np.asarray(a.forward, float).tolist(), "primitive": a.primitive}


def action_from_dict(d: dict[str, Any]) -> Action:
    return Action(np.asarray(d["point"], float), np.asarray(d["up"], float),
                  np.asarray(d["forward"], float), d["primitive"])


def result_to_dict(r: TrialResult) -> dict[str, Any]:
    return {"valid": bool(r.valid), "success": bool(r.success),
            "motion": np.asarray(r.motion, float).reshape(-1).tolist(),
            "moved_joint": int(r.moved_joint), "moved_link": r.moved_link, "reason": r.reason,
            "contact_displacement": np.asarray(r.contact_displacement, float).tolist(),
            "target_joint": int(r.target_joint), "target_link": r.target_link}


def result_from_dict(d: dict[str, Any]) -> TrialResult:
    return TrialResult(bool(d["valid"]), bool(d["success"]), np.asarray(d["motion"], float),
                       int(d["moved_joint"]), d["moved_link"], d.get("reason", ""),
                       np.asarray(d.get("contact_displacement", [0.0, 0.0, 0.0]), float),
                       int(d.get("target_joint", -1)), d.get("target_link", ""))


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@dataclass
class LoggedInteraction:
    """One executed interaction as recorded."""

    index: int  # 1-based, in the run
    object_id: int  # the scene object it was executed on (ids may change across restarts)
    instance: int | None  # the category instance, when the call loaded instances
    action: Action
    result: TrialResult
    cloud_file: str  # relative to the run directory
    frame_id: str = "world"  # frame of the cloud and the action

    def cloud(self, run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
        """(points (N, 3), normals (N, 3)) the action was chosen on."""
        with np.load(run_dir / self.cloud_file) as f:
            return f["points"], f["normals"]


class SessionRun:
    """One run of an exploration session: its directory and the events recorded so far."""

    def __init__(self, path: Path, session: str, category: str, primitive: str) -> None:
        self.path = Path(path)
        self.session, self.category, self.primitive = session, category, primitive
        # created by the first write, not here: a request refused before its run starts must
        # leave no empty run directory behind
        self.events: list[dict[str, Any]] = self._read()

    # --- reading --------------------------------------------------------------------------
    def _read(self) -> list[dict[str, Any]]:
        """The events of the file; a torn last line (crash mid-write) is cut off."""
        path = self.path / EVENTS
        if not path.exists():
            return []
        raw = path.read_bytes()
        keep = raw[:raw.rfind(b"\n") + 1]
        if len(keep) != len(raw):
            with open(path, "r+b") as f:
                f.truncate(len(keep))
                f.flush()
                os.fsync(f.fileno())
        return [json.loads(line) for line in keep.decode().splitlines() if line.strip()]

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def interactions(self) -> list[LoggedInteraction]:
        return [LoggedInteraction(int(e["index"]), int(e["object_id"]), e.get("instance"),
                                  action_from_dict(e["action"]), result_from_dict(e["result"]),
                                  e["cloud"], e.get("frame_id", "world"))
                for e in self.events if e["event"] == "interaction"]

    @property
    def count(self) -> int:
        return sum(e["event"] == "interaction" for e in self.events)

    @property
    def successes(self) -> int:
        return sum(bool(e["result"]["success"]) for e in self.events
                   if e["event"] == "interaction")

    @property
    def fitted(self) -> int:
        """Interactions the last recorded model update learned from (0: none yet)."""
        ups = [e for e in self.events if e["event"] == "update"]
        return int(ups[-1]["interactions"]) if ups else 0

    @property
    def checkpoint(self) -> str:
        """The checkpoint written by the last recorded model update ('' if none)."""
        ups = [e for e in self.events if e["event"] == "update" and e.get("checkpoint")]
        return str(ups[-1]["checkpoint"]) if ups else ""

    @property
    def complete(self) -> bool:
        """The last call on this run ran the loop to its end (budget spent, bar reached)."""
        ends = [e for e in self.events if e["event"] in ("run", "end")]
        return bool(ends) and ends[-1]["event"] == "end" and bool(ends[-1]["complete"])

    @property
    def checkpoint_name(self) -> str:
        """File name of the checkpoint a model update of this call saves, learning from the
        interactions recorded now (in the inference node's adapted_dir): one name per call
        and count, so a save whose update never got into the log (the planner died before
        recording it, the disk was full) overwrites no checkpoint the log names, and a
        resume starts from exactly the weights the log stands for."""
        calls = sum(e["event"] == "run" for e in self.events)
        return (f"w2e_session_{self.session}_{self.category}_{self.primitive}_{self.name}"
                f"_c{calls:03d}_n{self.count:04d}.pt")

    @property
    def restore_name(self) -> str:
        """File name of the checkpoint a resume of this run loads: the last recorded update's,
        else one no update saved (the configured checkpoint is loaded)."""
        return Path(self.checkpoint).name if self.checkpoint else self.checkpoint_name

    # --- writing ----------------------------------------------------------------------------
    def _make_dirs(self) -> None:
        (self.path / "clouds").mkdir(parents=True, exist_ok=True)

    def _append(self, event: dict[str, Any]) -> None:
        event = {"event": event.pop("event"), "time": round(time.time(), 3), **event}
        line = json.dumps(event, separators=(",", ":")) + "\n"
        try:
            self._make_dirs()
            _write_whole(self.path / EVENTS, line.encode())
        except OSError as exc:
            raise _cannot_write(self.path, exc) from exc
        self.events.append(event)

    def start(self, request: dict[str, Any]) -> int:
        """A call starts (or resumes) this run; the interactions already recorded."""
        n = self.count
        self._append({"event": "run", "resumed_from": n, "request": request})
        return n

    def append(self, object_id: int, instance: int | None, action: Action, result: TrialResult,
               points: np.ndarray, normals: np.ndarray,
               frame_id: str = "world") -> LoggedInteraction:
        """Record one executed interaction (its cloud first); durable when this returns, else
        :class:`LogWriteError` and nothing of it recorded."""
        index = self.count + 1
        rel = f"clouds/{index:06d}.npz"
        tmp = self.path / f"{rel}.tmp"
        try:
            self._make_dirs()
            with open(tmp, "wb") as f:
                np.savez(f, points=np.asarray(points, np.float32),
                         normals=np.asarray(normals, np.float32))
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path / rel)
            _fsync_dir(self.path / "clouds")
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise _cannot_write(self.path, exc) from exc
        self._append({"event": "interaction", "index": index, "object_id": int(object_id),
                      "instance": None if instance is None else int(instance),
                      "action": action_to_dict(action), "result": result_to_dict(result),
                      "cloud": rel, "frame_id": frame_id})
        return self.interactions[-1]

    def record_update(self, checkpoint: str, losses: dict[str, float] | None = None) -> None:
        """The model learned from every interaction recorded so far and saved ``checkpoint``."""
        self._append({"event": "update", "interactions": self.count, "checkpoint": checkpoint,
                      "losses": {k: float(v) for k, v in (losses or {}).items()}})

    def end(self, stopped: str, complete: bool, message: str) -> None:
        """How the call ended; ``complete`` closes the run (the next call starts a new one)."""
        self._append({"event": "end", "stopped": stopped, "complete": bool(complete),
                      "interactions": self.count, "message": message})


_CHECKPOINT = re.compile(r"(?P<run>w2e_session_.+)_c(?P<call>\d+)_n(?P<count>\d+)\.pt")


def run_checkpoints(directory: str | os.PathLike, name: str) -> list[Path]:
    """The checkpoints in ``directory`` of the run whose :attr:`SessionRun.checkpoint_name`
    is ``name``, oldest first (call, then count); [] when ``name`` is not such a name."""
    m = _CHECKPOINT.fullmatch(name)
    if m is None:
        return []
    found = []
    for p in Path(directory).glob(f"{m['run']}_c*_n*.pt"):
        o = _CHECKPOINT.fullmatch(p.name)
        if o is not None and o["run"] == m["run"]:
            found.append((int(o["call"]), int(o["count"]), p))
    return [p for *_, p in sorted(found)]


def session_dir(root: str | os.PathLike, session: str, category: str, primitive: str) -> Path:
    """``<root>/<session>/<category>_<primitive>``; every name checked (``""``: defaults)."""
    session = check_name(session or DEFAULT_SESSION, "session")
    category = check_name(category or "scene", "category")
    primitive = check_name(primitive, "primitive")
    return Path(root).expanduser() / session / f"{category}_{primitive}"


def open_session(root: str | os.PathLike, session: str, category: str, primitive: str,
                 resume: bool = True) -> SessionRun:
    """The run an explore call works on: the session's latest run while it is not complete
    (and ``resume``), else a new one (its directory is made by its first write)."""
    base = session_dir(root, session, category, primitive)
    runs = sorted(p for p in base.glob("run-[0-9][0-9][0-9][0-9]") if p.is_dir()) \
        if base.exists() else []
    names = (session or DEFAULT_SESSION, category or "scene", primitive)
    if runs and resume:
        last = SessionRun(runs[-1], *names)
        if not last.complete:
            return last
    number = int(runs[-1].name.split("-")[1]) + 1 if runs else 1
    return SessionRun(base / f"run-{number:04d}", *names)
