"""The Fast DDS profile of the container and of ``ipc-component``: quick re-announcements, diagnostics on stderr.

The participant re-announces itself every 0.25 s (Fast DDS default: 3 s).

Why: a new participant (``ipc-component``, ``ros2 component``, launch_ros) announces itself and the container
answers at once with its own announcement, but Fast DDS 2.14 often drops that answer because it arrives
before the new participant has started listening (the answer is received ~2 ms after the first
announcement and ignored). The newcomer then finds the container only at its next periodic
announcement, up to 3 s later; that happened in most command runs and made ``ipc-component load`` take
seconds. Re-announcing every 0.25 s bounds that delay at 0.25 s, for every
client, at the cost of one ~500-byte UDP datagram per known participant and initial peer per period. The
command line uses it too, so that the container also learns the client quickly (Fast DDS drops a service
reply to a client it has not discovered yet).

Fast DDS prints its own warnings and errors on stdout by default, where they land inside the output of
``ipc-component list`` or ``bag info`` (a shared-memory port another process holds is one such error, common
when many participants start at once). The profile sends them to stderr, where ROS logging goes too.

The profile is used only if nobody configured Fast DDS otherwise: no profiles file in the environment, no
``DEFAULT_FASTRTPS_PROFILES.xml`` / ``DEFAULT_FASTDDS_PROFILES.xml`` in the working directory, and no other RMW
selected. It goes through the variable the installed Fast DDS reads: ``FASTRTPS_DEFAULT_PROFILES_FILE`` on Fast
DDS 2 (Jazzy), which knows no other; ``FASTDDS_DEFAULT_PROFILES_FILE`` on Fast DDS 3 (Kilted), which still reads
the old name but prints a deprecation warning on stdout for every participant, before the profile could send it
to stderr, so into every command's output.
"""
from __future__ import annotations

import os
import pathlib
import sys
from typing import MutableMapping

PROFILE = pathlib.Path(__file__).with_name("fastdds_container.xml")
#: The profiles file variable of Fast DDS 2 and of Fast DDS 3.
FASTDDS2_VARIABLE, FASTDDS3_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE"
#: The profiles files Fast DDS 2 and 3 load from the working directory.
WORKING_DIRECTORY_PROFILES = ("DEFAULT_FASTRTPS_PROFILES.xml", "DEFAULT_FASTDDS_PROFILES.xml")
#: The metadata directory of the Fast DDS 3 wheel, ``ros-fastdds`` (Fast DDS 2's is ``ros-fastrtps``), up to its
#: version.
FASTDDS3_DIST_INFO = "ros_fastdds-"


def profile_variable() -> str:
    """The profiles file variable of the installed Fast DDS: Fast DDS 3 (Kilted on) ships as ``ros-fastdds``.

    The wheel's ``.dist-info`` directory on ``sys.path`` tells, as ``importlib.metadata.distribution`` would; but
    importing ``importlib.metadata`` alone costs a command 25 ms of CPU, the listing below a fraction of one.
    """
    for folder in sys.path:
        try:
            with os.scandir(folder or ".") as entries:
                if any(entry.name.startswith(FASTDDS3_DIST_INFO) and entry.name.endswith(".dist-info")
                       for entry in entries):
                    return FASTDDS3_VARIABLE
        except OSError:  # a zip archive or a folder that is gone
            continue
    return FASTDDS2_VARIABLE


def use_fastdds_profile(environ: MutableMapping[str, str] = os.environ) -> bool:
    """Select the project's participant profile (before ``rclpy.init``) unless Fast DDS is configured."""
    rmw = environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    if not rmw.startswith("rmw_fastrtps") or environ.get(FASTDDS2_VARIABLE) or environ.get(FASTDDS3_VARIABLE):
        return False
    if any(pathlib.Path(name).exists() for name in WORKING_DIRECTORY_PROFILES):
        return False
    environ[profile_variable()] = str(PROFILE)
    return True
