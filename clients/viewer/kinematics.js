// Pure motion maths for the viewer: quaternions ([x, y, z, w], scalar last, as on the wire),
// forward kinematics, clips that loop forward, and a small BVH reader for files chosen in the page.
// No DOM and no three.js here, so every function can be exercised on its own. Y up; cm.

export function qmul(a, b) {
  const [ax, ay, az, aw] = a, [bx, by, bz, bw] = b;
  return [aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
          aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz];
}

/** Rotates v by the unit quaternion q. */
export function qrot(q, v) {
  const [x, y, z, w] = q, [vx, vy, vz] = v;
  const tx = 2 * (y * vz - z * vy), ty = 2 * (z * vx - x * vz), tz = 2 * (x * vy - y * vx);
  return [vx + w * tx + y * tz - z * ty, vy + w * ty + z * tx - x * tz, vz + w * tz + x * ty - y * tx];
}

export function qnorm(q) {
  const n = Math.hypot(q[0], q[1], q[2], q[3]) || 1;
  return [q[0] / n, q[1] / n, q[2] / n, q[3] / n];
}

/** A rotation of `deg` degrees about the "X", "Y" or "Z" axis. */
export function qaxis(axis, deg) {
  const h = deg * Math.PI / 360, s = Math.sin(h), c = Math.cos(h);
  return axis === "X" ? [s, 0, 0, c] : axis === "Y" ? [0, s, 0, c] : [0, 0, s, c];
}

/**
 * World joint rotations and positions of one frame, {rotations, positions}. The skeleton's root
 * joint (`rootJoint`, Hips for Bandai Namco) takes the streamed `root` translation; every other
 * joint sits at its rest offset.
 */
export function fkTransforms(skel, root, rotations) {
  const n = skel.parents.length, gr = new Array(n), gp = new Array(n);
  for (let j = 0; j < n; j++) {
    const p = skel.parents[j], r = qnorm(rotations[j]);
    const t = j === skel.rootJoint ? root : skel.offsets[j];
    if (p < 0) { gr[j] = r; gp[j] = t.slice(); continue; }
    gr[j] = qmul(gr[p], r);
    const o = qrot(gr[p], t);
    gp[j] = [gp[p][0] + o[0], gp[p][1] + o[1], gp[p][2] + o[2]];
  }
  return { rotations: gr, positions: gp };
}

/** World joint positions of one frame (see `fkTransforms`). */
export function fk(skel, root, rotations) {
  return fkTransforms(skel, root, rotations).positions;
}

/**
 * The oriented solids (head with nose, hands with thumb, feet) for a clip's joints: those of the
 * first rig from the server (`GET /v1/demo/clip` `rigs`, calibrated on the rig's reference pose by
 * models/motion/orientation.py) whose solids' joints the clip has, by name, with the joint indices
 * turned into the clip's; [] when none fits (the figure then keeps a ball for a head).
 */
export function solidsFor(rigs, joints) {
  for (const rig of rigs || []) {
    const index = rig.solids.map((s) => joints.indexOf(rig.joints[s.joint]));
    if (rig.solids.length && index.every((j) => j >= 0)) {
      return rig.solids.map((s, i) => ({ ...s, joint: index[i] }));
    }
  }
  return [];
}

/**
 * Where a solid is in one frame: its joint's world position, and the joint's world rotation
 * times the part frame's fixed rotation, so the solid turns with the joint even when no joint moves.
 */
export function placeSolid(solid, worldRotations, worldPositions) {
  return { position: worldPositions[solid.joint], quaternion: qmul(worldRotations[solid.joint], solid.rotation) };
}

/** The 6 quads of a solid's 8 corners (corner k at bits 2, 1, 0 = x, y, z), counter-clockwise seen from outside. */
export const SOLID_FACES = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]];

/** Which side a joint is on, from its name: 1 left, -1 right, 0 centre (BN `_L`, CMU `Left…`, `l…`). */
export function sideOf(name) {
  if (/(_L$|^Left|^L(?=[A-Z])|^l(?=[A-Z]))/.test(name)) return 1;
  if (/(_R$|^Right|^R(?=[A-Z])|^r(?=[A-Z]))/.test(name)) return -1;
  return 0;
}

/**
 * The bones to draw as [parent, child] pairs, without the bone from a static top root to the
 * streamed root joint (Bandai Namco: joint_Root -> Hips), which would sweep across the floor.
 */
export function bones(skel) {
  const out = [];
  skel.parents.forEach((p, j) => {
    if (p >= 0 && !(j === skel.rootJoint && skel.parents[p] < 0)) out.push([p, j]);
  });
  return out;
}

/** The head joint (drawn as a ball), or -1. */
export function headJoint(joints) {
  const i = joints.findIndex((n) => /^head$/i.test(n));
  return i >= 0 ? i : joints.findIndex((n) => /head/i.test(n));
}

/** Left and right foot joints (for contact markers): the first joints named like feet, else -1. */
export function footJoints(joints) {
  const find = (side) => joints.findIndex((n) => /foot|ankle/i.test(n) && sideOf(n) === side);
  return [find(1), find(-1)];
}

/**
 * Completes a clip {joints, parents, offsets, rootJoint, fps, root[F][3], rotations[F][J][4], rigs}
 * with what drawing and looping need: per-joint side, the oriented solids (`solidsFor`), height
 * and floor of the first pose, and the horizontal shift that lets each pass of the loop continue
 * where the last one ended.
 */
export function finishClip(clip) {
  clip.side = clip.joints.map(sideOf);
  clip.bones = bones(clip);
  clip.head = headJoint(clip.joints);
  clip.feet = footJoints(clip.joints);
  clip.solids = solidsFor(clip.rigs, clip.joints);
  const n = clip.root.length;
  const a = clip.root[0], b = clip.root[n - 1], c = clip.root[Math.max(0, n - 2)];
  clip.loopShift = [b[0] - a[0] + (b[0] - c[0]), 0, b[2] - a[2] + (b[2] - c[2])];
  const ys = fk(clip, clip.root[0], clip.rotations[0]).map((p) => p[1]);
  clip.height = Math.max(1e-3, Math.max(...ys) - Math.min(...ys));
  clip.floor = Math.min(...ys);
  return clip;
}

/** Frame `seq` of an endlessly looping clip: pass k is shifted k loop shifts forward. */
export function clipFrame(clip, seq) {
  const n = clip.root.length, k = Math.floor(seq / n), i = seq % n, r = clip.root[i], s = clip.loopShift;
  return { root: [r[0] + k * s[0], r[1], r[2] + k * s[2]], rotations: clip.rotations[i] };
}

/** A clip from the service's demo clip JSON (`GET /v1/demo/clip`), with its rigs' solids. */
export function clipFromDemo(d) {
  return finishClip({ name: d.name, joints: d.joints, parents: d.parents, offsets: d.offsets,
                      rootJoint: d.root_joint, fps: d.fps, root: d.frames.root,
                      rotations: d.frames.rotations, header: null, rigs: d.rigs || [] });
}

/**
 * Reads a BVH file: hierarchy, then Euler channels as intrinsic rotations in channel order,
 * as quaternions. The streamed root is the first non-root joint with position channels (Bandai
 * Namco animates Hips under a static joint_Root), else the root. Keeps the header text, which
 * the session's `start` message sends so the server can map the joints. `rigs`: the server's
 * solids per skeleton (`solidsFor`).
 */
export function parseBVH(text, rigs = []) {
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
    else if (t === "}") { if (stack.pop() === -2) inEnd = false; }
    else if (t === "OFFSET") {
      const v = [+tok[i], +tok[i + 1], +tok[i + 2]]; i += 3;
      if (!inEnd) offsets[last] = v;
    } else if (t === "CHANNELS") {
      const n = +tok[i++]; channels[last] = tok.slice(i, i + n); i += n;
    }
  }
  const frames = +(/Frames:\s*(\d+)/.exec(motion) || [])[1];
  const dt = +(/Frame Time:\s*([\d.eE+-]+)/.exec(motion) || [])[1];
  const data = motion.trim().split(/\n/).slice(2).filter((l) => l.trim()).slice(0, frames)
    .map((l) => l.trim().split(/\s+/).map(Number));
  if (!joints.length || !data.length) throw new Error("empty BVH");
  let rootJoint = channels.findIndex((c, j) => j > 0 && c.includes("Xposition"));
  if (rootJoint < 0) rootJoint = 0;
  const above = [];  // the joints above the root joint, top first
  for (let a = parents[rootJoint]; a >= 0; a = parents[a]) above.unshift(a);
  const root = [], rotations = [];
  let held = null;  // the joints above: the first frame's rotations at their rest offsets (as `fk` places them)
  for (const row of data) {
    let col = 0;
    const pos = [];
    const rots = joints.map((_, j) => {
      let q = [0, 0, 0, 1];
      pos[j] = offsets[j].slice();
      for (const ch of channels[j]) {
        const v = row[col++];
        if (ch.endsWith("position")) pos[j]["XYZ".indexOf(ch[0])] = v;
        else q = qmul(q, qaxis(ch[0], v));
      }
      return q;
    });
    if (pos[rootJoint].some((v) => !Number.isFinite(v))) throw new Error(`frame ${root.length}: not a number`);
    // travel carried by joints above the root joint goes onto it, those held (as
    // models.motion.skeleton.travel_on): frames carry the root joint's translation only
    const chain = (at) => above.reduce(([r, t], a) => {
      const o = qrot(r, at[a]);
      return [qmul(r, qnorm(rots[a])), [t[0] + o[0], t[1] + o[1], t[2] + o[2]]];
    }, [[0, 0, 0, 1], [0, 0, 0]]);
    const [gr, gp] = chain(pos);
    if (!held) { const [r, t] = chain(offsets); held = { rots: above.map((a) => rots[a]), gr: r, gp: t }; }
    const o = qrot(gr, pos[rootJoint]), world = [gp[0] + o[0], gp[1] + o[1], gp[2] + o[2]];
    const back = [-held.gr[0], -held.gr[1], -held.gr[2], held.gr[3]];
    above.forEach((a, i) => { rots[a] = held.rots[i]; });
    rots[rootJoint] = qmul(back, qmul(gr, rots[rootJoint]));
    root.push(qrot(back, [world[0] - held.gp[0], world[1] - held.gp[1], world[2] - held.gp[2]]));
    rotations.push(rots);
  }
  const fps = dt > 0 ? Math.round(100 / dt) / 100 : 30;
  return finishClip({ name: "uploaded BVH", joints, parents, offsets, rootJoint, fps, root, rotations,
                      header: head.trimEnd() + "\n", rigs });
}
