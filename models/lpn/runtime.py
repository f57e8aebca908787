"""Streaming LPN-FiLM as a character controller (the `StreamingModel` interface, float32).

Per frame the network reads the trajectory (past, and a future blended from the control and its
last prediction), pose and local phases, and predicts the next. Per-session maths is compiled
(`kernels.py`; reference `tests/reference/lpn_step.py`). Without control, the input frames' Hips
velocity, facing and speed become the control. Styles are FiLM vectors mixed by the weights
(shortfall to `normal`). `STAGES` follow the core and change the output only, not the network's
state; a style without real clips gets no-op rows. The foot planter closes every step.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import replace
from functools import cached_property, partial
from itertools import chain
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..interface import FrameBatch, State
from ..motion import hinge_floor
from ..motion.assets import BANDAI_NAMCO_ANKLE_FLOOR, BANDAI_NAMCO_TOE_FLOOR
from ..motion.coupling import Coupling
from ..motion.features import body_joint
from ..motion.feet import FootPlanter, plant_frame
from ..motion.kinematics_kernels import forward_kinematics
from ..motion.rotation_ball import StyleBalls
from ..motion.rotations import quat_mul, yaw_quat
from ..motion.skeleton import Motion, Skeleton
from ..motion.style_carry import StyleCarry
from ..motion.twist import split_evenly, transfer_twist
from ..rowwise import Bfloat16Product, matmul_rows
from ..settings import get_settings
from ..stages import Pipeline, StageFrame, StageSpec
from . import arm_coupling, carriage, kernels, output_prior, rotation_prior
from . import features as lf
from .arm_coupling import ARM_COUPLING_FILE
from .carriage import CARRIAGE_FILE, Carriage
from .output_prior import OUTPUT_PRIOR_FILE, OutputPrior
from .rotation_prior import BALLS_FILE
from .style_table import StyleTable
from .styles import LPNStyles
from .weights import read_weights

if TYPE_CHECKING:
    from .network import LPN

# The stages after the core, in step order, each fitted into its file (`python -m models.lpn fit`)
STAGES = (
    StageSpec("carriage", CARRIAGE_FILE, lambda path, _: Carriage.load(path), carriage.fit),
    StageSpec("output_prior", OUTPUT_PRIOR_FILE, lambda path, _: OutputPrior.load(path), output_prior.fit),
    StageSpec("arm_coupling", ARM_COUPLING_FILE, lambda path, _: Coupling.load(path), arm_coupling.fit),
    StageSpec("rotation_balls", BALLS_FILE, lambda path, _: StyleBalls.load(path), rotation_prior.fit),
    hinge_floor.STAGE,
)
HIST = lf.PAST * lf.STEP + 1  # 31 frames of history, the last one is the current frame
CONTROL_SMOOTH_S = 0.25  # input velocity smoothing for derived control
RUN_SPEED = 220.0  # cm/s: derived gait switches to run above this input speed
CONTROL_BIAS = 2.0  # future sample k blends toward the control by 1 - (1 - k/6)^bias
PHASE_BLEND = 0.5  # next phase = blend of (current advanced by the predicted frequency) and the predicted phase
CONTACT_THRESHOLD = 0.35  # predicted contact (regressed 0/1) above which a foot counts as planted
CATCH_UP_S = 3.0  # s: a lead is made up this far on, a shortfall fades as fast (chosen on validation)
# cm/s: 1st and 5th percentile of the TRAIN walks' smoothed Hips speed: below, the network cannot walk
CRAWL_SPEED, WALK_SPEED = 63.0, 73.0
STOP_SPEED = 30.0  # cm/s: below this wanted speed the phases are damped (standing)
STOP_PHASE_DAMP = 0.6  # per-frame phase factor when the wanted speed is 0
STOP_ROOT_HOLD = 0.9  # share of the predicted root translation held back when the wanted speed is 0
# Joints `_untwist` leaves alone: leaves, and limb roots (their twist sets the knee / elbow plane)
OWN_ROTATIONS = ("Head", "Hand_L", "Hand_R", "Toes_L", "Toes_R", "UpperLeg_L", "UpperLeg_R", "UpperArm_L", "UpperArm_R")


class LPNModel(LPNStyles):
    name = "lpn"
    controllable = True  # reads FrameBatch.control (the service's `control` message)
    fps = lf.FPS
    bfloat16 = True  # expert products may run in bfloat16 (`_products`); False: always float32
    # the unseen-content fade after the planted feet (`novelty_stage`; docs/eval/ablation.md)
    fade_before_feet = False

    def __init__(
        self,
        arrays: dict[str, np.ndarray],
        skeleton: Skeleton,
        config: dict,
        stages: Pipeline | None = None,
    ):
        self.config = config
        self.skeleton = skeleton
        self.p = arrays
        self.E = config["model"]["experts"]
        self.H = config["model"]["hidden"]
        a = arrays
        self.gating = tuple((a[f"gating.{i}.weight"].T.copy(), a[f"gating.{i}.bias"]) for i in (0, 2, 4))
        self.layers = []
        for name in ("l1", "l2", "l3"):
            W = a[f"{name}.weight"]  # (E, in, out)
            E, n_in, n_out = W.shape
            self.layers.append((W.transpose(1, 0, 2).reshape(n_in, E * n_out).copy(), a[f"{name}.bias"], n_out))
        self.x_mean, self.x_std = a["X_mean"], a["X_std"]
        self.y_mean, self.y_std = a["Y_mean"], a["Y_std"]
        self.g_scale = float(a["G_scale"])
        self._lock = threading.Lock()
        styles = tuple(config["styles"])
        films = a["style_film"].reshape(len(styles), 4 * self.H)
        stages = stages if stages is not None else Pipeline.load(STAGES, Path(), skeleton, core_only=True)
        self._table = StyleTable(styles, films, (True,) * len(styles), skeleton, stages)  # replaced under the lock
        self._generator: LPN | None = None  # the FiLM generator, built on first use
        sk = skeleton
        self.offsets = sk.offsets.astype(np.float32)
        self.parents = sk.parents
        self.planter = FootPlanter.for_skeleton(sk, (BANDAI_NAMCO_ANKLE_FLOOR, BANDAI_NAMCO_TOE_FLOOR), lf.FPS)
        self.facing_joints = [body_joint(sk, p) for p in ("hip_l", "hip_r", "shoulder_l", "shoulder_r")]

    # ------------------------------------------------------------------ styles

    @property
    def stages(self) -> Pipeline:
        """The stages after the network (`STAGES`; a stage None is off)."""
        return self._table.stages

    @stages.setter
    def stages(self, stages: Pipeline) -> None:
        with self._lock:
            self._table = self._table.with_stages(stages)

    def styles(self) -> list[str]:
        return list(self._table.names)

    def film_from_clip(self, motion: Motion) -> np.ndarray:
        """A new style's FiLM vector (4, H): the generator over 4 s windows of the clip, averaged."""
        import torch

        from .dataset import clip_style_features
        from .train import tile_clip

        if motion.skeleton.names != self.skeleton.names:
            raise ValueError("a style clip must be on the model skeleton (Bandai Namco, 22 joints)")
        if motion.num_frames < self.fps:
            raise ValueError(f"style clip too short: {motion.num_frames} frames, need at least {int(self.fps)}")
        feats = tile_clip(clip_style_features(motion), 120)
        starts = range(0, len(feats) - 120 + 1, 60)
        windows = torch.from_numpy(np.stack([feats[s : s + 120] for s in starts]).astype(np.float32))
        with torch.no_grad():
            return self.generator().style_film(windows).mean(0).numpy().reshape(4, self.H)

    def set_style_film(self, name: str, film: np.ndarray) -> None:
        """Set (or add) style `name` with FiLM vector `film` (4, H); sessions see it next step."""
        self.set_style_upload(name, film, None)

    def set_style_upload(self, name: str, film: np.ndarray, prior: StyleCarry | None) -> None:
        """Set (or add) style `name` with `film` and its own output prior `prior`."""
        film = np.asarray(film, np.float32)
        if film.shape != (4, self.H) or not np.all(np.isfinite(film)):
            raise ValueError(f"a FiLM vector must be finite with shape (4, {self.H}), got {film.shape}")
        with self._lock:
            table = self._table.with_film(name, film.reshape(-1))
            stage = table.stages.output_prior
            if prior is not None and isinstance(stage, OutputPrior):
                stages = table.stages.replace(output_prior=stage.with_styles_of(OutputPrior((name,), prior, prior)))
                k = table.index(name)
                table = replace(table, stages=stages, fitted=tuple(f or i == k for i, f in enumerate(table.fitted)))
            self._table = table

    def remove_style(self, name: str) -> None:
        if name == "normal":
            raise ValueError("'normal' is the base style of LPN-FiLM and cannot be removed")
        with self._lock:
            if name not in self._table.names:
                raise KeyError(f"unknown style {name!r}")
            self._table = self._table.without(name)

    def generator(self) -> LPN:
        """The torch network (for the FiLM generator; built on first use)."""
        if self._generator is None:
            import torch

            from .network import LPN, LPNConfig

            net = LPN(LPNConfig(**self.config["model"]))
            state = {k: torch.as_tensor(v) for k, v in self.p.items() if k != "style_film"}
            net.load_state_dict(state)
            self._generator = net.eval()
        return self._generator

    def _blend(self, table: StyleTable, weights: np.ndarray) -> np.ndarray:
        """(B, S) style weights -> (B, 4, H) FiLM; the weights' shortfall from 1 goes to `normal`."""
        w = np.asarray(weights, np.float32)
        if w.ndim != 2 or w.shape[1] != len(table.names):
            raise ValueError(f"style_weights must be (B, {len(table.names)}), got {w.shape}")
        film = matmul_rows(w, table.films) + (1.0 - w.sum(1, keepdims=True)) * table.films[table.index("normal")]
        return film.reshape(-1, 4, self.H)

    # ------------------------------------------------------------------ state

    def init_state(self, batch: int) -> State:
        B = batch
        z = lambda *s: np.zeros((B, *s), np.float32)
        return {
            "frame": np.zeros(B, np.int64),
            "hist_pos": z(HIST, 2),
            "hist_dir": z(HIST, 2),
            "hist_vel": z(HIST, 2),
            "hist_gait": z(HIST),
            "hist_phase": z(HIST, lf.NUM_BONES, 2),
            "fut_pos": z(lf.FUTURE, 2),
            "fut_dir": z(lf.FUTURE, 2),
            "fut_vel": z(lf.FUTURE, 2),
            "fut_phase": z(lf.FUTURE, lf.NUM_BONES, 2),
            "pose": z(lf.NB, lf.POSE_CH),
            "yaw": z(),
            "in_pos": z(2),
            "in_vel": z(2),
            "lead": z(),
            **self.planter.init_state(B),
            **self.stages.init_state(B),  # keys "stage/name"
        }

    def _start(
        self, state: State, rows: np.ndarray, root: np.ndarray, rotations: np.ndarray, control: np.ndarray | None
    ) -> None:
        """Fresh sessions stand in the input's first pose; with control, in the rest pose facing its yaw."""
        root, rotations = root[rows].copy(), rotations[rows].copy()
        if control is not None:
            given = np.flatnonzero(np.asarray(control)[rows, 4] > 0.5)
            if len(given):
                rest = self.rest_motion()
                _, rest_pos = self._fk(rest.translations[:1, lf.HIPS], rest.rotations[:1])
                turn = np.asarray(control, np.float32)[rows[given], 2] - self._facing(rest_pos)[0]
                rotations[given] = rest.rotations[0]
                rotations[given, lf.HIPS] = quat_mul(
                    yaw_quat(turn.astype(np.float64)), np.broadcast_to(rest.rotations[0, lf.HIPS], (len(given), 4))
                )
                root[given, 1] = rest.translations[0, lf.HIPS, 1]
        grot, gpos = self._fk(root, rotations)
        yaw = self._facing(gpos)
        ground = gpos[:, lf.HIPS] * np.array([1.0, 0.0, 1.0], np.float32)
        pose = lf.pose_features(gpos, np.zeros_like(gpos), grot, ground, yaw)
        xz, d = ground[:, [0, 2]], lf.direction(yaw)
        state["pose"][rows] = pose
        state["yaw"][rows] = yaw
        state["hist_pos"][rows] = xz[:, None]
        state["hist_dir"][rows] = d[:, None]
        state["fut_pos"][rows] = xz[:, None]
        state["fut_dir"][rows] = d[:, None]
        for key in ("hist_vel", "hist_gait", "hist_phase", "fut_vel", "fut_phase", "in_vel", "lead"):
            state[key][rows] = 0.0
        state["in_pos"][rows] = xz
        for key, value in {**self.planter.init_state(len(rows)), **self.stages.init_state(len(rows))}.items():
            state[key][rows] = value

    # ------------------------------------------------------------------ step

    def step_batch(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> tuple[FrameBatch, State]:
        out, s = self.step_unplanted(state, frames, style_weights)
        planted, feet = plant_frame(self.planter, out, s)
        s.update(feet)
        return planted, s

    def step_unplanted(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> tuple[FrameBatch, State]:
        """`step_batch` up to the feet (`feet.plant_frame` plants the frame)."""
        root = np.asarray(frames.root, np.float32)
        rot_in = np.asarray(frames.rotations, np.float32)
        B = root.shape[0]
        table = self._table  # one snapshot of the style set: the FiLM vectors, stages and their rows agree
        film = self._blend(table, style_weights)
        if film.shape[0] != B:
            raise ValueError(f"style_weights has {film.shape[0]} rows for {B} frames")
        s = {k: v.copy() for k, v in state.items()}
        fresh = np.flatnonzero(s["frame"] == 0)
        if len(fresh):
            self._start(s, fresh, root, rot_in, frames.control)
        self._check_step(s, root, rot_in, frames.control, table.stages)
        control = self._control(s, frames, root, rot_in, fresh)
        x, g = self._inputs(s, control)
        y = self._network(x, g, film)
        out_root, out_rot, contacts = self._advance(s, y, control)
        out_rot = self._untwist(out_rot)
        frame = StageFrame(out_rot, style_weights, control[:, 3], table.index("normal"))
        out_rot, staged = table.stages.step_batch({k: v for k, v in s.items() if "/" in k}, frame, table.rows)
        s.update(staged)
        s["frame"] = s["frame"] + 1
        return FrameBatch(out_root.astype(np.float32, copy=False), out_rot.astype(np.float32, copy=False), contacts), s

    def _untwist(self, rotations: np.ndarray) -> np.ndarray:
        """Each bone's twist from the natural pose: the network sometimes turns a bone ~180 degrees about
        itself, which moves no joint but wrings a skinned body. Leaves and limb roots keep theirs."""
        source = np.broadcast_to(self._natural_pose, rotations.shape)
        out = transfer_twist(self.skeleton, source, rotations, OWN_ROTATIONS)
        # around such a flip spine and chest bend against each other: re-split their smooth composite
        spine, chest = self._torso
        natural = self._natural_pose
        out[:, spine], out[:, chest] = split_evenly(out[:, spine], out[:, chest], natural[spine], natural[chest])
        return out.astype(rotations.dtype)

    @cached_property
    def _torso(self) -> tuple[int, int]:
        return self.skeleton.index("Spine"), self.skeleton.index("Chest")

    @cached_property
    def _natural_pose(self) -> np.ndarray:
        from ..motion.assets import bandai_namco_pose

        return bandai_namco_pose().rotations[0].astype(np.float64)

    def _control(
        self, s: State, frames: FrameBatch, root: np.ndarray, rot_in: np.ndarray, fresh: np.ndarray
    ) -> np.ndarray:
        """(B, 4) control (forward, side in cm/s, yaw, gait): given rows as they are, others derived."""
        B = root.shape[0]
        if frames.control is None:
            control, given = np.zeros((B, 5), np.float32), np.zeros(B, bool)
        else:
            control = np.ascontiguousarray(frames.control, np.float32)
            given = control[:, 4] > 0.5
        tracker = kernels.Tracker(*(s[k] for k in kernels.Tracker._fields))
        root, rot_in = np.ascontiguousarray(root), np.ascontiguousarray(rot_in)
        walked = np.linalg.norm(s["hist_pos"][:, -1] - s["hist_pos"][:, -2], axis=-1)  # the character's last step
        return kernels.control_rows(control, given, root, rot_in, tracker, walked, self._body, self._rules)

    @cached_property
    def _body(self) -> kernels.Body:
        return kernels.Body(self.parents, self.offsets, np.array(self.facing_joints, np.int64), self.fps)

    @cached_property
    def _rules(self) -> kernels.Rules:
        smooth = 1.0 - np.exp(-1.0 / (self.fps * CONTROL_SMOOTH_S))
        return kernels.Rules(
            smooth, RUN_SPEED, STOP_SPEED, STOP_ROOT_HOLD, STOP_PHASE_DAMP, PHASE_BLEND, CONTACT_THRESHOLD, CATCH_UP_S,
            CRAWL_SPEED, WALK_SPEED,
        )  # fmt: skip

    @cached_property
    def _own_layout(self) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
        """Per state entry but the stages': shape without the session axis, dtype."""
        return {k: (v.shape[1:], v.dtype) for k, v in self.init_state(0).items() if "/" not in k}

    def _check_step(
        self, s: State, root: np.ndarray, rot_in: np.ndarray, control: np.ndarray | None, stages: Pipeline
    ) -> None:
        """The kernels trust every shape (no bounds checks): anything else is a clear error here."""
        B, J = root.shape[0], len(self.parents)
        if root.shape != (B, 3) or rot_in.shape != (B, J, 4):
            raise ValueError(
                f"frames must be root (B, 3) and rotations (B, {J}, 4), got {root.shape} and {rot_in.shape}"
            )
        if control is not None and np.shape(control) != (B, 5):
            raise ValueError(f"control must be ({B}, 5), got {np.shape(control)}")
        for key, (shape, dtype) in chain(self._own_layout.items(), stages.state_layout.items()):
            value = s.get(key)
            if not (
                isinstance(value, np.ndarray)
                and value.shape[:1] == (B,)
                and value.shape[1:] == shape
                and (value.dtype is dtype or value.dtype == dtype)
            ):
                got = f"{value.dtype} {value.shape}" if isinstance(value, np.ndarray) else type(value).__name__
                raise ValueError(f"state[{key!r}] must be {dtype} {(B, *shape)}, got {got}")

    def _inputs(self, s: State, control: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Blend the future trajectory toward the control, then build X and G (`kernels.network_inputs`)."""
        B = control.shape[0]
        x, g = np.empty((B, lf.X_DIM), np.float32), np.empty((B, lf.G_DIM), np.float32)
        kernels.network_inputs(control, _track(s), self.fps, CONTROL_BIAS, x, g)
        return x, g

    def _network(self, x: np.ndarray, g: np.ndarray, film: np.ndarray) -> np.ndarray:
        """Denormalised output (B, Y_DIM) as `LPN.forward` in eval mode: BLAS per expert layer."""
        x, g = np.ascontiguousarray(x, np.float32), np.ascontiguousarray(g, np.float32)
        film = np.ascontiguousarray(film, np.float32)
        alpha = kernels.gating(g, self.g_scale, self.gating)
        h = (x - self.x_mean) / self.x_std
        (W1, bias1, n1), (W2, bias2, n2), (W3, bias3, _) = self.layers
        p1, p2, p3 = self._products
        h1 = np.empty((len(x), n1), np.float32)
        kernels.hidden_layer(p1(h), alpha, bias1, film, 0, h1)
        h2 = np.empty((len(x), n2), np.float32)
        kernels.hidden_layer(p2(h1), alpha, bias2, film, 1, h2)
        return kernels.output_layer(p3(h2), alpha, bias3, self.y_mean, self.y_std)

    @cached_property
    def _products(self) -> list[Callable[[np.ndarray], np.ndarray]]:
        """The expert products: bfloat16 where native with batch-independent rows, else float32."""
        fast = get_settings().bfloat16_products and self.bfloat16
        out: list[Callable[[np.ndarray], np.ndarray]] = []
        for W, _, _ in self.layers:
            product = Bfloat16Product.for_weights(W) if fast else None
            out.append(product if product is not None else partial(matmul_rows, w=W))
        return out

    def _advance(self, s: State, y: np.ndarray, control: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Apply the prediction; returns output Hips translation, rotations and contacts. Training clips
        hardly ever stop, so below STOP_SPEED phases are damped and most root motion is held back."""
        return kernels.advance(y, control, _track(s), self._body, self._rules)

    # ------------------------------------------------------------------ kinematics

    def _fk(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (B, 22, 4) and positions (B, 22, 3); joint_Root static at the origin."""
        g_rot, g_pos = forward_kinematics(
            np.ascontiguousarray(root, np.float32),
            np.ascontiguousarray(rotations, np.float32),
            self.parents,
            self.offsets,
        )
        return g_rot.astype(np.float32), g_pos.astype(np.float32)

    def _facing(self, positions: np.ndarray) -> np.ndarray:
        hl, hr, sl, sr = (positions[:, j] for j in self.facing_joints)
        left = hl - hr + sl - sr
        return np.arctan2(-left[:, 2], left[:, 0]).astype(np.float32)  # forward = left x up = (-lz, 0, lx)

    # ------------------------------------------------------------------ offline helpers

    def run(
        self, motion: Motion | None, weights: np.ndarray, control: np.ndarray | None = None, frames: int | None = None
    ) -> tuple[Motion, np.ndarray]:
        """One session driven by `motion` or control (T, 5); `weights` (S,) or (T, S). (motion, contacts)."""
        from dataclasses import replace

        first = motion if motion is not None else self.rest_motion()
        T = frames or (len(control) if control is not None else first.num_frames)
        state = self.init_state(1)
        w = np.asarray(weights, np.float32)
        roots, rots, cons = [], [], []
        for t in range(T):
            src = min(t, first.num_frames - 1) if (motion is not None and control is None) else 0
            c = None if control is None else np.asarray(control[t : t + 1], np.float32)
            fb = FrameBatch(first.translations[src : src + 1, lf.HIPS], first.rotations[src : src + 1], control=c)
            out, state = self.step_batch(state, fb, (w[t] if w.ndim == 2 else w)[None])
            roots.append(out.root[0])
            rots.append(out.rotations[0])
            assert out.contacts is not None  # this model always reports contacts
            cons.append(out.contacts[0])
        trans = np.broadcast_to(self.skeleton.offsets, (T, self.skeleton.num_joints, 3)).copy()
        trans[:, lf.HIPS] = np.array(roots)
        return replace(first.slice(0, 1), rotations=np.array(rots), translations=trans, fps=self.fps), np.array(cons)

    def rest_motion(self) -> Motion:
        """The one-frame natural standing pose (committed asset) control-driven sessions start from."""
        from ..motion.assets import bandai_namco_pose

        return bandai_namco_pose()

    def weight_vector(self, mix: dict[str, float]) -> np.ndarray:
        names = self.styles()
        return np.array([mix.get(n, 0.0) for n in names], np.float32)


def _track(s: State) -> kernels.Track:
    """The state's trajectory entries as the kernels' record (the same arrays, updated in place)."""
    return kernels.Track(*(s[k] for k in kernels.Track._fields))


def load(weights_dir: Path, core_only: bool = False) -> LPNModel:
    """The committed model; `core_only`: the network and foot planter without the stages."""
    arrays, skeleton, config = read_weights(weights_dir)
    off = [name.removeprefix("lpn.") for name in get_settings().stages_off if name.startswith("lpn.")]
    stages = Pipeline.load(STAGES, Path(weights_dir), skeleton, core_only).without(*off)  # `Settings.stages_off`
    return LPNModel(arrays, skeleton, config, stages)
