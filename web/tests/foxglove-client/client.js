// A Foxglove client for puli-web's tests, as Foxglove's apps speak to a
// server: it subscribes to a channel, calls a service, gets, sets and
// follows a parameter, publishes into a channel, and follows the
// connection graph. Each thing it sees is printed as one JSON line;
// `{"event":"done"}` ends it (or a timeout). Usage:
//   node client.js URL CHANNEL SERVICE REQUEST_JSON PARAMETER VALUE_JSON PUBLISH_TOPIC PUBLISH_JSON [REFUSED_TOPIC]
// With REFUSED_TOPIC, it also publishes into that channel (ten a second)
// and waits to be told (a status naming it) why the server did not pass
// it on; then it goes on publishing for 2 s more and counts the statuses
// about it ("refusedStatuses") and the messages sent meanwhile
// ("sentAfterFirst"), to show it is told, not told for each message.
"use strict";

const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const [url, channel, service, request, parameter, value, publishTopic, publishJson, refusedTopic] = process.argv.slice(2);
const say = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");
const decoder = new TextDecoder();
const text = (view) => decoder.decode(new Uint8Array(view.buffer, view.byteOffset, view.byteLength));

// As the desktop apps (Electron pages from file://) say where they come from.
const client = new FoxgloveClient({ ws: new WebSocket(url, ["foxglove.sdk.v1"], { origin: "file://" }) });
const want = new Set(["message", "reply", "get", "set", "graph"]);
if (refusedTopic) want.add("refused");
const seen = new Set();
let sentRefused = 0;
let refusedStatuses = 0;
let firstRefusedAt = null;
const done = (what) => {
  seen.add(what);
  if ([...want].every((w) => seen.has(w))) {
    say({ event: "done", refusedStatuses, sentAfterFirst: firstRefusedAt === null ? 0 : sentRefused - firstRefusedAt });
    client.close();
    process.exit(0);
  }
};
setTimeout(() => {
  say({ event: "timeout", missing: [...want].filter((w) => !seen.has(w)) });
  process.exit(1);
}, 30000);

const subscriptions = new Map();
client.on("error", (e) => say({ event: "error", message: String(e && e.message) }));
client.on("close", (e) => say({ event: "close", code: e && e.code }));
client.on("serverInfo", (info) => {
  say({ event: "serverInfo", name: info.name, capabilities: info.capabilities });
  client.getParameters([parameter], "get");
  client.subscribeParameterUpdates([parameter]);
  client.subscribeConnectionGraph();
  // Publish into a channel: advertised, then a message every 100 ms
  // (the fleet hears of the new publisher meanwhile).
  const id = client.advertise({ topic: publishTopic, encoding: "json", schemaName: "json" });
  const data = new TextEncoder().encode(publishJson);
  setInterval(() => client.sendMessage(id, data), 100);
  if (refusedTopic) {
    const refused = client.advertise({ topic: refusedTopic, encoding: "json", schemaName: "json" });
    setInterval(() => {
      client.sendMessage(refused, data);
      sentRefused += 1;
    }, 100);
  }
});
client.on("status", (s) => {
  say({ event: "status", level: s.level, message: s.message });
  if (refusedTopic && s.message.includes(refusedTopic)) {
    refusedStatuses += 1;
    if (firstRefusedAt === null) {
      firstRefusedAt = sentRefused;
      setTimeout(() => done("refused"), 2000);
    }
  }
});
client.on("advertise", (channels) => {
  for (const c of channels) {
    if (c.topic !== channel || subscriptions.size) continue;
    say({ event: "advertised", topic: c.topic, encoding: c.encoding, schemaName: c.schemaName, schemaEncoding: c.schemaEncoding, schema: c.schema });
    subscriptions.set(client.subscribe(c.id), c.topic);
  }
});
client.on("message", (m) => {
  if (seen.has("message")) return;
  say({ event: "message", topic: subscriptions.get(m.subscriptionId), json: JSON.parse(text(m.data)) });
  done("message");
});
client.on("advertiseServices", (services) => {
  for (const s of services) {
    if (s.name !== service || seen.has("called")) continue;
    seen.add("called");
    say({ event: "service", name: s.name, request: s.request, response: s.response });
    client.sendServiceCallRequest({ serviceId: s.id, callId: 1, encoding: "json", data: new TextEncoder().encode(request) });
  }
});
client.on("serviceCallResponse", (r) => {
  say({ event: "reply", json: JSON.parse(text(r.data)) });
  done("reply");
});
client.on("serviceCallFailure", (f) => {
  say({ event: "serviceCallFailure", message: f.message });
  done("reply");
});
client.on("parameterValues", (p) => {
  say({ event: "parameterValues", id: p.id || null, parameters: p.parameters });
  if (p.id === "get") {
    done("get");
    client.setParameters([{ name: parameter, value: JSON.parse(value) }], "set");
  } else if (p.id === "set") {
    done("set");
  }
});
client.on("connectionGraphUpdate", (g) => {
  say({ event: "graph", publishedTopics: g.publishedTopics, subscribedTopics: g.subscribedTopics, advertisedServices: g.advertisedServices });
  if ((g.publishedTopics || []).some((t) => t.name === channel)) done("graph");
});
