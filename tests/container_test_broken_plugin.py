"""A plugin module that fails on import (loaded as ``tests.container_test_broken_plugin:Anything``)."""
raise ImportError("container_test_broken_plugin refuses to be imported")
