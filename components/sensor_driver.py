"""Shared machinery of the simulated sensor drivers (camera, lidar, IMU).

:class:`SensorDriver` is a :class:`~component_container.component_node.ComponentNode` that

* declares the parameters every driver has: ``qos``, ``frame_id``, ``topic`` and a rate parameter (``rate`` by
  default, ``fps`` for the camera), validates them and raises :class:`ValueError` naming the parameter and its
  allowed range when a value is wrong (the component container reports constructor exceptions to the user);
* bounds what one driver may ask of the container: a frame of at most :data:`MAX_FRAME_BYTES`, a rate in
  :data:`RATE`, and at most :data:`MAX_BYTES_PER_SECOND` (the load service answers anyone on the domain);
* lets the rate and ``frame_id`` be changed at run time (``ros2 param set``), validated with the same bounds: a
  refused value answers ``successful=false`` with the reason. The others are read-only and their descriptions
  say why;
* keeps a sequence counter per publisher (:meth:`SensorDriver.next_sequence`);
* runs a drift-free rate loop that calls the subclass's :meth:`SensorDriver.publish_frame` once per frame.

Rate loop
---------
Frame ``k`` (k = 0, 1, 2 ...) is due at ``t0 + k / rate`` on the steady clock, where ``t0``, set at the first
timer tick, lies half a timer period before a tick of the grid below (so ticks that are early or late by less
than half a period stay in phase). On every tick the driver publishes every frame that is due, i.e. until
``published_count + skipped_count == floor((now - t0) * rate) + 1``. Late ticks are therefore caught up and the
average rate is exact, without drift, however irregular the ticks are. The timer period is ``1 / rate`` but
never shorter than :attr:`SensorDriver.MIN_TIMER_PERIOD` (2 ms): above 500 Hz each tick publishes several
messages instead of asking the executor for one callback per message.

Shared tick grid
----------------
Ticks fall on multiples of the timer period on the steady clock: every driver of one period in the process
ticks at the same instants, so one executor wake-up serves them all. Each wake-up is expensive on virtual
CPUs (a thread that sleeps and wakes finds its caches cold: publishing one Imu right after a wake-up costs
more than twice what it costs in a tight loop), and ten IMUs at 1 kHz on their own phases would wake the
executor thousands of times a second: on one grid their drivers use about a quarter less CPU.
The first tick of a schedule publishes its first frame and moves the timer onto the grid (the next tick
comes half a period to one and a half periods later); frames are then due half a period before each tick.
All drivers share one steady :class:`~rclpy.clock.Clock`, because rclpy's EventsExecutor manages timers per
clock object, with a thread of its own for each, and dispatches the ready timers of one clock in one pass.

A tick publishes at most :attr:`SensorDriver.max_burst` frames (about 0.1 s worth, at least 3). When more are
due (the process was stalled, or producing a frame takes longer than its period) the oldest due frames are
dropped at the source and counted in :attr:`SensorDriver.skipped_count` instead of building an ever-growing
backlog. Skipped frames consume no sequence number: sequence numbers count published messages, so a gap seen
by a subscriber always means a message lost after publish().

A rate change restarts the schedule at the new rate from the moment of the change: the timer is reset to the
new period and the next frame is due one new period later, so a change never publishes a burst of frames that
the old or the new schedule would call overdue. The published and skipped counts go on.

``header.stamp`` of each message is the capture time: the node clock (``use_sim_time`` aware) read just before
the frame is built, so frames published in one catch-up burst carry their real, slightly later, build times.

Ownership
---------
Once ``publish()`` returned, the message and its buffers belong to the subscribers (the container may hand the
very same object to intra-process subscriptions). Drivers therefore build a fresh message object for every
publish and never touch it afterwards; the precomputed pools they copy from are immutable (``bytes``) or never
written. A frame's big data buffer is taken back only when no one holds it any more
(:class:`~components.frame_buffers.FrameBuffers`).
"""
from __future__ import annotations

import functools
import math
import time
from typing import Any, Callable, Iterable, Optional

from builtin_interfaces.msg import Time
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

from component_container.component_node import ComponentNode
from component_container.health import DROPPED, Health
from components.bounds import Bounds

#: Names accepted by the ``qos`` parameter.
QOS_CHOICES = ("reliable", "sensor_data")
#: Rates a driver may publish at, in Hz: above 2 kHz the executor does little else.
RATE = Bounds(0.01, 2000.0, "Hz")
#: Largest frame one driver may build, in bytes (a 4K rgba8 image is 33 MB).
MAX_FRAME_BYTES = 64 << 20
#: Most bytes per second one driver may publish (frame size times rate).
MAX_BYTES_PER_SECOND = 1_000_000_000
#: Why the parameters that shape the publishers cannot change at run time.
FIXED_PUBLISHERS = "the publishers are created with it at load; reload the component to change it"
#: Why the frame-geometry parameters cannot change at run time.
FIXED_GEOMETRY = "the frame geometry sizes the buffers precomputed at load; reload the component to change it"

#: Checks one parameter value and returns it in the type the driver uses; ValueError names the parameter.
Validator = Callable[[Any], Any]


def qos_profile_for(name: str) -> QoSProfile:
    """The QoS profile for a ``qos`` parameter value: ``'reliable'`` or ``'sensor_data'``."""
    if name == "reliable":
        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=10,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )
    if name == "sensor_data":
        return qos_profile_sensor_data
    raise ValueError(f"parameter 'qos': unknown QoS {name!r}; expected one of {', '.join(QOS_CHOICES)}")


def stamp_from_ns(nanoseconds: int) -> Time:
    """A fresh ``builtin_interfaces/Time`` for a time in nanoseconds."""
    sec, nanosec = divmod(nanoseconds, 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


#: The clock of every driver's rate-loop timer (see "Shared tick grid" in the module docstring).
STEADY_CLOCK = Clock(clock_type=ClockType.STEADY_TIME)


class SensorDriver(ComponentNode):
    """Base class of the simulated sensor drivers.

    Subclasses set the class attributes below, declare their own parameters and create their publishers in
    :meth:`configure`, and build and publish one frame in :meth:`publish_frame`.
    """

    #: Default of the ``topic`` parameter.
    DEFAULT_TOPIC = "~/data"
    #: Default of the ``frame_id`` parameter.
    DEFAULT_FRAME_ID = "sensor"
    #: Name of the rate parameter (``'fps'`` for cameras) and its default in Hz.
    RATE_PARAMETER = "rate"
    DEFAULT_RATE = 10.0
    #: Shortest timer period in seconds; faster rates publish several messages per tick.
    MIN_TIMER_PERIOD = 0.002
    #: How much backlog, in seconds of frames, one tick may catch up before older frames are skipped.
    MAX_CATCH_UP = 0.1
    #: Seconds between two "cannot keep up" warnings. Throttled here, not with rclpy's throttle_duration_sec:
    #: that one inspects the caller's source file on every call, and an overloaded driver skips on most ticks.
    SKIP_WARNING_INTERVAL = 5.0

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._published_count = 0
        self._skipped_count = 0
        self._skip_warned_ns: int | None = None
        self._skipped_unreported = 0
        self._sequences: dict[int, int] = {}
        self._timer = None
        self._dynamic: dict[str, tuple[Validator, Callable[[Any], None]]] = {}
        #: Bytes of one frame; the subclass's configure() sets it (until then the rate is checked alone).
        self.frame_bytes = 0
        try:
            qos = self.declare_choice_parameter(
                "qos", "reliable", QOS_CHOICES,
                "'reliable' (reliable, keep last 10, volatile) or 'sensor_data' (best effort, keep last 5)",
                fixed=FIXED_PUBLISHERS)
            self.qos_name: str = qos
            self.qos_profile: QoSProfile = qos_profile_for(qos)
            self.frame_id: str = self.declare_string_parameter(
                "frame_id", self.DEFAULT_FRAME_ID, "header.frame_id of the published messages", allow_empty=False,
                on_change=functools.partial(setattr, self, "frame_id"))
            self.topic: str = self.declare_topic_parameter("topic", self.DEFAULT_TOPIC, "topic to publish on")
            self.rate: float = self._declare(
                self.RATE_PARAMETER, self.DEFAULT_RATE, f"publishing rate in Hz, in {RATE} and at most "
                f"{MAX_BYTES_PER_SECOND / 1e6:g} MB/s of frames", self._checked_rate, on_change=self._change_rate)
            self.configure()
            self._checked_rate(self.rate)  # now that the frame size is known
            self.add_on_set_parameters_callback(self._validate_changes)
            self.add_post_set_parameters_callback(self._apply_changes)
            self._start_rate_loop()
        except BaseException:
            # The container reports the exception; do not leave a half-built node in the graph.
            self.destroy_node()
            raise

    # ------------------------------------------------------------------ subclass interface
    def configure(self) -> None:
        """Declare the driver's own parameters, create its publishers and precompute its pools."""

    def publish_frame(self) -> None:
        """Build one fresh frame stamped with the capture time and publish it."""
        raise NotImplementedError

    def rate_changed(self) -> None:
        """Adapt precomputed content that depends on the rate (called on the executor after a change)."""

    # ------------------------------------------------------------------ public state
    @property
    def published_count(self) -> int:
        """Frames published so far (for the camera: images; camera_info messages are not counted)."""
        return self._published_count

    @property
    def skipped_count(self) -> int:
        """Frames dropped at the source because a tick had more than :attr:`max_burst` frames to catch up."""
        return self._skipped_count

    @property
    def max_burst(self) -> int:
        """Most frames one timer tick publishes."""
        return self._max_burst

    @property
    def timer_period(self) -> float:
        """Period of the rate-loop timer in seconds."""
        return self._timer_period

    def health(self) -> Health:
        """For /diagnostics: running, with the frames skipped at the source so far as its drops."""
        return Health(values={DROPPED: str(self._skipped_count)})

    def next_sequence(self, publisher: Any) -> int:
        """Return the next sequence number of ``publisher`` (0, 1, 2 ... per publisher) and advance it."""
        key = id(publisher)
        sequence = self._sequences.get(key, 0)
        self._sequences[key] = sequence + 1
        return sequence

    def capture_ns(self) -> int:
        """The node clock's current time in nanoseconds: a frame's capture time (``use_sim_time`` aware).

        Without sim time the node clock is the system clock, which ``time.time_ns()`` reads directly;
        ``Clock.now()`` builds a ``Time`` object on the way, some thirty times the cost, once per message.
        """
        clock = self.get_clock()
        return clock.now().nanoseconds if clock.ros_time_is_active else time.time_ns()

    # ------------------------------------------------------------------ rate loop
    def _start_rate_loop(self) -> None:
        self._frames_due_done = 0  # published + skipped
        self._schedule()
        # A steady-clock timer: simulated hardware runs on wall time even when the node uses sim time.
        self._timer = self.create_timer(self._timer_period, self._on_tick, clock=STEADY_CLOCK)

    def _schedule(self) -> None:
        """Start the schedule at ``self.rate``: the next tick publishes the first frame of it."""
        self._timer_period = max(1.0 / self.rate, self.MIN_TIMER_PERIOD)
        per_tick = math.ceil(self._timer_period * self.rate)
        self._max_burst = max(3, 2 * per_tick + 1, math.ceil(self.rate * self.MAX_CATCH_UP))
        self._rate_origin_ns: Optional[int] = None
        self._frames_before_origin = self._frames_due_done

    def _change_rate(self, rate: float) -> None:
        """A validated new rate: restart the schedule and the timer from now (see the module docstring)."""
        self.rate = rate
        self._schedule()
        self._timer.timer_period_ns = round(self._timer_period * 1e9)
        self._timer.reset()  # the next tick comes one new period from now, not on the old schedule
        self.rate_changed()
        self.get_logger().info(f"{self.RATE_PARAMETER} changed to {rate:g} Hz")

    def _on_tick(self) -> None:
        now_ns = time.monotonic_ns()
        if self._rate_origin_ns is None:
            self._start_on_grid(now_ns)
        due_total = self._frames_before_origin + int((now_ns - self._rate_origin_ns) * self.rate / 1e9) + 1
        due = due_total - self._frames_due_done
        if due <= 0:
            return
        if due > self._max_burst:
            skipped = due - self._max_burst
            self._skipped_count += skipped
            self._frames_due_done += skipped
            due = self._max_burst
            self._report_skips(skipped, now_ns)
        for _ in range(due):
            self.publish_frame()
            self._published_count += 1
            self._frames_due_done += 1

    def _start_on_grid(self, now_ns: int) -> None:
        """The first tick of a schedule: move the timer onto the shared tick grid (module docstring).

        The next grid instant at least half a period away becomes the next tick; frames are due half a period
        before each tick, so this tick and every later one publishes one period's frames.
        """
        period_ns = round(self._timer_period * 1e9)
        next_tick = -(-now_ns // period_ns) * period_ns
        if next_tick - now_ns < period_ns // 2:
            next_tick += period_ns
        self._rate_origin_ns = next_tick - period_ns - period_ns // 2
        # rcl has no "next call at": a reset starts a period from now, and a new period leaves the next call
        # where it is. So the timer runs one shortened period, up to the grid, and then its own.
        self._timer.timer_period_ns = max(1, next_tick - time.monotonic_ns())
        self._timer.reset()
        self._timer.timer_period_ns = period_ns

    def _report_skips(self, skipped: int, now_ns: int) -> None:
        """Warn about skipped frames at most every SKIP_WARNING_INTERVAL seconds, counting all of them."""
        self._skipped_unreported += skipped
        if self._skip_warned_ns is not None and now_ns - self._skip_warned_ns < self.SKIP_WARNING_INTERVAL * 1e9:
            return
        since = ("" if self._skip_warned_ns is None
                 else f" in the last {(now_ns - self._skip_warned_ns) / 1e9:.1f} s")
        self.get_logger().warning(f"cannot keep up with {self.rate:g} Hz: skipped {self._skipped_unreported} frame(s)"
                               f"{since}, {self._skipped_count} in total")
        self._skip_warned_ns, self._skipped_unreported = now_ns, 0

    # ------------------------------------------------------------------ parameters
    def _declare(self, name: str, default: Any, description: str, validate: Validator, *,
                 fixed: str = "", on_change: Optional[Callable[[Any], None]] = None) -> Any:
        """Declare ``name``, validate its value and return it.

        With ``on_change`` the parameter is dynamic: a change is validated by ``validate`` and then handed to
        ``on_change``. Without it, it is read-only, and ``fixed`` says why in the descriptor.
        """
        if on_change is None:
            description = f"{description} (read-only: {fixed or 'set at load'})"
        else:
            description = f"{description} (can be changed at run time)"
        descriptor = ParameterDescriptor(description=description, read_only=on_change is None, dynamic_typing=True)
        value = validate(self.declare_parameter(name, default, descriptor).value)
        if on_change is not None:
            self._dynamic[name] = (validate, on_change)
        return value

    def _validate_changes(self, parameters: list[Parameter]) -> SetParametersResult:
        """rclpy's on-set callback: refuse a change that the declaring validator refuses, with its reason."""
        try:
            for parameter in parameters:
                if parameter.name in self._dynamic:
                    self._dynamic[parameter.name][0](parameter.value)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_changes(self, parameters: list[Parameter]) -> None:
        """rclpy's post-set callback: every change is valid and stored; the driver now uses it."""
        for parameter in parameters:
            if parameter.name in self._dynamic:
                validate, on_change = self._dynamic[parameter.name]
                on_change(validate(parameter.value))

    def _checked_rate(self, value: Any) -> float:
        """The rate parameter: in :data:`RATE`, and frames of ``frame_bytes`` at most MAX_BYTES_PER_SECOND."""
        RATE.check(f"'{self.RATE_PARAMETER}'", value)
        rate = float(value)
        if self.frame_bytes * rate > MAX_BYTES_PER_SECOND:
            highest = Bounds(RATE.minimum, MAX_BYTES_PER_SECOND / self.frame_bytes, "Hz")
            raise ValueError(
                f"parameter '{self.RATE_PARAMETER}' must be in {highest} for frames of {self.frame_bytes} bytes "
                f"(at most {MAX_BYTES_PER_SECOND / 1e6:g} MB/s per driver), got {rate!r}")
        return rate

    def declare_int_parameter(self, name: str, default: int, description: str, bounds: Bounds, *,
                              fixed: str = FIXED_GEOMETRY) -> int:
        """Declare a read-only integer parameter within ``bounds``, raising ValueError naming it."""
        def validate(value: Any) -> int:
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"parameter '{name}' must be an integer, got {value!r}")
            bounds.check(f"'{name}'", value)
            return value
        return self._declare(name, default, f"{description}, in {bounds}", validate, fixed=fixed)

    def declare_string_parameter(self, name: str, default: str, description: str, *, allow_empty: bool = True,
                                 fixed: str = "", on_change: Optional[Callable[[Any], None]] = None) -> str:
        """Declare a string parameter (dynamic with ``on_change``) and validate it."""
        def validate(value: Any) -> str:
            if not isinstance(value, str):
                raise ValueError(f"parameter '{name}' must be a string, got {value!r}")
            if not allow_empty and not value:
                raise ValueError(f"parameter '{name}' must not be empty")
            return value
        return self._declare(name, default, description, validate, fixed=fixed, on_change=on_change)

    def declare_choice_parameter(self, name: str, default: str, choices: Iterable[str], description: str, *,
                                 fixed: str) -> str:
        """Declare a read-only string parameter that must be one of ``choices``."""
        choices = tuple(choices)
        value = self.declare_string_parameter(name, default, description, fixed=fixed)
        if value not in choices:
            raise ValueError(f"parameter '{name}': unknown value {value!r}; expected one of {', '.join(choices)}")
        return value

    def declare_topic_parameter(self, name: str, default: str, description: str) -> str:
        """Declare a read-only topic-name parameter and check that the name is valid for this node."""
        value = self.declare_string_parameter(name, default, description, allow_empty=False, fixed=FIXED_PUBLISHERS)
        self.check_topic_name(name, value)
        return value

    def check_topic_name(self, parameter: str, topic: str) -> None:
        """Raise ValueError naming ``parameter`` unless ``topic`` expands to a valid topic name."""
        try:
            self.resolve_topic_name(topic)
        except Exception as exc:  # rclpy raises its own name-validation exceptions
            raise ValueError(f"parameter '{parameter}': invalid topic name {topic!r}: {exc}") from exc
