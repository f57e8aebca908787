// stylestream browser viewer: opens a session on WS /v1/stream (protocol v1, JSON frames), streams a
// clip at its frame rate (or, for LPN-FiLM, one control message per tick from keyboard / gamepad)
// and draws the input and the stylised skeleton side by side in 3-D. Plain ES modules, no build:
// kinematics.js (maths), scene.js (three.js), triangle.js (3-way style mix), controller.js.

import { clipFrame, clipFromDemo, fkTransforms, parseBVH } from "./kinematics.js";
import { SideBySideView } from "./scene.js";
import { StyleTriangle } from "./triangle.js";
import { Controller } from "./controller.js";

const params = new URLSearchParams(location.search);
const TOKEN = params.get("token");
const CONTROL_MODEL = "lpn"; // the model driven by control messages instead of clip frames
const MAX_IN_FLIGHT = 6; // below the server's per-session queue (8), so a stalled link never makes it drop frames
const TRIANGLE_SEND_MS = 100; // at most this often while the triangle's point is dragged
const HUD_EVERY_MS = 200; // the readout's refresh: readable, and cheap to repaint

const $ = (id) => document.getElementById(id);
const ui = {
  model: $("model"), style: $("style"), style2: $("style2"), blend: $("blend"), blendVal: $("blend-val"),
  intensity: $("intensity"), intensityVal: $("intensity-val"), transition: $("transition"),
  source: $("source"), file: $("bvh-file"), addStyle: $("add-style"), styleFile: $("style-file"), play: $("play"), reset: $("reset"), canvas: $("view"),
  status: $("status"), counts: $("counts"), rate: $("rate"), weights: $("weights"),
  latLast: $("lat-last"), latMean: $("lat-mean"), latP95: $("lat-p95"), latMax: $("lat-max"),
  subInput: $("sub-input"), subOutput: $("sub-output"), controlHud: $("control-hud"), controlReadout: $("control-readout"),
};

const state = {
  models: [], clip: null, demo: null, session: null, playing: false, seq: 0, previewSeq: 0,
  inputs: new Map(), sentAt: new Map(), lastOut: null, lastControl: null,
  lat: [], sent: 0, received: 0, dropped: 0, recvTimes: [], held: 0, timer: null, nextSendAt: 0,
  transition: null, hudAt: 0, blendSource: "picker", // "picker": style / mix-with controls; "triangle": the style triangle
};

const view = new SideBySideView(ui.canvas, () => requestRender());
const controller = new Controller(ui.canvas);
let lastTriangleSend = 0;
const triangle = new StyleTriangle($("triangle"), (mix, final) => {
  state.blendSource = "triangle";
  triangle.setActive(true);
  const now = performance.now();
  if (final || now - lastTriangleSend >= TRIANGLE_SEND_MS) { lastTriangleSend = now; sendStyle(); }
});
window.viewer = { state, view, controller, triangle, addStyleFromClip }; // for the console and the browser tests

const controlMode = () => ui.source.value === "control";

// ------------------------------------------------------------------ drawing
let viewClip = null;
function render() {
  const clip = state.clip;
  if (!clip) return;
  if (viewClip !== clip) { view.setClip(clip); viewClip = clip; }
  const shown = state.lastOut;
  let outPos = null;
  if (shown) {
    const out = fkTransforms(clip, shown.root, shown.rotations);
    outPos = out.positions;
    view.show("output", outPos, shown.contacts, out.rotations);
  }
  else view.show("output", null);
  if (controlMode()) {
    view.show("input", null);
    if (outPos) view.stages.input.follow(outPos[clip.rootJoint]);
    view.showControl(state.lastControl || { velocity: [0, 0], facing: controller.facing });
  } else {
    const input = (shown && state.inputs.get(shown.seq)) || clipFrame(clip, state.previewSeq);
    const pose = fkTransforms(clip, input.root, input.rotations);
    view.show("input", pose.positions, null, pose.rotations);
    view.showControl(null);
  }
  setText(ui.subInput, controlMode() ? "controller" : clip.name);
  setText(ui.subOutput, shown ? (state.session ? state.session.label : "") :
    (state.session ? "waiting for frames…" : "press play to stream"));
  view.render();
}
/** Text changes repaint the page, which costs as much as a 3-D frame on software WebGL: only on change. */
function setText(el, text) { if (el.textContent !== text) el.textContent = text; }
let renderQueued = false;
function requestRender() {
  if (renderQueued) return;
  renderQueued = true;
  requestAnimationFrame(() => { renderQueued = false; render(); });
}

// ------------------------------------------------------------------ REST
function withToken(path) {
  if (!TOKEN) return path;
  return path + (path.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(TOKEN);
}
async function getJSON(path) {
  const r = await fetch(withToken(path));
  if (!r.ok) throw new Error(`${path}: HTTP ${r.status}`);
  return r.json();
}

// ------------------------------------------------------------------ style messages
function setStatus(text, error = false) { ui.status.textContent = text; ui.status.classList.toggle("error", error); }
function setBodyState(s) { document.body.dataset.state = s; }

/** The style part of `start` and `style` messages, from whichever control was used last. */
function styleMessage() {
  const msg = { intensity: +ui.intensity.value };
  if (state.blendSource === "triangle") {
    const mix = triangle.mix(), names = Object.keys(mix);
    if (names.length === 1) msg.style = names[0]; else msg.mix = mix;
    return msg;
  }
  const s = ui.style.value, s2 = ui.style2.value, b = +ui.blend.value;
  if (s2 && s2 !== s && b > 0) msg.mix = b >= 1 ? { [s2]: 1 } : { [s]: 1 - b, [s2]: b };
  else msg.style = s;
  return msg;
}
function styleLabel() {
  const m = styleMessage();
  const what = m.mix ? Object.entries(m.mix).map(([k, v]) => `${k} ${v.toFixed(2)}`).join(" + ") : m.style;
  return `${ui.model.value} · ${what} · intensity ${m.intensity.toFixed(2)}`;
}

function sendStyle() {
  const s = state.session;
  ui.intensityVal.textContent = (+ui.intensity.value).toFixed(2);
  ui.blendVal.textContent = (+ui.blend.value).toFixed(2);
  ui.blend.disabled = !ui.style2.value;
  if (!s || !s.ready) { if (s) s.label = styleLabel(); requestRender(); return; }
  s.ws.send(JSON.stringify({ type: "style", ...styleMessage(),
                             transition_frames: Math.max(0, Math.round(+ui.transition.value || 0)) }));
}
function usePickers() { state.blendSource = "picker"; triangle.setActive(false); sendStyle(); }

// ------------------------------------------------------------------ session
function wsURL() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  return withToken(`${proto}//${location.host}/v1/stream`);
}

function openSession() {
  closeSession();
  const clip = state.clip;
  const ws = new WebSocket(wsURL());
  const session = { ws, ready: false, label: styleLabel(), model: ui.model.value, control: controlMode() };
  state.session = session;
  state.seq = 0; state.inputs.clear(); state.sentAt.clear(); state.lastOut = null;
  state.lat = []; state.sent = state.received = state.dropped = state.held = 0; state.recvTimes = [];
  state.transition = null;
  setBodyState("connecting"); setStatus("connecting…");
  ws.onopen = () => {
    const start = { type: "start", version: 1, model: session.model, fps: clip.fps, encoding: "json", ...styleMessage() };
    if (clip.header && !session.control) start.bvh_header = clip.header; else start.skeleton = "bandai-namco";
    ws.send(JSON.stringify(start));
  };
  ws.onmessage = (ev) => {
    if (state.session !== session) return;
    let m; try { m = JSON.parse(ev.data); } catch { return; }
    if (m.type === "frame") onFrame(m);
    else if (m.type === "started") {
      session.ready = true; session.id = m.session_id;
      setBodyState("streaming"); setStatus(`session ${m.session_id.slice(0, 8)} · ${m.model} · ${m.joints.length} joints`);
      if (state.playing) schedule();
    } else if (m.type === "style_set") {
      session.label = styleLabel();
      state.transition = { from: state.seq, frames: m.transition_frames || 0 };
      showWeights(m.weights);
    } else if (m.type === "reset_done") setStatus("state reset");
    else if (m.type === "error") setStatus(`${m.code}: ${m.message}`, true);
  };
  ws.onclose = (ev) => {
    if (state.session !== session) return;
    state.session = null; stopTimer(); updateHud();
    setBodyState(ev.code === 1000 ? "ended" : "closed");
    if (ev.code !== 1000) setStatus(`connection closed (${ev.code}${ev.reason ? ": " + ev.reason : ""})`, true);
    if (state.playing) { state.playing = false; ui.play.textContent = "▶ play"; ui.play.classList.remove("on"); }
    requestRender();
  };
  ws.onerror = () => setStatus("WebSocket error", true);
}

function closeSession() {
  const s = state.session;
  state.session = null; stopTimer();
  if (s && s.ws.readyState <= 1) {
    try { if (s.ready) s.ws.send(JSON.stringify({ type: "end" })); } catch { /* closing anyway */ }
    s.ws.close(1000);
  }
}

let weightsText = "";
function showWeights(weights) {
  weightsText = weights ? "style weights → " + Object.entries(weights).filter(([, v]) => +v > 1e-3)
    .map(([k, v]) => `${k} ${(+v).toFixed(2)}`).join(", ") : "";
  ui.weights.textContent = weightsText;
}

// ------------------------------------------------------------------ streaming
function stopTimer() { if (state.timer) { clearTimeout(state.timer); state.timer = null; } }

function schedule() { // open loop at the clip's frame rate: never waits for replies
  stopTimer();
  state.nextSendAt = performance.now();
  const tick = () => {
    const s = state.session;
    if (!state.playing || !s || !s.ready) { state.timer = null; return; }
    const period = 1000 / state.clip.fps;
    if (s.control) sendControl(s, period / 1000); else sendFrame(s);
    state.nextSendAt += period;
    const now = performance.now();
    if (state.nextSendAt < now - 5 * period) state.nextSendAt = now; // fell far behind (tab hidden): resync
    state.timer = setTimeout(tick, Math.max(0, state.nextSendAt - now));
  };
  tick();
}

/** Open loop while replies keep up; if the link stalls, hold back rather than flood the server's queue. */
function stalled(s) {
  if (s.ws.bufferedAmount > 1 << 20 || state.sent - state.received - state.dropped >= MAX_IN_FLIGHT) { state.held++; return true; }
  return false;
}

function sendFrame(s) {
  if (stalled(s)) return;
  const seq = state.seq++;
  const f = clipFrame(state.clip, seq);
  state.inputs.set(seq, f);
  state.sentAt.set(seq, performance.now());
  s.ws.send(JSON.stringify({ type: "frame", seq, root: f.root, rotations: f.rotations }));
  state.sent++;
  for (const k of state.inputs.keys()) { if (k >= seq - 240) break; state.inputs.delete(k); state.sentAt.delete(k); }
}

function sendControl(s, dt) {
  const msg = controller.sample(dt); // sampled every tick, so facing turns at its rate even when held back
  state.lastControl = msg;
  showControlReadout(msg);
  if (stalled(s)) return;
  const seq = state.seq++; // the reply to a control tick carries its seq, like a frame's
  state.sentAt.set(seq, performance.now());
  s.ws.send(JSON.stringify({ ...msg, seq }));
  for (const k of state.sentAt.keys()) { if (k >= seq - 240) break; state.sentAt.delete(k); } // dropped ticks
  state.sent++;
  requestRender();
}

function showControlReadout(msg) {
  const [f, side] = msg.velocity;
  setText(ui.controlReadout, `forward ${f.toFixed(2)} m/s · side ${side.toFixed(2)} m/s · facing ` +
    `${(msg.facing * 180 / Math.PI).toFixed(0)}° · ${msg.gait}` + (controller.gamepad ? ` · ${controller.gamepad}` : " · keyboard"));
}

function onFrame(m) {
  const now = performance.now();
  const t0 = state.sentAt.get(m.seq);
  state.sentAt.delete(m.seq);
  if (t0 !== undefined) { state.lat.push(now - t0); if (state.lat.length > 120) state.lat.shift(); }
  state.received++; state.dropped += m.dropped || 0;
  state.recvTimes.push(now); while (state.recvTimes.length && state.recvTimes[0] < now - 1000) state.recvTimes.shift();
  state.lastOut = { seq: m.seq, root: m.root, rotations: m.rotations, contacts: m.contacts };
  document.body.dataset.received = String(state.received);
  if (now - state.hudAt >= HUD_EVERY_MS) { state.hudAt = now; updateHud(); }
  requestRender();
}

function updateHud() {
  const lat = state.lat;
  if (lat.length) {
    const sorted = lat.slice().sort((a, b) => a - b);
    setText(ui.latLast, lat[lat.length - 1].toFixed(1));
    setText(ui.latMean, (lat.reduce((a, b) => a + b, 0) / lat.length).toFixed(1));
    setText(ui.latP95, sorted[Math.min(sorted.length - 1, Math.floor(0.95 * sorted.length))].toFixed(1));
    setText(ui.latMax, sorted[sorted.length - 1].toFixed(1));
  }
  setText(ui.counts, `sent ${state.sent} · received ${state.received} · dropped ${state.dropped}` +
    (state.held ? ` · held back ${state.held}` : ""));
  setText(ui.rate, String(state.recvTimes.length));
  const t = state.transition;
  if (t && t.frames > 0) {
    const done = Math.min(t.frames, Math.max(0, (state.lastOut ? state.lastOut.seq : 0) - t.from + 1));
    setText(ui.weights, weightsText + (done < t.frames ? ` · transition ${done}/${t.frames} frames` : ""));
  }
}

function play(on) {
  state.playing = on;
  ui.play.textContent = on ? "❚❚ pause" : "▶ play";
  ui.play.classList.toggle("on", on);
  if (!on) { stopTimer(); updateHud(); if (state.session) setBodyState("paused"); return; }
  if (!state.session || state.session.model !== ui.model.value || state.session.control !== controlMode()) openSession();
  else if (state.session.ready) { setBodyState("streaming"); schedule(); }
}

// ------------------------------------------------------------------ a new style from a dropped clip
const JOB_POLL_MS = 400;

/** A style name the server takes (a slug of 1-40 a-z, 0-9 and '-') from a file name, not yet in `taken`. */
function styleSlug(fileName, taken) {
  const base = fileName.replace(/\.bvh$/i, "").toLowerCase().replace(/[^a-z0-9]+/g, "-")
    .replace(/^-+|-+$/g, "").slice(0, 34).replace(/-+$/, "") || "clip";
  let name = base;
  for (let n = 2; taken.includes(name); n++) name = `${base}-${n}`;
  return name;
}

/** Upload a BVH clip as a new style of the chosen model, with a fine-tuning job followed to its
 * end, then stream with it: at once where the model makes a style from the clip on the spot
 * (LPN-FiLM answers 201 and its job refines it), else when the job is done (LTI). The page's
 * `data-upload` says where it is: uploading, queued, running, done or failed. */
async function addStyleFromClip(file) {
  const model = ui.model.value;
  const m = state.models.find((x) => x.name === model);
  const name = styleSlug(file.name, m ? m.styles : []);
  const form = new FormData();
  form.append("name", name); form.append("model", model); form.append("fine_tune", "true");
  form.append("file", file, file.name);
  document.body.dataset.upload = "uploading";
  setStatus(`uploading ${file.name} to ${model} as '${name}'…`);
  const r = await fetch(withToken("/v1/styles"), { method: "POST", body: form });
  const body = await r.json().catch(() => ({}));
  if (!r.ok) {
    document.body.dataset.upload = "failed";
    setStatus(`${file.name}: ${body.code || `HTTP ${r.status}`}: ${body.message || ""}`, true);
    return;
  }
  const live = r.status === 201;
  if (live) await useNewStyle(model, name);
  if (body.job) await followJob(body.job.id, model, name, live);
  else document.body.dataset.upload = "done";
}

async function followJob(id, model, name, live) {
  for (;;) {
    const job = await getJSON(`/v1/jobs/${id}`);
    document.body.dataset.upload = job.status;
    const pct = Math.round(100 * job.progress);
    if (job.status === "failed") { setStatus(`${model}.${name}: job failed: ${job.message}`, true); return; }
    if (job.status === "done") {
      if (!live) await useNewStyle(model, name);
      setStatus(`${model}.${name} ready${live ? " (fine-tuned)" : ""}`);
      return;
    }
    setStatus(`${model}.${name}: ${job.status} ${pct}%${job.message ? ` · ${job.message}` : ""}${live ? " · streaming it already" : ""}`);
    await new Promise((done) => setTimeout(done, JOB_POLL_MS));
  }
}

/** The server's styles again, and the new one picked (sent to a running session as a style change). */
async function useNewStyle(model, name) {
  state.models = await getJSON("/v1/models");
  if (ui.model.value !== model) return;
  fillStyles();
  ui.style.value = name;
  usePickers();
}

function acceptDroppedClips() {
  window.addEventListener("dragover", (e) => { e.preventDefault(); document.body.classList.add("dropping"); });
  window.addEventListener("dragleave", () => document.body.classList.remove("dropping"));
  window.addEventListener("drop", (e) => {
    e.preventDefault();
    document.body.classList.remove("dropping");
    const f = [...(e.dataTransfer ? e.dataTransfer.files : [])].find((x) => /\.bvh$/i.test(x.name));
    if (f) addStyleFromClip(f).catch((err) => setStatus(`${f.name}: ${err.message}`, true));
    else setStatus("drop a .bvh file to make a new style from it", true);
  });
  ui.addStyle.onclick = () => ui.styleFile.click();
  ui.styleFile.onchange = () => {
    const f = ui.styleFile.files[0];
    if (f) addStyleFromClip(f).catch((err) => setStatus(`${f.name}: ${err.message}`, true));
    ui.styleFile.value = "";
  };
}

// ------------------------------------------------------------------ wiring
function fillStyles() {
  const m = state.models.find((x) => x.name === ui.model.value);
  const styles = m ? m.styles : [];
  const want = params.get("style") || ui.style.value || "elderly";
  ui.style.innerHTML = ""; ui.style2.innerHTML = '<option value="">(none)</option>';
  styles.forEach((s, i) => {
    ui.style.add(new Option(`${i < 9 ? i + 1 + " " : ""}${s}`, s));
    ui.style2.add(new Option(s, s));
  });
  ui.style.value = styles.includes(want) ? want : styles[0] || "";
  triangle.setStyles(styles);
}

/** The controller drive is offered only while the chosen model is the one that takes control messages. */
function fillSources() {
  const offer = ui.model.value === CONTROL_MODEL;
  let option = ui.source.querySelector('option[value="control"]');
  if (offer && !option) ui.source.add(new Option("keyboard / gamepad", "control"));
  if (!offer && option) { if (controlMode()) ui.source.value = "demo"; option.remove(); }
  showDrive();
}
function showDrive() {
  ui.controlHud.hidden = !controlMode();
  document.body.dataset.mode = controlMode() ? "control" : "clip";
}

async function init() {
  try {
    [state.models, state.demo] = await Promise.all([getJSON("/v1/models"), getJSON("/v1/demo/clip").then(clipFromDemo)]);
  } catch (e) { setStatus(`could not load: ${e.message}`, true); setBodyState("error"); return; }
  state.clip = state.demo;
  for (const m of state.models) ui.model.add(new Option(m.name, m.name));
  const wantModel = params.get("model");
  if (wantModel && state.models.some((m) => m.name === wantModel)) ui.model.value = wantModel;
  fillStyles();
  fillSources();
  if (params.has("intensity")) ui.intensity.value = params.get("intensity");
  ui.intensityVal.textContent = (+ui.intensity.value).toFixed(2);
  setStatus(`${state.models.length} models · clip: ${state.clip.name}, ${state.clip.root.length} frames at ${state.clip.fps} fps`);
  setBodyState("ready");

  ui.model.onchange = () => { fillStyles(); fillSources(); if (state.session) openSession(); };
  ui.style.onchange = ui.style2.onchange = ui.blend.oninput = usePickers;
  ui.intensity.oninput = () => { ui.intensityVal.textContent = (+ui.intensity.value).toFixed(2); };
  ui.intensity.onchange = sendStyle;
  ui.play.onclick = () => play(!state.playing);
  ui.reset.onclick = () => {
    const s = state.session;
    if (s && s.ready) s.ws.send(JSON.stringify({ type: "reset" }));
    controller.reset();
  };
  ui.source.onchange = () => {
    showDrive();
    if (ui.source.value === "bvh") ui.file.click();
    else { state.clip = state.demo; restartClip(); }
  };
  ui.file.onchange = async () => {
    const f = ui.file.files[0];
    if (!f) { ui.source.value = "demo"; return; }
    try { state.clip = parseBVH(await f.text(), state.demo.rigs); state.clip.name = f.name; restartClip(); }
    catch (e) { setStatus(`${f.name}: ${e.message}`, true); ui.source.value = "demo"; }
  };
  window.addEventListener("keydown", (e) => {
    if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
    if (e.code === "Space") { e.preventDefault(); play(!state.playing); }
    const n = +e.key;
    if (n >= 1 && n <= 9 && ui.style.options[n - 1]) { ui.style.selectedIndex = n - 1; usePickers(); }
  });
  window.addEventListener("resize", requestRender);
  acceptDroppedClips();
  // preview while nothing streams: the input clip plays locally, or the controller's wish is shown
  setInterval(() => {
    const streaming = state.session && state.session.ready && state.playing; // then the send ticks do this
    if (controlMode() && !streaming) {
      state.lastControl = controller.sample(1 / 30);
      showControlReadout(state.lastControl);
      requestRender();
    } else if (!controlMode() && !state.lastOut) { state.previewSeq++; requestRender(); }
  }, 1000 / 30);
  requestRender();
  if (params.get("autoplay") === "1") { play(true); holdUntilStreaming(); }
}

// Headless screenshots (chromium --virtual-time-budget) run on virtual time, which does not wait
// for a WebSocket but does wait for pending fetches: keep a short real-time fetch pending until
// the stream is up, so the screenshot shows it. In a normal browser this ends within a second.
async function holdUntilStreaming(frames = 30, maxMs = 6000) {
  const t0 = Date.now();
  let n = 0;
  while (state.received < frames && n++ < 400 && Date.now() - t0 < maxMs) {
    try { await fetch(withToken("/viewer/hold?ms=15"), { cache: "no-store" }); } catch { return; }
  }
}

function restartClip() {
  state.previewSeq = 0;
  state.lastOut = null;
  state.lastControl = null;
  controller.reset();
  if (state.session) openSession();
  requestRender();
}

init();
