"""Streaming Style-ERD: the project's `StreamingModel` interface. Features and output pose by
compiled kernels (`kernels.py`, float64), the network in numpy (float32 by default; `ERDModel`).

State per session (session axis first):
    h, c                       (B, 7, layers, H)        LSTM states: the neutral branch, then one
                                                        residual branch per target style
    h.<name>, c.<name>         (B, layers, H)           the same for each uploaded style (`uploads.py`)
    prev_pos (B, 22, 3), prev_yaw (B,)                  previous input frame (causal velocities)
    gait_speed, gait (B,)                               the input's averaged Hips speed, gait share (`gait.py`)
    <stage>/<key>                                       the stages' (`stages.STAGES`)
    out_root (B, 3), frame (B,)                         last output Hips translation, frames seen
    style_in (B,), content (B,)                         input labels, -1 = unknown (the default)
    feet_*                                              the foot planter's (`models.motion.feet`)
Every branch advances every frame, so switching styles never meets a stale state.

Decoding keeps the decoder's positions; twists and leaves (head, hands, toes), never learned,
take the input's rotations (or the leaf prior's carry); elbows and knees keep their hinge plane.
Then the stages and the shared foot planter.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch

from ..interface import FrameBatch, State
from ..motion.feet import STATE_SHAPES as FEET_STATE
from ..motion.feet import FootPlanter, model_rig_planter, plant_frame
from ..motion.hinge import HINGE_FILE, Hinges, kernel_hinges
from ..motion.skeleton import Skeleton
from ..motion.twist import _kernel_plan
from ..motion.twist_kernels import transfer_twist_batch
from ..rowwise import matmul_rows
from ..settings import get_settings
from ..stages import Pipeline, Rows, StageFrame
from . import kernels
from .dataset import CONTENTS, STYLES, TARGET_STYLES
from .features import CONTACT, FPS, FeatureMaker
from .gait import UNMEASURED, followed, gait_share, hips_speed, smoothed_speed
from .stages import ON_INPUT, STAGES
from .uploads import BuiltIn, ERDStyles, Upload, branch_weights, runtime_layout

if TYPE_CHECKING:
    from .model import Generator

WEIGHTS_FILE = "erd.npz"
# cm: a foot the input has down is held this far from the network's leg (docs/eval/ablation.md)
HINT_HOLD_CM = 22.5
# cm, cm/s: past GIVE_CM a hold moves the root instead, at most GIVE_SPEED (validation: at LTI's 30
# cm/s the held legs jerked elderly's thighs; docs/eval/ablation.md)
GIVE_CM, GIVE_SPEED = 5.0, 120.0
RENAMED = {"slow_in": "leaf_prior/slow", "slow_out": "output_prior/slow"}  # state keys of older replicas


def foot_planter() -> FootPlanter:
    """Style-ERD's foot planter, the stream's and the offline path's."""
    return model_rig_planter(FPS, hint_offset=HINT_HOLD_CM, give=GIVE_CM, give_speed=GIVE_SPEED)


class Plan(NamedTuple):
    """The stages as one step reads them, replaced whole."""

    stages: Pipeline
    on_input: Pipeline
    on_output: Pipeline
    rows: Mapping[str, Rows]
    leafless: bool


def _sigmoid_(a: np.ndarray) -> np.ndarray:
    """Logistic sigmoid in place by torch's vectorised kernel (numpy's float32 exp is not vectorised)."""
    t = torch.from_numpy(a)
    torch.sigmoid(t, out=t)
    return a


class ERDModel(ERDStyles):
    """Style-ERD behind the streaming interface. `dtype` is the network's arithmetic: float32 by
    default (~2-4x faster, what lets 256 sessions fit in a frame); float64 is the tests' reference.
    Features and output pose are always float64."""

    name = "erd"
    fps = FPS  # the model runs at 30 fps (Bandai Namco)
    controllable = False  # reads frames, not control

    def __init__(
        self, params: dict[str, np.ndarray], config: dict, skeleton: Skeleton,
        mean: np.ndarray, std: np.ndarray, ref: np.ndarray,  # the features' normalisation, the reference pose
        meta: dict | None = None, dtype: type = np.float32, stages: Pipeline | None = None,
        hinges: Hinges | None = None, network_twists: bool = False,
    ):  # fmt: skip
        self.p = {k: np.asarray(v, dtype=np.float64) for k, v in params.items()}
        self.config = config
        self.meta = meta or {}
        self.skeleton = skeleton
        self.dtype = np.dtype(dtype)
        self.mean, self.std = np.asarray(mean, np.float64), np.asarray(std, np.float64)
        self.ref = np.asarray(ref, np.float64)
        # the decoding: hinged limbs; without a leaf prior, twists from the network or the input
        self.hinges, self.network_twists = hinges, network_twists
        self._decoding = (_kernel_plan(skeleton, ()), kernel_hinges(skeleton, hinges))  # `transfer_twist`'s, once
        self.maker = FeatureMaker(skeleton, self.ref)
        self.planter = foot_planter()
        self.H = config["latent"]
        self.Ln, self.Ls = config["neutral_layers"], config["style_layers"]
        if self.Ln != self.Ls:
            raise ValueError(
                f"the runtime stacks the neutral and style LSTM branches: it needs equal layer counts, "
                f"got {self.Ln} neutral and {self.Ls} style layers"
            )
        self.branches = ("neutral",) + tuple(TARGET_STYLES)  # branch 0 is the neutral one, weight 1
        self._scratch = threading.local()  # per thread: LSTM buffers reused between steps (`_workspace`)
        self._lock = threading.Lock()
        self.weights_dir: Path | None = None  # where `load` read it (an upload's stage sources live there)
        self._prepare_weights()
        self.uploads: tuple[Upload, ...] = ()  # uploaded styles, after the trained ones (`uploads.py`)
        self.codes: np.ndarray | None = None  # (styles, 6) the decoder's style code per style; None: one-hot
        self.stages = stages or Pipeline.load(STAGES, Path(), skeleton, core_only=True)
        self.built_in = BuiltIn(self.lstm_w, self.lstm_b, self.stages)
        self._compile_step()

    @property
    def stages(self) -> Pipeline:
        """The stages after the network (`stages.STAGES`; a stage None is off)."""
        return self._plan.stages

    @stages.setter
    def stages(self, stages: Pipeline) -> None:
        on_input, on_output = stages.split(ON_INPUT)
        rows = stages.rows(self.styles(), self.skeleton)
        self._plan = Plan(stages, on_input, on_output, rows, stages.leaf_prior is None)
        own = self.init_state(1).items()  # the entries the step checks (the planter checks its own)
        self._state_shapes = {k: v.shape[1:] for k, v in own if k not in FEET_STATE}

    def _compile_step(self) -> None:
        """One step on the rest pose, so numba compiles (or loads) the kernels when the model loads."""
        rest = np.zeros((1, 22, 4))
        rest[..., 3] = 1.0
        for weights in (np.zeros((1, len(TARGET_STYLES))), np.eye(len(TARGET_STYLES))[:1]):  # with a style: all of it
            self.step_batch(self.init_state(1), FrameBatch(np.zeros((1, 3)), rest), weights)

    def _prepare_weights(self) -> None:
        """Constants in the network's dtype and layout, once: label one-hots become row lookups, the
        seven LSTM branches are stacked ([input; hidden] weights, one batched product per layer), and
        the cell gate's rows are doubled so one sigmoid serves all gates (tanh(x) = 2 sigmoid(2x) - 1)."""
        p, dt, H = self.p, self.dtype, self.H
        n_in = len(self.mean)
        w0, b0 = p["encoder.0.weight"].T, p["encoder.0.bias"]
        zero = np.zeros((1, w0.shape[1]))
        self.enc_in = np.ascontiguousarray(w0[:n_in], dt)
        style_rows = np.concatenate([w0[n_in : n_in + len(STYLES)], zero])  # (8, hidden)
        content_rows = np.concatenate([w0[n_in + len(STYLES) :], zero]) + b0  # (11, hidden), with the bias
        self.enc_labels = (style_rows[:, None] + content_rows[None]).astype(dt)  # [style, content] -> row
        self.enc = [
            (np.ascontiguousarray(p[f"encoder.{i}.weight"].T, dt), p[f"encoder.{i}.bias"].astype(dt)) for i in (2, 4)
        ]
        self.dec = [
            (np.ascontiguousarray(p[f"decoder.{i}.weight"].T, dt), p[f"decoder.{i}.bias"].astype(dt)) for i in (0, 2, 4)
        ]
        # per layer, per branch: [input; hidden] @ [W_ih^T; W_hh^T] as one (2H, 4H) matrix: (7, 2H, 4H)
        prefixes = ["neutral."] + [f"branches.{k}." for k in range(len(TARGET_STYLES))]
        layouts = [runtime_layout(branch_weights(p, n), self.Ln, H, np.float64) for n in prefixes]
        self.lstm_w = [np.stack([w[l] for w, _ in layouts]).astype(dt) for l in range(self.Ln)]
        self.lstm_b = [np.stack([b[l] for _, b in layouts]).astype(dt) for l in range(self.Ln)]  # (7, 1, 4H)

    # ------------------------------------------------------------------ interface

    def styles(self) -> list[str]:
        return list(self.branches[1:])

    def contents(self) -> list[str]:
        return list(CONTENTS)

    def init_state(self, batch: int, content: str | None = None, input_style: str | None = None) -> State:
        """Fresh sessions; `content`/`input_style` label the input stream when known (default: unknown)."""
        ci = CONTENTS.index(content) if content is not None else -1
        si = STYLES.index(input_style) if input_style is not None else -1
        row = ci if ci >= 0 else len(CONTENTS)
        h0 = np.concatenate([self.p["neutral_h0"][row][None], self.p["style_h0"]]).astype(self.dtype)  # (7, layers, H)
        c0 = np.concatenate([self.p["neutral_c0"][row][None], self.p["style_c0"]]).astype(self.dtype)
        state: State = {"h": np.repeat(h0[None], batch, 0), "c": np.repeat(c0[None], batch, 0)}
        state.update(self._upload_states(batch))
        state.update(
            prev_pos=np.zeros((batch, 22, 3)),
            prev_yaw=np.zeros(batch),
            gait_speed=np.full(batch, UNMEASURED),
            gait=np.zeros(batch),
            out_root=np.zeros((batch, 3)),
            frame=np.zeros(batch, dtype=np.int64),
            style_in=np.full(batch, si, dtype=np.int64),
            content=np.full(batch, ci, dtype=np.int64),
        )
        state.update(self.stages.init_state(batch))
        state.update(self.planter.init_state(batch))
        return state

    def upgrade_state(self, state: State) -> State:
        """An older replica's or stage set's state brought current; a current state as it is."""
        wanted = {key for u in self.uploads for key in (f"h.{u.name}", f"c.{u.name}")}
        held = {k for k in state if k[:2] in ("h.", "c.")}
        if held == wanted and all(k in state for k in (*FEET_STATE, *self._state_shapes)):
            return state
        batch = len(state["frame"])
        old = {RENAMED.get(k, k): v for k, v in state.items() if not k.startswith("lock_") and k not in held - wanted}
        old = {**self._upload_states(batch), **old}  # a style added since starts at its initial state
        fresh = self.init_state(batch)  # what a new session starts these entries at
        for key in self._state_shapes:
            old.setdefault(key, fresh[key])
        if all(k in old for k in FEET_STATE):
            return old
        return self.planter.upgrade_state(old, batch)

    def step_batch(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> tuple[FrameBatch, State]:
        out, new = self.step_unplanted(state, frames, style_weights)
        planted, feet = plant_frame(self.planter, out, state)
        return planted, {**new, **feet}

    def step_unplanted(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> tuple[FrameBatch, State]:
        """`step_batch` up to the feet (`feet.plant_frame` plants the frame)."""
        root = np.ascontiguousarray(frames.root, np.float64)
        rot_in = np.ascontiguousarray(frames.rotations, np.float64)
        w = np.asarray(style_weights, np.float64)
        B = root.shape[0]
        J = self.skeleton.num_joints
        # the kernels trust every shape (no bounds checks): anything else is a clear error here
        if root.shape != (B, 3) or rot_in.shape != (B, J, 4):
            raise ValueError(
                f"frames must be root (B, 3) and rotations (B, {J}, 4), got {root.shape} and {rot_in.shape}"
            )
        if w.shape != (B, len(self.branches) - 1):
            raise ValueError(f"style_weights must be ({B}, {len(self.branches) - 1}), got {w.shape}")
        for key, shape in self._state_shapes.items():
            if state[key].shape != (B, *shape):
                raise ValueError(f"state[{key!r}] must be {(B, *shape)}, got {state[key].shape}")
        has_prev = state["frame"] > 0
        pos = self.maker.positions(root, rot_in)
        x, yaw = self.maker.features(rot_in, pos, state["prev_pos"], state["prev_yaw"], has_prev)
        y, new = self._network(x, state, w)
        out_root, out_rot = kernels.output_pose(
            x, y, yaw, has_prev, np.ascontiguousarray(state["out_root"], np.float64), root, rot_in, float(FPS)
        )
        gait_speed = smoothed_speed(state["gait_speed"], hips_speed(pos, state["prev_pos"], has_prev, FPS), has_prev)
        share = followed(state["gait"], gait_share(gait_speed), has_prev)
        out_rot, staged = self.stage_batch(state, rot_in, out_rot, w, share)
        new.update(
            prev_pos=pos,
            prev_yaw=yaw,
            gait_speed=gait_speed,
            gait=share,
            out_root=out_root,
            frame=state["frame"] + 1,
            style_in=state["style_in"].copy(),
            content=state["content"].copy(),
            **staged,
        )
        return FrameBatch(out_root, out_rot, x[:, CONTACT] > 0.5), new

    def stage_batch(
        self, state: State, rot_in: np.ndarray, decoded: np.ndarray, weights: np.ndarray, share: np.ndarray
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Network rotations (B, J, 4) through the decoding and the stages; also the stages' new state."""
        plan = self._plan
        source, staged = plan.on_input.step_batch(state, StageFrame(rot_in, weights, share, -1), plan.rows)
        if self.network_twists and plan.leafless:
            source = decoded
        source, decoded = (np.ascontiguousarray(a, np.float64) for a in (source, decoded))
        out = np.empty_like(decoded)  # `transfer_twist`, its constants made once
        transfer_twist_batch(*self._decoding, source, decoded, out)
        out, after = plan.on_output.step_batch(state, StageFrame(out, weights, share, -1), plan.rows)
        staged.update(after)
        return out, staged

    # ------------------------------------------------------------------ network

    def _workspace(self, batch: int) -> tuple[np.ndarray, np.ndarray]:
        """This thread's LSTM buffers, reused while the batch fits (page faults otherwise)."""
        held, K, H = getattr(self._scratch, "held", None), len(self.branches), self.H
        if held is None or held[0].shape[1] < batch or held[0].shape[0] != K:
            held = self._scratch.held = (
                np.empty((K, batch, 2 * H), self.dtype),
                np.empty((K, batch, 4 * H), self.dtype),
            )
        return held[0][:, :batch], held[1][:, :batch]

    def _network(self, x: np.ndarray, state: State, w: np.ndarray) -> tuple[np.ndarray, State]:
        """Encoder -> 7 stacked LSTM branches -> neutral + sum_s w_s branch_s -> decoder: ((B, 88), states)."""
        dt, H, B = self.dtype, self.H, x.shape[0]
        h = matmul_rows(((x - self.mean) / self.std).astype(dt), self.enc_in)
        h += self.enc_labels[state["style_in"], state["content"]]
        for W, b in self.enc:
            np.maximum(h, 0.0, out=h)
            h = matmul_rows(h, W) + b
        z = h
        hs, cs = (self._branch_states(state, key).astype(dt, copy=False) for key in "hc")  # (B, K, layers, H)
        new_h, new_c = np.empty_like(hs), np.empty_like(cs)
        K, one = len(self.branches), dt.type(1.0)
        inp = np.broadcast_to(z, (K, B, H))  # every branch reads the encoding
        xin, g = self._workspace(B)
        for l in range(self.Ln):
            # [input, hidden] (7, B, 2H) @ (7, 2H, 4H): the branch axis first, as np.matmul batches over it
            kernels.lstm_inputs(inp, hs, l, xin)
            g[...] = matmul_rows(xin, self.lstm_w[l])  # each row as if alone (`models.rowwise`)
            g += self.lstm_b[l]
            s = _sigmoid_(g)  # i, f, g, o gates through the sigmoid; the g gate's tanh = 2 s - 1
            twice_c = kernels.lstm_cell(s, cs, l, one, new_c, np.empty((K, B, H), dt))
            inp = kernels.lstm_hidden(s, _sigmoid_(twice_c), l, one, new_h, np.empty((K, B, H), dt))  # o tanh(c)
        weights = np.empty((B, len(self.branches)), dt)
        weights[:, 0] = 1.0
        weights[:, 1:] = w
        latent = np.einsum("bk,kbh->bh", weights, inp)
        code = weights[:, 1:] if self.codes is None else weights[:, 1:] @ self.codes  # uploads: their own code
        h = np.concatenate([latent, code], -1)
        for i, (W, b) in enumerate(self.dec):
            h = matmul_rows(h, W) + b
            if i < 2:
                np.maximum(h, 0.0, out=h)
        n = 1 + len(TARGET_STYLES)
        new = {"h": new_h[:, :n], "c": new_c[:, :n]}
        for i, u in enumerate(self.uploads):
            new[f"h.{u.name}"], new[f"c.{u.name}"] = new_h[:, n + i], new_c[:, n + i]
        return h, new

    def _branch_states(self, state: State, key: str) -> np.ndarray:
        """(B, K, layers, H) every branch's LSTM `key` ("h" or "c"): the trained ones', then each upload's."""
        if not self.uploads:
            return state[key]
        return np.concatenate([state[key], *(state[f"{key}.{u.name}"][:, None] for u in self.uploads)], 1)

    def _upload_states(self, batch: int) -> State:
        """Fresh LSTM states of the uploaded styles' branches (their fitted initial states)."""
        out: State = {}
        for u in self.uploads:
            out[f"h.{u.name}"] = np.repeat(u.h0[None].astype(self.dtype), batch, 0)
            out[f"c.{u.name}"] = np.repeat(u.c0[None].astype(self.dtype), batch, 0)
        return out

    # ------------------------------------------------------------------ offline helpers

    def torch_generator(self) -> Generator:
        """The same weights as a torch `Generator` (for whole-clip runs and tests)."""
        import torch

        from .model import ERDConfig, Generator

        cfg = ERDConfig(**self.config)
        gen = Generator(cfg, self.mean, self.std)
        state = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in self.p.items()}
        state["mean"], state["std"] = (
            torch.as_tensor(self.mean, dtype=torch.float32),
            torch.as_tensor(self.std, dtype=torch.float32),
        )
        gen.load_state_dict(state)
        return gen.eval()


def load(weights_dir: Path, dtype: type = np.float32, core_only: bool = False, hinges: bool = True) -> ERDModel:
    """The committed model; `dtype`: the network's (np.float64: the reference); `core_only`: no stages."""
    weights_dir = Path(weights_dir)
    config = json.loads((weights_dir / "config.json").read_text())
    with np.load(weights_dir / WEIGHTS_FILE) as z:
        arrays = {k: z[k] for k in z.files}
    skeleton = Skeleton(
        tuple(str(n) for n in arrays.pop("skeleton_names")),
        arrays.pop("skeleton_parents").astype(int),
        arrays.pop("skeleton_offsets"),
        arrays.pop("skeleton_end_sites"),
    )
    mean, std, ref = arrays.pop("norm_mean"), arrays.pop("norm_std"), arrays.pop("ref")
    off = [name.removeprefix("erd.") for name in get_settings().stages_off if name.startswith("erd.")]
    stages = Pipeline.load(STAGES, weights_dir, skeleton, core_only).without(*off)
    decode = Hinges.load(weights_dir / HINGE_FILE) if hinges and (weights_dir / HINGE_FILE).exists() else None
    own = config.get("train_config", {}).get("network_twists", False)
    model = ERDModel(
        arrays, config["model"], skeleton, mean, std, ref, config, dtype, stages, hinges=decode, network_twists=own
    )
    model.weights_dir = weights_dir
    return model


def export_weights(ckpt_path: Path, out_dir: Path | None = None, skeleton: Skeleton | None = None) -> Path:
    """Write models/weights/erd/{erd.npz, config.json, hinges.npz} from a training checkpoint."""
    import torch

    from ..settings import REPO_ROOT

    out_dir = Path(out_dir or REPO_ROOT / "models" / "weights" / "erd")
    out_dir.mkdir(parents=True, exist_ok=True)
    ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    if skeleton is None:
        from ..data import build_index, load_motion, select

        skeleton = load_motion(select(build_index(["bandai-namco-2"]), split="val")[0]).skeleton
    sd = ck["generator"]
    arrays = {k: v.numpy().astype(np.float32) for k, v in sd.items() if k not in ("mean", "std")}
    np.savez_compressed(
        out_dir / WEIGHTS_FILE,
        **arrays,
        norm_mean=sd["mean"].numpy(),
        norm_std=sd["std"].numpy(),
        ref=np.asarray(ck["ref"], np.float64),
        skeleton_names=np.array(skeleton.names),
        skeleton_parents=skeleton.parents,
        skeleton_offsets=skeleton.offsets,
        skeleton_end_sites=skeleton.end_sites,
    )
    hist = ck.get("history", [])
    config = {
        "model": ck["model_config"],
        "styles": list(TARGET_STYLES),
        "input_styles": list(STYLES),
        "contents": list(CONTENTS),
        "iterations": ck["iter"],
        "train_seconds": round(ck["seconds"], 1),
        "train_config": ck["train_config"],
        "classifier_val_acc": ck.get("classifier_val_acc"),
        "final_validation": hist[-1] if hist else None,
        "licence": "CC BY-NC 4.0 (inherited from Bandai Namco dataset 2)",
    }
    (out_dir / "config.json").write_text(json.dumps(config, indent=1))
    from .dataset import load_split, split_hinges

    split_hinges(load_split("train"), skeleton).save(out_dir / HINGE_FILE)
    return out_dir
