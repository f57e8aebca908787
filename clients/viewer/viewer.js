// stylestream browser viewer: streams a clip through WS /v1/stream (protocol v1, JSON frames) and
// draws the input and the stylised skeleton side by side. No dependencies: forward kinematics and
// a small perspective canvas-2D renderer are below. Quaternions are [x, y, z, w]; Y up; cm.

const params = new URLSearchParams(location.search);
const TOKEN = params.get("token");
const $ = (id) => document.getElementById(id);
const ui = {
  model: $("model"), style: $("style"), style2: $("style2"), blend: $("blend"), blendVal: $("blend-val"),
  intensity: $("intensity"), intensityVal: $("intensity-val"), transition: $("transition"),
  source: $("source"), file: $("bvh-file"), play: $("play"), reset: $("reset"), canvas: $("view"),
  status: $("status"), counts: $("counts"), rate: $("rate"), weights: $("weights"),
  latLast: $("lat-last"), latMean: $("lat-mean"), latP95: $("lat-p95"), latMax: $("lat-max"),
};

// ------------------------------------------------------------------ quaternions and kinematics
function qmul(a, b) {
  const [ax, ay, az, aw] = a, [bx, by, bz, bw] = b;
  return [aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
          aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz];
}
function qrot(q, v) { // rotate v by unit quaternion q
  const [x, y, z, w] = q, [vx, vy, vz] = v;
  const tx = 2 * (y * vz - z * vy), ty = 2 * (z * vx - x * vz), tz = 2 * (x * vy - y * vx);
  return [vx + w * tx + y * tz - z * ty, vy + w * ty + z * tx - x * tz, vz + w * tz + x * ty - y * tx];
}
function qnorm(q) { const n = Math.hypot(q[0], q[1], q[2], q[3]) || 1; return [q[0] / n, q[1] / n, q[2] / n, q[3] / n]; }
function qaxis(axis, deg) {
  const h = deg * Math.PI / 360, s = Math.sin(h);
  return axis === "X" ? [s, 0, 0, Math.cos(h)] : axis === "Y" ? [0, s, 0, Math.cos(h)] : [0, 0, s, Math.cos(h)];
}

// World joint positions of one frame. skel: {parents, offsets, rootJoint}; the root joint's
// translation is `root`, every other joint sits at its offset.
function fk(skel, root, rotations) {
  const n = skel.parents.length, gr = new Array(n), gp = new Array(n);
  for (let j = 0; j < n; j++) {
    const p = skel.parents[j], r = qnorm(rotations[j]);
    const t = j === skel.rootJoint ? root : skel.offsets[j];
    if (p < 0) { gr[j] = r; gp[j] = t.slice(); continue; }
    gr[j] = qmul(gr[p], r);
    const o = qrot(gr[p], t);
    gp[j] = [gp[p][0] + o[0], gp[p][1] + o[1], gp[p][2] + o[2]];
  }
  return gp;
}

// ------------------------------------------------------------------ clips
// clip: {name, joints, parents, offsets, rootJoint, fps, root: [[x,y,z]...], rotations: [[[x,y,z,w]...]...],
//        header?: BVH hierarchy text (uploaded files), side: [joint side per joint: -1 right, 1 left, 0 centre]}
function sideOf(name) {
  if (/(_L$|^Left|^L(?=[A-Z])|^l(?=[A-Z]))/.test(name)) return 1;
  if (/(_R$|^Right|^R(?=[A-Z])|^r(?=[A-Z]))/.test(name)) return -1;
  return 0;
}
function finishClip(clip) {
  clip.side = clip.joints.map(sideOf);
  const n = clip.root.length;
  // looping: each pass continues where the last ended (horizontal displacement plus one step)
  const a = clip.root[0], b = clip.root[n - 1], c = clip.root[Math.max(0, n - 2)];
  clip.loopShift = [b[0] - a[0] + (b[0] - c[0]), 0, b[2] - a[2] + (b[2] - c[2])];
  const rest = fk(clip, clip.root[0], clip.rotations[0]);
  const ys = rest.map((p) => p[1]);
  clip.height = Math.max(1e-3, Math.max(...ys) - Math.min(...ys));
  clip.floor = Math.min(...ys);
  return clip;
}
function clipFrame(clip, seq) {
  const n = clip.root.length, k = Math.floor(seq / n), i = seq % n, r = clip.root[i], s = clip.loopShift;
  return { root: [r[0] + k * s[0], r[1], r[2] + k * s[2]], rotations: clip.rotations[i] };
}

async function loadDemo() {
  const d = await getJSON("/v1/demo/clip");
  return finishClip({ name: d.name, joints: d.joints, parents: d.parents, offsets: d.offsets, rootJoint: d.root_joint,
                      fps: d.fps, root: d.frames.root, rotations: d.frames.rotations, header: null });
}

// Minimal BVH reader: hierarchy, Euler channels (intrinsic, in channel order) -> quaternions.
function parseBVH(text) {
  const [head, motion] = text.split(/\bMOTION\b/);
  if (!motion) throw new Error("no MOTION section");
  const tok = head.split(/\s+/).filter(Boolean);
  const joints = [], parents = [], offsets = [], channels = [], stack = [];
  let i = 0, last = -1, inEnd = false;
  while (i < tok.length) {
    const t = tok[i++];
    if (t === "ROOT" || t === "JOINT") {
      joints.push(tok[i++]); parents.push(stack.length ? stack[stack.length - 1] : -1);
      offsets.push([0, 0, 0]); channels.push([]); last = joints.length - 1;
    } else if (t === "End") { i++; inEnd = true; }
    else if (t === "{") { stack.push(inEnd ? -2 : last); }
    else if (t === "}") { const top = stack.pop(); if (top === -2) inEnd = false; }
    else if (t === "OFFSET") {
      const v = [+tok[i], +tok[i + 1], +tok[i + 2]]; i += 3;
      if (!inEnd) offsets[last] = v;
    } else if (t === "CHANNELS") {
      const n = +tok[i++]; channels[last] = tok.slice(i, i + n); i += n;
    }
  }
  const lines = motion.trim().split(/\n/);
  const frames = +(/Frames:\s*(\d+)/.exec(motion) || [])[1];
  const dt = +(/Frame Time:\s*([\d.eE+-]+)/.exec(motion) || [])[1];
  const data = lines.slice(2).filter((l) => l.trim()).slice(0, frames).map((l) => l.trim().split(/\s+/).map(Number));
  if (!joints.length || !data.length) throw new Error("empty BVH");
  // the streamed root: a non-root joint with position channels (Bandai Namco's Hips), else the root
  let rootJoint = channels.findIndex((c, j) => j > 0 && c.includes("Xposition"));
  if (rootJoint < 0) rootJoint = 0;
  const root = [], rotations = [];
  for (const row of data) {
    let col = 0, rt = null;
    const rots = joints.map((_, j) => {
      let q = [0, 0, 0, 1]; const pos = offsets[j].slice();
      for (const ch of channels[j]) {
        const v = row[col++];
        if (ch.endsWith("position")) pos["XYZ".indexOf(ch[0])] = v;
        else q = qmul(q, qaxis(ch[0], v));
      }
      if (j === rootJoint) rt = pos;
      return q;
    });
    root.push(rt); rotations.push(rots);
  }
  const fps = dt > 0 ? Math.round(1 / dt * 100) / 100 : 30;
  return finishClip({ name: "uploaded BVH", joints, parents, offsets, rootJoint, fps, root, rotations,
                      header: head.trimEnd() + "\n" });
}

// ------------------------------------------------------------------ renderer
const view = { yaw: 0.95, pitch: 0.16, zoom: 1.0 };
const COLORS = {
  input: { 1: "#4ea1ff", [-1]: "#a9d1ff", 0: "#d8e6f7", label: "#4ea1ff" },
  output: { 1: "#ff8a3d", [-1]: "#ffc592", 0: "#f7e4d6", label: "#ff8a3d" },
};

class Panel {
  constructor(kind) { this.kind = kind; this.center = null; }
  follow(pos, clip) { // the camera tracks the root horizontally; the floor grid shows the travel
    const r = pos[clip.rootJoint];
    this.center = [r[0], r[2]];
  }
}
const panels = { input: new Panel("input"), output: new Panel("output") };

function camera(panel, clip, x0, w, h) {
  const s = clip.height / 170, dist = 420 * s / view.zoom, cy = clip.floor + 85 * s;
  const tx = panel.center ? panel.center[0] : 0, tz = panel.center ? panel.center[1] : 0;
  const c = [tx + dist * Math.sin(view.yaw) * Math.cos(view.pitch), cy + dist * Math.sin(view.pitch),
             tz + dist * Math.cos(view.yaw) * Math.cos(view.pitch)];
  const f = norm3([tx - c[0], cy - c[1], tz - c[2]]), r = norm3(cross(f, [0, 1, 0])), u = cross(r, f);
  const focal = 1.15 * Math.min(h, w * 1.4), ox = x0 + w / 2, oy = h * 0.52;
  return (p) => {
    const d = [p[0] - c[0], p[1] - c[1], p[2] - c[2]], z = dot(d, f);
    return [ox + focal * dot(d, r) / z, oy - focal * dot(d, u) / z, z, focal / z];
  };
}
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm3 = (a) => { const n = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / n, a[1] / n, a[2] / n]; };

function drawGrid(ctx, proj, panel, clip) {
  const step = 50 * clip.height / 170, n = 7, y = clip.floor;
  const cx = panel.center ? Math.round(panel.center[0] / step) * step : 0;
  const cz = panel.center ? Math.round(panel.center[1] / step) * step : 0;
  ctx.lineWidth = 1;
  for (let a = -n; a <= n; a++) {
    const alpha = 0.28 * (1 - Math.abs(a) / (n + 1));
    ctx.strokeStyle = `rgba(150,165,185,${alpha.toFixed(3)})`;
    for (const [p, q] of [[[cx + a * step, y, cz - n * step], [cx + a * step, y, cz + n * step]],
                          [[cx - n * step, y, cz + a * step], [cx + n * step, y, cz + a * step]]]) {
      const P = proj(p), Q = proj(q);
      if (P[2] <= 1 || Q[2] <= 1) continue;
      ctx.beginPath(); ctx.moveTo(P[0], P[1]); ctx.lineTo(Q[0], Q[1]); ctx.stroke();
    }
  }
}

function bones(clip) {
  // skip the bone from a static top root to the streamed root joint (Bandai Namco: joint_Root -> Hips)
  const out = [];
  clip.parents.forEach((p, j) => { if (p >= 0 && !(j === clip.rootJoint && clip.parents[p] < 0)) out.push([p, j]); });
  return out;
}

function drawSkeleton(ctx, proj, pos, clip, colors) {
  const list = bones(clip);
  const thick = clip.height / 170;
  // shadow on the floor
  ctx.strokeStyle = "rgba(0,0,0,0.35)"; ctx.lineCap = "round";
  for (const [p, j] of list) {
    const P = proj([pos[p][0], clip.floor, pos[p][2]]), Q = proj([pos[j][0], clip.floor, pos[j][2]]);
    if (P[2] <= 1 || Q[2] <= 1) continue;
    ctx.lineWidth = 5 * thick * (P[3] + Q[3]) / 2;
    ctx.beginPath(); ctx.moveTo(P[0], P[1]); ctx.lineTo(Q[0], Q[1]); ctx.stroke();
  }
  const segs = list.map(([p, j]) => { const P = proj(pos[p]), Q = proj(pos[j]); return { P, Q, j, z: (P[2] + Q[2]) / 2 }; });
  segs.sort((a, b) => b.z - a.z); // far first
  for (const { P, Q, j } of segs) {
    if (P[2] <= 1 || Q[2] <= 1) continue;
    const side = clip.side[j];
    ctx.strokeStyle = colors[side]; ctx.lineWidth = Math.max(2, 4.5 * thick * (P[3] + Q[3]) / 2);
    ctx.beginPath(); ctx.moveTo(P[0], P[1]); ctx.lineTo(Q[0], Q[1]); ctx.stroke();
    ctx.fillStyle = colors[side];
    ctx.beginPath(); ctx.arc(Q[0], Q[1], Math.max(2, 3.2 * thick * Q[3]), 0, 2 * Math.PI); ctx.fill();
  }
  // head: the topmost leaf joint gets a round head
  const head = clip.headJoint ?? (clip.headJoint = findHead(clip));
  if (head >= 0) {
    const H = proj(pos[head]);
    if (H[2] > 1) {
      ctx.fillStyle = colors[0]; ctx.beginPath(); ctx.arc(H[0], H[1], Math.max(4, 9 * thick * H[3]), 0, 2 * Math.PI); ctx.fill();
    }
  }
}
function findHead(clip) {
  const i = clip.joints.findIndex((n) => /^head$/i.test(n));
  return i >= 0 ? i : clip.joints.findIndex((n) => /head/i.test(n));
}

function label(ctx, x, y, text, color, sub) {
  ctx.font = "600 15px system-ui, sans-serif"; ctx.fillStyle = color; ctx.textBaseline = "top";
  ctx.fillText(text, x, y);
  if (sub) { ctx.font = "12px system-ui, sans-serif"; ctx.fillStyle = "#8e97a5"; ctx.fillText(sub, x, y + 19); }
}

function render() {
  const cv = ui.canvas, dpr = window.devicePixelRatio || 1;
  const w = cv.clientWidth, h = cv.clientHeight;
  if (cv.width !== Math.round(w * dpr) || cv.height !== Math.round(h * dpr)) { cv.width = Math.round(w * dpr); cv.height = Math.round(h * dpr); }
  const ctx = cv.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.fillStyle = "#14171c"; ctx.fillRect(0, 0, w, h);
  const half = w / 2;
  ctx.fillStyle = "#171b21"; ctx.fillRect(half, 0, half, h);
  ctx.strokeStyle = "#2a313c"; ctx.lineWidth = 1; ctx.beginPath(); ctx.moveTo(half + 0.5, 0); ctx.lineTo(half + 0.5, h); ctx.stroke();
  const clip = state.clip;
  if (!clip) { label(ctx, 14, 12, "loading clip…", "#8e97a5"); return; }
  const shown = state.lastOut;
  const inFrame = shown ? state.inputs.get(shown.seq) : null;
  const input = inFrame || clipFrame(clip, state.previewSeq);
  const styleName = state.session ? state.session.label : "not connected";
  const sides = [
    ["input", input, 0, `${clip.name}`],
    ["output", shown, half, shown ? styleName : (state.session ? "waiting for frames…" : "press play to stream")],
  ];
  for (const [kind, frame, x0, sub] of sides) {
    ctx.save(); ctx.beginPath(); ctx.rect(x0, 0, half, h); ctx.clip();
    const panel = panels[kind];
    let pos = null;
    if (frame) { pos = fk(clip, frame.root, frame.rotations); panel.follow(pos, clip); }
    const proj = camera(panel, clip, x0, half, h);
    drawGrid(ctx, proj, panel, clip);
    if (pos) drawSkeleton(ctx, proj, pos, clip, COLORS[kind]);
    label(ctx, x0 + 14, 12, kind === "input" ? "input" : "stylised", COLORS[kind].label, sub);
    ctx.restore();
  }
}
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

// ------------------------------------------------------------------ streaming
const state = {
  models: [], clip: null, demo: null, session: null, playing: false, seq: 0, previewSeq: 0,
  inputs: new Map(), sentAt: new Map(), lastOut: null, lat: [], sent: 0, received: 0, dropped: 0,
  recvTimes: [], held: 0, timer: null, nextSendAt: 0, transition: null,
};

function setStatus(text, error = false) { ui.status.textContent = text; ui.status.classList.toggle("error", error); }
function setBodyState(s) { document.body.dataset.state = s; }

function styleMessage() {
  const s = ui.style.value, s2 = ui.style2.value, b = +ui.blend.value;
  const msg = { intensity: +ui.intensity.value };
  if (s2 && s2 !== s && b > 0) msg.mix = b >= 1 ? { [s2]: 1 } : { [s]: 1 - b, [s2]: b };
  else msg.style = s;
  return msg;
}
function styleLabel() {
  const m = styleMessage(), model = ui.model.value;
  const what = m.mix ? Object.entries(m.mix).map(([k, v]) => `${k} ${v.toFixed(2)}`).join(" + ") : m.style;
  return `${model} · ${what} · intensity ${m.intensity.toFixed(2)}`;
}

function wsURL() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  return withToken(`${proto}//${location.host}/v1/stream`);
}

function openSession() {
  closeSession();
  const clip = state.clip;
  const ws = new WebSocket(wsURL());
  const session = { ws, ready: false, label: styleLabel(), model: ui.model.value };
  state.session = session;
  state.seq = 0; state.inputs.clear(); state.sentAt.clear(); state.lastOut = null; state.lat = [];
  state.sent = state.received = state.dropped = state.held = 0; state.recvTimes = []; state.transition = null;
  setBodyState("connecting"); setStatus("connecting…");
  ws.onopen = () => {
    const start = { type: "start", version: 1, model: session.model, fps: clip.fps, encoding: "json", ...styleMessage() };
    if (clip.header) start.bvh_header = clip.header; else start.skeleton = "bandai-namco";
    ws.send(JSON.stringify(start));
  };
  ws.onmessage = (ev) => {
    if (state.session !== session) return;
    let m; try { m = JSON.parse(ev.data); } catch { return; }
    if (m.type === "frame") onFrame(m);
    else if (m.type === "started") {
      session.ready = true; session.id = m.session_id;
      setBodyState("streaming"); setStatus(`session ${m.session_id.slice(0, 8)} · ${m.model} · ${m.joints.length} joints`);
      showWeights(m.styles && session.label);
      if (state.playing) schedule();
    } else if (m.type === "style_set") {
      session.label = styleLabel();
      state.transition = { from: state.seq, frames: m.transition_frames || 0 };
      showWeights(null, m.weights);
    } else if (m.type === "reset_done") setStatus("state reset");
    else if (m.type === "error") setStatus(`${m.code}: ${m.message}`, true);
  };
  ws.onclose = (ev) => {
    if (state.session !== session) return;
    state.session = null; stopTimer();
    setBodyState(ev.code === 1000 ? "ended" : "closed");
    if (ev.code !== 1000) setStatus(`connection closed (${ev.code}${ev.reason ? ": " + ev.reason : ""})`, ev.code !== 1000);
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
function showWeights(_, weights) {
  weightsText = weights ? "style weights → " + Object.entries(weights).filter(([, v]) => +v > 1e-3).map(([k, v]) => `${k} ${(+v).toFixed(2)}`).join(", ") : "";
  ui.weights.textContent = weightsText;
}

function stopTimer() { if (state.timer) { clearTimeout(state.timer); state.timer = null; } }

function schedule() { // open loop at the clip's frame rate: never waits for replies
  stopTimer();
  state.nextSendAt = performance.now();
  const tick = () => {
    const s = state.session;
    if (!state.playing || !s || !s.ready) { state.timer = null; return; }
    sendFrame(s);
    const period = 1000 / state.clip.fps;
    state.nextSendAt += period;
    const now = performance.now();
    if (state.nextSendAt < now - 5 * period) state.nextSendAt = now; // fell far behind (tab hidden): resync
    state.timer = setTimeout(tick, Math.max(0, state.nextSendAt - now));
  };
  tick();
}

const MAX_IN_FLIGHT = 6; // below the server's per-session queue (8), so a stalled link never makes it drop frames
function sendFrame(s) {
  // open loop while replies keep up; if the link stalls, hold the clip rather than flood the queue
  if (s.ws.bufferedAmount > 1 << 20 || state.sent - state.received - state.dropped >= MAX_IN_FLIGHT) { state.held++; return; }
  const seq = state.seq++;
  const f = clipFrame(state.clip, seq);
  state.inputs.set(seq, f);
  state.sentAt.set(seq, performance.now());
  s.ws.send(JSON.stringify({ type: "frame", seq, root: f.root, rotations: f.rotations }));
  state.sent++;
  for (const k of state.inputs.keys()) { if (k >= seq - 240) break; state.inputs.delete(k); state.sentAt.delete(k); }
}

function onFrame(m) {
  const now = performance.now(), t0 = state.sentAt.get(m.seq);
  if (t0 !== undefined) { state.lat.push(now - t0); if (state.lat.length > 120) state.lat.shift(); }
  state.received++; state.dropped += m.dropped || 0;
  state.recvTimes.push(now); while (state.recvTimes.length && state.recvTimes[0] < now - 1000) state.recvTimes.shift();
  state.lastOut = { seq: m.seq, root: m.root, rotations: m.rotations };
  document.body.dataset.received = String(state.received);
  updateHud();
  requestRender();
}

function updateHud() {
  const lat = state.lat;
  if (lat.length) {
    const sorted = lat.slice().sort((a, b) => a - b);
    const mean = lat.reduce((a, b) => a + b, 0) / lat.length;
    ui.latLast.textContent = lat[lat.length - 1].toFixed(1);
    ui.latMean.textContent = mean.toFixed(1);
    ui.latP95.textContent = sorted[Math.min(sorted.length - 1, Math.floor(0.95 * sorted.length))].toFixed(1);
    ui.latMax.textContent = sorted[sorted.length - 1].toFixed(1);
  }
  ui.counts.textContent = `sent ${state.sent} · received ${state.received} · dropped ${state.dropped}` +
    (state.held ? ` · held back ${state.held}` : "");
  ui.rate.textContent = String(state.recvTimes.length);
  const t = state.transition;
  if (t && t.frames > 0) {
    const done = Math.min(t.frames, Math.max(0, (state.lastOut ? state.lastOut.seq : 0) - t.from + 1));
    ui.weights.textContent = weightsText + (done < t.frames ? ` · transition ${done}/${t.frames} frames` : "");
  }
}

function sendStyle() {
  const s = state.session;
  ui.intensityVal.textContent = (+ui.intensity.value).toFixed(2);
  ui.blendVal.textContent = (+ui.blend.value).toFixed(2);
  ui.blend.disabled = !ui.style2.value;
  if (!s || !s.ready) { if (s) s.label = styleLabel(); requestRender(); return; }
  const msg = { type: "style", ...styleMessage(), transition_frames: Math.max(0, Math.round(+ui.transition.value || 0)) };
  s.ws.send(JSON.stringify(msg));
}

function play(on) {
  state.playing = on;
  ui.play.textContent = on ? "❚❚ pause" : "▶ play";
  ui.play.classList.toggle("on", on);
  if (!on) { stopTimer(); if (state.session) setBodyState("paused"); return; }
  if (!state.session || state.session.model !== ui.model.value) openSession();
  else if (state.session.ready) { setBodyState("streaming"); schedule(); }
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
}

async function init() {
  render();
  try {
    [state.models, state.demo] = await Promise.all([getJSON("/v1/models"), loadDemo()]);
  } catch (e) { setStatus(`could not load: ${e.message}`, true); setBodyState("error"); return; }
  state.clip = state.demo;
  for (const m of state.models) ui.model.add(new Option(m.name, m.name));
  const wantModel = params.get("model");
  if (wantModel && state.models.some((m) => m.name === wantModel)) ui.model.value = wantModel;
  fillStyles();
  if (params.has("intensity")) ui.intensity.value = params.get("intensity");
  ui.intensityVal.textContent = (+ui.intensity.value).toFixed(2);
  setStatus(`${state.models.length} models · clip: ${state.clip.name}, ${state.clip.root.length} frames at ${state.clip.fps} fps`);
  setBodyState("ready");

  ui.model.onchange = () => { fillStyles(); if (state.session) { openSession(); } };
  ui.style.onchange = ui.style2.onchange = ui.blend.oninput = sendStyle;
  ui.intensity.oninput = () => { ui.intensityVal.textContent = (+ui.intensity.value).toFixed(2); };
  ui.intensity.onchange = sendStyle;
  ui.play.onclick = () => play(!state.playing);
  ui.reset.onclick = () => { const s = state.session; if (s && s.ready) s.ws.send(JSON.stringify({ type: "reset" })); };
  ui.source.onchange = () => {
    if (ui.source.value === "bvh") ui.file.click();
    else { state.clip = state.demo; restartClip(); }
  };
  ui.file.onchange = async () => {
    const f = ui.file.files[0];
    if (!f) { ui.source.value = "demo"; return; }
    try { state.clip = parseBVH(await f.text()); state.clip.name = f.name; restartClip(); }
    catch (e) { setStatus(`${f.name}: ${e.message}`, true); ui.source.value = "demo"; }
  };
  window.addEventListener("keydown", (e) => {
    if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
    if (e.code === "Space") { e.preventDefault(); play(!state.playing); }
    const n = +e.key;
    if (n >= 1 && n <= 9 && ui.style.options[n - 1]) { ui.style.selectedIndex = n - 1; sendStyle(); }
  });
  // orbit and zoom
  let drag = null;
  ui.canvas.addEventListener("pointerdown", (e) => { drag = [e.clientX, e.clientY]; ui.canvas.setPointerCapture(e.pointerId); });
  ui.canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    view.yaw -= (e.clientX - drag[0]) * 0.008;
    view.pitch = Math.max(-0.2, Math.min(1.3, view.pitch + (e.clientY - drag[1]) * 0.006));
    drag = [e.clientX, e.clientY]; requestRender();
  });
  ui.canvas.addEventListener("pointerup", () => { drag = null; });
  ui.canvas.addEventListener("wheel", (e) => {
    e.preventDefault(); view.zoom = Math.max(0.3, Math.min(4, view.zoom * Math.exp(-e.deltaY * 0.001))); requestRender();
  }, { passive: false });
  window.addEventListener("resize", requestRender);
  // preview: the input clip plays locally while not streaming
  setInterval(() => { if (!state.session || !state.lastOut) { state.previewSeq++; requestRender(); } }, 1000 / 30);
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
  panels.input.center = panels.output.center = null;
  state.previewSeq = 0;
  if (state.session) openSession();
  requestRender();
}

init();
