// Reads a Foxglove WebSocket server with the Foxglove app's own client libraries:
// @foxglove/ws-protocol's FoxgloveClient (over the `ws` package: node 20 has no global
// WebSocket) for the protocol, @foxglove/rosmsg + @foxglove/rosmsg2-serialization to decode
// each message with the schema the server advertised. tests/test_bridge.py runs it against
// `ftsensord bridge`; it is also a manual check of any bridge:
//
//   node check.mjs ws://127.0.0.1:8765 --count 100 --timeout 10 /wrench/tip /wrench/tip/status
//
// stdout, one JSON object a line: {"subprotocol", "serverInfo"} once, {"advertised": [...]}
// per advertise, then per message {"topic", "schema", "log_time_ns", "message"}; 64-bit
// integers as decimal strings, non-finite floats as "NaN"/"Infinity"/"-Infinity" (JSON has
// neither). Exit 0 after --count messages on the topics; else a line "check.mjs: ..." on
// stderr and exit 1 (bad arguments 2).

// The three are CommonJS packages: node's ES modules see their exports as one default object.
import wsProtocol from "@foxglove/ws-protocol";
import rosmsg from "@foxglove/rosmsg";
import rosmsg2 from "@foxglove/rosmsg2-serialization";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;
const { parse } = rosmsg;
const { MessageReader } = rosmsg2;

// The subprotocol the foxglove-sdk server accepts; FoxgloveClient.SUPPORTED_SUBPROTOCOL is
// still the older "foxglove.websocket.v1", which that server refuses (docs/guide/clients.md).
const DEFAULT_SUBPROTOCOL = "foxglove.sdk.v1";

function usage(message) {
  process.stderr.write(`check.mjs: ${message}\n` +
    "usage: node check.mjs URL [--count N] [--timeout SECONDS] [--subprotocol NAME] TOPIC...\n");
  process.exit(2);
}

function parseArgs(argv) {
  const opts = { count: 100, timeout: 10, subprotocol: DEFAULT_SUBPROTOCOL, topics: [] };
  for (let i = 0; i < argv.length; i++) {
    const a = argv[i];
    if (a === "--count" || a === "--timeout" || a === "--subprotocol") {
      if (i + 1 >= argv.length) usage(`${a} needs a value`);
      opts[a.slice(2)] = argv[++i];
    } else if (a.startsWith("--")) {
      usage(`unknown option ${a}`);
    } else if (opts.url === undefined) {
      opts.url = a;
    } else {
      opts.topics.push(a);
    }
  }
  if (opts.url === undefined || !/^wss?:\/\//.test(opts.url)) usage("the first argument is the server's ws:// URL");
  if (opts.topics.length === 0) usage("no topics to subscribe to");
  opts.count = Number(opts.count);
  opts.timeout = Number(opts.timeout);
  if (!Number.isInteger(opts.count) || opts.count < 1) usage("--count must be a positive integer");
  if (!(opts.timeout > 0)) usage("--timeout must be a positive number of seconds");
  return opts;
}

// JSON for what the decoder returns: bigint (uint64/int64) as exact decimal strings, typed
// arrays (fixed-size float64[N] fields) as arrays, NaN/Infinity as strings.
function toJson(value) {
  return JSON.stringify(value, (_key, v) => {
    if (typeof v === "bigint") return v.toString();
    if (typeof v === "number" && !Number.isFinite(v)) return String(v);
    if (ArrayBuffer.isView(v) && !(v instanceof DataView)) return Array.from(v);
    return v;
  });
}

function emit(obj) {
  process.stdout.write(toJson(obj) + "\n");
}

function finish(code, message) {
  if (message !== undefined) process.stderr.write(`check.mjs: ${message}\n`);
  process.stdout.write("", () => process.exit(code)); // what was printed reaches the pipe first
}

const opts = parseArgs(process.argv.slice(2));
const wanted = new Set(opts.topics);
const advertised = new Set();
const subscribed = new Map(); // subscription id -> { channel, reader }
let received = 0;
let done = false;

const timer = setTimeout(() => {
  const missing = [...wanted].filter((t) => !advertised.has(t));
  finish(1, `timed out after ${opts.timeout} s: ${received} of ${opts.count} messages` +
    (missing.length ? `; never advertised: ${missing.join(", ")}` : ""));
}, opts.timeout * 1000);

const ws = new WebSocket(opts.url, [opts.subprotocol]);
const client = new FoxgloveClient({ ws });

function fail(message) {
  if (done) return;
  done = true;
  clearTimeout(timer);
  finish(1, message);
}

client.on("error", (err) => {
  const text = err instanceof Error ? err.message : String(err);
  // A refused subprotocol shows as an HTTP 400 on the upgrade: name what was asked for.
  fail(`${opts.url}: ${text} (asked for subprotocol ${opts.subprotocol})`);
});
client.on("close", (event) => fail(`the server closed the connection (code ${event?.code ?? "?"}) ` +
  `after ${received} of ${opts.count} messages`));
client.on("open", () => {
  if (ws.protocol !== opts.subprotocol) fail(`the server chose subprotocol "${ws.protocol}", not ${opts.subprotocol}`);
});
client.on("serverInfo", (info) => emit({ subprotocol: ws.protocol, serverInfo: info }));

client.on("advertise", (channels) => {
  emit({ advertised: channels.map(({ id, topic, encoding, schemaName, schemaEncoding }) =>
    ({ id, topic, encoding, schemaName, schemaEncoding })) });
  for (const channel of channels) {
    if (!wanted.has(channel.topic) || advertised.has(channel.topic)) continue;
    advertised.add(channel.topic);
    if (channel.encoding !== "cdr" || channel.schemaEncoding !== "ros2msg") {
      fail(`${channel.topic}: encoding ${channel.encoding} with schema encoding ${channel.schemaEncoding}; ` +
        "this client decodes cdr with ros2msg schemas");
      return;
    }
    let reader;
    try {
      reader = new MessageReader(parse(channel.schema, { ros2: true }));
    } catch (err) {
      fail(`${channel.topic}: the advertised ${channel.schemaName} schema does not parse: ${err.message}`);
      return;
    }
    subscribed.set(client.subscribe(channel.id), { channel, reader });
  }
});

client.on("message", ({ subscriptionId, timestamp, data }) => {
  if (done) return;
  const sub = subscribed.get(subscriptionId);
  if (sub === undefined) {
    fail(`a message for subscription ${subscriptionId}, which this client never made`);
    return;
  }
  const { channel, reader } = sub;
  let message;
  try {
    message = reader.readMessage(new Uint8Array(data.buffer, data.byteOffset, data.byteLength));
  } catch (err) {
    fail(`${channel.topic}: a message does not decode as ${channel.schemaName}: ${err.message}`);
    return;
  }
  // CDR ignores trailing bytes: left over ones mean the schema and the payload disagree.
  if (reader.lastReadHadTrailingBytes()) {
    fail(`${channel.topic}: ${data.byteLength - reader.lastReadByteLength()} bytes left after decoding ` +
      `a ${channel.schemaName}: the payload is not the advertised schema`);
    return;
  }
  emit({ topic: channel.topic, schema: channel.schemaName, log_time_ns: timestamp, message });
  if (++received >= opts.count) {
    done = true;
    clearTimeout(timer);
    // A closing handshake, so the server sees a client leave, not a reset connection;
    // a server that never answers it does not hold the exit up for long.
    ws.once("close", () => finish(0));
    setTimeout(() => finish(0), 2000);
    client.close();
  }
});
