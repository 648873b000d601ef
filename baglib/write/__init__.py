"""The write path: :class:`~baglib.write.writer.BagWriter`, a bag directory being written (split files,
``metadata.yaml``), over the MCAP and SQLite3 storages and ``O_DIRECT`` file writes. Built on
``baglib.format`` only."""
