// Decodes recorded ROS 2 messages with Foxglove's published CDR reader (@foxglove/rosmsg2-serialization), the
// one Foxglove uses for bags, with the ros2msg schema the bag carries (parsed by @foxglove/rosmsg).
//
// Usage: node decode_cdr.js < messages
// Input, one JSON object per line: {"schema": ros2msg text, "data": CDR bytes in base64}.
// Output, one JSON object per line: the decoded message's fields, with byte arrays (uint8[]) in base64 and
// stamps as {sec, nanosec}.
"use strict";

const readline = require("readline");
const { parse } = require("@foxglove/rosmsg");
const { MessageReader } = require("@foxglove/rosmsg2-serialization");

const readers = new Map(); // schema text -> reader

function readerFor(schema) {
  if (!readers.has(schema)) readers.set(schema, new MessageReader(parse(schema, { ros2: true })));
  return readers.get(schema);
}

function plain(key, value) {
  if (value instanceof Uint8Array) return Buffer.from(value.buffer, value.byteOffset, value.byteLength).toString("base64");
  if (typeof value === "bigint") return Number(value);
  return value;
}

const lines = readline.createInterface({ input: process.stdin });
lines.on("line", (line) => {
  if (!line.trim()) return;
  const { schema, data } = JSON.parse(line);
  const bytes = new Uint8Array(Buffer.from(data, "base64"));
  process.stdout.write(JSON.stringify(readerFor(schema).readMessage(bytes), plain) + "\n");
});
