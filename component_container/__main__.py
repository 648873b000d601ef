"""``python -m component_container``: run a component container process.

Usage: ``python -m component_container [--executor single|multi|isolated] [--use-intra-process-comms]
[--allow-module-plugins] [--load FILE.yaml]... [--ros-args ...]``

SIGINT and SIGTERM unload every component (newest first, so a recorder finalizes its bag) and exit 0.
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from component_container.component_executors import EXECUTOR_KINDS, spin_in_thread
from component_container.component_manager import ComponentManager
from component_container.startup_file import StartupFileError, load_requests


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m component_container", description=__doc__.splitlines()[0])
    parser.add_argument("--executor", choices=EXECUTOR_KINDS, default="single",
                        help="executor model for the components (default: single)")
    parser.add_argument("--use-intra-process-comms", action="store_true",
                        help="components use intra-process communication unless a load request says false")
    parser.add_argument("--allow-module-plugins", action="store_true",
                        help="also accept plugin names of the form 'python.module:ClassName'")
    parser.add_argument("--load", action="append", default=[], metavar="FILE.yaml",
                        help="components to load at start-up (repeatable)")
    return parser.parse_args(remove_ros_args(argv)[1:])


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv if argv is None else argv)
    args = parse_arguments(argv)
    try:
        startup = [request for path in args.load for request in load_requests(path)]
    except StartupFileError as exc:
        print(exc, file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    try:
        manager = ComponentManager(args.executor, use_intra_process_comms=args.use_intra_process_comms,
                                   allow_module_plugins=args.allow_module_plugins)
    except Exception as exc:  # bad thread_num and the like: say so and exit non-zero
        print(f"Cannot start the container: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    for request in startup:
        try:
            manager.load(request)
        except Exception as exc:  # noqa: BLE001 - every load failure is reported, the container stays up
            manager.get_logger().error(f"Failed to load component {request.plugin_name}: {exc}")
    manager_executor = SingleThreadedExecutor()
    manager_executor.add_node(manager)
    manager_thread = spin_in_thread(manager_executor, "component_manager")
    stop.wait()
    manager.get_logger().info("Shutting down: unloading all components")
    manager_executor.shutdown(timeout_sec=5.0)
    manager_thread.join(timeout=5.0)
    manager.shutdown()
    manager.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
