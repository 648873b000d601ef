"""``--load FILE.yaml``: components to load when the container starts, as a launch file's
ComposableNodeContainer would list them.

```yaml
components:
  - package: components
    plugin: components::CameraDriver
    name: front_camera                 # optional
    namespace: /rig                    # optional
    parameters: {width: 1920, height: 1080}
    remaps: {"~/image_raw": /rig/front/image_raw}   # or a list of "from:=to"
    extra_arguments: {use_intra_process_comms: true}
    log_level: 20                      # optional
```
Nested parameter dictionaries are flattened to dotted names, as launch_ros does.
"""
from __future__ import annotations

import pathlib
from typing import Any

import yaml
from composition_interfaces.srv import LoadNode

from component_container.parameter_values import parameter_msg

_KEYS = {"package", "plugin", "name", "namespace", "parameters", "remaps", "extra_arguments", "log_level"}


class StartupFileError(Exception):
    """The file cannot be read or does not describe components."""


def flatten(parameters: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{'record': {'all_topics': True}}`` -> ``{'record.all_topics': True}``."""
    flat: dict[str, Any] = {}
    for key, value in parameters.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(flatten(value, f"{name}."))
        else:
            flat[name] = value
    return flat


def _remap_rules(remaps: Any) -> list[str]:
    if isinstance(remaps, dict):
        return [f"{source}:={target}" for source, target in remaps.items()]
    return [str(rule) for rule in remaps or []]


def load_requests(path: str | pathlib.Path) -> list[LoadNode.Request]:
    """The LoadNode requests the file describes, in file order."""
    try:
        document = yaml.safe_load(pathlib.Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise StartupFileError(f"Cannot read component file '{path}': {exc}") from exc
    entries = document.get("components") if isinstance(document, dict) else document
    if not isinstance(entries, list):
        raise StartupFileError(f"'{path}' must hold a list of components (under the key 'components')")
    return [load_request(entry, index + 1, f"'{path}'") for index, entry in enumerate(entries)]


def load_request(entry: Any, position: int, source: str = "request") -> LoadNode.Request:
    """One component entry (``package``, ``plugin``, ``parameters``...) as a LoadNode request."""
    if not isinstance(entry, dict) or not {"package", "plugin"} <= entry.keys() or entry.keys() - _KEYS:
        raise StartupFileError(
            f"{source} component #{position}: needs 'package' and 'plugin', may have "
            f"{', '.join(sorted(_KEYS - {'package', 'plugin'}))}; got {entry!r}")
    try:
        return LoadNode.Request(
            package_name=str(entry["package"]), plugin_name=str(entry["plugin"]),
            node_name=str(entry.get("name", "")), node_namespace=str(entry.get("namespace", "")),
            log_level=int(entry.get("log_level", 0)), remap_rules=_remap_rules(entry.get("remaps")),
            parameters=[parameter_msg(k, v) for k, v in flatten(entry.get("parameters") or {}).items()],
            extra_arguments=[parameter_msg(k, v) for k, v in (entry.get("extra_arguments") or {}).items()])
    except (TypeError, ValueError, AssertionError) as exc:
        raise StartupFileError(f"{source} component #{position}: {exc}") from exc
