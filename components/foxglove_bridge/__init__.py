"""``components::FoxgloveBridge``: a Foxglove WebSocket bridge component fed from the container (bridge.py)."""
