// A Foxglove WebSocket client for the bridge tests, built from Foxglove's own packages: the protocol client
// of @foxglove/ws-protocol and the ROS 2 CDR reader of @foxglove/rosmsg2-serialization, which decodes each
// message with the ros2msg schema the server advertised (parsed by @foxglove/rosmsg).
//
// Usage: node client.js ws://127.0.0.1:PORT [SUBPROTOCOL,...]
// Without a subprotocol list the client connects exactly as @foxglove/ws-protocol's README template does,
// offering only FoxgloveClient.SUPPORTED_SUBPROTOCOL ("foxglove.websocket.v1", as Lichtblick does); a list
// (e.g. "foxglove.sdk.v1", the name the Foxglove SDK's server accepts) replaces it.
// Commands, one JSON object per line on stdin:
//   {"op": "subscribe", "topic": T}        subscribe to the channel of topic T (once it is advertised)
//   {"op": "unsubscribe", "topic": T}
//   {"op": "getParameters", "names": [...], "id": ID}
//   {"op": "setParameters", "parameters": [{"name": N, "value": V}], "id": ID}
//   {"op": "subscribeConnectionGraph"}
//   {"op": "callService", "service": NAME, "request": {...}, "callId": N}
//   {"op": "close"}
// Events, one JSON object per line on stdout: {"event": "open" | "serverInfo" | "advertise" | "unadvertise" |
// "message" | "time" | "parameterValues" | "connectionGraph" | "advertiseServices" | "serviceResponse" |
// "serviceFailure" | "status" | "error" | "close" | "stray" (a message of a subscription already ended), ...}.
// A "message" event carries the topic, the schema name, the log time and, for the test drivers' types, the sequence number the driver wrote into the message
// (sensor_msgs/msg/Image: the first 8 bytes of data, little endian; sensor_msgs/msg/Imu:
// orientation_covariance[1]); a foxglove_msgs/msg/CompressedVideo message carries its timestamp
// ([sec, nanosec]), format and data (base64); for other types the names of the decoded fields.
"use strict";

const readline = require("readline");
const WebSocket = require("ws");
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const { parse } = require("@foxglove/rosmsg");
const { MessageReader, MessageWriter } = require("@foxglove/rosmsg2-serialization");

const url = process.argv[2];
const subprotocols = process.argv[3] ? process.argv[3].split(",") : [FoxgloveClient.SUPPORTED_SUBPROTOCOL];
const ws = new WebSocket(url, subprotocols);
const client = new FoxgloveClient({ ws });

const channelsByTopic = new Map();
const channelsById = new Map();
const readers = new Map();
const subscriptions = new Map(); // topic -> subscription id
const subscriptionTopics = new Map(); // subscription id -> topic
const pendingSubscribes = new Set();
const services = new Map(); // name -> service

function emit(event) {
  process.stdout.write(JSON.stringify(event, (key, value) => (typeof value === "bigint" ? Number(value) : value)) + "\n");
}

function definitions(schemaEncoding, schema) {
  if (schemaEncoding !== "ros2msg") {
    throw new Error(`unexpected schema encoding ${schemaEncoding}`);
  }
  return parse(schema, { ros2: true });
}

function sequenceOf(schemaName, message) {
  if (schemaName === "sensor_msgs/msg/Image") {
    const data = message.data;
    if (data.length < 8) return null;
    return Number(new DataView(data.buffer, data.byteOffset, 8).getBigUint64(0, true));
  }
  if (schemaName === "sensor_msgs/msg/Imu") {
    return message.orientation_covariance[1];
  }
  return null;
}

function subscribe(topic) {
  const channel = channelsByTopic.get(topic);
  if (channel === undefined) {
    pendingSubscribes.add(topic);
    return;
  }
  pendingSubscribes.delete(topic);
  if (subscriptions.has(topic)) return;
  const id = client.subscribe(channel.id);
  subscriptions.set(topic, id);
  subscriptionTopics.set(id, topic);
  emit({ event: "subscribed", topic, channel: channel.id });
}

function unsubscribe(topic) {
  pendingSubscribes.delete(topic);
  const id = subscriptions.get(topic);
  if (id === undefined) return;
  client.unsubscribe(id);
  subscriptions.delete(topic);
  subscriptionTopics.delete(id);
  emit({ event: "unsubscribed", topic });
}

function callService(command) {
  const service = services.get(command.service);
  if (service === undefined) {
    emit({ event: "error", error: `no service ${command.service}` });
    return;
  }
  const schema = service.request ? service.request.schema : service.requestSchema;
  const writer = new MessageWriter(definitions("ros2msg", schema));
  client.sendServiceCallRequest({
    serviceId: service.id, callId: command.callId, encoding: "cdr", data: new DataView(writer.writeMessage(command.request).buffer),
  });
}

let opened = false;
const queuedCommands = [];
client.on("open", () => {
  opened = true;
  emit({ event: "open", protocol: ws.protocol });
  for (const command of queuedCommands.splice(0)) run(command);
});
client.on("error", (error) => emit({ event: "error", error: String(error) }));
client.on("close", () => { emit({ event: "close" }); process.exit(0); });
client.on("serverInfo", (info) => emit({ event: "serverInfo", name: info.name, capabilities: info.capabilities,
  supportedEncodings: info.supportedEncodings }));
client.on("status", (status) => emit({ event: "status", level: status.level, message: status.message }));
client.on("time", (time) => emit({ event: "time", timestamp: Number(time.timestamp) }));

client.on("advertise", (channels) => {
  for (const channel of channels) {
    channelsByTopic.set(channel.topic, channel);
    channelsById.set(channel.id, channel);
    try {
      readers.set(channel.id, new MessageReader(definitions(channel.schemaEncoding, channel.schema)));
    } catch (error) {
      emit({ event: "error", error: `schema of ${channel.topic}: ${error}` });
    }
  }
  emit({ event: "advertise", channels: channels.map((c) => ({ id: c.id, topic: c.topic, encoding: c.encoding,
    schemaName: c.schemaName, schemaEncoding: c.schemaEncoding, schemaLength: c.schema.length })) });
  for (const topic of [...pendingSubscribes]) subscribe(topic);
});

client.on("unadvertise", (ids) => {
  const topics = [];
  for (const id of ids) {
    const channel = channelsById.get(id);
    if (channel === undefined) continue;
    topics.push(channel.topic);
    channelsById.delete(id);
    channelsByTopic.delete(channel.topic);
    readers.delete(id);
    const subscription = subscriptions.get(channel.topic);
    if (subscription !== undefined) {
      subscriptions.delete(channel.topic);
      subscriptionTopics.delete(subscription);
    }
  }
  emit({ event: "unadvertise", topics });
});

client.on("message", ({ subscriptionId, timestamp, data }) => {
  const topic = subscriptionTopics.get(subscriptionId);
  if (topic === undefined) { // arrived after the unsubscribe was sent
    emit({ event: "stray", subscriptionId });
    return;
  }
  const channel = channelsByTopic.get(topic);
  const reader = readers.get(channel.id);
  const bytes = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
  let decoded;
  try {
    decoded = reader.readMessage(bytes);
  } catch (error) {
    emit({ event: "error", error: `decoding ${topic}: ${error}` });
    return;
  }
  const sequence = sequenceOf(channel.schemaName, decoded);
  const event = { event: "message", topic, schemaName: channel.schemaName, logTime: Number(timestamp), size: bytes.length };
  if (sequence !== null) event.sequence = sequence;
  else event.fields = Object.keys(decoded);
  if (channel.schemaName === "foxglove_msgs/msg/CompressedVideo") {
    event.stamp = [decoded.timestamp.sec, decoded.timestamp.nanosec];
    event.format = decoded.format;
    event.data = Buffer.from(decoded.data.buffer, decoded.data.byteOffset, decoded.data.byteLength).toString("base64");
  }
  if (channel.schemaName === "rosgraph_msgs/msg/Clock") event.clock = decoded.clock;
  emit(event);
});

client.on("parameterValues", (event) => emit({ event: "parameterValues", id: event.id, parameters: event.parameters }));
client.on("connectionGraphUpdate", (update) => emit({ event: "connectionGraph", publishedTopics: update.publishedTopics,
  subscribedTopics: update.subscribedTopics, advertisedServices: update.advertisedServices,
  removedTopics: update.removedTopics, removedServices: update.removedServices }));
client.on("advertiseServices", (list) => {
  for (const service of list) services.set(service.name, service);
  emit({ event: "advertiseServices", services: list.map((s) => ({ id: s.id, name: s.name, type: s.type })) });
});
client.on("serviceCallResponse", (response) => {
  const service = [...services.values()].find((s) => s.id === response.serviceId);
  const schema = service.response ? service.response.schema : service.responseSchema;
  const reader = new MessageReader(definitions("ros2msg", schema));
  const bytes = new Uint8Array(response.data.buffer, response.data.byteOffset, response.data.byteLength);
  emit({ event: "serviceResponse", callId: response.callId, encoding: response.encoding, response: reader.readMessage(bytes) });
});
client.on("serviceCallFailure", (failure) => emit({ event: "serviceFailure", callId: failure.callId, message: failure.message }));

function run(command) {
  switch (command.op) {
    case "subscribe": subscribe(command.topic); break;
    case "unsubscribe": unsubscribe(command.topic); break;
    case "getParameters": client.getParameters(command.names, command.id); break;
    case "setParameters": client.setParameters(command.parameters, command.id); break;
    case "subscribeConnectionGraph": client.subscribeConnectionGraph(); break;
    case "callService": callService(command); break;
    case "close": client.close(); break;
    default: emit({ event: "error", error: `unknown command ${command.op}` });
  }
}

// Commands given before the connection is open wait for it.
const commands = readline.createInterface({ input: process.stdin });
commands.on("line", (line) => {
  if (!line.trim()) return;
  const command = JSON.parse(line);
  if (opened) run(command);
  else queuedCommands.push(command);
});
commands.on("close", () => (opened ? client.close() : queuedCommands.push({ op: "close" })));
