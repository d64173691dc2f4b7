// hilsim console: one WebSocket to the bridge that served this page; nothing else is fetched.
"use strict";

const $ = (id) => document.getElementById(id);
const stats = { sonarFrames: {}, states: 0, cameraFrames: 0, scenes: 0, objects: [], errors: [], serverErrors: [] };
window.hilsimConsole = stats;   // read by the browser tests
let ws = null, hello = null, lastState = null, cameraShown = false, cameraWanted = true;
const sonars = {};              // device -> {canvas, ctx, lut, key, info, image}
const track = [];

// ---- connection ------------------------------------------------------------------------------
function connect() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  ws = new WebSocket(`${proto}//${location.host}/ws`);
  ws.binaryType = "arraybuffer";
  ws.onopen = () => { $("conn").textContent = "live"; $("conn").className = "ok"; };
  ws.onclose = () => {
    $("conn").textContent = "offline"; $("conn").className = "bad";
    setTimeout(connect, 2000);
  };
  ws.onmessage = (ev) => {
    if (typeof ev.data === "string") onText(JSON.parse(ev.data)); else onBinary(ev.data);
  };
}

function send(msg) { if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(msg)); }

function onText(m) {
  if (m.type === "hello") onHello(m);
  else if (m.type === "state") onState(m);
  else if (m.type === "scene") onScene(m);
  else if (m.type === "error") { stats.serverErrors.push(m.message); say("refused: " + m.message); }
  else if (m.type === "ack") { if (m.op !== "camera") say(`${m.op} ${m.fault} on ${m.target}`); }
}

function onBinary(buf) {
  const dv = new DataView(buf);
  const n = dv.getUint32(0);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
  const payload = new Uint8Array(buf, 4 + n);
  if (header.type === "sonar") drawSonar(header, payload);
  else if (header.type === "camera") showCamera(header, payload);
}

function say(text) { $("message").textContent = text; }

// ---- hello: the static scene -------------------------------------------------------------------
function onHello(m) {
  hello = m;
  stats.objects = m.objects;
  $("scenario").textContent = `scenario ${m.scenario}`;
  track.length = 0;
  for (const p of m.track || []) track.push(p);
  buildThrusters(m.thrusters);
  buildEndpoints(m.endpoints);
  buildFaults(m.faults_menu);
  for (const d of m.sonars || []) {
    const s = sonarView(d);
    if (s.canvas.dataset.frames === "0") s.info.textContent = "no frame yet (this head pings while a client asks)";
  }
  $("camera-panel").style.display = m.cameras.length ? "" : "none";
  if (m.cameras.length) setCamera(cameraWanted && !document.hidden);
}

// an object moved: the views draw the objects where they are now
function onScene(m) {
  stats.scenes++;
  if (!hello) return;
  hello.objects = stats.objects = m.objects;
  if (lastState) { drawTop(lastState.vehicle); drawSide(lastState.vehicle); }
}

function el(tag, attrs = {}, text = "") {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text) e.textContent = text;
  return e;
}

function buildThrusters(names) {
  const tb = $("thrusters").tBodies[0];
  tb.textContent = "";
  names.forEach((name, i) => {
    const tr = el("tr", { id: `thr-${i}` });
    tr.append(el("td", {}, name));
    const c = el("td"); c.append(bar(`thr-${i}-cmd`, "cmd")); tr.append(c);
    const r = el("td"); r.append(bar(`thr-${i}-rpm`, "rpm")); r.append(el("span", { id: `thr-${i}-rpmtext`, class: "small" })); tr.append(r);
    tr.append(el("td", { id: `thr-${i}-src`, class: "small" }, "-"));
    tb.append(tr);
  });
}

function bar(id, kind) {
  const b = el("div", { class: `bar ${kind}`, id, "data-value": "0" });
  b.append(el("div"), el("span"));
  return b;
}

function setBar(id, frac) {
  const b = $(id);
  if (!b) return;
  const f = Math.max(-1, Math.min(1, frac || 0));
  b.dataset.value = f.toFixed(3);
  const d = b.firstChild;
  d.style.left = `${50 + Math.min(0, f) * 50}%`;
  d.style.width = `${Math.abs(f) * 50}%`;
}

function buildEndpoints(eps) {
  const tb = $("endpoints").tBodies[0];
  tb.textContent = "";
  eps.forEach((e, i) => {
    const tr = el("tr", { "data-device": e.device });
    for (const v of [e.device, e.protocol, e.transport, e.address]) tr.append(el("td", {}, String(v)));
    for (const k of ["clients", "served", "drops", "errors"]) tr.append(el("td", { class: "num", "data-k": k }, "-"));
    tr.append(el("td", { class: "err", "data-k": "last_error" }, ""));
    tb.append(tr);
  });
}

function buildFaults(menu) {
  const tb = $("faults").tBodies[0];
  tb.textContent = "";
  for (const f of menu) {
    const tr = el("tr", { "data-target": f.target, "data-fault": f.fault });
    tr.append(el("td", {}, f.label));
    const inj = el("button", { type: "button", class: "inject", "data-target": f.target, "data-fault": f.fault }, "inject");
    inj.onclick = () => send({ op: "fault", target: f.target, fault: f.fault });
    const clr = el("button", { type: "button", class: "clear", "data-target": f.target, "data-fault": f.fault }, "clear");
    clr.onclick = () => send({ op: "clear", target: f.target, fault: f.fault });
    const td = el("td"); td.append(inj, " ", clr); tr.append(td);
    tb.append(tr);
  }
}

// ---- state: 10 times a second -----------------------------------------------------------------
function fmt(v, d = 2) { return v === null || v === undefined ? "-" : Number(v).toFixed(d); }

function onState(s) {
  stats.states++;
  lastState = s;
  const v = s.vehicle;
  $("simtime").textContent = `t = ${fmt(v.t, 1)} s, ${s.pages} page(s)`;
  $("nav-depth").textContent = fmt(v.depth_m);
  $("nav-altitude").textContent = fmt(v.altitude_m);
  $("nav-heading").textContent = fmt(v.heading_deg, 1);
  $("nav-speed").textContent = fmt(v.speed_m_s);
  $("nav-pose").textContent = `position N ${fmt(v.position[0])} E ${fmt(v.position[1])} D ${fmt(v.position[2])} m, ` +
    `roll ${fmt(v.rpy_deg[0], 1)} pitch ${fmt(v.rpy_deg[1], 1)} deg`;
  const rd = $("readings"); rd.textContent = "";
  for (const [d, r] of Object.entries(s.readings)) {
    rd.append(el("div", {}, `${d}: ` + Object.entries(r).slice(0, 5).map(([k, x]) =>
      `${k} ${Array.isArray(x) ? x.map((y) => fmt(y)).join("/") : typeof x === "number" ? fmt(x, 3) : x}`).join(", ")));
  }
  const last = track[track.length - 1];
  if (!last || Math.hypot(last[0] - v.position[0], last[1] - v.position[1], last[2] - v.position[2]) > 0.02) {
    track.push(v.position.slice());
    if (track.length > 2000) track.shift();
  }
  s.thrusters.forEach((t, i) => {
    const cmd = typeof t.value === "number" ? t.value : 0;
    const scale = t.kind === "rpm" || t.kind === "erpm" ? (t.max_rpm * (t.kind === "erpm" ? 7 : 1)) : t.kind === "current" ? 25 : 1;
    setBar(`thr-${i}-cmd`, cmd / (scale || 1));
    setBar(`thr-${i}-rpm`, t.rpm / (t.max_rpm || 1));
    const rt = $(`thr-${i}-rpmtext`); if (rt) rt.textContent = ` ${t.rpm === null ? "-" : Math.round(t.rpm)}`;
    const src = $(`thr-${i}-src`);
    if (src) src.textContent = t.source ? `${t.source} (${t.kind} ${fmt(t.value, 3)})${t.timed_out ? ", timed out" : ""}` : "-";
  });
  updateEndpoints(s.devices);
  updateFaults(s);
  drawTop(v); drawSide(v);
}

const SERVED = ["sent", "requests", "replies", "frames_sent", "commands", "frames", "samples"];
function updateEndpoints(devices) {
  for (const tr of $("endpoints").tBodies[0].rows) {
    const st = devices[tr.dataset.device];
    if (!st) continue;
    let served = "-", drops = 0, errors = 0;
    for (const k of SERVED) if (typeof st[k] === "number") { served = st[k]; break; }
    for (const [k, x] of Object.entries(st)) {
      if (typeof x !== "number") continue;
      if (/drop/.test(k)) drops += x;
      else if (/error|malformed|bad|fail|exception|crc|refused/.test(k)) errors += x;
    }
    for (const td of tr.cells) {
      const k = td.dataset.k;
      if (k === "clients") td.textContent = st.clients ?? "-";
      else if (k === "served") td.textContent = served;
      else if (k === "drops") td.textContent = drops;
      else if (k === "errors") td.textContent = errors;
      else if (k === "last_error") { td.textContent = st.last_error || ""; td.title = JSON.stringify(st); }
    }
  }
}

function updateFaults(s) {
  const active = new Set(s.faults.map((f) => `${f.target}|${f.fault}`));
  for (const tr of $("faults").tBodies[0].rows) tr.classList.toggle("active", active.has(`${tr.dataset.target}|${tr.dataset.fault}`));
  const af = $("active-faults"); af.textContent = "";
  for (const f of s.faults) af.append(el("li", {}, `${f.fault} on ${f.target}`));
  const cl = $("contacts"); cl.textContent = "";
  for (const c of s.contacts.slice().reverse()) cl.append(el("li", {}, `t=${fmt(c.t, 1)} s ${c.event} ${c.object} ${fmt(c.force_N, 1)} N ${fmt(c.speed_m_s, 2)} m/s`));
}

// ---- top and side views ------------------------------------------------------------------------
function viewBox(objs, key, ix, iy) {
  let lo = [Infinity, Infinity], hi = [-Infinity, -Infinity];
  for (const o of objs) for (const p of o[key]) {
    lo = [Math.min(lo[0], p[ix]), Math.min(lo[1], p[iy])]; hi = [Math.max(hi[0], p[ix]), Math.max(hi[1], p[iy])];
  }
  if (!isFinite(lo[0])) { lo = [-5, -5]; hi = [5, 5]; }
  return { lo, hi };
}

function drawView(canvas, key, toScreen, vehiclePoly, trackXY) {
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#0a1418"; ctx.fillRect(0, 0, canvas.width, canvas.height);
  const objs = hello.objects.slice().sort((a, b) => area(b[key]) - area(a[key]));
  for (const o of objs) {
    ctx.beginPath();
    o[key].forEach((p, i) => { const [x, y] = toScreen(p); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
    ctx.closePath(); ctx.globalAlpha = 0.55; ctx.fillStyle = o.color; ctx.fill();
    ctx.globalAlpha = 1; ctx.strokeStyle = "#3a4a56"; ctx.stroke();
  }
  ctx.beginPath(); ctx.strokeStyle = "#6cd47a"; ctx.lineWidth = 1.5;
  trackXY.forEach((p, i) => { const [x, y] = toScreen(p); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
  ctx.stroke(); ctx.lineWidth = 1;
  ctx.beginPath();
  vehiclePoly.forEach((p, i) => { const [x, y] = toScreen(p); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
  ctx.closePath(); ctx.fillStyle = "#f0b94a"; ctx.fill(); ctx.strokeStyle = "#fff"; ctx.stroke();
}

function area(poly) { let a = 0; for (let i = 0; i < poly.length; i++) { const p = poly[i], q = poly[(i + 1) % poly.length]; a += p[0] * q[1] - q[0] * p[1]; } return Math.abs(a / 2); }

function fit(canvas, box, flipY) {
  const m = 12, w = canvas.width - 2 * m, h = canvas.height - 2 * m;
  const sx = w / (box.hi[0] - box.lo[0] || 1), sy = h / (box.hi[1] - box.lo[1] || 1), s = Math.min(sx, sy);
  const ox = m + (w - s * (box.hi[0] - box.lo[0])) / 2, oy = m + (h - s * (box.hi[1] - box.lo[1])) / 2;
  return flipY ? (x, y) => [ox + (x - box.lo[0]) * s, canvas.height - oy - (y - box.lo[1]) * s]
               : (x, y) => [ox + (x - box.lo[0]) * s, oy + (y - box.lo[1]) * s];
}

function hullCorners(ax, bx) {   // body-frame rectangle on two axes
  const h = hello.hull; return [[h.min[ax], h.min[bx]], [h.max[ax], h.min[bx]], [h.max[ax], h.max[bx]], [h.min[ax], h.max[bx]]];
}

function drawTop(v) {
  if (!hello) return;
  const c = $("top-view"), box = viewBox(hello.objects, "top", 1, 0);   // screen x = east, y = north
  const f = fit(c, { lo: [box.lo[0], box.lo[1]], hi: [box.hi[0], box.hi[1]] }, true);
  const yaw = v.rpy_deg[2] * Math.PI / 180, cy = Math.cos(yaw), sy = Math.sin(yaw);
  const poly = hullCorners(0, 1).map(([x, y]) => [v.position[0] + cy * x - sy * y, v.position[1] + sy * x + cy * y]);
  drawView(c, "top", (p) => f(p[1], p[0]), poly, track.map((p) => [p[0], p[1]]));
}

function drawSide(v) {
  if (!hello) return;
  const c = $("side-view"), box = viewBox(hello.objects, "side", 0, 1);   // screen x = north, y = down
  const f = fit(c, box, false);
  const pitch = v.rpy_deg[1] * Math.PI / 180, cp = Math.cos(pitch), sp = Math.sin(pitch);
  const poly = hullCorners(0, 2).map(([x, z]) => [v.position[0] + cp * x + sp * z, v.position[2] - sp * x + cp * z]);
  drawView(c, "side", (p) => f(p[0], p[1]), poly, track.map((p) => [p[0], p[2]]));
}

// ---- sonar fans -----------------------------------------------------------------------------------
const PALETTE = (() => {
  const p = new Uint8ClampedArray(256 * 4);
  for (let i = 0; i < 256; i++) {
    const x = i / 255;
    p[4 * i] = 255 * Math.min(1, 1.6 * x); p[4 * i + 1] = 255 * Math.min(1, Math.max(0, 1.4 * x - 0.2));
    p[4 * i + 2] = 255 * Math.min(1, Math.max(0, 2 * x - 1) + 0.15 * x); p[4 * i + 3] = 255;
  }
  return p;
})();

function sonarView(device) {
  let s = sonars[device];
  if (s) return s;
  const box = el("div", { class: "sonar" });
  const canvas = el("canvas", { id: `sonar-${device}`, width: "440", height: "340", "data-frames": "0" });
  const info = el("div", { class: "small", id: `sonar-${device}-info` });
  canvas.style.display = "none";               // shown with the first frame
  box.append(el("div", {}, device), canvas, info);
  $("sonar-list").append(box);
  s = sonars[device] = { canvas, ctx: canvas.getContext("2d"), info, key: "", lut: null, geo: null };
  return s;
}

function buildLut(s, h) {
  const W = s.canvas.width, H = s.canvas.height, az = h.azimuths, nb = h.shape[1], ns = h.shape[0];
  const half = Math.max(Math.abs(az[0]), Math.abs(az[nb - 1])) + (nb > 1 ? Math.abs(az[1] - az[0]) / 2 : 0.01);
  const rmax = h.range_max, rmin = h.range_min;
  const width = 2 * rmax * Math.sin(Math.min(half, Math.PI / 2));
  const scale = Math.min((W - 20) / width, (H - 24) / rmax);
  const cx = W / 2, cy = H - 14;
  const lut = new Int32Array(W * H).fill(-1);
  const edges = new Float64Array(nb + 1);
  for (let b = 1; b < nb; b++) edges[b] = (az[b - 1] + az[b]) / 2;
  edges[0] = az[0] - (nb > 1 ? (az[1] - az[0]) / 2 : 0.01); edges[nb] = az[nb - 1] + (nb > 1 ? (az[nb - 1] - az[nb - 2]) / 2 : 0.01);
  for (let py = 0; py < H; py++) for (let px = 0; px < W; px++) {
    const x = (px - cx) / scale, y = (cy - py) / scale, r = Math.hypot(x, y);
    if (r < rmin || r >= rmax) continue;
    const th = Math.atan2(x, y);
    if (th < edges[0] || th >= edges[nb]) continue;
    let lo = 0, hi = nb;                       // the beam whose edges hold th
    while (hi - lo > 1) { const mid = (lo + hi) >> 1; if (edges[mid] <= th) lo = mid; else hi = mid; }
    const row = Math.min(ns - 1, Math.floor((r - rmin) / (rmax - rmin) * ns));
    lut[py * W + px] = row * nb + lo;
  }
  s.lut = lut; s.geo = { cx, cy, scale, rmin, rmax, az0: edges[0], az1: edges[nb] };
  s.image = s.ctx.createImageData(W, H);
}

function niceStep(r) { for (const s of [0.25, 0.5, 1, 2, 5, 10, 20, 50, 100]) if (r / s <= 6) return s; return 200; }

function drawSonar(h, img) {
  const s = sonarView(h.device);
  s.canvas.style.display = "";
  const key = `${h.shape}|${h.range_min}|${h.range_max}|${h.azimuths[0]}|${h.azimuths[h.azimuths.length - 1]}`;
  if (key !== s.key) { buildLut(s, h); s.key = key; }
  const d = s.image.data, lut = s.lut;
  for (let i = 0, j = 0; i < lut.length; i++, j += 4) {
    const k = lut[i];
    if (k < 0) { d[j] = 12; d[j + 1] = 16; d[j + 2] = 20; d[j + 3] = 255; continue; }
    const v = img[k] * 4;
    d[j] = PALETTE[v]; d[j + 1] = PALETTE[v + 1]; d[j + 2] = PALETTE[v + 2]; d[j + 3] = 255;
  }
  const ctx = s.ctx, g = s.geo;
  ctx.putImageData(s.image, 0, 0);
  ctx.strokeStyle = "rgba(120,200,255,0.35)"; ctx.fillStyle = "rgba(170,220,255,0.8)"; ctx.font = "10px sans-serif";
  const step = niceStep(g.rmax);
  for (let r = Math.ceil(g.rmin / step) * step; r <= g.rmax + 1e-9; r += step) {   // range rings
    ctx.beginPath(); ctx.arc(g.cx, g.cy, r * g.scale, -Math.PI / 2 + g.az0, -Math.PI / 2 + g.az1); ctx.stroke();
    ctx.fillText(`${r} m`, g.cx + r * g.scale * Math.sin(g.az1) + 3, g.cy - r * g.scale * Math.cos(g.az1));
  }
  const deg = (g.az1 - g.az0) * 180 / Math.PI > 60 ? 20 : 10;
  for (let a = Math.ceil(g.az0 * 180 / Math.PI / deg) * deg; a <= g.az1 * 180 / Math.PI; a += deg) {   // bearing lines
    const t = a * Math.PI / 180;
    ctx.beginPath();
    ctx.moveTo(g.cx + g.rmin * g.scale * Math.sin(t), g.cy - g.rmin * g.scale * Math.cos(t));
    ctx.lineTo(g.cx + g.rmax * g.scale * Math.sin(t), g.cy - g.rmax * g.scale * Math.cos(t)); ctx.stroke();
    ctx.fillText(`${a}\u00b0`, g.cx + (g.rmax * g.scale + 2) * Math.sin(t) - 8, g.cy - (g.rmax * g.scale + 4) * Math.cos(t));
  }
  stats.sonarFrames[h.device] = (stats.sonarFrames[h.device] || 0) + 1;
  s.canvas.dataset.frames = String(stats.sonarFrames[h.device]);
  s.canvas.dataset.frameIndex = String(h.frame_index);
  s.info.textContent = `frame ${h.frame_index}, t ${fmt(h.t, 2)} s, range ${fmt(h.range_min)}-${fmt(h.range_max)} m, ` +
    `gain ${h.gain_db === null || h.gain_db === undefined ? "-" : fmt(h.gain_db, 1) + " dB"}, ${h.shape[1]} beams x ${h.shape[0]} samples`;
}

// ---- camera ---------------------------------------------------------------------------------------
function setCamera(show) {
  cameraShown = show;
  $("camera-toggle").textContent = show ? "hide" : "show";
  send({ op: "camera", show });
}

function showCamera(h, jpeg) {
  if (!cameraShown) return;
  const img = $("camera"), url = URL.createObjectURL(new Blob([jpeg], { type: "image/jpeg" }));
  const old = img.src;
  img.onload = () => { if (old.startsWith("blob:")) URL.revokeObjectURL(old); };
  img.src = url;
  stats.cameraFrames++;
  $("camera-info").textContent = `${h.mount}, t ${fmt(h.t, 2)} s`;
}

window.addEventListener("error", (e) => stats.errors.push(String(e.message)));
document.addEventListener("visibilitychange", () => { if (hello && hello.cameras.length) setCamera(cameraWanted && !document.hidden); });
document.addEventListener("DOMContentLoaded", () => {
  $("camera-toggle").onclick = () => { cameraWanted = !cameraShown; setCamera(cameraWanted); };
  connect();
});
