// The stock Foxglove WebSocket client (@foxglove/ws-protocol, over the `ws` package: Node 20
// has no global WebSocket) against a live hub: connect offering only the protocol's own name,
// subscribe to every channel advertised, and keep what arrives until a sensor fault has come
// and gone (a stream message with no value for a channel, then one with it again) and an alarm
// transition has arrived, or until the deadline. Writes everything as JSON to OUT.
//
//   node foxglove_live.js URL FAULT_TOPIC FAULT_FIELD DEADLINE_S OUT
const fs = require("fs");
const WebSocket = require("ws");
const { FoxgloveClient } = require("@foxglove/ws-protocol");

const [url, faultTopic, faultField, deadlineS, out] = process.argv.slice(2);
const MAX_PER_TOPIC = 20000; // bounded, whatever the server sends
const started = Date.now();
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const channels = {};
const bySubscription = {};
const messages = {};
let serverInfo = null;
let faultSeen = false;
let faultOver = false;
let finished = false;

function finish(reason) {
  if (finished) return;
  finished = true;
  clearInterval(ticker);
  const result = {
    reason, protocol: ws.protocol, serverInfo, channels: Object.values(channels), messages,
  };
  fs.writeFileSync(out, JSON.stringify(result));
  client.close();
  setTimeout(() => process.exit(0), 200);
}

client.on("serverInfo", (info) => { serverInfo = info; });
client.on("advertise", (advertised) => {
  for (const ch of advertised) {
    channels[ch.id] = ch;
    messages[ch.topic] = [];
    bySubscription[client.subscribe(ch.id)] = ch.topic;
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const topic = bySubscription[subscriptionId];
  const text = new TextDecoder().decode(data);
  if (messages[topic].length < MAX_PER_TOPIC) {
    messages[topic].push({ log_time: timestamp.toString(), text });
  }
  if (topic === faultTopic) {
    const value = JSON.parse(text)[faultField];
    const has = value !== undefined && value !== null;
    if (!has) faultSeen = true;
    if (has && faultSeen) faultOver = true;
  }
});
client.on("error", (err) => { console.error(`client error: ${err}`); });
client.on("close", () => { if (!finished) { console.error("closed by the server"); process.exit(3); } });

const ticker = setInterval(() => {
  const alarms = (messages["/alarms"] || []).length;
  if (faultOver && alarms > 0) finish("fault seen and over, alarm seen");
  else if (Date.now() - started > Number(deadlineS) * 1000) finish("deadline");
}, 100);
