// The page of `puli web`. Everything shown comes from the network (names
// of nodes, channels and services, types), so it is set as text
// (textContent, or an SVG text node's textContent), never as HTML: a node
// named `<img src=x onerror=...>` shows as those characters.
"use strict";

const SVG = "http://www.w3.org/2000/svg";

function cell(row, text, cls) {
  const td = document.createElement("td");
  td.textContent = text == null ? "" : String(text);
  if (cls) td.className = cls;
  row.appendChild(td);
  return td;
}

function svg(tag, attrs, parent) {
  const e = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, String(v));
  if (parent) parent.appendChild(e);
  return e;
}

// Names, and a mark where there are more: `more` is true, or how many.
function list(names, more) {
  const rest = typeof more === "number" && more > 0 ? " … +" + more : more === true ? " …" : "";
  return (names || []).join(" ") + rest;
}

function count(id, shown, truncated) {
  const hidden = truncated ? ", " + truncated + " more not shown" : "";
  document.getElementById(id).textContent = "(" + shown + hidden + ")";
}

function showMembers(frame) {
  const rows = [];
  for (const m of frame.members) {
    const tr = document.createElement("tr");
    tr.className = String(m.state);
    tr.dataset.name = String(m.name);
    cell(tr, m.name, "name");
    cell(tr, m.namespace, "namespace");
    cell(tr, m.state, "state");
    cell(tr, m.address, "address");
    cell(tr, m.site, "site");
    cell(tr, m.compat ? "yes" : "", "compat");
    cell(tr, list(m.publishes, m.more_channels), "channels");
    cell(tr, list(m.subscribes, m.more_channels), "channels");
    rows.push(tr);
  }
  document.querySelector("#members tbody").replaceChildren(...rows);
  count("count", rows.length, frame.truncated);
}

function showChannels(frame) {
  const rows = [];
  for (const c of frame.channels || []) {
    const tr = document.createElement("tr");
    tr.dataset.channel = String(c.name);
    cell(tr, c.name, "name");
    const type = cell(tr, c.type, "type");
    if (c.type_conflict) {
      type.classList.add("conflict");
      type.title = String(c.type_conflict);
    }
    cell(tr, c.rate_hz ? c.rate_hz : "", "rate");
    cell(tr, c.loss ? (100 * c.loss).toFixed(1) + " %" : "", "loss");
    cell(tr, list(c.publishers, c.publishers_more), "channels");
    cell(tr, list(c.subscribers, c.subscribers_more), "channels");
    rows.push(tr);
  }
  document.querySelector("#channels tbody").replaceChildren(...rows);
  count("channel-count", rows.length, frame.channels_truncated);
}

function showServices(frame) {
  const rows = [];
  for (const s of frame.services || []) {
    const tr = document.createElement("tr");
    tr.dataset.service = String(s.name);
    cell(tr, s.name, "name");
    let types = (s.request || "?") + " → " + (s.reply || "?");
    if (s.progress) types += " [progress " + s.progress + "]";
    if (s.sealed) types += " sealed";
    cell(tr, types, "type");
    cell(tr, list(s.servers, s.servers_more), "channels");
    cell(tr, list(s.clients, s.clients_more), "channels");
    rows.push(tr);
  }
  document.querySelector("#services tbody").replaceChildren(...rows);
  count("service-count", rows.length, frame.services_truncated);
}

// The connection graph: members on the left, channels on the right, a
// line for each publisher (solid) and subscriber (dashed). Drawn whole
// again on each frame; bounded, since a fleet of thousands is no picture.
const GRAPH_MEMBERS = 80;
const GRAPH_CHANNELS = 160;
let picked = null;

function showGraph(frame) {
  const graph = document.getElementById("graph");
  const members = [...new Set(frame.members.map((m) => String(m.name)))].slice(0, GRAPH_MEMBERS);
  const channels = (frame.channels || []).slice(0, GRAPH_CHANNELS);
  const left = frame.members.length > members.length || (frame.channels || []).length > channels.length;
  document.getElementById("graph-note").textContent = left
    ? "(the first " + members.length + " members and " + channels.length + " channels)"
    : "";
  const row = 22;
  const height = Math.max(members.length, channels.length, 1) * row + 10;
  const width = 900;
  const mx = 220, cx = 560;
  graph.setAttribute("viewBox", "0 0 " + width + " " + height);
  graph.setAttribute("height", height);
  const memberY = new Map(members.map((m, i) => [m, 14 + i * row]));
  const channelY = new Map(channels.map((c, i) => [String(c.name), 14 + i * row]));
  const edges = svg("g", { class: "edges" });
  for (const c of channels) {
    const y = channelY.get(String(c.name));
    const link = (name, kind) => {
      const my = memberY.get(String(name));
      if (my === undefined) return;
      const on = picked === null || picked === String(name) || picked === String(c.name);
      svg("path", {
        d: "M" + mx + " " + my + " C" + (mx + 160) + " " + my + " " + (cx - 160) + " " + y + " " + cx + " " + y,
        class: kind + (on ? "" : " faded"),
      }, edges);
    };
    for (const p of c.publishers || []) link(p, "pub");
    for (const s of c.subscribers || []) link(s, "sub");
  }
  const nodes = svg("g", { class: "nodes" });
  const label = (name, x, y, anchor, kind) => {
    const t = svg("text", { x: x, y: y + 4, "text-anchor": anchor, class: kind + (picked === name ? " picked" : "") }, nodes);
    t.textContent = name;
    t.dataset.name = name;
    t.addEventListener("click", () => {
      picked = picked === name ? null : name;
      showGraph(last);
    });
    svg("circle", { cx: anchor === "end" ? x + 6 : x - 6, cy: y, r: 3, class: kind }, nodes);
  };
  for (const m of members) label(m, mx - 10, memberY.get(m), "end", "member");
  for (const c of channels) label(String(c.name), cx + 10, channelY.get(String(c.name)), "start", "channel");
  graph.replaceChildren(edges, nodes);
}

let last = null;
let socket = null;

function showFleet(frame) {
  last = frame;
  showMembers(frame);
  showChannels(frame);
  showServices(frame);
  showGraph(frame);
  offerChannels(frame);
  offerPublish(frame);
  showServiceCards(frame);
}

// ---- Tabs ----

function showTab(name) {
  for (const b of document.querySelectorAll("nav .tab")) {
    b.setAttribute("aria-pressed", String(b.dataset.tab === name));
  }
  for (const page of document.querySelectorAll(".page")) {
    page.hidden = page.id !== "tab-" + name;
  }
  if (name === "channels") render(true);
}

for (const b of document.querySelectorAll("nav .tab")) {
  b.addEventListener("click", () => showTab(b.dataset.tab));
}

// ---- Channels: watched channels, their latest message, plots ----
//
// The server sends each watched channel decimated: at most 30 buckets a
// second, each with, per numeric field, [last, min, max] (a 1 kHz
// channel arrives as 30 points a second). The page keeps only the fields
// ticked for the plot, and only for the chosen window.

const watched = new Map(); // channel -> its card's parts (as the server answered)
const wanted = new Set(); // the channels asked for, sent whole each time
const MAX_WATCH = 16; // the server's bound too
const MAX_SERIES = 16; // fields plotted at once
let latest = 0; // the newest bucket's time (the server's clock), seconds
let dirty = false; // new points since the last drawing
const series = new Map(); // channel + "\u0000" + field -> {channel, field, t: [], v: []}
const PALETTE = ["#06c", "#d62", "#2a7", "#a3c", "#c93", "#2ab", "#c36", "#666"];
let paused = false;
let windowSecs = 60;
let plot = null;
let plotKeys = "";

function send(op) {
  if (socket && socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify(op));
}

function askWatch() {
  send({ op: "watch", channels: [...wanted] });
  document.getElementById("watch-add").disabled = wanted.size >= MAX_WATCH;
}

function offerChannels(frame) {
  const pick = document.getElementById("channel-pick");
  const names = (frame.channels || []).map((c) => String(c.name));
  const now = [...pick.options].map((o) => o.value);
  if (names.join("\u0000") === now.join("\u0000")) return;
  const chosen = pick.value;
  const options = names.map((n) => {
    const o = document.createElement("option");
    o.value = n;
    o.textContent = n;
    return o;
  });
  pick.replaceChildren(...options);
  if (names.includes(chosen)) pick.value = chosen;
}

document.getElementById("watch-add").addEventListener("click", () => {
  const name = document.getElementById("channel-pick").value;
  if (!name || wanted.has(name) || wanted.size >= MAX_WATCH) return;
  wanted.add(name);
  askWatch();
});

document.getElementById("window").addEventListener("change", (e) => {
  windowSecs = Number(e.target.value) || 60;
  render(true);
});

function setPaused(on) {
  paused = on;
  document.getElementById("pause").textContent = on ? "resume" : "pause";
  if (!on) render(true);
}

document.getElementById("pause").addEventListener("click", () => setPaused(!paused));

function card(name) {
  const box = document.createElement("div");
  box.className = "card";
  box.dataset.channel = name;
  const h = document.createElement("h3");
  const title = document.createElement("span");
  title.className = "name";
  title.textContent = name;
  const type = document.createElement("span");
  type.className = "note type";
  const rate = document.createElement("span");
  rate.className = "note rate";
  const note = document.createElement("span");
  note.className = "note dropped";
  const close = document.createElement("button");
  close.type = "button";
  close.textContent = "×";
  close.title = "stop watching";
  close.addEventListener("click", () => {
    wanted.delete(name);
    askWatch();
  });
  h.append(title, type, rate, note, close);
  const fields = document.createElement("div");
  fields.className = "fields";
  const pre = document.createElement("pre");
  pre.className = "last";
  box.append(h, fields, pre);
  document.getElementById("watched").appendChild(box);
  return { box, type, rate, note, fields, pre, boxes: new Map(), counts: [] };
}

function showWatching(frame) {
  const names = (frame.channels || []).map(String);
  for (const [name, parts] of watched) {
    if (!names.includes(name)) {
      parts.box.remove();
      watched.delete(name);
      for (const key of [...series.keys()]) if (series.get(key).channel === name) series.delete(key);
    }
  }
  for (const name of names) if (!watched.has(name)) watched.set(name, card(name));
  const refused = Object.entries(frame.refused || {});
  // What the server would not watch is no longer asked for.
  for (const [name] of refused) wanted.delete(name);
  document.getElementById("watch-add").disabled = wanted.size >= MAX_WATCH;
  document.getElementById("plot-note").textContent = refused.length
    ? "not watched: " + refused.map(([n, why]) => n + " (" + why + ")").join("; ")
    : watched.size ? "" : "Watch a channel, then tick the fields to plot.";
  render(true);
}

function fieldBox(parts, channel, field) {
  let box = parts.boxes.get(field);
  if (box) return box;
  const label = document.createElement("label");
  box = document.createElement("input");
  box.type = "checkbox";
  box.dataset.field = field;
  box.addEventListener("change", () => {
    const key = channel + "\u0000" + field;
    if (box.checked && series.size >= MAX_SERIES) {
      box.checked = false;
      document.getElementById("plot-note").textContent = "at most " + MAX_SERIES + " fields on the plot";
      return;
    }
    if (box.checked) series.set(key, { channel, field, t: [], v: [] });
    else series.delete(key);
    render(true);
  });
  const text = document.createElement("span");
  text.textContent = field;
  label.append(box, text);
  parts.fields.appendChild(label);
  parts.boxes.set(field, box);
  return box;
}

function showSamples(frame) {
  const dropped = frame.dropped || {};
  for (const b of frame.buckets || []) {
    const channel = String(b.channel);
    const parts = watched.get(channel);
    if (!parts) continue;
    const t = Number(b.t) / 1000;
    parts.counts.push([t, Number(b.n) || 0]);
    while (parts.counts.length && parts.counts[0][0] < t - 1) parts.counts.shift();
    const perSecond = parts.counts.reduce((sum, c) => sum + c[1], 0);
    parts.rate.textContent = perSecond + " msg/s";
    if (b.type) parts.type.textContent = String(b.type);
    const lost = dropped[channel];
    parts.note.textContent = (lost ? lost + " buckets dropped (slow page) " : "")
      + (b.left_out ? b.left_out + " fields not plotted" : "");
    for (const [field, agg] of Object.entries(b.v || {})) {
      fieldBox(parts, channel, field);
      const s = series.get(channel + "\u0000" + field);
      if (s && Array.isArray(agg)) {
        s.t.push(t);
        s.v.push(Number(agg[0]));
        dirty = true;
      }
    }
    if (b.last !== undefined) parts.pre.textContent = JSON.stringify(b.last, null, 2);
    if (t > latest) latest = t;
  }
  // Kept for the window only, paused or not, shown or not.
  trim(latest);
}

function trim(now) {
  const from = now - windowSecs;
  for (const s of series.values()) {
    let i = 0;
    while (i < s.t.length && s.t[i] < from) i++;
    if (i > 0) {
      s.t.splice(0, i);
      s.v.splice(0, i);
    }
  }
}

function render(force) {
  const box = document.getElementById("plot");
  if (box.closest(".page").hidden) return;
  if (paused && !force) return;
  if (!dirty && !force) return;
  dirty = false;
  trim(latest);
  const shown = [...series.values()].filter((s) => s.t.length > 0);
  box.dataset.points = String(shown.reduce((n, s) => n + s.t.length, 0));
  const keys = shown.map((s) => s.channel + "\u0000" + s.field).join("\u0001");
  if (!shown.length) {
    if (plot) plot.destroy();
    plot = null;
    plotKeys = "";
    return;
  }
  const data = uPlot.join(shown.map((s) => [s.t, s.v]));
  if (!plot || keys !== plotKeys) {
    if (plot) plot.destroy();
    plotKeys = keys;
    plot = new uPlot({
      width: Math.max(box.clientWidth, 600),
      height: 320,
      scales: { x: { time: true } },
      series: [{}].concat(shown.map((s, i) => ({
        label: s.channel + " " + s.field,
        stroke: PALETTE[i % PALETTE.length],
        width: 1.5,
        spanGaps: true,
      }))),
      cursor: { drag: { x: true, y: false } },
      hooks: { setSelect: [(u) => { if (u.select.width > 0) setPaused(true); }] },
    }, data, box);
    return;
  }
  if (!paused) plot.setData(data);
}

setInterval(() => render(false), 100);

// ---- Settings: a control per setting, from what its owner says of it ----
//
// A range its check gives makes a slider, a one-of a choice, a bool a
// checkbox, anything else a box (JSON for a native setting). A change is
// asked of the owner; its refusal shows with the owner's reason. The
// server sends the settings again whenever they change, a change made
// elsewhere included.

const settingRows = new Map(); // name -> the row's parts
let nextId = 1;
const waiting = new Map(); // request id -> setting name

function askSetting(name, op, extra) {
  const id = nextId++;
  waiting.set(id, name);
  const parts = settingRows.get(name);
  if (parts) {
    parts.status.textContent = "asking…";
    parts.status.className = "status-cell asking";
    parts.busy = true;
  }
  send(Object.assign({ op: op, id: id, name: name }, extra));
}

function controlOf(s) {
  const name = String(s.name);
  if (s.read_only) {
    const span = document.createElement("span");
    span.className = "read-only";
    return { el: span, show: (v) => { span.textContent = v; } };
  }
  const numeric = s.kind === "int" || s.kind === "float";
  if (numeric && typeof s.min === "number" && typeof s.max === "number" && s.max > s.min) {
    const wrap = document.createElement("span");
    const range = document.createElement("input");
    range.type = "range";
    range.min = String(s.min);
    range.max = String(s.max);
    range.step = s.kind === "int" ? "1" : String((s.max - s.min) / 1000);
    range.dataset.setting = name;
    const out = document.createElement("output");
    range.addEventListener("input", () => { out.textContent = range.value; });
    range.addEventListener("change", () => askSetting(name, "set", { text: range.value }));
    wrap.append(range, out);
    return {
      el: wrap,
      input: range,
      show: (v, s) => {
        if (typeof s.value === "number") range.value = String(s.value);
        out.textContent = v;
      },
    };
  }
  if ((s.one_of || []).length) {
    const select = document.createElement("select");
    select.dataset.setting = name;
    for (const choice of s.one_of) {
      const o = document.createElement("option");
      o.value = String(choice);
      o.textContent = String(choice);
      select.appendChild(o);
    }
    select.addEventListener("change", () => askSetting(name, "set", { text: select.value }));
    return { el: select, input: select, show: (v, s) => { if (s.value !== null) select.value = String(s.value); } };
  }
  if (s.kind === "bool") {
    const box = document.createElement("input");
    box.type = "checkbox";
    box.dataset.setting = name;
    box.addEventListener("change", () => askSetting(name, "set", { text: String(box.checked) }));
    return { el: box, input: box, show: (v, s) => { box.checked = s.value === true; } };
  }
  const box = document.createElement("input");
  box.type = "text";
  box.dataset.setting = name;
  box.placeholder = s.kind === "native" ? "JSON" : "";
  box.addEventListener("keydown", (e) => {
    if (e.key !== "Enter") return;
    if (s.kind !== "native") return askSetting(name, "set", { text: box.value });
    let value;
    try { value = JSON.parse(box.value); } catch (err) {
      const parts = settingRows.get(name);
      if (parts) { parts.status.textContent = "not JSON: " + err.message; parts.status.className = "status-cell refused"; }
      return;
    }
    askSetting(name, "set", { json: value });
  });
  return {
    el: box,
    input: box,
    show: (v, s) => { box.value = s.kind === "native" && s.value !== null ? JSON.stringify(s.value) : (v === "?" ? "" : v); },
  };
}

function controlShape(s) {
  return JSON.stringify([s.kind, s.read_only, s.min, s.max, s.one_of]);
}

function settingRow(s) {
  const tr = document.createElement("tr");
  tr.dataset.setting = String(s.name);
  const parts = { tr, busy: false, shape: "" };
  parts.name = cell(tr, s.name, "name");
  parts.valueCell = cell(tr, "", "value");
  parts.unit = cell(tr, "", "unit");
  parts.about = cell(tr, "", "about");
  parts.owner = cell(tr, "", "owner");
  const actions = cell(tr, "", "actions");
  const reset = document.createElement("button");
  reset.type = "button";
  reset.textContent = "reset";
  reset.title = "back to the owner's default";
  reset.addEventListener("click", () => askSetting(String(s.name), "reset", {}));
  actions.appendChild(reset);
  parts.status = cell(tr, "", "status-cell");
  return parts;
}

function showSettings(frame) {
  const names = new Set();
  const body = document.querySelector("#settings tbody");
  const rows = [];
  for (const s of frame.settings || []) {
    const name = String(s.name);
    names.add(name);
    let parts = settingRows.get(name);
    if (!parts) {
      parts = settingRow(s);
      settingRows.set(name, parts);
    }
    const shape = controlShape(s);
    if (shape !== parts.shape) {
      parts.shape = shape;
      parts.control = controlOf(s);
      parts.valueCell.replaceChildren(parts.control.el);
    }
    const text = s.text == null ? "?" : String(s.text);
    // Not under the operator's hand, nor while a change is asked.
    const editing = parts.control.input && document.activeElement === parts.control.input;
    if (!editing && !parts.busy) parts.control.show(text, s);
    parts.valueCell.dataset.value = text;
    parts.last = s;
    parts.unit.textContent = s.unit || "";
    parts.about.textContent = s.description || "";
    let owner = (s.owners || []).join(", ");
    if (s.locked) owner += " (locked: two owners)";
    else if (s.stale) owner += " (gone)";
    parts.owner.textContent = owner;
    // A change confirmed here says so while the value is the one set; a
    // refusal stays until the next change asked.
    const said = parts.status.classList;
    const confirmedHere = said.contains("done") && text === parts.confirmedText;
    if (!parts.busy && !said.contains("refused") && !confirmedHere) {
      parts.status.textContent = s.refusal ? "last refused: " + s.refusal : "";
      parts.status.className = "status-cell";
    }
    rows.push(parts.tr);
  }
  for (const name of [...settingRows.keys()]) if (!names.has(name)) settingRows.delete(name);
  body.replaceChildren(...rows);
  count("setting-count", rows.length, frame.truncated);
  document.getElementById("settings-note").textContent = frame.spent
    ? "This server has asked as many settings as one client may: restart it to see new ones."
    : "";
}

function showDone(frame) {
  const name = waiting.get(frame.id);
  waiting.delete(frame.id);
  const parts = settingRows.get(String(frame.name || name));
  if (!parts) return;
  parts.busy = false;
  if (frame.ok) {
    parts.confirmedText = frame.text == null ? "?" : String(frame.text);
    parts.status.textContent = "set: " + (frame.text == null ? "" : frame.text);
    parts.status.className = "status-cell done";
  } else {
    parts.status.textContent = (frame.refused ? "refused: " : "failed: ") + String(frame.error);
    parts.status.className = "status-cell refused";
    // The owner's value, not the one it refused.
    if (parts.last) parts.control.show(parts.valueCell.dataset.value, parts.last);
  }
}

// ---- Forms from a JSON Schema (a request's, a message's type) ----
//
// An object's fields and a tuple's items get an input each (a number, a
// checkbox, a text); anything deeper is a JSON box. The form's value is
// the JSON its inputs make.

function scalarKind(schema) {
  if (!schema || typeof schema !== "object") return null;
  if (schema.type === "number") return "number";
  if (schema.type === "integer") return "integer";
  if (schema.type === "boolean") return "boolean";
  if (schema.type === "string" && !schema.contentEncoding) return "string";
  if (Array.isArray(schema.anyOf) && schema.anyOf.some((s) => s && s.type === "integer")) return "integer";
  return null;
}

function scalarInput(kind, name) {
  const input = document.createElement("input");
  input.dataset.field = name;
  if (kind === "boolean") {
    input.type = "checkbox";
    return { el: input, value: () => input.checked };
  }
  if (kind === "number" || kind === "integer") {
    input.type = "number";
    input.step = kind === "integer" ? "1" : "any";
    input.value = "0";
    return {
      el: input,
      value: () => {
        const n = Number(input.value);
        // An integer too large for a double travels as its digits.
        return kind === "integer" && !Number.isSafeInteger(n) ? input.value.trim() : n;
      },
    };
  }
  input.type = "text";
  return { el: input, value: () => input.value };
}

function jsonInput(name, initial) {
  const box = document.createElement("textarea");
  box.dataset.field = name;
  box.rows = 3;
  box.value = initial;
  return { el: box, value: () => JSON.parse(box.value) };
}

function formFor(schema) {
  const wrap = document.createElement("div");
  wrap.className = "fields-form";
  const row = (label, input) => {
    const l = document.createElement("label");
    const t = document.createElement("span");
    t.textContent = label;
    l.append(t, input.el);
    wrap.appendChild(l);
  };
  const kind = scalarKind(schema);
  if (kind) {
    const input = scalarInput(kind, "value");
    row("value", input);
    return { el: wrap, value: input.value };
  }
  if (schema && schema.type === "object" && schema.properties && typeof schema.properties === "object") {
    const inputs = [];
    for (const [name, field] of Object.entries(schema.properties)) {
      const k = scalarKind(field);
      const input = k ? scalarInput(k, name) : jsonInput(name, "null");
      row(name, input);
      inputs.push([name, input]);
    }
    return { el: wrap, value: () => Object.fromEntries(inputs.map(([n, i]) => [n, i.value()])) };
  }
  if (schema && Array.isArray(schema.prefixItems)) {
    const inputs = schema.prefixItems.map((item, i) => {
      const k = scalarKind(item);
      const input = k ? scalarInput(k, String(i)) : jsonInput(String(i), "null");
      row("[" + i + "]", input);
      return input;
    });
    return { el: wrap, value: () => inputs.map((i) => i.value()) };
  }
  const input = jsonInput("json", "null");
  row("JSON", input);
  return { el: wrap, value: input.value };
}

const schemaWaiters = new Map(); // "of\u0000name" -> callbacks

function askSchema(of, name, then) {
  const key = of + "\u0000" + name;
  if (!schemaWaiters.has(key)) schemaWaiters.set(key, []);
  schemaWaiters.get(key).push(then);
  send({ op: "schema", of: of, name: name });
}

function showSchema(frame) {
  const key = String(frame.of) + "\u0000" + String(frame.name);
  const waiting = schemaWaiters.get(key) || [];
  schemaWaiters.delete(key);
  for (const then of waiting) then(frame);
}

// ---- Publish ----

let publishForm = null;

function offerPublish(frame) {
  const pick = document.getElementById("publish-pick");
  const names = (frame.channels || []).map((c) => String(c.name));
  const now = [...pick.options].map((o) => o.value);
  if (names.join("\u0000") === now.join("\u0000")) return;
  const chosen = pick.value;
  pick.replaceChildren(...names.map((n) => {
    const o = document.createElement("option");
    o.value = n;
    o.textContent = n;
    return o;
  }));
  if (names.includes(chosen)) pick.value = chosen;
  else pickPublish();
}

function pickPublish() {
  const name = document.getElementById("publish-pick").value;
  const box = document.getElementById("publish-form");
  publishForm = null;
  box.replaceChildren();
  if (!name) return;
  askSchema("channel", name, (answer) => {
    if (document.getElementById("publish-pick").value !== name) return;
    document.getElementById("publish-type").textContent = answer.type ? String(answer.type) : "no type announced";
    publishForm = formFor(answer.schema);
    box.replaceChildren(publishForm.el);
  });
}

document.getElementById("publish-pick").addEventListener("change", pickPublish);

document.getElementById("publish-send").addEventListener("click", () => {
  const status = document.getElementById("publish-status");
  const channel = document.getElementById("publish-pick").value;
  if (!publishForm || !channel) return;
  let value;
  try { value = publishForm.value(); } catch (e) {
    status.textContent = "not JSON: " + e.message;
    status.className = "status-cell refused";
    return;
  }
  status.textContent = "publishing…";
  status.className = "status-cell asking";
  send({ op: "publish", id: nextId++, channel: channel, value: value });
});

function showPublished(frame) {
  const status = document.getElementById("publish-status");
  status.textContent = frame.ok ? "published on " + String(frame.channel) : "not published: " + String(frame.error);
  status.className = "status-cell " + (frame.ok ? "done" : "refused");
}

// ---- Services: a card per service, a form from its request type ----

const serviceCards = new Map(); // service -> its card's parts
const calls = new Map(); // call id -> what shows it
const MAX_PROGRESS_LINES = 20;

function startCall(service, target, request, show) {
  const id = nextId++;
  calls.set(id, show);
  show.begin(id);
  const op = { op: "call", id: id, service: service, request: request };
  if (target) op.target = target;
  send(op);
  return id;
}

function callView(out, cancel) {
  return {
    id: null,
    begin(id) {
      this.id = id;
      out.replaceChildren();
      out.className = "call-out asking";
      this.line("calling…");
      if (cancel) cancel.disabled = false;
    },
    line(text, cls) {
      const p = document.createElement("div");
      p.textContent = text;
      if (cls) p.className = cls;
      out.appendChild(p);
      while (out.childNodes.length > MAX_PROGRESS_LINES) out.removeChild(out.firstChild);
    },
    end(cls) {
      out.className = "call-out " + cls;
      if (cancel) cancel.disabled = true;
    },
  };
}

function showCall(frame) {
  const show = calls.get(frame.id);
  if (!show) return;
  const json = (v) => JSON.stringify(v);
  switch (frame.event) {
    case "started": show.line("at " + String(frame.node)); break;
    case "progress": show.line("progress " + json(frame.value), "progress"); break;
    case "reply":
      show.line("reply " + json(frame.value) + (frame.missed_progress ? " (" + frame.missed_progress + " progress missed)" : ""), "reply");
      show.end("done");
      calls.delete(frame.id);
      break;
    case "failed":
      show.line(frame.code !== undefined
        ? "fault " + frame.code + ": " + String(frame.message) + " (at " + String(frame.node) + ")"
        : "failed: " + String(frame.error), "fault");
      show.end("refused");
      calls.delete(frame.id);
      break;
    case "cancelled":
      show.line("cancelled", "fault");
      show.end("refused");
      calls.delete(frame.id);
      break;
  }
}

function serviceCard(s) {
  const name = String(s.name);
  const box = document.createElement("div");
  box.className = "card";
  box.dataset.service = name;
  const h = document.createElement("h3");
  const title = document.createElement("span");
  title.className = "name";
  title.textContent = name;
  const types = document.createElement("span");
  types.className = "note";
  h.append(title, types);
  const controls = document.createElement("div");
  controls.className = "controls";
  const targetLabel = document.createElement("label");
  const targetText = document.createElement("span");
  targetText.textContent = "server ";
  const target = document.createElement("select");
  target.className = "target";
  targetLabel.append(targetText, target);
  const call = document.createElement("button");
  call.type = "button";
  call.className = "call";
  call.textContent = "call";
  const cancel = document.createElement("button");
  cancel.type = "button";
  cancel.className = "cancel";
  cancel.textContent = "cancel";
  cancel.disabled = true;
  const save = document.createElement("button");
  save.type = "button";
  save.className = "save";
  save.textContent = "save as a button";
  controls.append(targetLabel, call, cancel, save);
  const formBox = document.createElement("div");
  formBox.className = "form";
  const out = document.createElement("div");
  out.className = "call-out";
  box.append(h, formBox, controls, out);
  const parts = { box, types, target, formBox, out, form: null, view: callView(out, cancel) };
  const request = () => {
    try { return { ok: true, value: parts.form ? parts.form.value() : null }; } catch (e) {
      out.replaceChildren();
      parts.view.line("not JSON: " + e.message, "fault");
      return { ok: false };
    }
  };
  call.addEventListener("click", () => {
    const r = request();
    if (r.ok) startCall(name, target.value || null, r.value, parts.view);
  });
  cancel.addEventListener("click", () => {
    if (parts.view.id !== null) send({ op: "cancel", id: parts.view.id });
  });
  save.addEventListener("click", () => {
    const r = request();
    if (!r.ok) return;
    saveButton({ service: name, target: target.value || null, request: r.value });
  });
  parts.ask = () => askSchema("service", name, (answer) => {
    parts.form = formFor(answer.schema);
    formBox.replaceChildren(parts.form.el);
  });
  return parts;
}

function showServiceCards(frame) {
  const list = document.getElementById("service-cards");
  const names = new Set();
  const boxes = [];
  for (const s of frame.services || []) {
    const name = String(s.name);
    names.add(name);
    let parts = serviceCards.get(name);
    if (!parts) {
      parts = serviceCard(s);
      serviceCards.set(name, parts);
    }
    let types = (s.request || "?") + " → " + (s.reply || "?");
    if (s.progress) types += ", progress " + s.progress;
    // The form again when the servers announce another type.
    if (parts.types.textContent !== types) parts.ask();
    parts.types.textContent = types;
    const servers = ["", ...(s.servers || []).map(String)];
    const now = [...parts.target.options].map((o) => o.value);
    if (servers.join("\u0000") !== now.join("\u0000")) {
      const chosen = parts.target.value;
      parts.target.replaceChildren(...servers.map((n) => {
        const o = document.createElement("option");
        o.value = n;
        o.textContent = n || "any";
        return o;
      }));
      if (servers.includes(chosen)) parts.target.value = chosen;
    }
    boxes.push(parts.box);
  }
  for (const name of [...serviceCards.keys()]) if (!names.has(name)) serviceCards.delete(name);
  list.replaceChildren(...boxes);
  count("service-card-count", boxes.length, frame.services_truncated);
}

// Saved buttons (after SORMA's scottwish): a call, its server and its
// request, kept in this browser's localStorage, one click to run.
const BUTTONS_KEY = "puli-web-buttons";
const MAX_BUTTONS = 50;

function loadButtons() {
  try {
    const saved = JSON.parse(localStorage.getItem(BUTTONS_KEY) || "[]");
    return Array.isArray(saved) ? saved.filter((b) => b && typeof b.service === "string").slice(0, MAX_BUTTONS) : [];
  } catch (e) {
    return [];
  }
}

function storeButtons(buttons) {
  try { localStorage.setItem(BUTTONS_KEY, JSON.stringify(buttons)); } catch (e) { /* full or off: kept for now */ }
}

let buttons = loadButtons();

function saveButton(b) {
  if (buttons.length >= MAX_BUTTONS) return;
  b.label = b.service + (b.target ? "@" + b.target : "") + " " + JSON.stringify(b.request);
  buttons.push(b);
  storeButtons(buttons);
  showButtons();
}

function showButtons() {
  const panel = document.getElementById("buttons");
  const items = buttons.map((b, i) => {
    const wrap = document.createElement("div");
    wrap.className = "saved";
    const go = document.createElement("button");
    go.type = "button";
    go.className = "run";
    go.textContent = String(b.label);
    const drop = document.createElement("button");
    drop.type = "button";
    drop.textContent = "×";
    drop.title = "forget this button";
    const out = document.createElement("div");
    out.className = "call-out";
    const view = callView(out, null);
    go.addEventListener("click", () => startCall(String(b.service), b.target ? String(b.target) : null, b.request, view));
    drop.addEventListener("click", () => {
      buttons.splice(i, 1);
      storeButtons(buttons);
      showButtons();
    });
    wrap.append(go, drop, out);
    return wrap;
  });
  if (!items.length) {
    const none = document.createElement("p");
    none.className = "note";
    none.textContent = "none yet: fill a service's form and save it as a button";
    items.push(none);
  }
  panel.replaceChildren(...items);
}

showButtons();

// ---- The socket ----

function connect() {
  const status = document.getElementById("status");
  socket = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  socket.onopen = () => {
    status.textContent = "live";
    status.className = "status live";
    // Again after a reconnection: the server forgot.
    if (wanted.size) askWatch();
  };
  socket.onmessage = (event) => {
    let frame;
    try { frame = JSON.parse(event.data); } catch (e) { return; }
    if (frame.kind === "fleet") showFleet(frame);
    else if (frame.kind === "watching") showWatching(frame);
    else if (frame.kind === "samples") showSamples(frame);
    else if (frame.kind === "settings") showSettings(frame);
    else if (frame.kind === "done") showDone(frame);
    else if (frame.kind === "call") showCall(frame);
    else if (frame.kind === "schema") showSchema(frame);
    else if (frame.kind === "published") showPublished(frame);
  };
  socket.onclose = () => {
    status.textContent = "connection lost: retrying";
    status.className = "status lost";
    setTimeout(connect, 1000);
  };
}

connect();
