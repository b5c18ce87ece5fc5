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

function showFleet(frame) {
  last = frame;
  showMembers(frame);
  showChannels(frame);
  showServices(frame);
  showGraph(frame);
}

function connect() {
  const status = document.getElementById("status");
  const socket = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  socket.onopen = () => { status.textContent = "live"; status.className = "status live"; };
  socket.onmessage = (event) => {
    let frame;
    try { frame = JSON.parse(event.data); } catch (e) { return; }
    if (frame.kind === "fleet") showFleet(frame);
  };
  socket.onclose = () => {
    status.textContent = "connection lost: retrying";
    status.className = "status lost";
    setTimeout(connect, 1000);
  };
}

connect();
