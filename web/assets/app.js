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

function list(names, more) {
  return (names || []).join(" ") + (more ? " …" : "");
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
    cell(tr, list(c.publishers), "channels");
    cell(tr, list(c.subscribers), "channels");
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
    cell(tr, list(s.servers), "channels");
    cell(tr, list(s.clients), "channels");
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

const watched = new Map(); // channel -> its card's parts
const series = new Map(); // channel + "\u0000" + field -> {channel, field, t: [], v: []}
const PALETTE = ["#06c", "#d62", "#2a7", "#a3c", "#c93", "#2ab", "#c36", "#666"];
let paused = false;
let windowSecs = 60;
let plot = null;
let plotKeys = "";

function send(op) {
  if (socket && socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify(op));
}

function watchOnly(names) {
  send({ op: "watch", channels: names });
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
  if (!name || watched.has(name)) return;
  watchOnly([...watched.keys(), name]);
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
  close.addEventListener("click", () => watchOnly([...watched.keys()].filter((n) => n !== name)));
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
      }
    }
    if (b.last !== undefined) parts.pre.textContent = JSON.stringify(b.last, null, 2);
  }
}

function trim(now) {
  // A little more than the window, so zooming out shows no gap at once.
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
  trim(Date.now() / 1000);
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

// ---- The socket ----

function connect() {
  const status = document.getElementById("status");
  socket = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  socket.onopen = () => {
    status.textContent = "live";
    status.className = "status live";
    // Again after a reconnection: the server forgot.
    if (watched.size) watchOnly([...watched.keys()]);
  };
  socket.onmessage = (event) => {
    let frame;
    try { frame = JSON.parse(event.data); } catch (e) { return; }
    if (frame.kind === "fleet") showFleet(frame);
    else if (frame.kind === "watching") showWatching(frame);
    else if (frame.kind === "samples") showSamples(frame);
  };
  socket.onclose = () => {
    status.textContent = "connection lost: retrying";
    status.className = "status lost";
    setTimeout(connect, 1000);
  };
}

connect();
