"""The read path: any rosbag2 bag (Foxy to Jazzy, MCAP or SQLite3) as connections and messages in log-time
order. :class:`~baglib.read.reader.BagReader` over one storage reader per file (the interface in
``storage_reader``). Built on ``baglib.format`` only: reading never imports the writer or the repair tool."""
