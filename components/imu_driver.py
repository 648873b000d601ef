"""Simulated IMU: publishes ``sensor_msgs/Imu`` at ``rate`` (default 200 Hz, up to 1 kHz and beyond).

Parameters (validated at construction; a bad value raises ValueError naming the parameter and its range).
``rate`` and ``frame_id`` can be changed at run time (``ros2 param set``); ``topic`` and ``qos`` are read-only:

============  ==============  ============================================================
``rate``      200.0           messages per second (0.01 ... 2000)
``frame_id``  ``'imu'``       header.frame_id
``topic``     ``'~/imu'``
``qos``       ``'reliable'``  ``'reliable'`` or ``'sensor_data'`` (best effort)
============  ==============  ============================================================

Contents: a gyro/accelerometer-only IMU at rest on a gently yawing platform. ``linear_acceleration`` is gravity
(+9.80665 m/s^2 on z) plus noise, ``angular_velocity`` a slow yaw oscillation plus noise; both covariances are
diagonal with the noise variances. Noise samples come from a pool drawn once, taken at a rolling index.

No orientation estimate is provided: per REP 145, ``orientation_covariance[0] == -1`` and ``orientation`` is the
identity quaternion, which consumers must ignore.

Sequence number: ``orientation_covariance[1]`` holds the message sequence number (0, 1, 2 ...) as a float64,
exact up to 2**53. Since element 0 is -1 the rest of the orientation covariance carries no meaning, so this does
not disturb REP 145 consumers.

The yaw oscillation follows the capture time, so it stays continuous when the rate changes.

Rate: above 500 Hz the base class's catch-up loop publishes several messages per 2 ms timer tick instead of
asking the executor for one timer callback per message.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Quaternion, Vector3
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Imu
from std_msgs.msg import Header

from components.sensor_driver import SensorDriver

GRAVITY = 9.80665
ACCEL_NOISE_SIGMA = 0.02   # m/s^2
GYRO_NOISE_SIGMA = 0.002   # rad/s
YAW_RATE_AMPLITUDE = 0.2   # rad/s
YAW_RATE_FREQUENCY = 0.25  # Hz
NOISE_POOL = 4096          # samples; a prime stride walks the pool
NOISE_STRIDE = 1031

_new = object.__new__


def _layout(msg: Any) -> list[tuple[str, type, Any]]:
    """Every slot of ``msg`` and of the messages in it, with the type of its value (and the flag's value)."""
    out = []
    for slot in msg.__slots__:
        value = getattr(msg, slot)
        out.append((slot, type(value), value if slot == "_check_fields" else None))
        if hasattr(value, "__slots__"):
            out.extend((f"{slot}.{name}", kind, flag) for name, kind, flag in _layout(value))
    return out


class ImuDriver(SensorDriver):
    """Simulated 6-axis IMU (no orientation) publishing sensor_msgs/Imu."""

    DEFAULT_TOPIC = "~/imu"
    DEFAULT_FRAME_ID = "imu"
    RATE_PARAMETER = "rate"
    DEFAULT_RATE = 200.0

    def __init__(self, node_name: str = "imu", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)

    def configure(self) -> None:
        noise = np.random.default_rng(0x1B0).normal(0.0, 1.0, (NOISE_POOL, 6))
        noise[:, :3] *= GYRO_NOISE_SIGMA
        noise[:, 3:] *= ACCEL_NOISE_SIGMA
        self._noise = tuple(tuple(row) for row in noise.tolist())  # plain floats: no numpy per message
        self._gyro_var = GYRO_NOISE_SIGMA ** 2
        self._accel_var = ACCEL_NOISE_SIGMA ** 2
        # Templates that make_imu copies (numpy copies of 9 doubles: 0.4 us each); never written.
        self._orientation_covariance = np.zeros(9)
        self._orientation_covariance[0] = -1.0
        self._gyro_covariance = np.diag([self._gyro_var] * 3).ravel()
        self._accel_covariance = np.diag([self._accel_var] * 3).ravel()
        self._check_fields = Imu()._check_fields  # what the constructors would set (ROS_PYTHON_CHECK_FIELDS)
        self.publisher = self.create_publisher(Imu, self.topic, self.qos_profile)
        self.frame_bytes = len(serialize_message(self.construct_imu(0, 0)))
        if not self.assembly_matches():
            self.get_logger().warning("sensor_msgs/Imu is not laid out as make_imu expects; building each message "
                                   "with the constructors instead (about 12 us more per message)")
            self.make_imu = self.construct_imu

    def make_imu(self, sequence: int, stamp_ns: int) -> Imu:
        """A fresh Imu message; sequence number in orientation_covariance[1].

        Ten drivers at 1 kHz make building the messages most of the drivers' cost: ``Imu()`` runs the
        generated constructors and property setters of six messages and three arrays (more than half of what
        one publish costs). This assembles the same objects through the generated classes' slots instead, in
        less than half the time. :meth:`assembly_matches` checks at load that the result is the
        message :meth:`construct_imu` builds with the public constructors; where it is not, the driver uses
        that one.
        """
        gx, gy, gz, ax, ay, az = self._readings(sequence, stamp_ns)
        check = self._check_fields
        stamp = _new(Time)
        stamp._check_fields = check
        stamp._sec, stamp._nanosec = divmod(stamp_ns, 1_000_000_000)
        header = _new(Header)
        header._check_fields, header._stamp, header._frame_id = check, stamp, self.frame_id
        orientation = _new(Quaternion)
        orientation._check_fields = check
        orientation._x = orientation._y = orientation._z = 0.0
        orientation._w = 1.0
        angular_velocity = _new(Vector3)
        angular_velocity._check_fields = check
        angular_velocity._x, angular_velocity._y, angular_velocity._z = gx, gy, gz
        linear_acceleration = _new(Vector3)
        linear_acceleration._check_fields = check
        linear_acceleration._x, linear_acceleration._y, linear_acceleration._z = ax, ay, az
        orientation_covariance = self._orientation_covariance.copy()
        orientation_covariance[1] = sequence
        msg = _new(Imu)
        msg._check_fields, msg._header, msg._orientation = check, header, orientation
        msg._orientation_covariance = orientation_covariance
        msg._angular_velocity = angular_velocity
        msg._angular_velocity_covariance = self._gyro_covariance.copy()
        msg._linear_acceleration = linear_acceleration
        msg._linear_acceleration_covariance = self._accel_covariance.copy()
        return msg

    def construct_imu(self, sequence: int, stamp_ns: int) -> Imu:
        """The message :meth:`make_imu` assembles, built with the public constructors and setters."""
        gx, gy, gz, ax, ay, az = self._readings(sequence, stamp_ns)
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        orientation_covariance = self._orientation_covariance.copy()
        orientation_covariance[1] = sequence
        return Imu(header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=self.frame_id),
                   orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                   orientation_covariance=orientation_covariance,
                   angular_velocity=Vector3(x=gx, y=gy, z=gz),
                   angular_velocity_covariance=self._gyro_covariance.copy(),
                   linear_acceleration=Vector3(x=ax, y=ay, z=az),
                   linear_acceleration_covariance=self._accel_covariance.copy())

    def _readings(self, sequence: int, stamp_ns: int) -> tuple[float, float, float, float, float, float]:
        """Gyro x, y, z and accelerometer x, y, z of frame ``sequence`` captured at ``stamp_ns``."""
        gx, gy, gz, ax, ay, az = self._noise[(sequence * NOISE_STRIDE) % NOISE_POOL]
        yaw_rate = YAW_RATE_AMPLITUDE * math.sin(2.0 * math.pi * YAW_RATE_FREQUENCY * stamp_ns / 1e9)
        return gx, gy, yaw_rate + gz, ax, ay, GRAVITY + az

    def assembly_matches(self) -> bool:
        """Whether :meth:`make_imu` builds what :meth:`construct_imu` builds: equal messages, equal bytes from
        rclpy's serializer, and every field of the same type and flags."""
        stamp_ns, sequence = 1_700_000_000_123_456_789, 2 ** 40 + 7
        try:
            assembled = type(self).make_imu(self, sequence, stamp_ns)  # the assembly, even after a fallback
            constructed = self.construct_imu(sequence, stamp_ns)
            return (assembled == constructed
                    and serialize_message(assembled) == serialize_message(constructed)
                    and _layout(assembled) == _layout(constructed))
        except (AttributeError, TypeError, ValueError):  # a slot that is not there any more
            return False

    def publish_frame(self) -> None:
        stamp_ns = self.capture_ns()
        self.publisher.publish(self.make_imu(self.next_sequence(self.publisher), stamp_ns))
