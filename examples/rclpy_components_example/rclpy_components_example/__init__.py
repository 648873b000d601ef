"""Example rclpy components for the component container (see docs/writing-components.md).

* ``rclpy_components_example::CounterPublisher`` publishes ``"<prefix> <n> @<object id>"`` on ``counter``;
* ``rclpy_components_example::ZeroCopyListener`` subscribes to it and counts the messages it got by reference
  (the very object the publisher built) and those it got as copies, in its ``/diagnostics`` status.
"""
