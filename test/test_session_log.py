"""The exploration log on disk: what the planner resumes an interrupted session from."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from w2e_ros.core.exploration.session_log import EVENTS, open_session, session_dir
from w2e_ros.core.robot.primitives import Action, TrialResult


def _interaction(k: int) -> tuple[Action, TrialResult, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(k)
    action = Action(rng.normal(size=3), np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0]),
                    "pull")
    result = TrialResult(True, k % 2 == 0, np.array([0.02 * k, 0.0]), 0, "door_link",
                         "" if k % 2 == 0 else "moved too little", np.array([0.0, 0.01, 0.0]),
                         0, "door_link")
    return action, result, rng.normal(size=(64, 3)), rng.normal(size=(64, 3))


def test_recorded_interactions_read_back_exactly_and_the_run_resumes(tmp_path):
    run = open_session(tmp_path, "", "door", "pull")
    assert run.path == session_dir(tmp_path, "default", "door", "pull") / "run-0001"
    assert run.start({"budget": 3}) == 0
    written = [_interaction(k) for k in range(3)]
    for k, (a, r, p, n) in enumerate(written):
        run.append(7 + k, 30, a, r, p, n, "world")
        if k == 1:
            run.record_update("/tmp/ckpt.pt", {"loss": 0.5})
    assert (run.count, run.fitted, run.checkpoint, run.successes) == (3, 2, "/tmp/ckpt.pt", 2)
    # the process dies here (no "end"): the next call for the session gets the same run
    again = open_session(tmp_path, "default", "door", "pull")
    assert again.path == run.path and not again.complete
    assert again.start({"budget": 3}) == 3
    for rec, (a, r, p, n) in zip(again.interactions, written, strict=True):
        np.testing.assert_allclose(rec.action.point, a.point)
        assert rec.result.success == r.success and rec.result.reason == r.reason
        np.testing.assert_allclose(rec.result.motion, r.motion)
        points, normals = rec.cloud(again.path)
        np.testing.assert_allclose(points, p.astype(np.float32))
        np.testing.assert_allclose(normals, n.astype(np.float32))
    assert [rec.index for rec in again.interactions] == [1, 2, 3]
    assert again.interactions[0].object_id == 7 and again.interactions[0].instance == 30
    # a cancelled / failed call leaves the run open; a complete one closes it
    again.end("cancelled", complete=False, message="cancelled")
    assert open_session(tmp_path, "", "door", "pull").path == run.path
    again.end("budget", complete=True, message="done")
    fresh = open_session(tmp_path, "", "door", "pull")
    assert fresh.name == "run-0002" and fresh.count == 0
    assert fresh.checkpoint_name != run.checkpoint_name
    # sessions are separate, and resume=False always starts a new run
    assert open_session(tmp_path, "lab1", "door", "pull").path.parent.parent.name == "lab1"
    assert fresh.start({}) == 0  # run-0002 is open: resumed, unless resume=False
    assert open_session(tmp_path, "", "door", "pull").name == "run-0002"
    assert open_session(tmp_path, "", "door", "pull", resume=False).name == "run-0003"


def test_a_line_torn_by_a_crash_is_cut_off_and_the_log_goes_on(tmp_path):
    run = open_session(tmp_path, "s", "door", "push")
    run.start({})
    a, r, p, n = _interaction(0)
    run.append(1, None, a, r, p, n)
    with open(run.path / EVENTS, "a") as f:
        f.write('{"event":"interaction","index":2,"obj')  # killed mid-write
    again = open_session(tmp_path, "s", "door", "push")
    assert again.count == 1
    again.append(1, None, a, r, p, n)
    lines = (run.path / EVENTS).read_text().splitlines()
    assert [json.loads(x)["event"] for x in lines] == ["run", "interaction", "interaction"]
    assert [rec.index for rec in again.interactions] == [1, 2]


# a process whose files may not grow past LIMIT bytes (RLIMIT_FSIZE, SIGXFSZ ignored): a write
# across it is cut short and the next one fails (EFBIG), as a filling disk cuts a write short
# and then says ENOSPC; no root needed (a small tmpfs would need it)
_APPEND_CAPPED = """
import pickle, resource, signal, sys
from w2e_ros.core.exploration.session_log import LogWriteError, open_session
root, limit, points = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
run = open_session(root, "s", "door", "pull")
a, r = pickle.loads(sys.stdin.buffer.read())
import numpy as np
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
try:
    run.append(1, None, a, r, np.zeros((points, 3)), np.zeros((points, 3)))
    print("written")
except LogWriteError as e:
    print("refused:", e)
"""


@pytest.mark.parametrize("where", ["line", "cloud"])
def test_a_write_the_disk_cannot_take_is_undone_and_the_log_goes_on(tmp_path, where):
    import pickle

    run = open_session(tmp_path, "s", "door", "pull")
    run.start({})
    for k in range(8):  # a log longer than one small cloud file
        a, r, _, _ = _interaction(k)
        run.append(k, None, a, r, np.zeros((4, 3)), np.zeros((4, 3)))
    before = (run.path / EVENTS).read_bytes()
    # "line": the cloud (4 points, < 1 kB) fits, the line is cut 100 bytes in; "cloud": the
    # cloud (4000 points, ~100 kB) is cut
    limit, points = (len(before) + 100, 4) if where == "line" else (len(before) + 100, 4000)
    a, r, _, _ = _interaction(8)
    out = subprocess.run([sys.executable, "-c", _APPEND_CAPPED, str(tmp_path), str(limit),
                          str(points)], input=pickle.dumps((a, r)), capture_output=True,
                         check=True).stdout.decode()
    assert out.startswith("refused: exploration log ") and "cannot write" in out, out
    assert (run.path / EVENTS).read_bytes() == before  # no torn line left
    assert not list((run.path / "clouds").glob("*.tmp"))
    # space again: the log goes on where it stopped, every line whole
    again = open_session(tmp_path, "s", "door", "pull")
    assert again.count == 8
    again.append(8, None, a, r, np.zeros((4, 3)), np.zeros((4, 3)))
    again.end("budget", complete=False, message="")
    lines = [json.loads(x) for x in (run.path / EVENTS).read_text().splitlines()]
    assert [e["index"] for e in lines if e["event"] == "interaction"] == list(range(1, 10))


@pytest.mark.parametrize("name", ["../up", "a/b", ".hidden", "", "x" * 65, "spa ce"])
def test_session_names_are_plain_directory_names(tmp_path, name):
    with pytest.raises(ValueError):
        open_session(tmp_path, name or "/", "door", "pull")
