// The VL-Map fleet dashboard (served at /dashboard; docs/api.md). Plain JavaScript, no dependency.
//
// One push stream (GET /v1/events, read with fetch() because EventSource cannot send the key) tells the page
// of every belief version of every session the key may read; the page then reads what changed, one request
// of each kind at a time per session (a session at sensor rate is shown at the rate the page can follow, not
// queued): the summary (information gain, MAP voxel, mean and covariance, mass per place), the top-down mass
// (GET .../belief/topdown: nx * ny floats rather than the whole grid), the scene graph after a replacement.
// The utterances come with their events; GET .../utterances gives those from before the page opened.

const KEY = "vlmap.viewerKey";
const ROOT = new URL(".", location.href); // the service's root, also behind a proxy's path prefix
const DECADES = 4; // the heat map's log scale spans this many decades below the largest column
const [MAP_WIDTH, MAP_HEIGHT] = [640, 640]; // the most the map takes on the page (px)
const SHOWN_PLACES = 8; // places listed per table, those of at least 0.001 of the mass
const GONE = "This session is gone (deleted, or expired after its idle time).";

const $ = (id) => document.getElementById(id);

class AuthError extends Error {} // 401: no key, or one the service does not know
class Forbidden extends Error {} // 403: a known key that may not read this (another robot's session)
class NotFound extends Error {} // a session read answered 404: deleted or expired

const state = {
  key: null,
  sessions: new Map(), // id -> {id, robot_id, target_label, version, updated_at, information_gain}
  selected: null,
  view: null, // the selected session: see select()
  stream: null, // AbortController of the push stream
  firstPaint: false,
};

// -- HTTP ----------------------------------------------------------------------------------------------------

function headers(extra = {}) {
  return state.key ? { Authorization: `Bearer ${state.key}`, ...extra } : extra;
}

/** GET a JSON answer; null for 304 Not Modified (with `etag`: the version already held). */
async function getJSON(path, etag = null) {
  const response = await fetch(new URL(path, ROOT), {
    headers: headers(etag ? { "If-None-Match": etag } : {}),
    cache: "no-store",
  });
  if (response.status === 304) return null;
  if (response.status === 401 || response.status === 403) {
    const body = await response.json().catch(() => ({}));
    const message = body.message || `HTTP ${response.status}`;
    throw response.status === 401 ? new AuthError(message) : new Forbidden(message);
  }
  if (response.status === 404) throw new NotFound(`${path}: HTTP 404`);
  if (!response.ok) throw new Error(`${path}: HTTP ${response.status}`);
  return response.json();
}

/** Runs `task` at most once at a time: a request while it runs makes it run once more when it is done. */
class Coalesced {
  constructor(task) {
    this.task = task;
    this.running = false;
    this.again = false;
  }

  request() {
    if (this.running) {
      this.again = true;
      return;
    }
    this.running = true;
    this.task()
      .catch(report)
      .finally(() => {
        this.running = false;
        if (this.again) {
          this.again = false;
          this.request();
        }
      });
  }
}

// -- the push stream -----------------------------------------------------------------------------------------

/**
 * Follow a Server-Sent Events stream with fetch(), resuming with Last-Event-ID after a break; `onResume` is
 * called each time a stream resumes (the server sends no sync then).
 */
async function follow(path, signal, onEvent, onResume) {
  let last = null;
  let retryMs = 1000;
  while (!signal.aborted) {
    try {
      const extra = { Accept: "text/event-stream" };
      if (last) extra["Last-Event-ID"] = last;
      const response = await fetch(new URL(path, ROOT), { headers: headers(extra), cache: "no-store", signal });
      if (response.status === 401 || response.status === 403) {
        askForKey(`the push stream answered HTTP ${response.status}`);
        return;
      }
      if (!response.ok) throw new Error(`push stream: HTTP ${response.status}`);
      setStatus("live", "live");
      if (last) onResume();
      const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
      let buffer = "";
      let frame = {};
      for (let chunk; !(chunk = await reader.read()).done; ) {
        const lines = (buffer + chunk.value).split("\n");
        buffer = lines.pop();
        for (const raw of lines) {
          const line = raw.replace(/\r$/, "");
          if (line === "") {
            if (frame.data !== undefined) {
              if (frame.id) last = frame.id;
              onEvent(frame.event || "message", JSON.parse(frame.data), frame.id);
            }
            frame = {};
          } else if (!line.startsWith(":")) {
            const at = line.indexOf(":");
            const field = at < 0 ? line : line.slice(0, at);
            const value = at < 0 ? "" : line.slice(at + 1).replace(/^ /, "");
            if (field === "retry" && /^\d+$/.test(value)) retryMs = Number(value);
            else if (field === "data") frame.data = frame.data === undefined ? value : `${frame.data}\n${value}`;
            else frame[field] = value;
          }
        }
      }
    } catch (error) {
      if (signal.aborted) return;
      console.warn("push stream", error);
    }
    setStatus("reconnecting", "broken");
    await new Promise((resume) => setTimeout(resume, retryMs));
  }
}

function onEvent(name, data, id) {
  if (name === "sync") {
    // Events may have been missed: read the state again.
    loadSessions().catch(report);
    if (state.view) {
      state.view.refresh.request();
      state.view.history.request();
    }
    return;
  }
  if (name !== "belief") return;
  const kind = data.cause.kind;
  if (kind === "deleted") {
    dropSession(data.session_id, "This session was deleted.");
    return;
  }
  const known = state.sessions.get(data.session_id);
  const row = known || { id: data.session_id, information_gain: null, refresh: null };
  Object.assign(row, {
    robot_id: data.robot_id,
    target_label: data.target_label || null,
    version: Math.max(data.version, known ? known.version : 0),
    updated_at: data.updated_at,
  });
  state.sessions.set(row.id, row);
  summaryOf(row);
  renderSessions();
  const view = state.view;
  if (view && view.id === data.session_id) {
    if (kind === "utterance") addUtterance(view, { event_id: id, version: data.version, updated_at: data.updated_at, ...data.cause });
    if (kind === "scene_graph") view.sceneGraphStale = true;
    view.refresh.request();
  }
}

// -- the session list ----------------------------------------------------------------------------------------

async function loadSessions() {
  const answer = await getJSON("v1/sessions");
  const fresh = new Map();
  for (const s of answer.sessions) {
    const row = state.sessions.get(s.id) || { id: s.id, information_gain: null, refresh: null };
    Object.assign(row, { robot_id: s.robot_id, target_label: s.target_label, version: s.version, updated_at: s.updated_at });
    fresh.set(s.id, row);
    summaryOf(row);
  }
  state.sessions = fresh;
  renderSessions();
}

/** Read a session's summary for its row (the information gain), coalesced per session. */
function summaryOf(row) {
  if (state.view && state.view.id === row.id) return; // the detail view reads it anyway
  row.refresh ||= new Coalesced(async () => {
    let summary;
    try {
      summary = await getJSON(`v1/sessions/${encodeURIComponent(row.id)}/belief`);
    } catch (error) {
      if (!(error instanceof NotFound)) throw error;
      dropSession(row.id, GONE);
      return;
    }
    row.information_gain = summary.summary.information_gain_nats;
    renderSessions();
  });
  row.refresh.request();
}

/**
 * Take a session off the list, saying `message` where it is the one selected. An expired session has no
 * event: a 404 on one of its reads, or its absence from the list read again when the stream resumes, is how
 * the page learns it is gone.
 */
function dropSession(id, message) {
  state.sessions.delete(id);
  if (state.selected === id) $("detail-meta").textContent = message;
  renderSessions();
}

function ago(unixSeconds) {
  const s = Math.max(0, Date.now() / 1000 - unixSeconds);
  if (s < 60) return `${s.toFixed(0)} s ago`;
  if (s < 3600) return `${(s / 60).toFixed(0)} min ago`;
  return `${(s / 3600).toFixed(1)} h ago`;
}

function cell(tr, text, className) {
  const td = tr.insertCell();
  td.textContent = text;
  if (className) td.className = className;
  return td;
}

let renderQueued = false;
function renderSessions() {
  if (renderQueued) return;
  renderQueued = true;
  requestAnimationFrame(() => {
    renderQueued = false;
    const byRobot = new Map();
    for (const row of state.sessions.values()) {
      if (!byRobot.has(row.robot_id)) byRobot.set(row.robot_id, []);
      byRobot.get(row.robot_id).push(row);
    }
    const robots = $("robots");
    robots.replaceChildren();
    for (const robot of [...byRobot.keys()].sort()) {
      const title = document.createElement("h4");
      title.textContent = robot;
      const table = document.createElement("table");
      const head = table.createTHead().insertRow();
      for (const name of ["session", "target", "version", "last update", "info gain (nats)"]) {
        const th = document.createElement("th");
        th.textContent = name;
        head.append(th);
      }
      const body = table.createTBody();
      for (const row of byRobot.get(robot).sort((a, b) => b.updated_at - a.updated_at)) {
        const tr = body.insertRow();
        tr.dataset.session = row.id;
        tr.tabIndex = 0;
        if (row.id === state.selected) tr.className = "selected";
        cell(tr, row.id.slice(0, 8)).title = row.id;
        cell(tr, row.target_label || "(not named yet)");
        cell(tr, String(row.version), "num");
        cell(tr, ago(row.updated_at), "ago").dataset.at = row.updated_at;
        cell(tr, row.information_gain === null ? "…" : row.information_gain.toFixed(2), "num");
        tr.addEventListener("click", () => select(row.id));
        tr.addEventListener("keydown", (e) => e.key === "Enter" && select(row.id));
      }
      robots.append(title, table);
    }
    $("no-sessions").hidden = state.sessions.size > 0;
  });
}

// -- the selected session ------------------------------------------------------------------------------------

async function select(id) {
  state.selected = id;
  history.replaceState(null, "", `#session=${encodeURIComponent(id)}`);
  const path = `v1/sessions/${encodeURIComponent(id)}`;
  const view = {
    id,
    path,
    sceneGraph: null,
    sceneGraphStale: true,
    summary: null,
    summaryTag: null,
    topdown: null,
    topdownTag: null,
    heat: null, // the top-down mass as an image, nx x ny pixels
    utterances: new Map(), // event id -> record
  };
  view.refresh = new Coalesced(async () => {
    try {
      await refreshView(view);
    } catch (error) {
      if (error instanceof NotFound) {
        dropSession(id, GONE);
        return;
      }
      if (state.view === view && !(error instanceof AuthError)) {
        $("detail-meta").textContent = `Could not read the session: ${error.message}`;
      }
      throw error;
    }
  });
  view.history = new Coalesced(async () => {
    const answer = await getJSON(`${path}/utterances`);
    for (const record of answer.utterances) addUtterance(view, record, false);
    $("history-note").textContent = answer.complete
      ? ""
      : "Older utterances are no longer in the session's event history.";
    renderUtterances(view);
  });
  state.view = view;
  $("detail").hidden = false;
  $("detail").dataset.version = "";
  $("detail-title").textContent = `Session ${id}`;
  $("detail-meta").textContent = "loading…";
  renderSessions();
  view.history.request();
  view.refresh.request();
}

async function refreshView(view) {
  // Cleared before the read, so that a replacement announced while it runs is read by the next refresh; set
  // again when this one fails, or the map would lack the scene graph until the next replacement.
  const readGraph = view.sceneGraphStale;
  view.sceneGraphStale = false;
  let summary, topdown, graph;
  try {
    [summary, topdown, graph] = await Promise.all([
      getJSON(`${view.path}/belief`, view.summaryTag),
      getJSON(`${view.path}/belief/topdown`, view.topdownTag),
      readGraph ? getJSON(`${view.path}/scene-graph`) : null,
    ]);
  } catch (error) {
    if (readGraph) view.sceneGraphStale = true;
    throw error;
  }
  if (state.view !== view) return;
  if (graph) view.sceneGraph = graph;
  if (summary) {
    view.summary = summary;
    view.summaryTag = `"v${summary.version}"`;
    const row = state.sessions.get(view.id);
    if (row) {
      row.information_gain = summary.summary.information_gain_nats;
      renderSessions();
    }
  }
  if (topdown) {
    view.topdown = topdown;
    view.topdownTag = `"v${topdown.version}"`;
    view.heat = heatImage(topdown);
  }
  drawView(view);
}

function addUtterance(view, record, render = true) {
  view.utterances.set(record.event_id, record);
  if (render) renderUtterances(view);
}

function sortedUtterances(view) {
  return [...view.utterances.values()].sort((a, b) => a.updated_at - b.updated_at);
}

function renderUtterances(view) {
  if (state.view !== view) return;
  const said = sortedUtterances(view);
  const list = $("history");
  list.replaceChildren();
  for (const u of [...said].reverse()) {
    const li = document.createElement("li");
    const when = document.createElement("span");
    when.className = "when";
    when.textContent = new Date(u.updated_at * 1000).toLocaleTimeString();
    const text = document.createElement("span");
    text.textContent = `“${u.utterance}” → v${u.version}`;
    li.append(when, text);
    if (!u.fused || u.reason) {
      const why = document.createElement("div");
      why.className = u.fused ? "meta" : "refused";
      why.textContent = u.reason || "not fused";
      li.append(why);
    }
    list.append(li);
  }
  const last = said[said.length - 1];
  $("last-utterance").textContent = last ? `“${last.utterance}”` : "none yet";
  const hypotheses = $("hypotheses");
  hypotheses.replaceChildren();
  for (const h of last && last.hypotheses ? [...last.hypotheses].sort((a, b) => b.weight - a.weight) : []) {
    const li = document.createElement("li");
    li.append(bar(h.weight), document.createTextNode(`${h.weight.toFixed(2)} ${h.text}`));
    hypotheses.append(li);
  }
  if (view.summary) drawMap(view); // the anchors it outlines
}

function bar(fraction) {
  const span = document.createElement("span");
  span.className = "bar";
  span.style.width = `${Math.max(1, Math.round(fraction * 80))}px`;
  return span;
}

function placeTable(table, places) {
  table.replaceChildren();
  for (const p of places.filter((place) => place.mass >= 0.001).slice(0, SHOWN_PLACES)) {
    const tr = table.insertRow();
    const name = cell(tr, "");
    name.append(bar(p.mass), document.createTextNode(p.kind === "region" ? p.label || p.id : `${p.label} ${p.id}`));
    cell(tr, p.mass.toFixed(3), "num");
  }
}

function drawView(view) {
  if (!view.summary || !view.topdown) return;
  const s = view.summary.summary;
  const row = state.sessions.get(view.id);
  $("detail-title").textContent = `${(row && row.robot_id) || ""} · ${view.summary.target_label || "(target not named yet)"}`;
  $("detail-meta").textContent =
    `session ${view.id} · version ${view.summary.version} · ${s.n_voxels.toLocaleString()} voxels · ` +
    `information gain ${s.information_gain_nats.toFixed(2)} nats · MAP voxel p = ${s.map_voxel.probability.toPrecision(3)}`;
  placeTable($("objects"), s.objects);
  placeTable($("regions"), s.regions);
  placeTable($("structure"), s.structure);
  $("elsewhere").textContent = `elsewhere (mid-air, under furniture): ${s.mass_elsewhere.toFixed(3)}`;
  drawMap(view);
  $("detail").dataset.version = String(Math.min(view.summary.version, view.topdown.version));
  if (!state.firstPaint) {
    state.firstPaint = true;
    performance.mark("vlmap:heatmap");
  }
}

// -- the heat map --------------------------------------------------------------------------------------------

// Colours from dark (least mass) to bright (most), 256 steps between these stops.
const STOPS = [[0, 0, 4], [40, 11, 84], [101, 21, 110], [159, 42, 99], [212, 72, 66], [245, 125, 21], [250, 193, 39], [252, 255, 164]];
const LUT = (() => {
  const lut = new Uint8ClampedArray(256 * 3);
  for (let i = 0; i < 256; i++) {
    const x = (i / 255) * (STOPS.length - 1);
    const k = Math.min(Math.floor(x), STOPS.length - 2);
    const f = x - k;
    for (let c = 0; c < 3; c++) lut[i * 3 + c] = STOPS[k][c] + f * (STOPS[k + 1][c] - STOPS[k][c]);
  }
  return lut;
})();

function heatImage(topdown) {
  const [nx, ny] = topdown.shape;
  const bytes = Uint8Array.from(atob(topdown.mass), (c) => c.charCodeAt(0));
  const mass = new DataView(bytes.buffer);
  const image = new ImageData(nx, ny);
  const top = topdown.max_mass > 0 ? topdown.max_mass : 1;
  for (let i = 0; i < nx; i++) {
    for (let j = 0; j < ny; j++) {
      const m = mass.getFloat32((i * ny + j) * 4, true);
      const t = m > 0 ? Math.max(0, 1 + Math.log10(m / top) / DECADES) : 0;
      const c = Math.round(t * 255) * 3;
      const at = ((ny - 1 - j) * nx + i) * 4; // y up
      image.data[at] = LUT[c];
      image.data[at + 1] = LUT[c + 1];
      image.data[at + 2] = LUT[c + 2];
      image.data[at + 3] = 255;
    }
  }
  const canvas = document.createElement("canvas");
  canvas.width = nx;
  canvas.height = ny;
  canvas.getContext("2d").putImageData(image, 0, 0);
  return canvas;
}

function drawMap(view) {
  const { topdown, summary, heat } = view;
  if (!topdown || !summary) return;
  const canvas = $("heatmap");
  const [nx, ny] = topdown.shape;
  const size = topdown.voxel_size;
  const [x0, y0] = topdown.min_corner;
  const pad = 8;
  const scale = Math.min(MAP_WIDTH / (nx * size), MAP_HEIGHT / (ny * size)); // px per metre
  canvas.width = Math.round(nx * size * scale + 2 * pad);
  canvas.height = Math.round(ny * size * scale + 2 * pad);
  canvas.closest("figure").style.width = `${Math.max(canvas.width, 320)}px`; // the caption wraps below it
  const ctx = canvas.getContext("2d");
  const px = (x) => pad + (x - x0) * scale;
  const py = (y) => canvas.height - pad - (y - y0) * scale;
  ctx.fillStyle = "#111";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  ctx.imageSmoothingEnabled = false;
  ctx.drawImage(heat, px(x0), py(y0 + ny * size), nx * size * scale, ny * size * scale);

  const graph = view.sceneGraph || { regions: [], objects: [] };
  ctx.font = "11px system-ui, sans-serif";
  ctx.setLineDash([5, 4]);
  ctx.strokeStyle = "rgba(160, 200, 255, 0.9)";
  ctx.fillStyle = "rgba(160, 200, 255, 0.95)";
  ctx.lineWidth = 1;
  for (const r of graph.regions) {
    const [cx, cy] = r.center;
    const [sx, sy] = r.size;
    ctx.strokeRect(px(cx - sx / 2), py(cy + sy / 2), sx * scale, sy * scale);
    ctx.fillText(r.name || r.id, px(cx - sx / 2) + 3, py(cy + sy / 2) + 12);
  }
  ctx.setLineDash([]);
  const said = sortedUtterances(view);
  const last = said[said.length - 1];
  const anchors = new Set(last && last.hypotheses ? last.hypotheses.flatMap((h) => h.anchor_ids) : []);
  const massive = new Set(summary.summary.objects.slice(0, 5).map((p) => p.id));
  for (const o of graph.objects) {
    const [cx, cy] = o.center;
    const [sx, sy] = o.size;
    const yaw = o.yaw || 0;
    ctx.save();
    ctx.translate(px(cx), py(cy));
    ctx.rotate(-yaw); // the canvas's y axis points down
    ctx.lineWidth = anchors.has(o.id) ? 2.5 : 1;
    ctx.strokeStyle = anchors.has(o.id) ? "rgba(255, 255, 255, 0.95)" : "rgba(255, 255, 255, 0.45)";
    ctx.strokeRect((-sx / 2) * scale, (-sy / 2) * scale, sx * scale, sy * scale);
    ctx.restore();
    if (anchors.has(o.id) || massive.has(o.id)) {
      ctx.fillStyle = "rgba(255, 255, 255, 0.95)";
      ctx.fillText(`${o.label} ${o.id}`, px(cx) + 4, py(cy) - 4);
    }
  }

  const s = summary.summary;
  const [mx, my] = s.map_voxel.center;
  ctx.strokeStyle = "#39ff88";
  ctx.lineWidth = 2;
  ctx.beginPath();
  ctx.moveTo(px(mx) - 6, py(my) - 6);
  ctx.lineTo(px(mx) + 6, py(my) + 6);
  ctx.moveTo(px(mx) + 6, py(my) - 6);
  ctx.lineTo(px(mx) - 6, py(my) + 6);
  ctx.stroke();
  const [ex, ey] = s.mean;
  const [[a, b], [, c]] = s.covariance;
  const half = (a + c) / 2;
  const spread = Math.sqrt(((a - c) / 2) ** 2 + b * b);
  const angle = 0.5 * Math.atan2(2 * b, a - c);
  ctx.strokeStyle = "#00e5ff";
  ctx.fillStyle = "#00e5ff";
  ctx.beginPath();
  ctx.ellipse(px(ex), py(ey), 2 * Math.sqrt(half + spread) * scale, 2 * Math.sqrt(Math.max(half - spread, 0)) * scale, -angle, 0, 2 * Math.PI);
  ctx.stroke();
  ctx.beginPath();
  ctx.arc(px(ex), py(ey), 3, 0, 2 * Math.PI);
  ctx.fill();
}

function drawLegend() {
  const legend = $("legend");
  const ctx = legend.getContext("2d");
  for (let x = 0; x < legend.width; x++) {
    const c = Math.round((x / (legend.width - 1)) * 255) * 3;
    ctx.fillStyle = `rgb(${LUT[c]}, ${LUT[c + 1]}, ${LUT[c + 2]})`;
    ctx.fillRect(x, 0, 1, legend.height);
  }
}

// -- the key and the page ------------------------------------------------------------------------------------

function setStatus(text, kind = "") {
  $("status").textContent = text;
  $("status").className = `status ${kind}`;
}

function report(error) {
  if (error instanceof AuthError) askForKey(error.message);
  else console.warn(error);
}

function askForKey(message = "") {
  if (state.stream) state.stream.abort();
  state.stream = null;
  sessionStorage.removeItem(KEY);
  state.key = null;
  $("main").hidden = true;
  $("forget").hidden = true;
  $("key-form").hidden = false;
  $("key-error").textContent = message ? `The service refused the key: ${message}` : "";
  setStatus("not connected");
  $("key").focus();
}

/** Follow the fleet's push stream (a new one: the last is ended). */
function listen() {
  if (state.stream) state.stream.abort();
  state.stream = new AbortController();
  // Events missed while the stream was broken are replayed, but an expiry is no event: read the list again.
  follow("v1/events", state.stream.signal, onEvent, () => loadSessions().catch(report));
}

async function open(key) {
  state.key = key;
  setStatus("connecting…");
  try {
    await loadSessions();
  } catch (error) {
    // A key that may not list sessions cannot serve the dashboard at all: ask for another.
    if (error instanceof AuthError || error instanceof Forbidden) return askForKey(error.message);
    setStatus(`the service did not answer: ${error.message}`, "broken");
    return;
  }
  $("key-form").hidden = true;
  $("main").hidden = false;
  $("forget").hidden = false;
  listen();
  const wanted = new URLSearchParams(location.hash.slice(1)).get("session");
  if (wanted) select(wanted);
}

$("key-form").addEventListener("submit", (event) => {
  event.preventDefault();
  const key = $("key").value.trim();
  $("key").value = "";
  sessionStorage.setItem(KEY, key);
  open(key);
});
$("forget").addEventListener("click", () => askForKey());
// A page left for another stays in the browser's back-forward cache with its requests open: the stream would
// keep one of the six connections a browser gives a host. So it ends when the page is hidden, and a page
// shown again from that cache follows anew and reads what it missed.
window.addEventListener("pagehide", () => state.stream && state.stream.abort());
window.addEventListener("pageshow", (event) => {
  if (event.persisted && state.stream) {
    listen();
    onEvent("sync", {});
  }
});
setInterval(() => {
  for (const td of document.querySelectorAll("td.ago")) td.textContent = ago(Number(td.dataset.at));
}, 1000);
drawLegend();
const stored = sessionStorage.getItem(KEY);
if (stored === null) askForKey();
else open(stored);
