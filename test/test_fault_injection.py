"""What bench/fault_injection.py counts as survived: each fault noticed within its bound (the
call's next step, or its answer; a fault held until the call ends must be named by the answer),
the log never rewritten, every session numbered 1..n; and the filler that makes a disk full."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("fault_injection",
                                              ROOT / "bench" / "fault_injection.py")
fi = importlib.util.module_from_spec(spec)
spec.loader.exec_module(fi)


def _fault(kind: str, **kw) -> dict:
    return {"kind": kind, "node": "sim_bridge", "then": "step", **kw}


@pytest.mark.parametrize("fault, ok, named", [
    # a kill: the next step (resumed) or the answer within 10 s; what the answer says is free
    (_fault("kill", next_event_s=3.0, call_end_s=40.0), True, None),
    (_fault("kill", next_event_s=40.3, call_end_s=41.0), False, None),
    # held until the call ends: a step in flight is no sign of notice, the answer is
    (_fault("stop_camera", next_event_s=0.1, call_end_s=7.2, call_success=False,
            message="segmentation: no frame on 'objects' for 5 s"), True, True),
    (_fault("stop_camera", next_event_s=0.1, call_end_s=41.0, call_success=False,
            message="segmentation: no frame on 'objects' for 5 s"), False, True),
    (_fault("stop_camera", next_event_s=0.1, call_end_s=6.0, call_success=False,
            message="segmentation: objects [7] not seen within 40 s"), False, False),
    # a call that finished without what the fault took away: nothing to name
    (_fault("stop_bridge", next_event_s=0.0, call_end_s=2.4, call_success=True,
            message="10 interaction(s) ..."), True, None),
    # a held trial: the executor's trial_timeout_s is its own bound, 10 s after it
    (_fault("hang_trial", next_event_s=2.3, call_end_s=12.6, call_success=False,
            message="execute_interaction: the robot side did not answer in time: ..."),
     True, True),
    (_fault("hang_trial", next_event_s=2.3, call_end_s=30.0, call_success=False,
            message="execute_interaction (result): no answer within 60 s"), False, False),
    (_fault("disk_full", next_event_s=1.0, call_end_s=1.0, call_success=False,
            message="exploration log /x: cannot write (No space left on device): ..."),
     True, True),
])
def test_a_fault_is_survived_when_noticed_in_time_and_named_when_it_must_be(fault, ok, named):
    got = fi.judge(fault, trial_timeout_s=8.0)
    assert (got["ok"], got["named"]) == (ok, named), got
    assert got["bound_s"] == (18.0 if fault["kind"] == "hang_trial" else 10.0)


def test_the_log_may_grow_but_never_change_and_a_session_is_1_to_n():
    a, b, c = ({"index": i, "result": {"success": False}} for i in (1, 2, 3))
    assert fi.log_problems([a, b], [a, b, c], 1) == []
    assert fi.log_problems([a, b], [a, {**b, "result": {"success": True}}], 2)  # rewritten
    assert fi.log_problems([a, b], [a], 3)  # lost
    assert fi.session_problems("s", [1, 2, 3], 3) == []
    assert fi.session_problems("s", [1, 2, 2, 3], 3)  # duplicated
    assert fi.session_problems("s", [1, 3], 3)  # lost


def test_per_kind_counts_and_times():
    faults = [fi.judge(f) for f in (
        _fault("kill", next_event_s=1.0), _fault("kill", next_event_s=30.0),
        _fault("disk_full", next_event_s=0.0, then="call ended", call_end_s=0.5,
               call_success=True, message="done"))]
    got = fi.per_kind(faults)
    assert got["kill"]["faults"] == 2 and got["kill"]["ok"] == 1
    assert got["kill"]["noticed_s_max"] == 30.0
    assert got["disk_full"]["no_effect"] == 1 and got["disk_full"]["calls_ended"] == 1
    assert set(got) == {"kill", "disk_full"}


def test_the_filler_stops_at_a_full_disk_without_raising():
    # /dev/full says ENOSPC to every write, as a file system with no space left does
    assert fi.fill(Path("/dev/full")) == 0
