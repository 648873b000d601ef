"""``ipc-component``: the command line above the container and the components.

``cli`` parses the verbs (the ``ros2 component`` ones, ``bag info|play|recover``, ``types``, ``create``);
``bag_play`` runs a player in a container of its own; ``create`` writes a new package of components;
``container_discovery`` finds every container of the domain; ``repeated_call`` calls a service until it
answers (Fast DDS drops replies to clients it has not matched).
"""
