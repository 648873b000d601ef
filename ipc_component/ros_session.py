"""What the verbs that talk to containers share: one rclpy session per command, its time budgets, and CliError.

Its own module so that every verb module can use it without importing ``ipc_component.cli``, which imports the
verb modules to build the parser.
"""
from __future__ import annotations

import os
import time
from typing import TYPE_CHECKING, Any, Callable, Sequence

if TYPE_CHECKING:
    from ipc_component.fleet_link import Fleet

BUDGET = 5.0             # s: discovery and listing, and waiting for a container's service
CALL_TIMEOUT = 60.0      # s: waiting for a LoadNode / UnloadNode reply (component constructors may be slow)
GONE_GRACE = 2.0         # s: a container whose service stays absent this long while we wait has left
#: s: a command that loaded or unloaded components waits until its graph has not changed for SETTLE_QUIET (at most
#: SETTLE_LIMIT) before it destroys its participant: see RosSession.graph_changed
SETTLE_QUIET, SETTLE_LIMIT = 0.3, 3.0
#: s: what destroying a command's node and rclpy context may take (tens of ms, normally) before the command ends
#: without it: see end_ros
TEARDOWN_LIMIT = 2.0
# Fast DDS's highest domain: its ports (7400 + 250 * domain + offsets) must stay below 65536. Above it, Fast DDS
# ends the process with status 1 and no message on stderr.
MAX_FASTDDS_DOMAIN = 232


class CliError(Exception):
    """A failure to report on stderr; the command exits with 1."""


#: What end_ros runs: each session's destruction of its node and rclpy context, in the order they ended.
_teardowns: list[Callable[[], None]] = []


def end_ros_later(node: Any, context: Any, executor: Any = None) -> None:
    """Leave destroying ``node`` (if any), shutting down ``executor`` (if any) and ``context`` to :func:`end_ros`,
    once the command is done."""
    import rclpy

    def teardown() -> None:
        try:
            if executor is not None:
                executor.shutdown(timeout_sec=1.0)
            if node is not None:
                node.destroy_node()
        finally:
            rclpy.try_shutdown(context=context)

    _teardowns.append(teardown)


def end_ros(status: int) -> int:
    """Destroy what the command's ROS sessions left (:func:`end_ros_later`), last, and return ``status``; if
    that has not finished within TEARDOWN_LIMIT s, the process ends with ``status`` all the same.

    Why last, and bounded: Fast DDS 2.14 and 3.2 can livelock destroying a participant (docs/limitations.md),
    for good, and out of Python's reach (component_container.exit_timer). The command's work is done and
    printed by then; it ends with the status it has, after the Python stacks of the stuck teardown on stderr.
    The other participants take it as gone when its lease runs out, as after a kill (seen in ``record start``
    and ``record stop``, which hung instead).
    """
    from component_container.exit_timer import end_within

    def teardown_all() -> None:
        while _teardowns:
            _teardowns.pop(0)()

    if _teardowns:
        end_within(TEARDOWN_LIMIT, status, teardown_all)
    return status


class RosSession:
    """rclpy set up for one command: its own context, a hidden node and an executor; destroyed by :func:`end_ros`
    when the command ends (leaving the ``with`` block only waits for a quiet graph, see :meth:`graph_changed`)."""

    def __init__(self, ros_args: Sequence[str]) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.impl.implementation_singleton import rclpy_implementation
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.parameter import Parameter

        from component_container.discovery_profile import use_fastdds_profile

        use_fastdds_profile()  # Fast DDS's diagnostics on stderr, not in the output; quick discovery
        self.context = Context()
        rclpy.init(args=["ipc-component", *ros_args], context=self.context)
        try:
            domain = self.context.get_domain_id()
            if domain > MAX_FASTDDS_DOMAIN and rclpy.get_rmw_implementation_identifier().startswith("rmw_fastrtps"):
                raise CliError(f"ROS_DOMAIN_ID {domain} is out of range: Fast DDS accepts 0 to {MAX_FASTDDS_DOMAIN}")
            self.node = Node(
                f"_ipc_component_{os.getpid()}", context=self.context, start_parameter_services=False,
                enable_rosout=False,
                parameter_overrides=[Parameter("start_type_description_service", value=False)])
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
            self._settle = False
        except rclpy_implementation.RCLError as exc:  # e.g. ROS_STATIC_PEERS naming a host that does not resolve
            rclpy.try_shutdown(context=self.context)
            raise CliError(f"Could not start ROS: {str(exc).splitlines()[0]}") from exc
        except BaseException:
            rclpy.try_shutdown(context=self.context)
            raise

    def __enter__(self) -> "RosSession":
        return self

    def graph_changed(self) -> None:
        """This command loaded or unloaded components: let discovery take in what that changed before the
        participant is destroyed. Fast DDS (2.14 and 3.2) can deadlock destroying a participant while its
        discovery thread reports an endpoint that went away: the destroying thread waits for the report to end,
        and the report waits for a lock that thread holds. Seen in ``record stop``, whose unloads make each
        container remove a recorder's two dozen endpoints just before the command ends: it hung for good in
        ``destroy_node`` (docs/limitations.md). Waiting narrows that window; it cannot close it."""
        self._settle = True

    def _wait_for_quiet_graph(self) -> None:
        """Spin until the topics and services this participant knows stayed the same for SETTLE_QUIET s, at
        most SETTLE_LIMIT s."""
        def graph() -> tuple[list, list]:
            return self.node.get_topic_names_and_types(), self.node.get_service_names_and_types()

        end = time.monotonic() + SETTLE_LIMIT
        last, since = graph(), time.monotonic()
        while time.monotonic() < end and time.monotonic() - since < SETTLE_QUIET:
            self.executor.spin_once(timeout_sec=0.05)
            now = graph()
            if now != last:
                last, since = now, time.monotonic()

    def __exit__(self, *exc: Any) -> None:
        try:
            if self._settle:
                self._wait_for_quiet_graph()
        finally:
            end_ros_later(self.node, self.context, self.executor)

    def find_container(self, container: str, deadline: float) -> None:
        """Wait (until ``deadline``) for ``container`` to show up as a container; CliError if it does not."""
        from ipc_component.container_discovery import list_containers

        found = list_containers(self.node, self.executor, deadline=deadline, discovery_until=deadline,
                                container=container, list_components=False)
        if not found:
            raise CliError(f"Unable to find container node '{container}'\n    {self.where_searched()}")

    def where_searched(self) -> str:
        """The discovery settings a search used, for a message that found nothing.

        A container in another ROS domain, or beyond the automatic discovery range, is invisible; naming both
        tells a user who started the container in another shell what to compare.
        """
        def setting(name: str, used: object) -> str:
            return f"{name}={used}" + ("" if os.environ.get(name) else " (not set)")

        searched = [setting("ROS_DOMAIN_ID", self.context.get_domain_id()),
                    setting("ROS_AUTOMATIC_DISCOVERY_RANGE",
                            os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or "SUBNET")]
        if os.environ.get("ROS_STATIC_PEERS"):
            searched.append(f"ROS_STATIC_PEERS={os.environ['ROS_STATIC_PEERS']}")
        return (f"Searched {', '.join(searched)}: a container started with other values is not seen, check "
                "them in both shells.")

    def fleet(self, containers: Sequence[str]) -> Fleet:
        """A :class:`~ipc_component.fleet_link.Fleet` of ``containers`` on this session's node (imported here, as
        rclpy is: the verbs that only read bags load no ROS at all)."""
        from ipc_component.fleet_link import Fleet

        return Fleet(self.node, self.executor, containers)

    def container_client(self, srv_type: Any, container: str, service: str, deadline: float) -> Any:
        """A client of ``<container>/_container/<service>``, found, ready and able to get replies.

        Both clients (this one, then the harmless ListNodes one) are created before anything is waited for,
        so that they are announced in this participant's first discovery exchange with the container
        instead of a second one after it. The order matters: endpoints are announced in creation order over
        one reliable, ordered discovery stream, so once the container answers ListNodes it has also matched
        this client's reply reader.
        """
        from composition_interfaces.srv import ListNodes

        from ipc_component.repeated_call import RepeatedCall

        client = self.node.create_client(srv_type, f"{container}/_container/{service}")
        harmless = RepeatedCall(self.node.create_client(ListNodes, f"{container}/_container/list_nodes"),
                                ListNodes.Request)
        try:
            self.find_container(container, deadline)
            self.ensure_replies(harmless, deadline)
        finally:
            harmless.close()
            self.node.destroy_client(harmless.client)
        while not client.service_is_ready():
            if time.monotonic() >= deadline:
                raise CliError(f"No '{service}' service found for '{container}' container")
            self.executor.spin_once(timeout_sec=0.02)
        return client

    def ensure_replies(self, harmless: Any, deadline: float) -> None:
        """Make sure the container can answer this process before sending a request that must not be lost.

        A service is "ready" once this side has matched it; the container may not have discovered this
        process's reply readers yet, and Fast DDS then drops the reply. A harmless ListNodes call, repeated
        until one is answered (``harmless``, a ipc_component.repeated_call.RepeatedCall), waits out
        that discovery (at most until ``deadline``; then the real call goes ahead and its own timeout applies).
        """
        while harmless.reply is None and time.monotonic() < deadline:
            harmless.step(time.monotonic())
            self.executor.spin_once(timeout_sec=0.02)

    def call(self, client: Any, request: Any, container: str, timeout: float = CALL_TIMEOUT) -> Any:
        """Call a service and wait for the reply, at most ``timeout`` s; CliError text is the reason."""
        future = client.call_async(request)
        deadline = time.monotonic() + timeout
        absent_since: float | None = None
        try:
            while not future.done():
                now = time.monotonic()
                if now >= deadline:
                    raise CliError(f"No reply from '{container}' container within {timeout:g} s")
                self.executor.spin_once(timeout_sec=min(0.1, deadline - now))
                if future.done():
                    break
                if client.service_is_ready():
                    absent_since = None
                elif absent_since is None:
                    absent_since = now
                elif now - absent_since > GONE_GRACE:
                    raise CliError(f"'{container}' container left before replying")
        finally:
            if not future.done():
                future.cancel()
                client.remove_pending_request(future)
        return future.result()
