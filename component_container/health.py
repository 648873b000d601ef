"""What a component reports about itself on ``/diagnostics`` (see component_container.diagnostics).

The container already knows whether a component is running; a component with more to say (a recorder's bag,
write rate, drops, free disk) overrides :meth:`ComponentNode.health` and returns one of these.
"""
from __future__ import annotations

from dataclasses import dataclass, field

# diagnostic_msgs/DiagnosticStatus levels
OK = 0
WARN = 1
ERROR = 2

# Keys of ``Health.values`` that viewers show in their own columns (``ipc-component top``): a component that
# loses messages or writes to a disk reports them under these names.
#: Messages this component lost so far (a recorder's drops, a driver's frames skipped at the source).
DROPPED = "dropped"
#: Megabytes free on the disk this component writes to (the container: its bag root, or working directory).
FREE_DISK_MB = "free disk (MB)"


@dataclass
class Health:
    """A component's own view of its health: a level, one line of message and key/value details."""

    level: int = OK
    message: str = "running"
    values: dict[str, str] = field(default_factory=dict)
