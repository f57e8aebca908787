// The 3-D drawing: one three.js scene seen through two viewports side by side, the input on the
// left and the stylised output on the right. Each side has its own camera following its own
// character, and both share one orbit (OrbitControls on a detached camera), so dragging turns
// both views together and the two skeletons stay comparable even when the output's root drifts
// from the input's. Each side's objects live on their own layer, so a camera sees its own
// skeleton and floor grid only. Drawing happens on demand (new frame or camera move), not every
// animation frame, to leave the CPU to the stream.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { SOLID_FACES, placeSolid } from "./kinematics.js";

/** Skeleton colours by side (1 left, -1 right, 0 centre); the tests look for the left-limb hues. */
export const PALETTE = {
  input: { 1: 0x4ea1ff, [-1]: 0xa9d1ff, 0: 0xd8e6f7 },
  output: { 1: 0xff8a3d, [-1]: 0xffc592, 0: 0xf7e4d6 },
};
/** The nose and thumb stubs on head and hands, on both figures: bright against the dark floor. */
export const MARK_COLOUR = 0xffd400;
const FACE_COLOUR = 0xffc9a0; // the head's front
const BACKGROUND = 0x14171c;
const CONTACT_COLOUR = 0x7ee787;
const UP = new THREE.Vector3(0, 1, 0);
// default orbit, in units of a 170 cm character: yaw from +Z, pitch above the horizon, distance
const ORBIT = { yaw: 0.95, pitch: 0.16, distance: 380 };

const unitCylinder = new THREE.CylinderGeometry(1, 1, 1, 12, 1);
const unitSphere = new THREE.SphereGeometry(1, 16, 12);
const unitRing = new THREE.RingGeometry(0.55, 1, 32).rotateX(-Math.PI / 2);
const unitDisc = new THREE.CircleGeometry(1, 32).rotateX(-Math.PI / 2);

/**
 * A square floor grid of `cells` x `cells` cells of size `step`, centred on the origin, whose lines
 * fade into the background towards the rim. Each line is cut into one segment per cell: a long
 * segment reaching behind the camera is dropped whole by some WebGL implementations (SwiftShader),
 * which would blank the floor in front of the viewer.
 */
function floorGrid(cells, step) {
  const half = cells / 2, positions = [], colours = [];
  const line = new THREE.Color(0x4a5361), bg = new THREE.Color(BACKGROUND), c = new THREE.Color();
  const shade = (x, z) => {
    const fade = Math.min(1, Math.hypot(x, z) / half);
    c.copy(line).lerp(bg, fade * fade);
    colours.push(c.r, c.g, c.b);
  };
  for (let i = -half; i <= half; i++) {
    for (let k = -half; k < half; k++) {
      for (const [x0, z0, x1, z1] of [[i, k, i, k + 1], [k, i, k + 1, i]]) {
        positions.push(x0 * step, 0, z0 * step, x1 * step, 0, z1 * step);
        shade(x0, z0); shade(x1, z1);
      }
    }
  }
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.Float32BufferAttribute(positions, 3));
  geometry.setAttribute("color", new THREE.Float32BufferAttribute(colours, 3));
  return new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({ vertexColors: true }));
}

/**
 * The faces of one oriented solid (corners in its part frame, `SOLID_FACES` order x-, x+, y-, y+,
 * z-, z+) as a flat-shaded geometry with a colour per face: the side colour, or the mark colour for
 * nose and thumb; the head's front warm, a hand's palm dark (z+ on the left hand, z- on the right),
 * a foot's top light and its sole dark, so a part rolled about its own axis shows.
 */
function solidGeometry(solid, colours) {
  const base = new THREE.Color(solid.mark ? MARK_COLOUR : colours[solid.side]);
  const tints = SOLID_FACES.map(() => base.clone());
  const kind = solid.part.split("_")[0];
  if (!solid.mark && kind === "head") tints[1].lerp(new THREE.Color(FACE_COLOUR), 0.6);
  if (!solid.mark && kind === "hand") tints[solid.side > 0 ? 5 : 4].multiplyScalar(0.35);
  if (kind === "foot" || kind === "toe") { tints[3].lerp(new THREE.Color(0xffffff), 0.5); tints[2].multiplyScalar(0.35); }
  const positions = [], colour = [];
  SOLID_FACES.forEach(([a, b, c, d], f) => {
    for (const k of [a, b, c, a, c, d]) {
      positions.push(...solid.corners[k]);
      colour.push(tints[f].r, tints[f].g, tints[f].b);
    }
  });
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.Float32BufferAttribute(positions, 3));
  geometry.setAttribute("color", new THREE.Float32BufferAttribute(colour, 3));
  geometry.computeVertexNormals(); // not indexed: one normal per face
  return geometry;
}

/**
 * Bones as cylinders, joints as balls, one material per body side; the head (with a nose), hands
 * (palm and thumb) and feet as oriented solids turned by the joints' world rotations, or a ball
 * for a head when the server has no solids for the skeleton.
 */
class Figure {
  constructor(clip, colours, scale) {
    this.clip = clip;
    this.group = new THREE.Group();
    const material = (side) => new THREE.MeshLambertMaterial({ color: colours[side] });
    this.materials = { 1: material(1), [-1]: material(-1), 0: material(0) };
    this.radius = 2.2 * scale;
    this.bones = clip.bones.map(([p, c]) => this.add(unitCylinder, this.materials[clip.side[c]]));
    const drawn = new Set(clip.bones.flat());
    const headSolid = clip.solids.some((s) => s.part === "head");
    this.joints = clip.joints.map((_, j) => {
      if (!drawn.has(j)) return null;
      const ball = this.add(unitSphere, this.materials[clip.side[j]]);
      ball.scale.setScalar(j === clip.head && !headSolid ? 9 * scale : 1.45 * this.radius);
      return ball;
    });
    this.solidMaterial = new THREE.MeshLambertMaterial({ vertexColors: true });
    this.solids = clip.solids.map((solid) => this.add(solidGeometry(solid, colours), this.solidMaterial));
  }

  add(geometry, material) {
    const mesh = new THREE.Mesh(geometry, material);
    this.group.add(mesh);
    return mesh;
  }

  /** Places every mesh for one frame of world joint positions and rotations (no rotations: no solids). */
  pose(positions, rotations) {
    const a = new THREE.Vector3(), b = new THREE.Vector3(), d = new THREE.Vector3();
    this.clip.bones.forEach(([p, c], i) => {
      const mesh = this.bones[i];
      a.fromArray(positions[p]); b.fromArray(positions[c]);
      const length = d.subVectors(b, a).length();
      mesh.visible = length > 1e-6;
      if (!mesh.visible) return;
      mesh.position.addVectors(a, b).multiplyScalar(0.5);
      mesh.quaternion.setFromUnitVectors(UP, d.divideScalar(length));
      mesh.scale.set(this.radius, length, this.radius);
    });
    this.joints.forEach((ball, j) => { if (ball) ball.position.fromArray(positions[j]); });
    this.clip.solids.forEach((solid, i) => {
      const mesh = this.solids[i];
      mesh.visible = !!rotations;
      if (!rotations) return;
      const { position, quaternion } = placeSolid(solid, rotations, positions);
      mesh.position.fromArray(position);
      mesh.quaternion.fromArray(quaternion);
    });
  }

  dispose() {
    Object.values(this.materials).forEach((m) => m.dispose());
    this.solidMaterial.dispose();
    this.solids.forEach((mesh) => mesh.geometry.dispose());
  }
}

/** One side: its layer, camera, floor grid, figure with a blob shadow, foot-contact rings, control arrows. */
class Stage {
  constructor(scene, layer, colours) {
    this.scene = scene;
    this.layer = layer;
    this.colours = colours;
    this.camera = new THREE.PerspectiveCamera(40, 1, 1, 20000);
    this.camera.layers.set(layer);
    this.focus = new THREE.Vector3();
    this.figure = null;
    this.grid = null;
    this.contacts = [0, 1].map(() => this.own(new THREE.Mesh(unitRing,
      new THREE.MeshBasicMaterial({ color: CONTACT_COLOUR, transparent: true, opacity: 0.9, depthWrite: false }))));
    this.contacts.forEach((ring) => { ring.visible = false; });
    this.shadow = this.own(new THREE.Mesh(unitDisc,
      new THREE.MeshBasicMaterial({ color: 0x000000, transparent: true, opacity: 0.35, depthWrite: false })));
    this.shadow.visible = false;
    this.velocityArrow = this.own(new THREE.ArrowHelper(new THREE.Vector3(0, 0, 1), new THREE.Vector3(), 1, colours[1]));
    this.facingArrow = this.own(new THREE.ArrowHelper(new THREE.Vector3(0, 0, 1), new THREE.Vector3(), 1, 0xe6e9ee));
    this.velocityArrow.visible = this.facingArrow.visible = false;
  }

  own(object) {
    object.traverse((o) => o.layers.set(this.layer));
    this.scene.add(object);
    return object;
  }

  setClip(clip, scale) {
    if (this.figure) { this.scene.remove(this.figure.group); this.figure.dispose(); }
    if (this.grid) { this.scene.remove(this.grid); this.grid.geometry.dispose(); this.grid.material.dispose(); }
    this.clip = clip;
    this.scale = scale;
    this.figure = new Figure(clip, this.colours, scale);
    this.own(this.figure.group);
    this.figure.group.visible = false;
    this.gridStep = 50 * scale;
    this.grid = this.own(floorGrid(24, this.gridStep));
    this.contacts.forEach((ring) => ring.scale.setScalar(7 * scale));
    this.shadow.scale.setScalar(28 * scale);
    this.follow(clip.root[0]);
  }

  /** The camera's focus: above the root at half the character's height, on the floor grid. */
  follow(root) {
    const s = this.scale;
    this.focus.set(root[0], this.clip.floor + 85 * s, root[2]);
    const step = this.gridStep;
    this.grid.position.set(Math.round(root[0] / step) * step, this.clip.floor, Math.round(root[2] / step) * step);
  }

  /**
   * One frame: world joint positions (or null to hide), optional [left, right] foot contacts and
   * world joint rotations (for the head, hand and foot solids).
   */
  show(positions, contacts, rotations) {
    this.figure.group.visible = this.shadow.visible = !!positions;
    if (!positions) { this.contacts.forEach((ring) => { ring.visible = false; }); return; }
    this.figure.pose(positions, rotations);
    const root = positions[this.clip.rootJoint];
    this.follow(root);
    this.shadow.position.set(root[0], this.clip.floor + 0.2 * this.scale, root[2]); // grounds the figure
    this.clip.feet.forEach((joint, i) => {
      const ring = this.contacts[i], on = Array.isArray(contacts) && joint >= 0 && +contacts[i] > 0.5;
      ring.visible = on;
      if (on) ring.position.set(positions[joint][0], this.clip.floor + 0.4 * this.scale, positions[joint][2]);
    });
  }

  /**
   * The controller's wish instead of a skeleton: an arrow for the velocity (1 m/s = 1 m long)
   * and one for the facing, both from the stage's focus on the floor.
   */
  showControl(control) {
    const on = !!control;
    this.velocityArrow.visible = this.facingArrow.visible = on;
    if (!on) return;
    const s = this.scale, yaw = control.facing, [forward, side] = control.velocity;
    const ahead = new THREE.Vector3(Math.sin(yaw), 0, Math.cos(yaw));
    const left = new THREE.Vector3(Math.cos(yaw), 0, -Math.sin(yaw));
    const velocity = ahead.clone().multiplyScalar(forward).addScaledVector(left, side);
    const origin = new THREE.Vector3(this.focus.x, this.clip.floor + 2 * s, this.focus.z);
    this.facingArrow.position.copy(origin);
    this.facingArrow.setDirection(ahead);
    this.facingArrow.setLength(60 * s, 15 * s, 9 * s);
    const speed = velocity.length();
    this.velocityArrow.visible = speed > 1e-3;
    if (speed > 1e-3) {
      this.velocityArrow.position.copy(origin);
      this.velocityArrow.setDirection(velocity.divideScalar(speed));
      this.velocityArrow.setLength(100 * s * speed, 22 * s, 14 * s);
    }
  }
}

/**
 * Whether WebGL runs on the CPU (SwiftShader, llvmpipe: no GPU, or headless test browsers). There
 * multisampling costs about a quarter of the frame time, so edges stay aliased.
 */
export function softwareWebGL() {
  const gl = document.createElement("canvas").getContext("webgl2");
  if (!gl) return false;
  const info = gl.getExtension("WEBGL_debug_renderer_info");
  const name = String(gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER));
  const lose = gl.getExtension("WEBGL_lose_context");
  if (lose) lose.loseContext();
  return /swiftshader|llvmpipe|softpipe|software/i.test(name);
}

export class SideBySideView {
  /** canvas: the page's canvas; onChange: called when the camera moved and a redraw is due. */
  constructor(canvas, onChange) {
    this.canvas = canvas;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: !softwareWebGL() });
    this.renderer.setPixelRatio(Math.min(2, window.devicePixelRatio || 1));
    this.scene = new THREE.Scene();
    const sky = new THREE.HemisphereLight(0xffffff, 0x3a4250, 2.2);
    const sun = new THREE.DirectionalLight(0xffffff, 1.6);
    sun.position.set(0.4, 1, 0.6);
    for (const light of [sky, sun]) { light.layers.enableAll(); this.scene.add(light); }
    this.stages = { input: new Stage(this.scene, 1, PALETTE.input), output: new Stage(this.scene, 2, PALETTE.output) };
    // the shared orbit: a detached camera circling the origin; each stage adds its own focus
    this.orbit = new THREE.PerspectiveCamera(40, 1, 1, 20000);
    this.controls = new OrbitControls(this.orbit, canvas);
    this.controls.enablePan = false;
    this.controls.mouseButtons.RIGHT = null; // the right button steers the controller (controller.js)
    this.controls.addEventListener("change", onChange);
    this.scale = 1;
  }

  /** A new clip (skeleton and size): rebuilds both figures and puts the orbit at its default. */
  setClip(clip) {
    this.scale = clip.height / 170;
    for (const stage of Object.values(this.stages)) stage.setClip(clip, this.scale);
    const s = this.scale, d = ORBIT.distance * s;
    this.orbit.position.set(d * Math.sin(ORBIT.yaw) * Math.cos(ORBIT.pitch), d * Math.sin(ORBIT.pitch),
                            d * Math.cos(ORBIT.yaw) * Math.cos(ORBIT.pitch));
    this.controls.minDistance = 80 * s;
    this.controls.maxDistance = 2000 * s;
    this.controls.maxPolarAngle = Math.PI / 2 + 0.2; // a little below the floor, never upside down
    this.controls.update();
  }

  show(kind, positions, contacts, rotations) { this.stages[kind].show(positions, contacts, rotations); }

  showControl(control) { this.stages.input.showControl(control); }

  render() {
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    if (!w || !h) return;
    const size = this.renderer.getSize(new THREE.Vector2());
    if (size.x !== w || size.y !== h) this.renderer.setSize(w, h, false);
    const half = Math.floor(w / 2), offset = this.orbit.position.clone().sub(this.controls.target);
    this.renderer.setScissorTest(true);
    this.renderer.setClearColor(BACKGROUND);
    [["input", 0, half], ["output", half, w - half]].forEach(([kind, x, width]) => {
      const { camera, focus } = this.stages[kind];
      camera.aspect = width / h;
      camera.near = 1 * this.scale;
      camera.far = 5000 * this.scale;
      camera.updateProjectionMatrix();
      camera.position.copy(focus).add(offset);
      camera.quaternion.copy(this.orbit.quaternion);
      this.renderer.setViewport(x, 0, width, h);
      this.renderer.setScissor(x, 0, width, h);
      this.renderer.render(this.scene, camera);
    });
  }
}
