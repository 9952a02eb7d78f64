"""The Fast DDS participant ids and profiles a stack gives its nodes, and the shared-memory
cleanup that must never remove a port a living process still uses (issue 41)."""

from __future__ import annotations

import mmap
import subprocess
import sys
import uuid
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from lxml import etree

from w2e_ros.ros.processes import SHM_DIR, clean_shm, shm_files, shm_ports_in_use
from w2e_ros.ros.transport import (
    STACK_PARTICIPANT_IDS,
    control_profile_path,
    free_participant_id,
    node_transport_env,
    profile_copy,
    profile_path,
    unicast_ports,
    user_profile,
)

NS = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
# what `make clean-ros` runs, listing only: the test must not remove other runs' dead files
CLEAN_DRY_RUN = [sys.executable, "-m", "w2e_ros.ros.processes", "clean", "--dry-run"]
SCHEMA = Path(sys.prefix) / "share" / "fastRTPS_profiles.xsd"  # installed by the ROS wheels


def test_unicast_ports_follow_fast_dds_default_mapping():
    # domain 186, participant 0: 7400 + 250 * 186 + 10 / + 11 (seen as fastrtps_port53911)
    assert unicast_ports(186, 0) == (53910, 53911)
    assert unicast_ports(0, 3) == (7416, 7417)
    # the band stays below the next domain's ports
    assert unicast_ports(5, STACK_PARTICIPANT_IDS[-1])[1] < unicast_ports(6, 0)[0]


def test_a_fresh_id_first_then_the_lowest_no_survivor_holds():
    d = 7
    first = STACK_PARTICIPANT_IDS[0]
    assert free_participant_id(d, set(), set()) == first
    # a survivor still maps the first id's port: it is skipped though never given
    assert free_participant_id(d, set(), {unicast_ports(d, first)[1]}) == first + 1
    # given before: a fresh one wins even when the old one is free
    assert free_participant_id(d, {first, first + 1}, set()) == first + 2
    # every id given once: the lowest whose ports nobody maps any more
    given = set(STACK_PARTICIPANT_IDS)
    busy = {p for i in STACK_PARTICIPANT_IDS[:3] for p in unicast_ports(d, i)}
    assert free_participant_id(d, given, busy) == first + 3
    all_busy = {p for i in STACK_PARTICIPANT_IDS for p in unicast_ports(d, i)}
    with pytest.raises(RuntimeError, match="mapped by a living process"):
        free_participant_id(d, given, all_busy)


@pytest.mark.parametrize("path", [profile_path(), control_profile_path()],
                         ids=["large_messages", "control"])
def test_the_shipped_profiles_and_a_per_node_copy_are_valid_fast_dds_xml(path, tmp_path):
    schema = etree.XMLSchema(etree.parse(str(SCHEMA)))
    assert schema.validate(etree.parse(str(path))), schema.error_log
    for localhost in (False, True):
        copy = profile_copy(path, tmp_path, 77, localhost=localhost)
        assert schema.validate(etree.parse(str(copy))), schema.error_log
        rtps = ET.parse(copy).getroot().find(".//f:participant/f:rtps", NS)
        assert rtps.findtext("f:participantID", namespaces=NS) == "77"
        peers = rtps.findall("f:builtin/f:initialPeersList/f:locator/f:udpv4/f:address", NS)
        assert [p.text for p in peers] == (["127.0.0.1"] if localhost else [])


SHM_MAPS = """
import os, time, rclpy
rclpy.init(); node = rclpy.create_node("maps_probe"); time.sleep(1.0)
print(sum("/dev/shm/fastrtps_port" in line for line in open("/proc/self/maps")), flush=True)
"""


@pytest.mark.parametrize("large", [False, True], ids=["control", "large_messages"])
def test_under_localhost_discovery_only_the_cloud_nodes_use_shared_memory(large, tmp_path):
    """rmw_fastrtps's LOCALHOST mode adds shared memory to any profile; a control node's
    environment (node_transport_env) keeps it UDP only, a cloud node keeps its segment."""
    from w2e_ros.ros.processes import pick_domain_id, ros_env

    env = node_transport_env(ros_env(domain_id=pick_domain_id()), large, tmp_path)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT"
    out = subprocess.run([sys.executable, "-c", SHM_MAPS], env=env, capture_output=True,
                         text=True, timeout=120)
    ports = int(out.stdout.split()[-1])
    assert (ports > 0) == large, out.stdout + out.stderr


def test_the_control_profile_is_udp_only():
    root = ET.parse(control_profile_path()).getroot()
    kinds = {d.findtext("f:type", namespaces=NS)
             for d in root.iterfind(".//f:transport_descriptor", NS)}
    assert kinds == {"UDPv4"}
    rtps = root.find(".//f:participant/f:rtps", NS)
    assert rtps.findtext("f:useBuiltinTransports", namespaces=NS) == "false"


def test_only_a_profile_of_the_users_own_counts_as_a_choice():
    assert user_profile({}) is None
    assert user_profile({"FASTRTPS_DEFAULT_PROFILES_FILE": str(profile_path())}) is None
    assert user_profile({"FASTDDS_DEFAULT_PROFILES_FILE": "/my.xml"}) == "/my.xml"


@pytest.fixture
def fake_port():
    """A Fast DDS-like port in /dev/shm: segment, listener lock and semaphore."""
    port = 60000 + uuid.uuid4().int % 5000
    files = [SHM_DIR / f"fastrtps_port{port}", SHM_DIR / f"fastrtps_port{port}_el",
             SHM_DIR / f"sem.fastrtps_port{port}_mutex"]
    before = shm_files()
    for f in files:
        f.write_bytes(b"\0" * mmap.PAGESIZE)
    yield port, files, before
    for f in files:
        f.unlink(missing_ok=True)


def test_a_port_a_living_process_maps_is_kept_whole_and_removed_whole_once_unmapped(fake_port):
    port, files, before = fake_port
    with open(files[0], "r+b") as f, mmap.mmap(f.fileno(), 0):
        assert port in shm_ports_in_use()
        assert clean_shm(before) == []  # not even the lock file or the semaphore
        assert all(f.exists() for f in files)
    assert port not in shm_ports_in_use()
    assert sorted(clean_shm(before)) == sorted(files)


def test_make_clean_ros_leaves_what_another_process_maps(fake_port):
    port, files, _ = fake_port
    holder = subprocess.Popen(
        [sys.executable, "-c", "import mmap, sys; f = open(sys.argv[1], 'r+b'); "
         "m = mmap.mmap(f.fileno(), 0); print('mapped', flush=True); sys.stdin.read()",
         str(files[0])], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "mapped"
        out = subprocess.run(CLEAN_DRY_RUN, capture_output=True, text=True, check=True)
        assert all(str(f) not in out.stdout for f in files)
        assert all(f.exists() for f in files)
    finally:
        holder.stdin.close()
        holder.wait()
    out = subprocess.run(CLEAN_DRY_RUN, capture_output=True, text=True, check=True)
    assert all(str(f) in out.stdout for f in files)  # what `make clean-ros` would remove now


HOLD_DOMAIN = """
import sys
from w2e_ros.ros.processes import pick_domain_id
print(pick_domain_id(), flush=True)
sys.stdin.readline()
"""


def test_a_domain_another_living_process_picked_is_never_picked_until_it_exits():
    """Two runs at once on one host once shared domain 117 and one's client called the other's
    planner: pick_domain_id holds a lock per domain for the life of the process."""
    from w2e_ros.ros import processes

    holder = subprocess.Popen([sys.executable, "-c", HOLD_DOMAIN], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        held = int(holder.stdout.readline())
        picked = {processes.pick_domain_id() for _ in range(99)}
        assert held not in picked and len(picked) == 99
    finally:
        holder.communicate("\n", timeout=30)
    # its lock went with it: the next round of this process's order reaches the domain again
    assert held in {processes.pick_domain_id() for _ in range(100)}
    # and this process holds only its latest few picks, not every domain it ever used
    assert len(processes._DOMAIN_LOCKS) == processes.DOMAIN_LOCKS_HELD
