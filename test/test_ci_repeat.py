"""`.ci/repeat`: the script that says whether CI can be trusted counts what failed, per test,
and its record adds up over invocations."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _repeat(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / ".ci" / "repeat"), *args], cwd=ROOT,
                          text=True, capture_output=True, timeout=300)


def test_repeat_counts_failures_per_test_and_records_every_run(tmp_path):
    flaky = tmp_path / "test_flaky.py"  # fails on its second run only
    flaky.write_text(
        "from pathlib import Path\n"
        f"MARK = Path({str(tmp_path / 'ran')!r})\n"
        "def test_steady():\n    assert True\n"
        "def test_second_run_fails():\n"
        "    first = not MARK.exists()\n    MARK.touch()\n    assert first\n")
    rec = tmp_path / "record.json"
    out = _repeat("--ros", "3", "--files", str(flaky), "--out", str(tmp_path / "logs"),
                  "--record", str(rec))
    assert out.returncode == 1, out.stdout + out.stderr
    # runs 2 and 3 fail; the class name carries the folder as pytest's rootdir sees it
    assert re.search(r"^\s+2  \S*test_flaky::test_second_run_fails$", out.stdout, re.M), out.stdout
    entries = json.loads(rec.read_text())
    assert len(entries) == 1 and [r["exit"] != 0 for r in entries[0]["runs"]] == [
        False, True, True]
    assert all(r["tests"] == 2 for r in entries[0]["runs"])
    assert entries[0]["ros_files"] == [str(flaky)]

    (tmp_path / "ran").unlink()  # a second invocation: one clean run, added to the record
    flaky.write_text("def test_steady():\n    assert True\n")
    out = _repeat("--ros", "1", "--files", str(flaky), "--out", str(tmp_path / "logs2"),
                  "--record", str(rec))
    assert out.returncode == 0, out.stdout + out.stderr
    assert len(json.loads(rec.read_text())) == 2
    assert "recorded ros runs: 4, 2 with a failure" in out.stdout
