"""run_node's shutdown: a callback still running at SIGTERM finishes before the node goes."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

NODE = '''
import sys, time
from std_msgs.msg import String
from rclpy.node import Node
from w2e_ros.ros.spin import run_node

class Slow(Node):
    def __init__(self):
        super().__init__("slow")
        self.pub = self.create_publisher(String, "out", 10)
        self.create_timer(0.05, self.tick)

    def tick(self):
        print("busy", flush=True)
        time.sleep(1.5)  # past the executor's own 1 s shutdown wait
        self.pub.publish(String(data="done"))
        print("published", flush=True)

run_node(Slow, threads=2)
'''


def test_sigterm_waits_for_the_callback_in_flight(tmp_path: Path) -> None:
    script = tmp_path / "slow_node.py"
    script.write_text(NODE)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout.readline().strip() == "busy"  # the callback is in flight
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "published" in out  # the callback ran to its end
    assert "never retrieved" not in out and "Destroyable" not in out, out
    assert proc.returncode == 0, out
