"""`source .venv/bin/activate` gives a shell the ROS environment the venv holds (ament index:
this package and its interfaces), `deactivate` puts the shell back, and `make install` extends
the activate script of a fresh venv (config/venv_ros_env.sh, idempotent)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from w2e_ros.ros.transport import PROFILE_FILE, PROFILE_VARS

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "config" / "venv_ros_env.sh"
VENV = Path(sys.prefix)

LOOKUP = ("from ament_index_python.packages import get_package_share_directory as g; "
          "from ament_index_python import get_resource as r; "
          "print(g('w2e_ros')); print(r('rosidl_interfaces', 'w2e_msgs')[0].split()[0])")


def _bash(script: str, **env: str) -> subprocess.CompletedProcess:
    """A login-free bash with no ROS variables of its own, in the repository root."""
    clean = {k: v for k, v in os.environ.items()
             if k not in ("AMENT_PREFIX_PATH", "ROS_DISTRO", "VIRTUAL_ENV", *PROFILE_VARS)
             and not k.startswith("_ROS_WHEELS")}
    clean.update(env)
    return subprocess.run(["bash", "-c", script], cwd=ROOT, env=clean, capture_output=True,
                          text=True, timeout=60)


@pytest.mark.skipif(not (VENV / "bin" / "activate").is_file(), reason="not run from a venv")
def test_an_activated_shell_finds_the_package_and_its_interfaces():
    res = _bash(f'source "{VENV}/bin/activate" && python -c "{LOOKUP}"')
    assert res.returncode == 0, res.stderr
    share, interfaces = res.stdout.splitlines()
    assert Path(share).resolve() == (VENV / "share" / "w2e_ros").resolve()
    assert "action/ExecuteInteraction.action" in interfaces


@pytest.fixture
def fresh_venv(tmp_path: Path) -> Path:
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                   timeout=60)
    return venv


def test_activation_sets_and_deactivate_restores_the_ros_variables(fresh_venv: Path):
    pristine = (fresh_venv / "bin" / "activate").read_text()
    for _ in range(2):  # the second run replaces the blocks of the first
        subprocess.run(["bash", str(SCRIPT), str(fresh_venv)], check=True, timeout=60,
                       capture_output=True)
    text = (fresh_venv / "bin" / "activate").read_text()
    assert text.count("_W2E_ROS_ENV=1") == 1 and text.startswith(pristine[:40])
    show = 'echo "${AMENT_PREFIX_PATH-unset}|${ROS_DISTRO-unset}"'
    act = f'source "{fresh_venv}/bin/activate"'
    res = _bash(f"{show}; {act}; {show}; {act}; {show}; deactivate; {show}; "
                "set | grep -c '^_W2E' || true")
    assert res.stdout.split() == ["unset|unset", f"{fresh_venv}|jazzy", f"{fresh_venv}|jazzy",
                                  "unset|unset", "0"], res.stderr
    res = _bash(f"{act}; {show}; deactivate; {show}", AMENT_PREFIX_PATH="/opt/ros/jazzy",
                ROS_DISTRO="humble")
    assert res.stdout.split() == [f"{fresh_venv}:/opt/ros/jazzy|jazzy", "/opt/ros/jazzy|humble"]


def test_make_install_extends_the_activate_script():
    if shutil.which("make") is None:
        pytest.skip("no make")
    # a dry run with no stamps: what `make install` does on a fresh machine
    res = subprocess.run(["make", "-n", "install", "STAMP=/nonexistent/stamps"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "bash config/venv_ros_env.sh .venv" in res.stdout


def test_activation_sets_the_transport_profile_unless_the_shell_names_one(fresh_venv: Path):
    subprocess.run(["bash", str(SCRIPT), str(fresh_venv)], check=True, timeout=60,
                   capture_output=True)
    show = 'echo "${FASTRTPS_DEFAULT_PROFILES_FILE-unset}|${FASTDDS_DEFAULT_PROFILES_FILE-unset}"'
    act = f'source "{fresh_venv}/bin/activate"'
    shipped = f"{fresh_venv}/share/w2e_ros/config/{PROFILE_FILE}"
    res = _bash(f"{show}; {act}; {show}; {act}; {show}; deactivate; {show}")
    assert res.stdout.split() == ["unset|unset", f"{shipped}|{shipped}", f"{shipped}|{shipped}",
                                  "unset|unset"], res.stderr
    # a profile the user chose (either variable) wins, and deactivate leaves it as it was
    res = _bash(f"{act}; {show}; deactivate; {show}", FASTDDS_DEFAULT_PROFILES_FILE="/my.xml")
    assert res.stdout.split() == ["/my.xml|/my.xml", "unset|/my.xml"], res.stderr
