"""The status page (served at `/` by services/server/http.py): one
self-contained HTML file, no framework and no external resources, so it
works on a LAN without internet. Its script polls /status and reloads
/preview.png every 2 s and shows, for someone watching a render farm:

- the phase and what the render waits for (tracers, a chunk's owner, jobs
  in flight while draining), and a failure if there is one;
- a progress bar towards the stop condition, with elapsed time and ETA;
- the main numbers, with thousands separators;
- inline SVG charts of photons/s, hit points/s and the mean pixel radius
  over the render (`history`), so a drop in throughput or the convergence
  shows at a glance;
- recent warnings: evictions, rejoins, refusals, lost jobs;
- a tracer table that fits 1280 px (state, chunks, tracing, loading and waiting shares, queue,
  rays/s, heartbeat age), its raw counters in a collapsed <details>;
- for a chunked scene, who holds each chunk and its portal traffic;
- every field of /status, pretty-printed, in a collapsed <details>.

Keys it reads (all optional, so an older or partial status still shows):
iteration, photons_emitted (or photons), photons_committed, photons_per_s,
hit_points_per_s, jobs_in_flight, eta_s, phase, waiting_for, failure,
emission_paused, progress {fraction, elapsed_s, eta_s, stop, limit, value},
history {t, photons_per_s, hit_points_per_s, mean_radius}, server_s,
warnings [{t_s, kind, text}], evictions [{id, reason, t_s}], tracers [{id,
state, chunks, resident, busy, time: {tracing, loading, waiting, idle}, queue, photons_per_s, rays_per_s, heartbeat_age_s, ...}],
chunk_table [{chunk, tracers, resident, portal_rays_in, portal_rays_out}]
(services/server/history.py makes the derived ones). Text from the status
is only ever set as textContent, never parsed as HTML.
"""

PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>dosppm render</title>
<style>
  * { box-sizing: border-box; }
  body { font: 14px/1.35 system-ui, sans-serif; margin: 0; padding: 12px 20px 24px;
         color: #222; background: #f5f5f2; }
  h1 { font-size: 18px; margin: 0; }
  h2 { font-size: 14px; margin: 16px 0 6px; color: #444; }
  header { display: flex; align-items: baseline; gap: 16px; flex-wrap: wrap; }
  .muted, .sub { color: #666; }
  .sub { margin: 2px 0 0; font-size: 13px; }
  #phase { font-weight: 600; }
  #phase.wait { color: #a66300; } #phase.bad, #state { color: #b00020; }
  .bar { position: relative; height: 22px; margin-top: 10px; border-radius: 4px;
         background: #dfdfda; overflow: hidden; }
  #bar_fill { height: 100%; width: 0; background: #3b78c3; transition: width .4s; }
  #bar_text { position: absolute; inset: 0; text-align: center; line-height: 22px;
              font-weight: 600; color: #111; text-shadow: 0 0 3px #fff; }
  .top { display: grid; grid-template-columns: minmax(0, 380px) minmax(0, 1fr); gap: 16px;
         align-items: start; margin-top: 12px; }
  #preview { display: block; width: 100%; height: auto; image-rendering: pixelated;
             background: #000; border-radius: 4px; min-height: 60px; }
  .tiles { display: grid; grid-template-columns: repeat(4, minmax(0, 1fr)); gap: 8px; margin: 0; }
  .tile, .chart { background: #fff; border: 1px solid #ddd; border-radius: 4px; padding: 5px 8px; }
  .tile dt { color: #666; font-size: 12px; }
  .tile dd { margin: 0; font-size: 18px; font-variant-numeric: tabular-nums; overflow-wrap: anywhere; }
  .charts { display: grid; grid-template-columns: repeat(3, minmax(0, 1fr)); gap: 8px; margin-top: 8px; }
  .chart .ct { font-size: 12px; color: #666; display: flex; justify-content: space-between; }
  .chart .ct b { color: #222; font-variant-numeric: tabular-nums; }
  svg { display: block; width: 100%; height: auto; }
  svg .line { fill: none; stroke: #3b78c3; stroke-width: 1.5; vector-effect: non-scaling-stroke; }
  svg .area { fill: #3b78c3; opacity: .12; }
  svg .grid { stroke: #e6e6e2; stroke-width: 1; }
  svg text { font: 10px system-ui, sans-serif; fill: #777; }
  table { border-collapse: collapse; width: 100%; background: #fff; }
  th, td { padding: 3px 8px; border-bottom: 1px solid #e6e6e2; text-align: right;
           font-variant-numeric: tabular-nums; white-space: nowrap; }
  th { background: #ecece8; color: #444; font-weight: 600; }
  th.l, td.l { text-align: left; white-space: normal; overflow-wrap: anywhere; }
  .badge { display: inline-block; padding: 0 6px; border-radius: 8px; font-size: 12px; color: #fff; }
  .s-tracing { background: #2e7d32; } .s-loading { background: #c77700; } .s-waiting { background: #5c6bc0; }
  .s-idle { background: #888; }
  .meter i.tracing { background: #2e7d32; } .meter i.loading { background: #c77700; }
  .meter i.waiting { background: #5c6bc0; }
  .s-silent, .s-evicted { background: #b00020; } .s-rejoined { background: #3b78c3; }
  .meter { display: inline-flex; width: 60px; height: 8px; margin-right: 6px; background: #e6e6e2;
           border-radius: 4px; overflow: hidden; vertical-align: middle; }
  .meter i { display: block; height: 100%; background: #2e7d32; }
  .late { color: #b00020; font-weight: 600; }
  #warnings { margin: 0; padding-left: 18px; }
  #warnings li { margin: 2px 0; overflow-wrap: anywhere; }
  #warnings .age { color: #666; font-variant-numeric: tabular-nums; margin-right: 8px; }
  details { margin-top: 12px; }
  summary { cursor: pointer; color: #444; font-weight: 600; }
  .scroll { overflow: auto; max-width: 100%; }
  .tall { max-height: 280px; }
  #chunks { width: auto; min-width: 50%; }
  pre { white-space: pre-wrap; overflow-wrap: anywhere; font-size: 12px; margin: 6px 0 0;
        background: #fff; border: 1px solid #ddd; border-radius: 4px; padding: 8px; }
</style>
</head>
<body>
<header>
  <h1>dosppm render</h1>
  <span id="phase">connecting...</span>
  <span id="state"></span>
</header>
<div class="bar" id="progress" role="progressbar" aria-valuemin="0" aria-valuemax="100">
  <div id="bar_fill"></div><span id="bar_text"></span>
</div>
<p class="sub" id="progress_line"></p>
<div class="top">
  <img id="preview" src="/preview.png" alt="preview (no image yet)">
  <div>
    <dl class="tiles">
      <div class="tile"><dt>Iteration</dt><dd id="iteration">-</dd></div>
      <div class="tile"><dt>Photons emitted</dt><dd id="photons">-</dd></div>
      <div class="tile"><dt>Photons committed</dt><dd id="committed">-</dd></div>
      <div class="tile"><dt>Jobs in flight</dt><dd id="jobs_in_flight">-</dd></div>
      <div class="tile"><dt>Photons/s (mean)</dt><dd id="photons_per_s">-</dd></div>
      <div class="tile"><dt>Hit points/s (mean)</dt><dd id="hit_points_per_s">-</dd></div>
      <div class="tile"><dt>ETA</dt><dd id="eta">-</dd></div>
      <div class="tile"><dt>Tracers</dt><dd id="tracer_summary">-</dd></div>
    </dl>
    <div class="charts" id="charts">
      <div class="chart"><div class="ct">Photons/s <b id="now_photons">-</b></div>
        <svg id="chart_photons" viewBox="0 0 300 110" role="img" aria-label="photons per second"></svg></div>
      <div class="chart"><div class="ct">Hit points/s <b id="now_hit_points">-</b></div>
        <svg id="chart_hit_points" viewBox="0 0 300 110" role="img"
             aria-label="hit points per second"></svg></div>
      <div class="chart"><div class="ct">Mean pixel radius <b id="now_radius">-</b></div>
        <svg id="chart_radius" viewBox="0 0 300 110" role="img" aria-label="mean pixel radius"></svg></div>
    </div>
    <h2>Warnings</h2>
    <ul id="warnings"><li class="muted">None.</li></ul>
  </div>
</div>
<h2>Tracers</h2>
<table id="tracers"></table>
<details><summary>Raw tracer counters</summary>
  <div class="scroll"><table id="tracers_raw"></table></div></details>
<section id="chunks_section" hidden>
  <h2>Chunks</h2>
  <p class="sub">Rays that crossed a portal into and out of each chunk, since the render started.</p>
  <div class="scroll tall"><table id="chunks"></table></div>
</section>
<details><summary>All fields (/status)</summary><pre id="fields"></pre></details>
<script>
"use strict";
const NF = new Intl.NumberFormat("en-US");
const SILENT_S = 3;

function present(v) { return v !== null && v !== undefined; }

function num(v) {
  if (!present(v)) return "-";
  if (typeof v !== "number") return typeof v === "object" ? JSON.stringify(v) : String(v);
  if (Number.isInteger(v) || Math.abs(v) >= 100) return NF.format(Math.round(v));
  return String(Number(v.toPrecision(3)));
}

function short(v) {
  if (!present(v)) return "-";
  const a = Math.abs(v);
  for (const [d, u] of [[1e9, "G"], [1e6, "M"], [1e3, "k"]]) {
    if (a >= d) return Number((v / d).toPrecision(3)) + u;
  }
  return num(v);
}

function dur(s) {
  if (!present(s)) return "unknown";
  if (s < 90) return s.toFixed(0) + " s";
  if (s < 5400) return (s / 60).toFixed(1) + " min";
  return (s / 3600).toFixed(1) + " h";
}

function pick(status, keys) {
  for (const k of keys) if (k in status) return status[k];
  return null;
}

function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (present(text)) e.textContent = text;
  if (cls) e.className = cls;
  return e;
}

function setText(id, text) { document.getElementById(id).textContent = text; }

function showPhase(s) {
  const w = s.waiting_for, phase = document.getElementById("phase");
  let text = s.phase || "", cls = "wait";
  if (s.failure) { text = "Stopping: " + s.failure; cls = "bad"; }
  else if (w && "tracers" in w) text = `Waiting for tracers: ${w.registered} of ${w.min_tracers} registered`;
  else if (w && w.chunk_owners) text = "Waiting for a tracer to hold chunk(s) " + w.chunk_owners.join(", ");
  else if (s.phase === "draining") text = `Draining: waiting for ${num(s.jobs_in_flight)} jobs in flight`;
  else if (s.phase === "render") {
    text = "Rendering" + (s.emission_paused ? " (emission paused: statistics updates queued)" : "");
    cls = s.emission_paused ? "wait" : "";
  }
  phase.textContent = text;
  phase.className = cls;
}

function showProgress(s) {
  const p = s.progress || {}, f = p.fraction;
  const bar = document.getElementById("progress");
  document.getElementById("bar_fill").style.width = (present(f) ? 100 * f : 0) + "%";
  bar.setAttribute("aria-valuenow", present(f) ? (100 * f).toFixed(1) : "0");
  setText("bar_text", present(f) ? (100 * f).toFixed(1) + " %" : "no limit: renders until stopped");
  const parts = ["elapsed " + dur(present(p.elapsed_s) ? p.elapsed_s : s.seconds)];
  if (p.stop === "time") parts.push("stops at " + dur(p.limit) + " (time limit)");
  if (p.stop === "photons") parts.push(`${num(p.value)} of ${num(p.limit)} photons (photon limit)`);
  if (p.stop === "iterations") parts.push(`iteration ${num(p.value)} of ${num(p.limit)} (iteration limit)`);
  parts.push("ETA " + dur(present(p.eta_s) ? p.eta_s : s.eta_s));
  setText("progress_line", parts.join("  \\u00b7  "));
}

// element id -> status keys, first present wins
const FIELDS = {
  iteration: ["iteration"], photons: ["photons_emitted", "photons"],
  committed: ["photons_committed"], photons_per_s: ["photons_per_s"],
  hit_points_per_s: ["hit_points_per_s"], jobs_in_flight: ["jobs_in_flight"],
};

function showNumbers(s) {
  for (const [id, keys] of Object.entries(FIELDS)) setText(id, num(pick(s, keys)));
  setText("eta", dur(s.eta_s));
  const counts = {};
  for (const t of s.tracers || []) {
    const k = t.state || "registered";
    counts[k] = (counts[k] || 0) + 1;
  }
  const order = ["tracing", "loading", "waiting", "idle", "rejoined", "silent"];
  const parts = Object.entries(counts).sort(([a], [b]) => (order.indexOf(a) >>> 0) - (order.indexOf(b) >>> 0))
    .map(([k, n]) => n + " " + k);
  setText("tracer_summary", parts.length ? parts.join(", ") : "none");
}

function chart(id, nowId, t, ys, fromZero) {
  const svg = document.getElementById(id);
  const pts = [];
  (t || []).forEach((x, i) => { if (present(ys[i])) pts.push([Number(x), Number(ys[i])]); });
  setText(nowId, pts.length ? short(pts[pts.length - 1][1]) : "-");
  if (pts.length < 2) {
    svg.innerHTML = '<text x="150" y="58" text-anchor="middle">collecting samples...</text>';
    return;
  }
  const x0 = pts[0][0], x1 = pts[pts.length - 1][0];
  let lo = fromZero ? 0 : Math.min(...pts.map(p => p[1])), hi = Math.max(...pts.map(p => p[1]));
  if (!fromZero) lo -= 0.05 * (hi - lo);
  if (hi <= lo) hi = lo + (Math.abs(lo) || 1);
  const top = 14, bottom = 96;
  const sx = x => (300 * (x - x0) / (x1 - x0 || 1)).toFixed(1);
  const sy = y => (bottom - (bottom - top) * (y - lo) / (hi - lo)).toFixed(1);
  const line = pts.map(([x, y]) => sx(x) + "," + sy(y)).join(" ");
  svg.innerHTML =
    `<line class="grid" x1="0" y1="${top}" x2="300" y2="${top}"/>` +
    `<line class="grid" x1="0" y1="${bottom}" x2="300" y2="${bottom}"/>` +
    `<polygon class="area" points="${sx(x0)},${bottom} ${line} ${sx(x1)},${bottom}"/>` +
    `<polyline class="line" points="${line}"/>` +
    `<text x="2" y="10">${short(hi)}</text><text x="2" y="92">${short(lo)}</text>` +
    `<text x="2" y="108">${dur(x0)}</text>` +
    `<text x="298" y="108" text-anchor="end">${dur(x1)}</text>`;
}

function showCharts(s) {
  const h = s.history || {};
  chart("chart_photons", "now_photons", h.t, h.photons_per_s || [], true);
  chart("chart_hit_points", "now_hit_points", h.t, h.hit_points_per_s || [], true);
  chart("chart_radius", "now_radius", h.t, h.mean_radius || [], false);
}

function showWarnings(s) {
  const ul = document.getElementById("warnings"), ws = s.warnings || [];
  ul.replaceChildren();
  if (!ws.length) ul.append(el("li", "None.", "muted"));
  for (const w of ws) {
    const li = el("li");
    const age = present(s.server_s) && present(w.t_s) ? dur(Math.max(0, s.server_s - w.t_s)) + " ago" : "";
    li.append(el("span", age, "age"), document.createTextNode(w.text));
    ul.append(li);
  }
}

function ranges(list) {
  if (!Array.isArray(list)) return num(list);
  const out = [];
  for (let i = 0; i < list.length; i++) {
    let j = i;
    while (j + 1 < list.length && list[j + 1] === list[j] + 1) j++;
    out.push(j > i + 1 ? list[i] + "\\u2013" + list[j] : j > i ? list[i] + ", " + list[j] : String(list[i]));
    i = j;
  }
  const text = out.join(", ");
  return text.length > 32 ? text.slice(0, 30) + "\\u2026" : text;
}

function row(table, cells) {
  const tr = table.insertRow();
  for (const c of cells) tr.append(c);
  return tr;
}

function badge(state, title) {
  const td = el("td", null, "l"), b = el("span", state, "badge s-" + state);
  if (title) b.title = title;
  td.append(b);
  return td;
}

// Its time over the last heartbeats: tracing, loading a chunk and waiting
// as one stacked bar (idle is the rest), the three shares as text.
function timeCell(time) {
  const td = el("td");
  if (!time) { td.textContent = "-"; return td; }
  const m = el("span", null, "meter"), parts = ["tracing", "loading", "waiting"];
  for (const k of parts) {
    const fill = el("i", null, k);
    fill.style.width = (100 * time[k]).toFixed(0) + "%";
    m.append(fill);
  }
  m.title = parts.concat(["idle"]).map(k => k + " " + (100 * time[k]).toFixed(0) + " %").join(", ");
  td.append(m, document.createTextNode(parts.map(k => (100 * time[k]).toFixed(0)).join(" / ") + " %"));
  return td;
}

function showTracers(s) {
  const table = document.getElementById("tracers"), tracers = s.tracers || [];
  table.replaceChildren();
  row(table, ["Tracer", "State", "Chunks", "In memory", "Tracing / loading / waiting", "Queue", "Photons/s",
              "Heartbeat"]
    .map((h, i) => el("th", h, i < 3 ? "l" : "")));
  for (const t of tracers) {
    const chunks = el("td", ranges(t.chunks), "l");
    chunks.title = Array.isArray(t.chunks) ? t.chunks.join(", ") : "";
    const mem = Array.isArray(t.resident) && Array.isArray(t.chunks)
      ? t.chunks.filter(k => t.resident.includes(k)).length + " of " + t.chunks.length : "-";
    const age = el("td", present(t.heartbeat_age_s) ? t.heartbeat_age_s.toFixed(1) + " s ago" : "-");
    if (t.heartbeat_age_s > SILENT_S) age.className = "late";
    row(table, [el("td", t.id, "l"), badge(t.state || "-"), chunks, el("td", mem), timeCell(t.time),
                el("td", num(t.queue)), el("td", num(t.photons_per_s)), age]);
  }
  const here = new Set(tracers.map(t => t.id)), shown = new Set();
  for (const e of (s.evictions || []).slice().reverse()) {
    if (here.has(e.id) || shown.has(e.id)) continue;
    shown.add(e.id);
    const when = present(s.server_s) ? dur(Math.max(0, s.server_s - e.t_s)) + " ago: " : "";
    const why = el("td", when + e.reason, "l");
    why.colSpan = 6;
    row(table, [el("td", e.id, "l"), badge("evicted", e.reason), why]);
  }
  showRaw(tracers);
}

function showRaw(tracers) {
  const columns = [];
  for (const t of tracers) for (const k of Object.keys(t)) if (!columns.includes(k)) columns.push(k);
  const table = document.getElementById("tracers_raw");
  table.replaceChildren();
  row(table, columns.map(c => el("th", c)));
  for (const t of tracers) row(table, columns.map(c => el("td", num(t[c]))));
}

function showChunks(s) {
  const rows = s.chunk_table || [];
  document.getElementById("chunks_section").hidden = rows.length < 2;
  const table = document.getElementById("chunks");
  table.replaceChildren();
  row(table, ["Chunk", "Tracers", "In memory", "Portal rays in", "Portal rays out"]
    .map((h, i) => el("th", h, i === 1 ? "l" : "")));
  for (const c of rows) {
    const n = c.tracers.length, r = c.resident.length;
    const mem = n === 0 ? "no tracer" : r === n ? "yes" : r === 0 ? "no" : r + " of " + n;
    row(table, [el("td", String(c.chunk)), el("td", c.tracers.join(", ") || "none", "l"), el("td", mem),
                el("td", num(c.portal_rays_in)), el("td", num(c.portal_rays_out))]);
  }
  if (present(s.chunks) && s.chunks > rows.length && rows.length) {
    row(table, [el("td", `${num(s.chunks - rows.length)} more chunks not listed`, "l")]).cells[0].colSpan = 5;
  }
}

function pretty(v, depth) {
  const pad = "  ".repeat(depth + 1), end = "  ".repeat(depth);
  if (Array.isArray(v) && v.every(x => x === null || typeof x !== "object")) {
    return "[" + v.map(x => JSON.stringify(x)).join(", ") + "]";
  }
  if (Array.isArray(v)) {
    return v.length ? "[\\n" + v.map(x => pad + pretty(x, depth + 1)).join(",\\n") + "\\n" + end + "]" : "[]";
  }
  if (v && typeof v === "object") {
    const ks = Object.keys(v);
    return ks.length ? "{\\n" + ks.map(k => pad + JSON.stringify(k) + ": " + pretty(v[k], depth + 1))
      .join(",\\n") + "\\n" + end + "}" : "{}";
  }
  return JSON.stringify(v);
}

function reloadPreview() {
  document.getElementById("preview").src = "/preview.png?t=" + Date.now();
}

async function refresh() {
  const state = document.getElementById("state");
  try {
    const response = await fetch("/status", {cache: "no-store"});
    const status = await response.json();
    if (!response.ok) throw new Error(status.error || response.statusText);
    for (const show of [showPhase, showProgress, showNumbers, showCharts, showWarnings,
                        showTracers, showChunks]) show(status);
    setText("fields", pretty(status, 0));
    state.textContent = "";
  } catch (e) {
    state.textContent = "status unavailable: " + e.message;
  }
  reloadPreview();
  setTimeout(refresh, 2000);
}

refresh();
</script>
</body>
</html>
"""
