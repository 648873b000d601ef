"""The bag library: rosbag2 bags on disk, below every component and the CLI.

Everything that knows the file formats lives here and nothing here knows about nodes or containers, so the
recorder, the player and ``ipc-component bag ...`` share one implementation. Four layers, imports pointing
down only (``tests/test_layout.py`` enforces it)::

    tools/    info, repair (bag recover), merge (bag merge)        uses read + write + format
    read/     reader, mcap_reader, sqlite_reader, metadata_read,   uses format
              timeline (several bags as one stream)
    write/    writer, mcap_storage, sqlite_storage, direct_file    uses format
    format/   mcap_records, metadata, message_definitions, service_events, bag_files, fleet_keys,
              cdr_size / cdr_fast (objects to CDR), cdr_read (CDR to objects)

``read`` and ``write`` never import each other.
"""
