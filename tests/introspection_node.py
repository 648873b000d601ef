"""An out-of-process node with two services and their clients, all with service introspection CONTENTS.

Run by tests/test_service_recording.py as ``python introspection_node.py``. It offers ``/set_flag``
(std_srvs/SetBool) and ``/trigger_me`` (std_srvs/Trigger), publishes ``/chatter`` (std_msgs/String) and talks
over stdin/stdout, one line each way:

* prints ``ready`` once its endpoints exist;
* ``wait TOPIC N``: waits until TOPIC has N subscriptions in the graph, prints ``matched``;
* ``call N``: calls ``/set_flag`` N times (``data`` = i % 2 == 0) and ``/trigger_me`` N times, publishes N
  ``/chatter`` messages, prints ``done``;
* end of input: exits (the test closes it once the recorders hold every event).

The event publishers are reliable and transient_local (depth 100): a recorder whose subscription matches a
moment after the calls still gets every event, so the counts the tests check do not depend on discovery
timing.
"""
from __future__ import annotations

import sys
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.service_introspection import ServiceIntrospectionState
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger

EVENT_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)
CHATTER_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


def on_set_flag(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
    response.success = request.data
    response.message = f"flag {'set' if request.data else 'cleared'}"
    return response


def on_trigger(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
    response.success, response.message = True, "triggered"
    return response


def call(executor: SingleThreadedExecutor, client: object, request: object) -> object:
    future = client.call_async(request)  # type: ignore[attr-defined]
    executor.spin_until_future_complete(future, timeout_sec=10.0)
    if not future.done():
        raise SystemExit(f"no reply from {client.srv_name}")  # type: ignore[attr-defined]
    return future.result()


def main() -> None:
    rclpy.init()
    node = Node("introspection_node")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    clock = node.get_clock()
    endpoints = [node.create_service(SetBool, "/set_flag", on_set_flag),
                 node.create_service(Trigger, "/trigger_me", on_trigger)]
    set_flag = node.create_client(SetBool, "/set_flag")
    trigger = node.create_client(Trigger, "/trigger_me")
    for endpoint in (*endpoints, set_flag, trigger):
        endpoint.configure_introspection(clock, EVENT_QOS, ServiceIntrospectionState.CONTENTS)
    chatter = node.create_publisher(String, "/chatter", CHATTER_QOS)
    for client in (set_flag, trigger):
        if not client.wait_for_service(timeout_sec=10.0):
            raise SystemExit(f"{client.srv_name} did not appear")
    print("ready", flush=True)
    for line in sys.stdin:
        command, *args = line.split()
        if command == "wait":
            topic, count = args[0], int(args[1])
            deadline = time.monotonic() + 20.0
            while node.count_subscribers(topic) < count and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            print("matched" if node.count_subscribers(topic) >= count else "timeout", flush=True)
        elif command == "call":
            for i in range(int(args[0])):
                call(executor, set_flag, SetBool.Request(data=i % 2 == 0))
                call(executor, trigger, Trigger.Request())
                chatter.publish(String(data=f"chatter {i}"))
            print("done", flush=True)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
