"""Writers of the bag layouts older rosbag2 releases produced, for tests of the reader.

No rosbag2 binary can be installed here and bags fetched from elsewhere are not committed, so these
write the layouts from the rosbag2 sources that define them (ros2/rosbag2, read at its history):

* ``metadata.yaml`` versions 4 to 9: ``rosbag2_storage/include/rosbag2_storage/yaml.hpp`` (which
  entry each version has) and ``rosbag2_storage/src/rosbag2_storage/qos.cpp`` (QoS profiles: a YAML
  *string* with rmw's integer policies before version 9, a list with string policies in 9);
* SQLite3 schema versions 2 (Foxy, Galactic), 3 (Humble, rosbag2 #1156: ``schema`` and ``metadata``
  tables) and 4 (Iron, Jazzy, #1293 and #1272: ``message_definitions``, ``topics.type_description_hash``):
  ``SqliteStorage::initialize`` in ``rosbag2_storage_sqlite3/src/rosbag2_storage_sqlite3/sqlite_storage.cpp``
  (``rosbag2_storage_default_plugins/src/.../sqlite/sqlite_storage.cpp`` before Humble);
* MCAP as ``rosbag2_storage_mcap/src/mcap_storage.cpp`` lays it out (schema per type, channel metadata
  ``offered_qos_profiles`` and ``topic_type_hash``; the ``rosbag2`` metadata record holding
  ``ROS_DISTRO`` in Iron, #1241, and ``serialized_metadata`` since #1423), written with the ``mcap``
  package's writer, with or without chunks, chunk compression and summary;
* rosbag2_compression: ``compression_mode`` ``FILE`` (each storage file zstd-compressed as a whole,
  ``<file>.zstd``, ``zstd_compressor.cpp`` ``compress_uri``) or ``MESSAGE`` (each message's data one
  zstd frame, ``compress_serialized_bag_message``), ``compression_format`` ``zstd``
  (``compression_options.cpp``).
"""
from __future__ import annotations

import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
import zstandard
from mcap.writer import CompressionType, IndexType, Writer

# rmw's policy numbers (rmw/types.h), as metadata before version 9 stores them.
HISTORY = {"system_default": 0, "keep_last": 1, "keep_all": 2, "unknown": 3}
RELIABILITY = {"system_default": 0, "reliable": 1, "best_effort": 2, "unknown": 3, "best_available": 4}
DURABILITY = {"system_default": 0, "transient_local": 1, "volatile": 2, "unknown": 3, "best_available": 4}
LIVELINESS = {"system_default": 0, "automatic": 1, "manual_by_topic": 3, "unknown": 4, "best_available": 5}


@dataclass
class LegacyTopic:
    """A topic; ``qos`` in the version-9 dict form (converted to the older forms when written)."""

    name: str
    type: str
    qos: list[dict[str, Any]] = field(default_factory=list)
    type_hash: str = ""
    definition: tuple[str, str] = ("ros2msg", "string data\n")


#: (topic name, log time, publish time, data)
LegacyMessage = tuple[str, int, int, bytes]


def qos_text(profiles: list[dict[str, Any]], version: int) -> str:
    """The QoS list as the YAML string rosbag2 stores (metadata < 9, sqlite3 rows, MCAP channels)."""
    return yaml.safe_dump(qos_list(profiles, version), sort_keys=False) if profiles else ""


def qos_list(profiles: list[dict[str, Any]], version: int) -> list[dict[str, Any]]:
    if version >= 9:
        return [dict(profile) for profile in profiles]
    return [{**profile, "history": HISTORY[profile["history"]], "reliability": RELIABILITY[profile["reliability"]],
             "durability": DURABILITY[profile["durability"]], "liveliness": LIVELINESS[profile["liveliness"]]}
            for profile in profiles]


def metadata_document(version: int, storage: str, files: list[str], topics: list[LegacyTopic],
                      messages_per_file: list[list[LegacyMessage]], compression_mode: str = "",
                      compression_format: str = "", custom_data: dict[str, str] | None = None,
                      ros_distro: str = "") -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` mapping of ``version``, with only the entries it has."""
    everything = [message for messages in messages_per_file for message in messages]
    start = min((m[1] for m in everything), default=0)
    end = max((m[1] for m in everything), default=0)
    topic_entries = []
    for topic in topics:
        entry: dict[str, Any] = {"name": topic.name, "type": topic.type, "serialization_format": "cdr",
                                 "offered_qos_profiles": qos_list(topic.qos, 9) if version >= 9
                                 else qos_text(topic.qos, version)}
        if version >= 7:
            entry["type_description_hash"] = topic.type_hash
        topic_entries.append({"topic_metadata": entry,
                              "message_count": sum(1 for m in everything if m[0] == topic.name)})
    document: dict[str, Any] = {
        "version": version, "storage_identifier": storage, "relative_file_paths": files,
        "duration": {"nanoseconds": end - start}, "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": len(everything), "topics_with_message_count": topic_entries,
        "compression_format": compression_format, "compression_mode": compression_mode,
    }
    if version >= 5:
        document["files"] = [
            {"path": name, "starting_time": {"nanoseconds_since_epoch": min((m[1] for m in messages), default=0)},
             "duration": {"nanoseconds": max((m[1] for m in messages), default=0)
                          - min((m[1] for m in messages), default=0)},
             "message_count": len(messages)}
            for name, messages in zip(files, messages_per_file, strict=True)]
    if version >= 6:
        document["custom_data"] = custom_data
    if version >= 8:
        document["ros_distro"] = ros_distro
    return document


def write_metadata(bag: Path, document: dict[str, Any]) -> None:
    (bag / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": document},
                                                      sort_keys=False))


def write_sqlite(path: Path, schema_version: int, topics: list[LegacyTopic], messages: list[LegacyMessage],
                 metadata_version: int, ros_distro: str = "", serialized_metadata: str = "",
                 compress_messages: bool = False) -> None:
    """A ``.db3`` of ``schema_version`` 2, 3 or 4 (see the module doc); only the receive time is stored."""
    db = sqlite3.connect(path)
    qos_column = ", offered_qos_profiles TEXT NOT NULL"
    hash_column = ", type_description_hash TEXT NOT NULL" if schema_version >= 4 else ""
    if schema_version >= 3:
        db.execute("CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, ros_distro TEXT NOT NULL)")
        db.execute("CREATE TABLE metadata(id INTEGER PRIMARY KEY, metadata_version INTEGER NOT NULL,"
                   " metadata TEXT NOT NULL)")
        db.execute("INSERT INTO schema VALUES (?, ?)", (schema_version, ros_distro))
    db.execute("CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL,"
               f" serialization_format TEXT NOT NULL{qos_column}{hash_column})")
    if schema_version >= 4:
        db.execute("CREATE TABLE message_definitions(id INTEGER PRIMARY KEY, topic_type TEXT NOT NULL,"
                   " encoding TEXT NOT NULL, encoded_message_definition TEXT NOT NULL,"
                   " type_description_hash TEXT NOT NULL)")
    db.execute("CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL,"
               " timestamp INTEGER NOT NULL, data BLOB NOT NULL)")
    db.execute("CREATE INDEX timestamp_idx ON messages (timestamp ASC)")
    ids = {}
    for topic in topics:
        row = [topic.name, topic.type, "cdr", qos_text(topic.qos, metadata_version)]
        if schema_version >= 4:
            row.append(topic.type_hash)
            db.execute("INSERT INTO message_definitions (topic_type, encoding, encoded_message_definition,"
                       " type_description_hash) VALUES (?, ?, ?, ?)", (topic.type, *topic.definition, topic.type_hash))
        ids[topic.name] = db.execute(f"INSERT INTO topics VALUES (NULL{', ?' * len(row)})", row).lastrowid
    compressor = zstandard.ZstdCompressor()
    db.executemany("INSERT INTO messages (timestamp, topic_id, data) VALUES (?, ?, ?)", [
        (log_time, ids[topic], compressor.compress(data) if compress_messages else data)
        for topic, log_time, _, data in messages])
    if schema_version >= 3 and serialized_metadata:
        db.execute("INSERT INTO metadata (metadata_version, metadata) VALUES (?, ?)",
                   (metadata_version, serialized_metadata))
    db.commit()
    db.close()


def write_mcap(path: Path, topics: list[LegacyTopic], messages: list[LegacyMessage], qos_version: int,
               chunked: bool = True, compression: CompressionType = CompressionType.ZSTD, summary: bool = True,
               chunk_size: int = 4096, rosbag2_metadata: dict[str, str] | None = None,
               type_hashes: bool = True) -> None:
    """An ``.mcap`` file laid out as rosbag2_storage_mcap writes it; ``summary=False`` leaves out the
    whole summary section (the footer then says there is none), as a writer that never finished would;
    ``type_hashes=False`` leaves out ``topic_type_hash`` (before Iron)."""
    with open(path, "wb") as stream:
        writer = Writer(stream, chunk_size=chunk_size, compression=compression, use_chunking=chunked,
                        index_types=IndexType.ALL if summary else IndexType.NONE,
                        repeat_channels=summary, repeat_schemas=summary, use_statistics=summary,
                        use_summary_offsets=summary)
        writer.start(profile="ros2", library="legacy_bags")
        channels = {}
        schemas: dict[str, int] = {}
        for topic in topics:
            if topic.type not in schemas:
                encoding, text = topic.definition
                schemas[topic.type] = writer.register_schema(topic.type, encoding, text.encode())
            metadata = {"offered_qos_profiles": qos_text(topic.qos, qos_version)}
            if type_hashes:
                metadata["topic_type_hash"] = topic.type_hash
            channels[topic.name] = writer.register_channel(topic.name, "cdr", schemas[topic.type], metadata)
        for sequence, (topic, log_time, publish_time, data) in enumerate(messages):
            writer.add_message(channels[topic], log_time, data, publish_time, sequence)
        if rosbag2_metadata is not None:
            writer.add_metadata("rosbag2", rosbag2_metadata)
        writer.finish()


def compress_file(path: Path) -> Path:
    """``path`` replaced by ``path.zstd``, as rosbag2's FILE compression leaves each storage file."""
    target = path.with_name(path.name + ".zstd")
    with open(path, "rb") as source, open(target, "wb") as destination:
        zstandard.ZstdCompressor().copy_stream(source, destination)
    path.unlink()
    return target
