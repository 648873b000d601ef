"""What a bag is made of, with no I/O policy: MCAP records, ``metadata.yaml``, message definitions and type
hashes, service event names, and CDR (exact size, fast serialization, reading). The read and write layers and
the tools build on it; it imports neither."""
