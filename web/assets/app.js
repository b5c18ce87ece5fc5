// The page of `puli web`. Everything shown comes from the network (names
// of nodes and channels), so it is set as text (textContent), never as
// HTML: a node named `<img src=x onerror=...>` shows as those characters.
"use strict";

function cell(row, text, cls) {
  const td = document.createElement("td");
  td.textContent = text == null ? "" : String(text);
  if (cls) td.className = cls;
  row.appendChild(td);
  return td;
}

function showFleet(frame) {
  const body = document.querySelector("#members tbody");
  const rows = [];
  for (const m of frame.members) {
    const tr = document.createElement("tr");
    tr.className = String(m.state);
    tr.dataset.name = String(m.name);
    cell(tr, m.name, "name");
    cell(tr, m.namespace, "namespace");
    cell(tr, m.state, "state");
    cell(tr, m.address, "address");
    cell(tr, m.remote ? m.remote.site : "", "site");
    cell(tr, m.compat ? "yes" : "", "compat");
    const more = m.more_channels ? " …" : "";
    cell(tr, (m.publishes || []).join(" ") + more, "channels");
    cell(tr, (m.subscribes || []).join(" ") + more, "channels");
    rows.push(tr);
  }
  body.replaceChildren(...rows);
  const hidden = frame.truncated ? ", " + frame.truncated + " more not shown" : "";
  document.getElementById("count").textContent = "(" + rows.length + hidden + ")";
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
