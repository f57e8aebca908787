// Controller mode for LPN-FiLM: keyboard, mouse and gamepad become one `control` message per tick,
// {"type": "control", "velocity": [forward_m_s, side_m_s], "facing": yaw_radians, "gait": "walk" | "run"}.
// Conventions of models/motion/features.py: yaw is about +Y with 0 facing +Z; in the character's
// frame +Z is forward and +X is to its left, so `side` > 0 moves left and turning left raises yaw.
// The mapping from held keys / stick deflection to a message is pure (`intentFromKeys`,
// `intentFromGamepad`, `controlMessage`); `Controller` only tracks what is held.

/** Top speeds in m/s by gait (Bandai Namco walks ~1.3 m/s, runs ~3 m/s). */
export const SPEEDS = {
  walk: { forward: 1.4, back: 0.9, side: 0.9 },
  run: { forward: 3.5, back: 1.5, side: 1.8 },
};
export const TURN_RATE = 2.0; // rad/s at full Q/E or stick deflection
export const MOUSE_TURN = 0.006; // rad per pixel of right-button drag
export const DEADZONE = 0.15; // of a stick's range

const KEYS = {
  forward: ["KeyW", "ArrowUp"], back: ["KeyS", "ArrowDown"], left: ["KeyA", "ArrowLeft"], right: ["KeyD", "ArrowRight"],
  turnLeft: ["KeyQ"], turnRight: ["KeyE"], run: ["ShiftLeft", "ShiftRight"],
};
export const CONTROL_KEYS = new Set(Object.values(KEYS).flat());

/**
 * What held keys ask for: forward/side in -1…1 (a diagonal is as fast as a straight line),
 * turn in -1…1 (+ = left), run.
 */
export function intentFromKeys(held) {
  const any = (names) => names.some((k) => held.has(k));
  let forward = any(KEYS.forward) - any(KEYS.back), side = any(KEYS.left) - any(KEYS.right);
  const n = Math.hypot(forward, side);
  if (n > 1) { forward /= n; side /= n; }
  return { forward, side, turn: any(KEYS.turnLeft) - any(KEYS.turnRight), run: any(KEYS.run) };
}

function deadzone(x, y) { // radial, rescaled so the stick's full range still reaches 1
  const r = Math.hypot(x, y);
  if (r < DEADZONE) return [0, 0];
  const k = Math.min(1, (r - DEADZONE) / (1 - DEADZONE)) / r;
  return [x * k, y * k];
}

/**
 * The same from a Gamepad API standard-mapping pad ({axes, buttons}): left stick moves (up =
 * forward), right stick x turns, left-stick press or right trigger runs. Null when idle, so
 * the keyboard keeps control while a pad lies untouched.
 */
export function intentFromGamepad(pad) {
  if (!pad || !pad.axes || pad.axes.length < 2) return null;
  const [sx, sy] = deadzone(pad.axes[0] || 0, pad.axes[1] || 0);
  const [tx] = deadzone(pad.axes[2] || 0, 0);
  const pressed = (i) => !!pad.buttons && !!pad.buttons[i] && (pad.buttons[i].pressed || pad.buttons[i].value > 0.5);
  const intent = { forward: -sy, side: -sx, turn: -tx, run: pressed(10) || pressed(7) };
  const idle = !intent.forward && !intent.side && !intent.turn && !intent.run;
  return idle ? null : intent;
}

/** Turns `facing` by an intent's turn over `dt` seconds plus a mouse turn, wrapped to (-π, π]. */
export function advanceFacing(facing, turn, dt, mouseTurn = 0) {
  const yaw = facing + turn * TURN_RATE * dt + mouseTurn;
  return Math.atan2(Math.sin(yaw), Math.cos(yaw));
}

/** The wire message for an intent and a facing (velocities in m/s, rounded to mm/s). */
export function controlMessage(intent, facing) {
  const gait = intent.run ? "run" : "walk", top = SPEEDS[gait];
  const forward = intent.forward * (intent.forward >= 0 ? top.forward : top.back);
  const side = intent.side * top.side;
  const round = (x) => Math.round(x * 1000) / 1000 + 0; // + 0: no -0 on the wire
  return { type: "control", velocity: [round(forward), round(side)], facing: round(facing), gait };
}

/** Tracks held keys and right-button mouse drags on `surface`; `sample(dt)` makes a tick's message. */
export class Controller {
  constructor(surface, getGamepads = () => (navigator.getGamepads ? navigator.getGamepads() : [])) {
    this.held = new Set();
    this.facing = 0;
    this.mouseTurn = 0;
    this.getGamepads = getGamepads;
    this.gamepad = null; // id of the pad in use, for the HUD
    const typing = (e) => e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement;
    window.addEventListener("keydown", (e) => {
      if (!CONTROL_KEYS.has(e.code) || typing(e)) return;
      this.held.add(e.code);
      if (e.code.startsWith("Arrow")) e.preventDefault(); // no page scrolling
    });
    window.addEventListener("keyup", (e) => this.held.delete(e.code));
    window.addEventListener("blur", () => this.held.clear()); // keys released while away never arrive
    let drag = null;
    surface.addEventListener("contextmenu", (e) => e.preventDefault());
    surface.addEventListener("pointerdown", (e) => { if (e.button === 2) drag = e.clientX; });
    surface.addEventListener("pointermove", (e) => {
      if (drag === null) return;
      this.mouseTurn -= (e.clientX - drag) * MOUSE_TURN; // drag right: turn right
      drag = e.clientX;
    });
    window.addEventListener("pointerup", () => { drag = null; });
  }

  /** The current intent: a gamepad being used wins over the keyboard. */
  intent() {
    for (const pad of this.getGamepads() || []) {
      const intent = intentFromGamepad(pad);
      if (intent) { this.gamepad = pad.id; return intent; }
    }
    this.gamepad = null;
    return intentFromKeys(this.held);
  }

  /** Advances the facing by `dt` seconds and returns this tick's control message. */
  sample(dt) {
    const intent = this.intent();
    this.facing = advanceFacing(this.facing, intent.turn, dt, this.mouseTurn);
    this.mouseTurn = 0;
    return controlMessage(intent, this.facing);
  }

  /** Facing back to `facing`; keys still held stay held (they are released with keyup). */
  reset(facing = 0) { this.facing = facing; this.mouseTurn = 0; }
}
