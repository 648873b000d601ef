"""The harness names a process that Fast DDS cut off from its shared-memory ports (ipc_testing.fastdds_shm): a
real container whose port segments are removed while it reads them, as Fast DDS removes a port it finds broken,
answers no participant that comes after, and a call of the harness from such a participant says which process and
which ports."""
from __future__ import annotations

import os
import re
import subprocess
import sys

from container_process import REPO, Containers
from ipc_testing.fastdds_shm import SHM, read_ports, stranded

#: The worker's own domain's ports: 7400 + 250 * domain and the 250 after (the RTPS port mapping). The ports every
#: domain shares (7000 and up) are left alone: every participant that starts on the machine tries them, and each
#: would log a removed one as an error ("Failed init_port ...: open_and_lock_file failed").
DOMAIN = int(os.environ["ROS_DOMAIN_ID"])
DOMAIN_PORTS = range(7400 + 250 * DOMAIN, 7400 + 250 * (DOMAIN + 1))

#: A client that comes after the removal, in a process of its own: its calls go to the port by its name.
LATE_CLIENT = """
import rclpy
from rclpy.node import Node
from ipc_testing.client import ContainerClient
rclpy.init()
try:
    ContainerClient(Node("late_client"), "/ComponentManager").list(timeout=3.0)
except AssertionError as failure:
    print(failure)
else:
    print("answered")
"""


def test_a_container_whose_ports_fast_dds_removed_answers_no_newcomer_and_the_failed_call_names_it(
        containers: Containers) -> None:
    process, _client = containers.start()
    ports = [name for name in read_ports().get(process.pid, []) if int(name.rsplit("port", 1)[1]) in DOMAIN_PORTS]
    assert ports, f"the container {process.pid} reads no port of its domain: {read_ports()}"
    assert process.pid not in stranded()
    for name in ports:
        (SHM / name).unlink()  # what Fast DDS does to a port it finds broken, while its reader lives on
    assert stranded().get(process.pid) == ports

    late = subprocess.run([sys.executable, "-c", LATE_CLIENT], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert late.stdout.startswith(
        "no reply from /ComponentManager/_container/list_nodes within 3 s. Fast DDS removed the shared-memory ports "
        "of live processes, which no participant started since reaches: "), late
    # among them this container (another test's process in that state would be named too: it is one)
    assert re.search(rf"process {process.pid} \([^)]*\) reads {', '.join(ports)}(;|$)", late.stdout, re.M), late
