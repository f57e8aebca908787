// The style triangle: three styles at the corners of a triangle and a point dragged inside it;
// the point's barycentric coordinates are the style mix ({"mix": {a: wa, b: wb, c: wc}} in the
// protocol's style message). The maths is pure (`barycentric`, `pointAt`, `mixFrom`); the SVG
// widget calls back with the mix while the point is dragged.

const SVG = "http://www.w3.org/2000/svg";

/** Barycentric coordinates of 2-D point p in triangle [a, b, c] (may be negative outside). */
export function barycentric(p, [a, b, c]) {
  const det = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1]);
  const wa = ((b[1] - c[1]) * (p[0] - c[0]) + (c[0] - b[0]) * (p[1] - c[1])) / det;
  const wb = ((c[1] - a[1]) * (p[0] - c[0]) + (a[0] - c[0]) * (p[1] - c[1])) / det;
  return [wa, wb, 1 - wa - wb];
}

/** The point with barycentric coordinates w in triangle t. */
export function pointAt(w, t) {
  return [0, 1].map((k) => w[0] * t[0][k] + w[1] * t[1][k] + w[2] * t[2][k]);
}

/** The triangle's point nearest to p (p itself when inside), as barycentric coordinates >= 0 summing to 1. */
export function clampedBarycentric(p, t) {
  const w = barycentric(p, t);
  if (w.every((x) => x >= 0)) return w;
  let best = null;
  for (const [i, j] of [[0, 1], [1, 2], [2, 0]]) { // nearest point on each edge
    const a = t[i], b = t[j], ab = [b[0] - a[0], b[1] - a[1]];
    const s = Math.max(0, Math.min(1, ((p[0] - a[0]) * ab[0] + (p[1] - a[1]) * ab[1]) / (ab[0] ** 2 + ab[1] ** 2)));
    const q = [a[0] + s * ab[0], a[1] + s * ab[1]], d = Math.hypot(p[0] - q[0], p[1] - q[1]);
    if (!best || d < best.d) { best = { d, w: [0, 0, 0] }; best.w[i] = 1 - s; best.w[j] = s; }
  }
  return best.w;
}

/**
 * The style mix for corner styles and weights: weights of a style at two corners add up, shares
 * under 0.5 % are left out (the server renormalises), rounded to 3 decimals.
 */
export function mixFrom(styles, weights) {
  const mix = {};
  styles.forEach((s, i) => { if (s && weights[i] >= 0.005) mix[s] = (mix[s] || 0) + weights[i]; });
  for (const s in mix) mix[s] = Math.round(mix[s] * 1000) / 1000;
  return mix;
}

/** The widget: an SVG triangle with a draggable point and a style picker at each corner. */
export class StyleTriangle {
  /** root: a container holding an <svg> and three <select data-corner="0|1|2">; onMix(mix, final). */
  constructor(root, onMix) {
    this.root = root;
    this.onMix = onMix;
    this.svg = root.querySelector("svg");
    this.pickers = [...root.querySelectorAll("select[data-corner]")];
    this.corners = [[80, 8], [8, 132], [152, 132]]; // viewBox 0 0 160 140: top, bottom left, bottom right
    this.weights = [1 / 3, 1 / 3, 1 / 3];
    this.draw();
    let dragging = false;
    const move = (e, final) => {
      const r = this.svg.getBoundingClientRect();
      const p = [(e.clientX - r.left) * 160 / r.width, (e.clientY - r.top) * 140 / r.height];
      this.set(clampedBarycentric(p, this.corners), final);
    };
    this.svg.addEventListener("pointerdown", (e) => {
      dragging = true;
      this.svg.setPointerCapture(e.pointerId);
      move(e, false);
    });
    this.svg.addEventListener("pointermove", (e) => { if (dragging) move(e, false); });
    this.svg.addEventListener("pointerup", (e) => { if (dragging) { dragging = false; move(e, true); } });
    this.pickers.forEach((p) => p.addEventListener("change", () => this.onMix(this.mix(), true)));
  }

  draw() {
    const [a, b, c] = this.corners;
    this.svg.innerHTML = "";
    const el = (name, attrs) => {
      const e = document.createElementNS(SVG, name);
      for (const k in attrs) e.setAttribute(k, attrs[k]);
      this.svg.appendChild(e);
      return e;
    };
    el("polygon", { points: `${a} ${b} ${c}`, class: "tri" });
    for (const q of this.corners) el("circle", { cx: q[0], cy: q[1], r: 3.5, class: "corner" });
    this.guides = this.corners.map(() => el("line", { class: "guide" }));
    this.knob = el("circle", { r: 6, class: "knob" });
    this.place();
  }

  place() {
    const [x, y] = pointAt(this.weights, this.corners);
    this.knob.setAttribute("cx", x); this.knob.setAttribute("cy", y);
    this.guides.forEach((g, i) => {
      g.setAttribute("x1", x); g.setAttribute("y1", y);
      g.setAttribute("x2", this.corners[i][0]); g.setAttribute("y2", this.corners[i][1]);
      g.style.opacity = (0.15 + 0.85 * this.weights[i]).toFixed(2);
    });
  }

  /** Moves the point to barycentric weights `w` and reports the mix (final: the drag ended). */
  set(w, final = true) {
    this.weights = w;
    this.place();
    this.onMix(this.mix(), final);
  }

  styles() { return this.pickers.map((p) => p.value); }

  mix() { return mixFrom(this.styles(), this.weights); }

  /** Fills the corner pickers with a model's styles, keeping choices that still exist. */
  setStyles(styles) {
    this.pickers.forEach((picker, i) => {
      const keep = picker.value;
      picker.innerHTML = "";
      styles.forEach((s) => picker.add(new Option(s, s)));
      picker.value = styles.includes(keep) ? keep : styles[i % Math.max(1, styles.length)] || "";
    });
  }

  setActive(on) { this.root.classList.toggle("active", on); }
}
