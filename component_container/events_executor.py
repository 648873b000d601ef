"""``--executor events``: rclpy's C++ EventsExecutor (``rclpy.experimental``), supervised like the other models.

The EventsExecutor has no wait set: the middleware's "new message / request / response / QoS event" callbacks
and a timer thread post events to one queue, and the thread that spins runs them. That saves the wait-set
rebuild per wake-up that costs the other models most of their CPU at high rates. What rclpy 7.1.6 ships (read
in rclpy's ``src/rclpy/events_executor/*.cpp``, the pybind11 version with ``EventsQueue``; each point below was
also reproduced against the installed wheel) needs these changes to run components under supervision:

* **Where callbacks run.** The C++ calls the user callbacks itself (``HandleSubscriptionReady`` calls
  ``subscription.callback``, ``HandleTimerReady`` ``timer.callback``, ``HandleServiceReady`` ``service.callback``
  then ``service.send_response``, ``HandleWaitableReady`` ``waitable.take_data`` then ``waitable.execute``; a
  client only completes the request's future). ``Executor._make_handler`` is never used. These attributes are
  read at every event, so supervision replaces them on the entity objects (:class:`SupervisedEventsExecutor`):
  each call goes through the node's CallbackGate and hands what it raises to ``on_error(node, exc)``. The C++
  learns a node's entities only from the node's ``subscriptions``/``timers``/``clients``/``services``/
  ``waitables``/``guards`` properties; it is given a :class:`NodeView` instead of the node, whose properties
  wrap every entity before the C++ can see it, so no entity, however late it is created, runs unsupervised.
* **Timer info.** rclpy 9 (Kilted) calls a timer callback that has any parameter with a ``TimerInfo`` (rclpy 7
  never passes one): the wrapper keeps the original's signature (``functools.wraps``) and forwards it.
* **Message info.** A subscription callback that takes ``(message, info)`` is called with ONE argument, the
  tuple; rclpy then fails with ``SystemError: null argument to internal routine``, out of ``spin()``. The
  wrapper unpacks it (and would accept two arguments from a fixed rclpy).
* **Coroutine callbacks** of subscriptions and services are not awaited by the C++ (a service would send the
  coroutine object as its response); the wrapper runs them as tasks and a service answers when its task is done.
* **No guard conditions.** The entity update raises ``RuntimeError("Guard conditions not supported")`` out of
  ``spin()`` when any node has one, or a waitable containing one. The intra-process path therefore wakes its
  subscribers with a task posted to the executor (:class:`TaskWakeup`), not a guard condition; a component that
  has guard conditions is refused at load, and one that creates one later fails (unload/exit policy), its guard
  condition never being shown to the C++. Such components need ``--executor single|multi|isolated``.
* **add_node/remove_node are not thread-safe while spinning.** They change a Python set that the entity update
  iterates while it calls the nodes' properties (Python code, which lets other threads run): a load or unload
  on the service thread could end ``spin()`` with "Set changed size during iteration". Here both are posted to
  the executor's own thread. A new component therefore starts when that thread is free, as with ``single``.
* **Entities destroyed on another thread.** The update registers entities from a snapshot; one whose destroy
  was requested in between (an unload destroying its node on the unload thread) raises InvalidHandle inside the
  update (rclpy refuses new users of a handle once its destroy is requested, even while it is in use), which
  leaves the executor's entity sets half-updated ("Attempt to replace existing callback" from then on), so it
  cannot be retried like the wait-set race of :class:`SpinThread`. A NodeView *pins* every entity it reports
  until the update is over: the entity's ``destroy()`` (which ``Node.destroy_*`` call) is postponed to then
  (:class:`DestroyPins`); and it shows a node that is being removed as empty.
* **spin() without a timeout** runs nothing and keeps a core busy (rclpy 7.1.6); :class:`EventsSpinThread`
  spins in slices of ``SPIN_SLICE`` seconds.

What stays unsafe, hence opt-in (docs/container.md): errors outside user callbacks are not attributable here.
A message the C++ fails to take or deserialize, or an rcl error in its timer or entity bookkeeping, ends the
executor thread and so the container (status 1, like any dead container thread), where the wait-set models
blame the component. Tasks (a component's ``create_task`` coroutines, futures' done callbacks such as a client's
response callback) are not attributed in any model; an exception in one ends the thread in every model. The
interpreter exiting while a thread still spins an EventsExecutor aborts the process (``terminate called
without an active exception``): the executor is always shut down first, and ``__main__`` leaves with
``os._exit`` if a component callback never returns. The C++ timer manager scans all timers of a clock on
every tick and prints a warning from 8 timers per clock on.
"""
from __future__ import annotations

import contextlib
import faulthandler
import functools
import inspect
import threading
import weakref
from typing import Any, Callable, Iterable

from rclpy.callback_groups import CallbackGroup
from rclpy.context import Context
from rclpy.exceptions import InvalidHandle
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.subscription import Subscription
from rclpy.task import Future, Task

from component_container.callback_supervision import (
    COMPONENT_ERRORS,
    CallbackGate,
    ErrorHandler,
    SpinThread,
    reraise,
)

#: Seconds per ``spin_until_future_complete`` call of the events thread (a stop ends a slice at once).
SPIN_SLICE = 1.0
#: What a supervised call returns when it did not run (node being removed) or raised.
SKIPPED = object()


class UnsupportedByEventsExecutor(RuntimeError):
    """The component uses something rclpy's EventsExecutor cannot run (guard conditions)."""


def unsupported_entities(node: Node) -> str:
    """Why ``node`` cannot run on the EventsExecutor, or '' if it can."""
    if next(iter(node.guards), None) is not None:
        return "guard conditions"
    if any(w.get_num_entities().num_guard_conditions for w in node.waitables):
        return "a waitable with guard conditions"
    return ""


def unsupported_message(node: Node, what: str) -> str:
    return (f"{node.get_fully_qualified_name()} has {what}, which rclpy's EventsExecutor cannot run; "
            "load it into a container with --executor single, multi or isolated")


class SupervisedEventsExecutor(_rclpy.EventsExecutor):
    """rclpy's EventsExecutor with every component callback supervised, and node changes made thread-safe.

    ``add_node``/``remove_node`` may be called from any thread; they take effect on the spinning thread.
    """

    def __init__(self, context: Context, on_error: ErrorHandler | None = None) -> None:
        super().__init__(context)
        faulthandler.enable()  # as rclpy's own factory does: a crash in the C++ still shows the Python stacks
        context.on_shutdown(self.wake)  # ditto: a context shut down elsewhere stops the spinning
        self.gate = CallbackGate()
        self._on_error = on_error or reraise
        self._lock = threading.Lock()
        self._views: dict[Node, NodeView] = {}
        self._unarmed: dict[Node, list[TaskWakeup]] = {}  # wake-ups of nodes not added yet
        self._supervised: weakref.WeakSet[Any] = weakref.WeakSet()
        self._pins = DestroyPins()

    # --- nodes -----------------------------------------------------------------------------------------
    def add_node(self, node: Node) -> bool:
        """Start running ``node`` (once the spinning thread gets to it); False if it is already added.

        Raises UnsupportedByEventsExecutor for a node with guard conditions.
        """
        with self._lock:
            view = self._views.get(node)
            if view is not None:
                return False  # also rclpy's Node.executor setter, re-entering from _adopt
            what = unsupported_entities(node)
            if what:
                raise UnsupportedByEventsExecutor(unsupported_message(node, what))
            view = self._views[node] = NodeView(node, self)
        self.create_task(self._adopt, view)
        return True

    def remove_node(self, node: Node) -> None:
        """Stop running ``node``: from now on the C++ sees none of its entities; the node itself leaves the
        executor on the spinning thread. The node may be destroyed as soon as this returns."""
        with self._lock:
            view = self._views.pop(node, None)
            self._unarmed.pop(node, None)
        if view is not None:
            view.released = True
            self.create_task(super().remove_node, view)

    def _adopt(self, view: NodeView) -> None:
        """On the spinning thread: hand the node's view to the C++ and arm its intra-process wake-ups."""
        if view.released:
            return  # unloaded before the events thread got to it
        try:
            super().add_node(view)
        except COMPONENT_ERRORS as exc:
            self._on_error(view.node, exc)
            return
        with self._lock:
            view.adopted = True
            waiting = self._unarmed.pop(view.node, [])
        for wakeup in waiting:
            wakeup.arm()

    def make_wakeup(self, node: Node, callback: Callable[[], None], group: CallbackGroup | None) -> TaskWakeup:
        """The intra-process wake-up of ``node``: a supervised task; armed once the node runs here."""
        wakeup = TaskWakeup(self, node, callback)
        with self._lock:
            view = self._views.get(node)
            armed = view is not None and view.adopted
            if not armed:
                self._unarmed.setdefault(node, []).append(wakeup)
        if armed:
            wakeup.arm()
        return wakeup

    def forget_wakeup(self, wakeup: TaskWakeup) -> None:
        with self._lock:
            waiting = self._unarmed.get(wakeup.node)
            if waiting is not None and wakeup in waiting:
                waiting.remove(wakeup)
                if not waiting:
                    del self._unarmed[wakeup.node]

    # --- what the C++ sees of a node ---------------------------------------------------------------------
    def present(self, view: NodeView, entities: Iterable[Any], supervise: Callable[[Node, Any], None],
                alive: Callable[[Any], bool]) -> list[Any]:
        """``entities`` of ``view``'s node as the C++ may register them: supervised, and pinned until the
        entity update that asked has finished (a task posted now runs after it)."""
        if view.released:
            return []
        shown = []
        for entity in entities:
            if entity not in self._supervised:
                supervise(view.node, entity)
                self._pins.guard(entity)
                self._supervised.add(entity)
            if self._pins.pin(entity, alive):
                shown.append(entity)
        if shown:
            self.create_task(self._pins.unpin_all, shown)
        return shown

    def refuse(self, view: NodeView, what: str) -> None:
        """The node acquired something the C++ cannot run: it is hidden, and the component fails (once)."""
        if not view.refused:
            view.refused = True
            self._on_error(view.node, UnsupportedByEventsExecutor(unsupported_message(view.node, what)))

    # --- supervision --------------------------------------------------------------------------------------
    def call(self, node: Node, callback: Callable[..., Any], *args: Any) -> Any:
        """Run one callback of ``node`` under its gate; SKIPPED if it did not run or raised. A coroutine it
        returns runs as a supervised task, which is returned."""
        if not self.gate.enter(node):
            return SKIPPED
        try:
            result = callback(*args)
        except COMPONENT_ERRORS as exc:
            self._on_error(node, exc)
            return SKIPPED
        finally:
            self.gate.leave(node)
        if inspect.iscoroutine(result):
            return self.create_task(self.awaited(node, result))
        return result

    async def awaited(self, node: Node, coroutine: Any) -> Any:
        """Await a coroutine of ``node`` under its gate; SKIPPED if it did not run or raised."""
        if not self.gate.enter(node):
            coroutine.close()
            return SKIPPED
        try:
            return await coroutine
        except COMPONENT_ERRORS as exc:
            self._on_error(node, exc)
            return SKIPPED
        finally:
            self.gate.leave(node)

    def supervise_subscription(self, node: Node, subscription: Subscription) -> None:
        original = subscription.callback
        # The C++ reads the same attribute to choose how to call; functools.wraps keeps the signature (and so
        # the setter's classification) of the original.
        with_info = subscription._callback_type == Subscription.CallbackType.WithMessageInfo

        @functools.wraps(original)
        def supervised(*args: Any) -> None:
            if with_info and len(args) == 1:
                args = args[0]  # rclpy 7.1.6 passes (message, info) as one tuple
            self.call(node, original, *args)

        subscription.callback = supervised

    def supervise_timer(self, node: Node, timer: Any) -> None:
        original = timer.callback

        # rclpy 9's C++ calls a timer callback that has any parameter with a TimerInfo (rclpy 7 never passes
        # one): functools.wraps shows it the original's signature, and the wrapper forwards what it is given.
        @functools.wraps(original)
        def supervised(*args: Any) -> None:
            self.call(node, original, *args)  # a coroutine becomes a supervised task: the C++ gets None, not it

        timer.callback = supervised

    def supervise_service(self, node: Node, service: Any) -> None:
        original, send = service.callback, service.send_response

        def supervised_send(response: Any, header: Any) -> None:
            if isinstance(response, Task):  # a coroutine callback: answer when it is done
                response.add_done_callback(lambda task: supervised_send(task.result(), header))
            elif response is not SKIPPED:  # a callback that raised sends nothing, as in the wait-set models
                self.call(node, send, response, header)

        service.callback = functools.wraps(original)(lambda request, response: self.call(
            node, original, request, response))
        service.send_response = supervised_send

    def supervise_waitable(self, node: Node, waitable: Any) -> None:
        take, execute = waitable.take_data, waitable.execute

        async def supervised_execute(data: Any) -> None:
            if data is not SKIPPED:
                await self.awaited(node, execute(data))

        waitable.take_data = lambda: self.call(node, take)
        waitable.execute = supervised_execute


def _supervise_nothing(_node: Node, _entity: Any) -> None:
    """Clients run no component code in the C++: it only completes the request's future."""


def _handle_alive(entity: Any) -> bool:
    try:
        with entity.handle:
            return True
    except InvalidHandle:
        return False


def _waitable_alive(waitable: Any) -> bool:
    try:
        waitable.__enter__()  # the handles of a waitable that has them (QoS events, actions)
    except InvalidHandle:
        return False
    waitable.__exit__(None, None, None)
    return True


class DestroyPins:
    """Entities the C++ may be registering right now; a ``destroy()`` of one of them waits until it is not."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pinned: dict[Any, int] = {}
        self._postponed: dict[Any, Callable[[], None]] = {}

    def guard(self, entity: Any) -> None:
        """Route ``entity.destroy()`` (what ``Node.destroy_*`` call) through the pins."""
        destroy = entity.destroy

        def pinned_destroy() -> None:
            with self._lock:
                if entity in self._pinned:
                    self._postponed[entity] = destroy
                    return
            destroy()

        entity.destroy = pinned_destroy

    def pin(self, entity: Any, alive: Callable[[Any], bool]) -> bool:
        """Pin ``entity`` if it is still alive (False: its destroy was requested before it was guarded)."""
        with self._lock:
            self._pinned[entity] = self._pinned.get(entity, 0) + 1
        if alive(entity):
            return True
        self.unpin_all([entity])
        return False

    def unpin_all(self, entities: list[Any]) -> None:
        for entity in entities:
            with self._lock:
                self._pinned[entity] -= 1
                if self._pinned[entity]:
                    continue
                del self._pinned[entity]
                destroy = self._postponed.pop(entity, None)
            if destroy is not None:
                with contextlib.suppress(InvalidHandle):  # Node.destroy_* would have ignored it too
                    destroy()


class NodeView:
    """What the C++ executor gets instead of a component's node: its entities, supervised and pinned while the
    C++ registers them (see the module docstring), none once the node is being removed, and none of what it
    cannot run. Everything else is the node's."""

    def __init__(self, node: Node, executor: SupervisedEventsExecutor) -> None:
        self.node = node
        self._executor = weakref.ref(executor)  # the C++ holds the views: no cycle through it
        self.released = False
        self.adopted = False
        self.refused = False

    def _present(self, entities: Iterable[Any], supervise: Callable[[Node, Any], None],
                 alive: Callable[[Any], bool] = _handle_alive) -> list[Any]:
        executor = self._executor()
        return [] if executor is None else executor.present(self, entities, supervise, alive)

    @property
    def subscriptions(self) -> list[Any]:
        executor = self._executor()
        return self._present(self.node.subscriptions, executor.supervise_subscription) if executor else []

    @property
    def timers(self) -> list[Any]:
        executor = self._executor()
        return self._present(self.node.timers, executor.supervise_timer) if executor else []

    @property
    def clients(self) -> list[Any]:
        return self._present(self.node.clients, _supervise_nothing)

    @property
    def services(self) -> list[Any]:
        executor = self._executor()
        return self._present(self.node.services, executor.supervise_service) if executor else []

    @property
    def waitables(self) -> list[Any]:
        executor = self._executor()
        if executor is None:
            return []
        runnable = []
        for waitable in self.node.waitables:
            if waitable.get_num_entities().num_guard_conditions:
                executor.refuse(self, "a waitable with guard conditions")
            else:
                runnable.append(waitable)
        return self._present(runnable, executor.supervise_waitable, _waitable_alive)

    @property
    def guards(self) -> list[Any]:
        executor = self._executor()
        if executor is not None and next(iter(self.node.guards), None) is not None:
            executor.refuse(self, "guard conditions")
        return []

    @property
    def executor(self) -> Any:
        return self.node.executor

    @executor.setter
    def executor(self, executor: Any) -> None:
        self.node.executor = executor  # Node._wake_executor: entities created later reach the C++

    def __getattr__(self, name: str) -> Any:
        return getattr(self.node, name)  # get_logger, for the C++'s own error reports


class TaskWakeup:
    """An intra-process wake-up on the EventsExecutor: a supervised task posted to its queue, at most one
    pending. Triggers before the node runs on the executor are held until it does (:meth:`arm`)."""

    def __init__(self, executor: SupervisedEventsExecutor, node: Node, callback: Callable[[], None]) -> None:
        self._executor = executor
        self.node = node
        self._callback = callback
        self._lock = threading.Lock()
        self._armed = False
        self._pending = False
        self._destroyed = False

    def trigger(self) -> None:
        with self._lock:
            if self._pending or self._destroyed:
                return
            self._pending = True
            if not self._armed:
                return
        self._executor.create_task(self._run)

    def arm(self) -> None:
        with self._lock:
            self._armed = True
            if not self._pending or self._destroyed:
                return
        self._executor.create_task(self._run)

    def _run(self) -> None:
        with self._lock:
            self._pending = False
            if self._destroyed:
                return
        self._executor.call(self.node, self._callback)

    def destroy(self) -> None:
        with self._lock:
            self._destroyed = True
        self._executor.forget_wakeup(self)


class EventsSpinThread(SpinThread):
    """Spins a SupervisedEventsExecutor in slices (its ``spin()`` without a timeout does not work in 7.1.6)."""

    def run_executor(self) -> None:
        while self.executor.context.ok() and not self._stopping:
            # A new future for each slice: each call adds a done callback to the future it is given.
            self.executor.spin_until_future_complete(Future(), timeout_sec=SPIN_SLICE)

    def interrupt(self) -> None:
        """End the current slice at once: ``shutdown(0)`` stops the C++ event loop without waiting for it (with
        a timeout it would wait holding the GIL, which a callback still running needs to return)."""
        self.executor.shutdown(timeout_sec=0.0)
