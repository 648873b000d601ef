"""A process whose ROS participant never finishes its destruction: Fast DDS's livelock, on demand.

Fast DDS 2.14 and 3.2 can livelock destroying a participant (docs/limitations.md): the destroying thread never
leaves ``DomainParticipant::set_listener(nullptr)``, the first step of rmw_fastrtps's participant destruction,
and it holds the GIL there (rclpy destroys a node without releasing it). It happens once in hundreds of
destructions, too rarely to test by waiting for it. This library, preloaded into a process (``LD_PRELOAD``),
stands in for that one Fast DDS call: with ``nullptr`` it blocks for good, the same thread at the same place;
any other call goes on to Fast DDS. Everything else is the real rclpy and Fast DDS. Built with the system C
compiler, as the interface type support is.
"""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

#: ``eprosima::fastdds::dds::DomainParticipant::set_listener(DomainParticipantListener*)``, the same symbol in
#: Fast DDS 2.14 and 3.2; its return value (ReturnCode_t, 32 bits, trivially copyable) comes back in a register.
SET_LISTENER = "_ZN8eprosima7fastdds3dds17DomainParticipant12set_listenerEPNS1_25DomainParticipantListenerE"
#: What the library writes on stderr when it holds a destruction: a test's evidence that it took effect.
HELD = "held participant destruction"

SOURCE = f"""\
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdio.h>
#include <unistd.h>

typedef unsigned int (*set_listener_fn)(void *participant, void *listener);

unsigned int {SET_LISTENER}(void *participant, void *listener) {{
  if (listener == NULL) {{
    fputs("{HELD}\\n", stderr);
    for (;;) pause();
  }}
  return ((set_listener_fn)dlsym(RTLD_NEXT, "{SET_LISTENER}"))(participant, listener);
}}
"""


def held_participant_library(directory: Path) -> Path:
    """Build the library into ``directory`` (once) and return its path, for ``LD_PRELOAD``."""
    library = directory / "held_participant.so"
    if not library.exists():
        compiler = shutil.which("cc") or shutil.which("gcc")
        assert compiler, "no C compiler (cc or gcc) to build the held-participant library"
        source = directory / "held_participant.c"
        source.write_text(SOURCE)
        subprocess.run([compiler, "-shared", "-fPIC", "-O2", "-o", str(library), str(source), "-ldl"],
                       check=True, capture_output=True, text=True)
    return library
