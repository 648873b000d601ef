"""Which components of the domain's containers are recorders, for ``record stop | split | status``.

A recorder is recognised by what it is: a node that serves the services every ``components::Recorder`` offers
(``~/get_stats`` and ``~/split_bagfile``, with their types), placed in its container through ListNodes. A name
alone would not do: a recorder with ``record.compress`` loads an ImageEncoder named ``<recorder>_encoder`` beside
it (components/recorder/compression.py), which the fleet's ``record_*`` matches as well, and a container may hold
several sessions' recorders at once.

Fleet recorders are named ``record_<session>`` in their container's namespace (``recorder_full_name``). A
component named that way is waited for until the graph shows its ``~/get_stats``, so that a recorder whose services
are not discovered yet is not taken for something else: every recorder and every encoder offers ``get_stats``, and
a recorder creates ``split_bagfile`` before it (a participant announces its endpoints in creation order).
"""
from __future__ import annotations

import fnmatch
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ipc_component.ros_session import BUDGET, CliError, RosSession

if TYPE_CHECKING:
    from ipc_component.container_discovery import ContainerListing

NODE_PREFIX = "record_"
RECORDER_SERVICES = {"get_stats": "std_srvs/srv/Trigger", "split_bagfile": "rosbag2_interfaces/srv/SplitBagfile"}
#: s: how often the graph is looked at again while a fleet recorder's services are not discovered yet
POLL = 0.02


def recorder_node(session: str) -> str:
    """The node name of ``session``'s recorder in each container."""
    return f"{NODE_PREFIX}{session}"


def recorder_full_name(container: str, session: str) -> str:
    """The recorder's node lives in its container's name as namespace: service names stay unique in the domain
    (containers must have distinct names anyway, or their own services would clash)."""
    return f"{container.rstrip('/')}/{recorder_node(session)}"


@dataclass(frozen=True)
class PlacedRecorder:
    """A recorder found in a container: its component id there and its node's full name."""

    container: str
    unique_id: int
    node: str

    @property
    def session(self) -> str:
        """The fleet session its name says (``record_<session>``), or '' for a recorder named otherwise."""
        prefix = recorder_full_name(self.container, "")
        return self.node[len(prefix):] if self.node.startswith(prefix) else ""


def _recorder_services(node: Any) -> dict[str, set[str]]:
    """Per node (full name), which of the recorder services the graph shows it offering with their types."""
    offered: dict[str, set[str]] = {}
    for name, types in node.get_service_names_and_types():
        owner, _, service = name.rpartition("/")
        if RECORDER_SERVICES.get(service) in types:
            offered.setdefault(owner, set()).add(service)
    return offered


def find_recorders(ros: RosSession, spin_time: float, session: str | None,
                   fleet_only: bool) -> list[PlacedRecorder]:
    """The recorders of the domain's containers, sorted by container: those of ``session`` (any session's without
    it); with ``fleet_only``, only fleet recorders (named ``record_<session>``), else every recorder.

    Raises CliError when there is none, naming what was found instead (:func:`_absence`): a command that finds no
    recorder says whether it found no container, a container that did not answer, or components that are not
    (or not yet) recorders."""
    from ipc_component.container_discovery import list_containers

    start = time.monotonic()
    listings = list_containers(ros.node, ros.executor, deadline=start + BUDGET + spin_time,
                               discovery_until=start + spin_time)
    fleet_named = [name for listing in listings for _id, name in listing.components
                   if fnmatch.fnmatchcase(name, recorder_full_name(listing.container, "*"))]
    offered = _recorder_services(ros.node)
    deadline = time.monotonic() + BUDGET
    while any("get_stats" not in offered.get(name, ()) for name in fleet_named) and time.monotonic() < deadline:
        ros.executor.spin_once(timeout_sec=POLL)
        offered = _recorder_services(ros.node)
    found = [PlacedRecorder(listing.container, unique_id, name) for listing in listings
             for unique_id, name in listing.components
             if offered.get(name) == set(RECORDER_SERVICES)]
    if fleet_only:
        found = [recorder for recorder in found if recorder.session]
    if session is not None:
        found = [recorder for recorder in found if recorder.session == session]
    if not found:
        wanted = (f" of session '{session}'" if session is not None
                  else " of a fleet session" if fleet_only else "")
        raise CliError(f"No recorder{wanted} found" + _absence(ros, listings, offered, spin_time))
    return found


def _absence(ros: RosSession, listings: list[ContainerListing], offered: dict[str, set[str]],
             spin_time: float) -> str:
    """What the lookup found where it found no recorder: no container (and where it searched), or per container
    discovered, why its listing failed or its components that are named or serve like a recorder, each with its
    session and the recorder services the graph did not show it offering."""
    if not listings:
        return f": no container discovered within {spin_time:g} s (--spin-time)\n    {ros.where_searched()}"
    described = []
    for listing in listings:
        candidates = []
        for _id, name in listing.components:
            services = offered.get(name, set())
            session = PlacedRecorder(listing.container, 0, name).session
            if services or session:
                missing = sorted(set(RECORDER_SERVICES) - services)
                candidates.append(name + (f" (session '{session}')" if session else "")
                                  + (f" without {' or '.join(missing)}" if missing else ""))
        detail = (listing.error if listing.error is not None else ", ".join(candidates) if candidates
                  else f"no recorder among {len(listing.components)} component(s)")
        described.append(f"\n    {listing.container}: {detail}")
    return f" in the {len(listings)} container(s) discovered" + "".join(described)
