"""A wait set built once and kept while an executor's entities stay the same, as rclcpp's executors do.

rclpy's ``Executor._wait_for_ready_callbacks`` rebuilds its wait set in Python at every wake-up: it walks every
node's entities, filters them, enters every handle's context manager, allocates an rcl wait set, and after the
wait compares every entity's handle pointer with the ready lists. With a few dozen entities that is most of an
executor thread that wakes a few hundred times a second. :class:`WaitSetCache` does that walk once and keeps the
result (handles entered, so that nothing in it can be destroyed under ``rcl_wait``) until the executor's
*generation* changes: a node was added or removed, or a node created or destroyed an entity (rclpy's Node then
calls ``executor.wake()``). Between those, a wake-up only clears and refills the same rcl wait set and looks up
the ready pointers.

:func:`wait_for_ready_callbacks` is the generator the supervised executors use in place of rclpy's. It yields
the same ``(handler, entity, node)`` triples, in rclpy's order, and differs only in what it remembers:

* While a handler is still in flight (a multi-threaded worker runs it, or a coroutine awaits), entities that
  cannot execute are left out of the wait, as rclpy does; otherwise every cached entity is waited on.
* Before each yield it checks that the generation has not moved; if it has, the cache is rebuilt first and an
  entity its node destroyed (or of a node removed) is not handed out. rclpy instead hands out the ready
  entities of the node snapshot it waited on, which is what :class:`~component_container.callback_supervision.
  SpinThread`'s InvalidHandle tolerance is for.
* It does not end after a round with work: the cache lives as long as the generator, which rclpy's
  ``wait_for_ready_callbacks`` keeps while it is called with the same arguments.
"""
from __future__ import annotations

from contextlib import ExitStack
from typing import TYPE_CHECKING, Any, Callable, Generator, Iterable

from rclpy.event_handler import EventHandler
from rclpy.exceptions import InvalidHandle
from rclpy.executors import ConditionReachedException, ExternalShutdownException, ShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.waitable import NumberOfEntities

if TYPE_CHECKING:
    from rclpy.executors import Executor

#: The entity kinds rclpy waits on by handle, in the order it hands their ready callbacks out.
HANDLE_KINDS = ("timer", "subscription", "guard_condition", "client", "service")
_NODE_LISTS = {"timer": "timers", "subscription": "subscriptions", "guard_condition": "guards",
               "client": "clients", "service": "services"}
_ADD = {"timer": "add_timer", "subscription": "add_subscription", "guard_condition": "add_guard_condition",
        "client": "add_client", "service": "add_service"}

Ready = tuple[Any, Node, str]


class WaitSetCache:
    """The entities of ``nodes`` at ``generation``, their handles entered, and one rcl wait set sized for them."""

    def __init__(self, executor: Executor, nodes: Iterable[Node], generation: int) -> None:
        self.generation = generation
        self._stack = ExitStack()
        #: kind -> [(entity, node, handle)] of every entity that could be entered (not being destroyed)
        self.entries: dict[str, list[tuple[Any, Node, Any]]] = {kind: [] for kind in HANDLE_KINDS}
        #: rclpy's QoS event handlers (a few per publisher and subscription), waited on by their event handle
        self.events: list[tuple[EventHandler, Node, Any]] = []
        self.waitables: list[tuple[Any, Node]] = []
        self.by_pointer: dict[int, tuple[Any, Node]] = {}
        self.members: set[int] = set()
        try:
            self._gather(nodes)
            # The executor's own guard conditions: node changes, task completions, shutdown, SIGINT.
            self.own_guards = [self._enter(gc.handle) for gc in (executor._guard, executor._sigint_gc)]
            self._stack.enter_context(executor.context.handle)
            count = NumberOfEntities(len(self.entries["subscription"]),
                                     len(self.entries["guard_condition"]) + len(self.own_guards),
                                     len(self.entries["timer"]), len(self.entries["client"]),
                                     len(self.entries["service"]))
            count.num_events += len(self.events)
            for waitable, _node in self.waitables:
                count += waitable.get_num_entities()
            self.wait_set = _rclpy.WaitSet(count.num_subscriptions, count.num_guard_conditions, count.num_timers,
                                           count.num_clients, count.num_services, count.num_events,
                                           executor.context.handle)
        except BaseException:
            self._stack.close()
            raise

    def _enter(self, handle: Any) -> Any:
        self._stack.enter_context(handle)
        return handle

    def _gather(self, nodes: Iterable[Node]) -> None:
        for node in nodes:
            for kind in HANDLE_KINDS:
                for entity in getattr(node, _NODE_LISTS[kind]):
                    try:
                        handle = self._enter(entity.handle)
                    except InvalidHandle:
                        continue  # destroyed since the node listed it; the wake-up that follows rebuilds
                    self.entries[kind].append((entity, node, handle))
                    self.by_pointer[handle.pointer] = (entity, node)
                    self.members.add(id(entity))
            for waitable in node.waitables:
                try:
                    self._stack.enter_context(waitable)
                except InvalidHandle:
                    continue
                if type(waitable) is EventHandler:  # noqa: E721 - a subclass may wait differently
                    # Its event handle, entered with it; added directly rather than by its add_to_wait_set.
                    self.events.append((waitable, node, waitable._EventHandler__event))
                else:
                    self.waitables.append((waitable, node))
                self.members.add(id(waitable))

    def close(self) -> None:
        """Release the handles: entities destroyed meanwhile are freed now."""
        self._stack.close()

    def wait(self, can_execute: Callable[[Any], bool] | None) -> list[Ready]:
        """Wait (forever) on the cached entities that ``can_execute`` admits (all if None); return the ready
        waitables, timers, subscriptions, clients and services. A node guard condition that fires is marked
        ``_executor_triggered`` (see :meth:`triggered_guards`); one that fired earlier and was not handled yet is
        triggered again first, as rclpy does."""
        admitted = (lambda _entity: True) if can_execute is None else can_execute
        wait_set = self.wait_set
        wait_set.clear_entities()
        for kind in HANDLE_KINDS:
            add = getattr(wait_set, _ADD[kind])
            for entity, _node, handle in self.entries[kind]:
                if admitted(entity):
                    add(handle)
        for gc, _node, _handle in self.entries["guard_condition"]:
            if gc._executor_triggered and admitted(gc):
                gc.trigger()
        for handle in self.own_guards:
            wait_set.add_guard_condition(handle)
        events = [(w, node, wait_set.add_event(handle)) for w, node, handle in self.events if admitted(w)]
        waitables = [(w, node) for w, node in self.waitables if admitted(w)]
        for waitable, _node in waitables:
            waitable.add_to_wait_set(wait_set)

        wait_set.wait(-1)

        ready: list[Ready] = []
        for waitable, node, index in events:  # rclpy's EventHandler.is_ready, without its Python call
            if waitable._ready_to_take_data or wait_set.is_ready("event", index):
                waitable._ready_to_take_data = True
                ready.append((waitable, node, "waitable"))
        ready += [(w, node, "waitable") for w, node in waitables if w.is_ready(wait_set)]
        for kind in HANDLE_KINDS:
            for pointer in wait_set.get_ready_entities(kind):
                found = self.by_pointer.get(pointer)
                if found is None:
                    continue  # the executor's own guard conditions
                if kind == "guard_condition":
                    found[0]._executor_triggered = True  # auto-taken by the wait: remember until handled
                else:
                    ready.append((found[0], found[1], kind))
        return ready

    def triggered_guards(self) -> list[Ready]:
        """Node guard conditions that fired and were not handled yet."""
        return [(gc, node, "guard_condition") for gc, node, _handle in self.entries["guard_condition"]
                if gc._executor_triggered]


def _order(ready: list[Ready], guards: list[Ready]) -> list[Ready]:
    """rclpy's order: waitables, then timers, subscriptions, guard conditions, clients, services."""
    rank = {"waitable": 0, "timer": 1, "subscription": 2, "guard_condition": 3, "client": 4, "service": 5}
    return sorted(ready + guards, key=lambda item: rank[item[2]])


def wait_for_ready_callbacks(executor: Executor, generation: Callable[[], int],
                             condition: Callable[[], bool]) -> Generator[tuple[Any, Any, Node], None, None]:
    """rclpy's ``_wait_for_ready_callbacks`` for all of ``executor``'s nodes and no timeout, over a
    :class:`WaitSetCache` that is rebuilt when ``generation()`` changes."""
    takes = {"waitable": executor._take_waitable, "timer": executor._take_timer,
             "subscription": executor._take_subscription, "guard_condition": executor._take_guard_condition,
             "client": executor._take_client, "service": executor._take_service}
    cache: WaitSetCache | None = None

    def current() -> WaitSetCache:
        nonlocal cache
        now = generation()
        if executor._guard is None:
            raise ShutdownException()  # shut down on another thread since the loop checked
        if cache is None or cache.generation != now:
            stale, cache = cache, WaitSetCache(executor, executor.get_nodes(), now)
            if stale is not None:
                stale.close()
        return cache

    try:
        while not executor._is_shutdown and not condition():
            in_flight = yield from _pending_tasks(executor)
            ready = current().wait(executor.can_execute if in_flight else None)
            if executor._is_shutdown:
                raise ShutdownException()
            if not executor.context.ok():
                raise ExternalShutdownException()
            for entity, node, kind in _order(ready, cache.triggered_guards()):
                if id(entity) not in current().members:
                    continue  # destroyed, or its node removed, since the wait
                if kind == "timer" and not entity.handle.is_timer_ready():
                    continue  # rcl reports a cancelled timer ready
                if entity.callback_group.can_execute(entity):
                    yield executor._make_handler(entity, node, takes[kind]), entity, node
    finally:
        if cache is not None:
            cache.close()
    if executor._is_shutdown:
        raise ShutdownException()
    raise ConditionReachedException()


def _pending_tasks(executor: Executor) -> Generator[tuple[Any, Any, Node], None, bool]:
    """Yield the tasks in progress before waiting for new work, as rclpy does, and drop the finished ones;
    return whether any task is still in flight (its entity or callback group may be busy)."""
    with executor._tasks_lock:
        tasks = list(executor._tasks)
    if not tasks:
        return False
    nodes = set(executor.get_nodes())
    for task, entity, node in reversed(tasks):
        if not task.executing() and not task.done() and (node is None or node in nodes):
            yield task, entity, node
    with executor._tasks_lock:
        executor._tasks = [t for t in executor._tasks if not t[0].done() and not t[0].cancelled()]
        return bool(executor._tasks)
