"""Tools on whole bags, above the read and write paths: ``info`` (what ``ros2 bag info`` prints) and
``repair`` (``bag recover``)."""
