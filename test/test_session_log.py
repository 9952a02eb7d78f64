"""The exploration log on disk: what the planner resumes an interrupted session from."""

from __future__ import annotations

import json

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


@pytest.mark.parametrize("name", ["../up", "a/b", ".hidden", "", "x" * 65, "spa ce"])
def test_session_names_are_plain_directory_names(tmp_path, name):
    with pytest.raises(ValueError):
        open_session(tmp_path, name or "/", "door", "pull")
