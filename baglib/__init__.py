"""The bag library: rosbag2 bags on disk, below every component and the CLI.

Everything that knows the file formats lives here and nothing here knows about nodes or containers, so the
recorder, the player and ``ipc-component bag ...`` all share one implementation:

* ``writer``: :class:`~baglib.writer.BagWriter`, a bag directory being written (split files, metadata);
* ``mcap_storage`` / ``sqlite_storage``: the two storage back-ends (MCAP with the ros2 profile, SQLite3);
* ``reader``: :class:`~baglib.reader.BagReader`, any rosbag2 bag (Foxy to Jazzy) as connections and
  messages in log-time order, over ``mcap_reader`` / ``sqlite_reader`` (the interface in ``storage_reader``);
* ``metadata``: ``metadata.yaml`` (rosbag2's BagMetadata) and the topic/file records it holds;
  ``metadata_read``: reading it in every version from 4 to 9;
* ``mcap_records``: an MCAP file as complete records up to its first damage, and its summary;
* ``repair``: ``bag recover``, making a bag a crash left unfinished readable again;
* ``info``: what ``ros2 bag info`` prints;
* ``cdr_fast`` / ``cdr_size``: message objects to the exact CDR bytes a DDS reader receives;
* ``message_definitions``: the ``.msg`` text and RIHS01 type hash of installed types;
* ``service_events``: service event topics (``<service>/_service_event``) and types (``pkg/srv/Name_Event``);
* ``direct_file``: ``O_DIRECT`` writes for big payloads.
"""
