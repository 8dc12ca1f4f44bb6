// A viewer of a capsule_drake run, made only of Foxglove's own packages: it connects to the
// run's Foxglove WebSocket server, subscribes to every channel the server advertises,
// decodes each message with the schema the server advertised for it (ros2msg schemas, CDR
// payloads) and prints, as one JSON object, what it decoded per topic: the schema's name,
// the count, and the first message (large arrays shortened to their length).
// Usage: node client.mjs ws://127.0.0.1:PORT SECONDS [TOPIC ...]
// It ends when every named topic (and every advertised one) has a decoded message, or
// after SECONDS. With CAPSULE_CLIENT_DUMP=DIR in the environment it also writes the last
// message of each topic, whole, to DIR/<topic with / as _>.json (for a picture of what
// it saw: benchmarks/live_client_picture.py).
import wsProtocol from "@foxglove/ws-protocol";
import rosmsg from "@foxglove/rosmsg";
import serialization from "@foxglove/rosmsg2-serialization";
import WebSocket from "ws";
import fs from "node:fs";
import path from "node:path";

const { FoxgloveClient } = wsProtocol;
const { parse } = rosmsg;
const { MessageReader } = serialization;
const [url, seconds, ...wanted] = process.argv.slice(2);
const client = new FoxgloveClient({
  // foxglove-sdk's server names the protocol "foxglove.sdk.v1" (the ws-protocol spec's v1,
  // renamed); the client library still offers the older name, so both are offered.
  ws: new WebSocket(url, ["foxglove.sdk.v1", FoxgloveClient.SUPPORTED_SUBPROTOCOL]),
});
const channels = new Map(); // subscription id -> {topic, schemaName, reader}
const decoded = {};
const errors = [];

function shorten(value) {
  if (value instanceof Uint8Array || ArrayBuffer.isView(value)) return `<${value.length} values>`;
  if (Array.isArray(value)) {
    return value.length > 12 ? `<${value.length} items>` : value.map(shorten);
  }
  if (typeof value === "bigint") return Number(value);
  if (value && typeof value === "object") {
    return Object.fromEntries(Object.entries(value).map(([k, v]) => [k, shorten(v)]));
  }
  return value;
}

const dump = process.env.CAPSULE_CLIENT_DUMP;
const last = {};

function whole(value) {
  if (value instanceof Uint8Array || ArrayBuffer.isView(value)) return Array.from(value);
  if (Array.isArray(value)) return value.map(whole);
  if (typeof value === "bigint") return Number(value);
  if (value && typeof value === "object") {
    return Object.fromEntries(Object.entries(value).map(([k, v]) => [k, whole(v)]));
  }
  return value;
}

function writeDump() {
  if (!dump) return;
  fs.mkdirSync(dump, { recursive: true });
  for (const [topic, message] of Object.entries(last)) {
    fs.writeFileSync(path.join(dump, topic.replaceAll("/", "_") + ".json"),
                     JSON.stringify(whole(message)));
  }
}

function done() {
  const topics = new Set([...wanted, ...[...channels.values()].map((c) => c.topic)]);
  return topics.size > 0 && [...topics].every((t) => decoded[t]);
}

function finish(code) {
  writeDump();
  const advertised = [...channels.values()].map((c) => c.topic);
  process.stdout.write(JSON.stringify({ decoded, errors, advertised }) + "\n");
  client.close();
  process.exit(code);
}

client.on("advertise", (advertised) => {
  for (const channel of advertised) {
    try {
      if (channel.encoding !== "cdr" || channel.schemaEncoding !== "ros2msg") {
        throw new Error(`${channel.topic}: ${channel.encoding}/${channel.schemaEncoding}`);
      }
      const reader = new MessageReader(parse(channel.schema, { ros2: true }));
      const id = client.subscribe(channel.id);
      channels.set(id, { topic: channel.topic, schemaName: channel.schemaName, reader });
    } catch (e) {
      errors.push(String(e));
    }
  }
});
client.on("message", ({ subscriptionId, data }) => {
  const channel = channels.get(subscriptionId);
  if (!channel) return;
  try {
    const message = channel.reader.readMessage(data);
    if (dump) last[channel.topic] = message;
    const entry = decoded[channel.topic];
    if (entry) entry.count += 1;
    else decoded[channel.topic] = { schema: channel.schemaName, count: 1, first: shorten(message) };
  } catch (e) {
    errors.push(`${channel.topic}: ${e}`);
  }
  if (done()) finish(0);
});
client.on("error", (e) => errors.push(`connection: ${e}`));
client.on("close", () => finish(done() ? 0 : 1));
setTimeout(() => finish(1), Number(seconds) * 1000);
