"""Set parameters of a running node, as ``ros2 param set`` does, for installs without the ros2 command line.

    python examples/rclpy_components_example/set_parameter.py /counter_publisher prefix:=hi rate:=5.0

Values are typed as ``ros2 param set`` types them (YAML: ``5`` is an integer, ``5.0`` a float). Prints
``Set parameter successful`` or ``Setting parameter failed: <reason>`` per parameter; exit code 1 if one
failed or the node did not answer within 10 s. The request is sent again every second until it is answered:
Fast DDS drops a reply to a client whose reader it has not matched yet, and setting a value twice is harmless.
"""
from __future__ import annotations

import sys
import time

import rclpy
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node

from component_container.parameter_values import parameter_msg, parse_assignment

TIMEOUT = 10.0


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    node_name, assignments = argv[0], argv[1:]
    try:
        parameters = [parameter_msg(*parse_assignment(text)) for text in assignments]
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 2
    rclpy.init(args=[sys.argv[0]])  # not the name:=value words: rcl would take them for remap rules
    try:
        node = Node(f"_set_parameter_{time.monotonic_ns()}")
        client = node.create_client(SetParameters, f"{node_name}/set_parameters")
        deadline = time.monotonic() + TIMEOUT
        if not client.wait_for_service(timeout_sec=TIMEOUT):
            print(f"No parameter service of '{node_name}' found within {TIMEOUT:g} s", file=sys.stderr)
            return 1
        while True:
            future = client.call_async(SetParameters.Request(parameters=parameters))
            rclpy.spin_until_future_complete(node, future, timeout_sec=1.0)
            if future.done():
                break
            client.remove_pending_request(future)
            if time.monotonic() > deadline:
                print(f"No reply from '{node_name}' within {TIMEOUT:g} s", file=sys.stderr)
                return 1
        failed = False
        for text, result in zip(assignments, future.result().results):
            if result.successful:
                print(f"{text}: Set parameter successful")
            else:
                failed = True
                print(f"{text}: Setting parameter failed: {result.reason}")
        return 1 if failed else 0
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
