"""``python -m component_container``: run a component container process.

Usage: ``python -m component_container [--executor single|multi|isolated|events]
[--use-intra-process-comms] [--allow-module-plugins] [--allow-plugins PATTERN]... [--bag-root DIR]
[--on-component-error unload|exit] [--shutdown-timeout SECONDS] [--load FILE.yaml]... [--ros-args ...]``

SIGINT and SIGTERM unload every component (newest first, so a recorder finalizes its bag) within the shutdown
timeout and exit 0; a second signal, or a shutdown that overruns, exits at once with status 1. A component
error under ``--on-component-error exit`` and a dead container thread exit with status 1 too, and so does a
shutdown that leaves a component callback running: the shutdown overran, and the interpreter is not finalized
under running component code (nor under rclpy's C++ EventsExecutor, which aborts the process when it is torn
down while a thread is in it).
"""
from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
from pathlib import Path

import rclpy
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from component_container.bag_root import bag_root_directory
from component_container.callback_supervision import SpinThread
from component_container.component_executors import EXECUTOR_KINDS, SupervisedSingleThreadedExecutor
from component_container.component_manager import ComponentManager
from component_container.discovery_profile import use_fastdds_profile
from component_container.process_tuning import apply_low_latency
from component_container.startup_file import StartupFileError, load_requests
from component_container.exit_timer import end_within
from component_container.supervisor import ERROR_POLICIES, ExitRequest, join_in_main_thread

# Beyond the shutdown timeout, what the last steps (manager node, rclpy context) may take before a forced exit.
EXIT_MARGIN = 2.0
# Making the container node (normally well under a second) or refusing it, before a forced exit with status 2.
START_LIMIT = 10.0


def positive_seconds(text: str) -> float:
    value = float(text)
    if not 0.0 < value <= 3600.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 3600] seconds, got {text}")
    return value


def existing_directory(text: str) -> Path:
    """``--bag-root``: argparse prints the reason only for an ArgumentTypeError."""
    try:
        return bag_root_directory(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m component_container", description=__doc__.splitlines()[0])
    parser.add_argument("--executor", choices=EXECUTOR_KINDS, default="single",
                        help="executor model for the components (default: single; events: rclpy's "
                             "EventsExecutor, see docs/container.md)")
    parser.add_argument("--use-intra-process-comms", action="store_true",
                        help="components use intra-process communication unless a load request says false")
    parser.add_argument("--allow-module-plugins", action="store_true",
                        help="also accept plugin names of the form 'python.module:ClassName'")
    parser.add_argument("--allow-plugins", action="append", default=[], metavar="PATTERN",
                        help="load only plugins whose name matches this fnmatch pattern, e.g. 'components::*' "
                             "(repeatable; default: every registered plugin)")
    parser.add_argument("--bag-root", type=existing_directory, metavar="DIR",
                        help="every path a request names (storage.uri, QoS override files) must resolve inside "
                             "DIR; relative paths are taken inside it (default: no limit, relative to the cwd)")
    parser.add_argument("--on-component-error", choices=ERROR_POLICIES, default="unload",
                        help="a component callback raised: unload only that component (default), or finalize "
                             "every bag and exit with status 1 so that launch can respawn the container")
    parser.add_argument("--shutdown-timeout", type=positive_seconds, default=10.0, metavar="SECONDS",
                        help="bound on an unload and on the whole shutdown (default: 10)")
    parser.add_argument("--low-latency", action="store_true",
                        help="tune the whole process for replay timing: a 0.2 ms interpreter switch interval and "
                             "malloc thresholds that reuse large buffers (component_container.process_tuning)")
    parser.add_argument("--load", action="append", default=[], metavar="FILE.yaml",
                        help="components to load at start-up (repeatable)")
    return parser.parse_args(remove_ros_args(argv)[1:])


def force_exit(status: int) -> None:
    """Leave now, whatever threads are still stuck (a hung disk): what is unfinished is left for repair. Called
    from a signal handler too, which may run while this thread is inside a write to the same stream (the
    flush then raises RuntimeError): the output is flushed where it can be, and the exit happens regardless."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(status)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv if argv is None else argv)
    args = parse_arguments(argv)
    try:
        startup = [request for path in args.load for request in load_requests(path)]
    except StartupFileError as exc:
        print(exc, file=sys.stderr)
        return 2
    exit_request = ExitRequest()

    def on_signal(signum: int, _frame: object) -> None:
        if exit_request.request(0, signal.Signals(signum).name) > 1:
            os.write(sys.stderr.fileno(), b"Second signal: exiting without finishing the shutdown\n")
            force_exit(1)

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    if args.low_latency:
        apply_low_latency()
    use_fastdds_profile()
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    built: list[ComponentManager] = []

    def start() -> None:
        try:
            built.append(ComponentManager(args.executor, use_intra_process_comms=args.use_intra_process_comms,
                                          allow_module_plugins=args.allow_module_plugins,
                                          allow_plugins=args.allow_plugins, bag_root=args.bag_root,
                                          on_component_error=args.on_component_error,
                                          shutdown_timeout=args.shutdown_timeout, exit_request=exit_request))
        except Exception as exc:  # bad thread_num and the like: say so and exit non-zero
            print(f"Cannot start the container: {exc}", file=sys.stderr)
            rclpy.try_shutdown()

    # A refused start destroys the half-built node, and with it the participant: bounded like the last step.
    end_within(START_LIMIT, 2, start)
    if not built:
        return 2
    manager = built[0]
    for request in startup:
        try:
            manager.load(request)
        except Exception as exc:  # noqa: BLE001 - every load failure is reported, the container stays up
            manager.get_logger().error(f"Failed to load component {request.plugin_name}: {exc}")
    manager_executor = SupervisedSingleThreadedExecutor(
        on_error=lambda _node, exc: manager.supervisor.thread_died("component_manager", exc))
    manager_executor.add_node(manager)
    service = SpinThread(manager_executor, "component_manager", manager.supervisor.thread_died)
    manager.service_thread = service.thread
    exit_request.wait_in_main_thread()
    manager.get_logger().info(f"Shutting down ({exit_request.reason}): unloading all components")
    status = [exit_request.status]

    def shut_down() -> None:
        if not manager.shutdown(args.shutdown_timeout):
            status[0] = max(status[0], 1)
        service.stop(1.0)  # never finalize the interpreter under a waiting executor

        def destroy() -> None:  # the participant with the last node: bounded even when it holds the GIL
            manager.destroy_node()
            rclpy.try_shutdown()

        end_within(EXIT_MARGIN, 1, destroy)

    finisher = threading.Thread(target=shut_down, name="shutdown", daemon=True)
    finisher.start()
    join_in_main_thread(finisher, args.shutdown_timeout + EXIT_MARGIN)
    if finisher.is_alive():
        print(f"Shutdown did not finish within {args.shutdown_timeout:.1f} s: exiting with status 1",
              file=sys.stderr)
        force_exit(1)
    if any(thread.is_alive() for thread in manager.threads().values()):
        print("A component callback was still running after the shutdown: exiting with status 1", file=sys.stderr)
        force_exit(1)
    return status[0]


if __name__ == "__main__":
    sys.exit(main())
