"""Trained LTI style translators and the streaming interface the service calls.

One `StyleTranslator` per output style: the block-diagonal LTI system, the per-DOF normalisation,
the input's training range and the footplant classifier. Every frame, per session:

    u = (features(frame) - in_mean) / in_std          (features: representation.py)
    v = u saturated into the training range           (`saturation`: hi + k_p tanh((u - hi) / k_p) past it)
    [x'; y] = M [x; v]     with M = [[A, B], [C, D]]   (block-diagonal per joint)
    out = y * out_std + out_mean + (u - v) in_std     (the input's excess passes through)
    or, the stage off (the paper's core), v = u and
    out = (1 - w) out + w in,  w = max_d erf(max(0, dist_d - k_p) / k_c)   (eased: `kernels.ease`)
    pose = inverse representation(out), then the rotation prior, hinge floor, raised arm, feet

The output keeps the input's yaw change (`keep_heading`: translated yaw drifts). `translate`
streams a clip offline; `tests/reference/lti_offline.py` is the numpy reference.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Collection
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.special import erf

from models.interface import FrameBatch, State
from models.motion.assets import bandai_namco_skeleton
from models.motion.feet import model_rig_planter
from models.motion.hands import RAISE_RAMP_CM, SWAY_FRAMES, HandMeter
from models.motion.hinge import HINGE_FILE, Hinges, kernel_floor
from models.motion.skeleton import Motion, Skeleton
from models.motion.style_carry import StyleCarry

from . import kernels, raised_arm
from . import representation as rep
from .footplant import FootplantClassifier
from .styles import LTIStyles

# The stages around the systems, in step order; off via `LTIStyleModel(off=...)` or `lti.<name>`.
STAGES = ("saturation", "rotation_prior", "hinge_floor", "raised_arm", "foot_pitch", "root_give")
CARRY = "carry"  # the state's packed carry (`kernels.CARRY`); each style's LTI state is its x.<style>
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights" / "lti"
ARM_PREFIX = "arm_"  # key prefix of a translator file's raised-arm carry (`StyleCarry.named`)
STORED = ("in_mean", "in_std", "out_mean", "out_std", "in_lo", "in_hi", "orders", "ref")  # saved as they are
EASE_S = 0.1  # time constant of each of the two followers easing the erf blend weight (`kernels.ease`)
RAISE_EASE_S = 0.05  # and the raised-arm shares: quicker, so a raised arm is not late
HINT_SPEED = 120.0  # cm/s: a foot the footplant classifier calls planted plants when slower (`FootPlanter.hint_speed`)
# cm: a hold that needs the leg moved further lets the foot go (`FootPlanter.max_offset`); longer
# holds turn the thighs out of the style, shorter ones let feet slide (docs/eval/ablation.md).
HOLD_CM = 8.0
# cm: ... but a foot the footplant classifier calls planted is held to this (`hint_offset`): the
# translated foot often lands still moving (chosen on validation, docs/eval/ablation.md).
HINT_HOLD_CM = 12.0
# cm, cm/s (`root_give`): past GIVE_CM a hold moves the root instead, at most GIVE_SPEED. LTI's
# per-joint systems slide a planted foot under a body that does not follow (chosen on validation).
GIVE_CM = 5.0
GIVE_SPEED = 30.0
_NO_CONTROL = np.zeros((0, 5))  # the fade's control rows when a frame carries none
# `kernels.step`'s fade arrays when there is no fade: no state rows, each reference array typed as
# `NoveltyReference.arrays` (a kernel is compiled per argument type)
_EMPTY = np.zeros((0, 0))
NO_FADE = (
    _NO_CONTROL,
    _EMPTY,
    (np.zeros((0, 0), np.int64), np.zeros(0, np.int64), np.zeros(0), _EMPTY, _EMPTY),
    _EMPTY,
    np.zeros(0),
)
WAVE_MEANS = 32  # carry columns of the removed waving arm's running means (input and output, 2 sides x 2 joints x 4)
COMPACT_FROM = 16  # sessions in a step from which numpy, not a Python loop, finds the styles in use (`_side_by_side`)


def _writable(a: np.ndarray) -> np.ndarray:
    """`a` as the compiled step takes it, writable C-contiguous float64: copied only where it is not."""
    ready = isinstance(a, np.ndarray) and a.flags.writeable and a.flags.c_contiguous and a.dtype == np.float64
    return a if ready else np.array(a, dtype=np.float64, order="C")


_LOCKED: set = set()  # the step kernel, once compiled, barred from compiling again (`LTIStyleModel._step`)
Fading = tuple[str, tuple] | None  # the unseen-content fade's state key and reference, or none
Stepped = tuple[FrameBatch, State]


@dataclass
class StyleTranslator:
    style: str
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    in_mean: np.ndarray
    in_std: np.ndarray
    out_mean: np.ndarray
    out_std: np.ndarray
    in_lo: np.ndarray  # per-DOF training range of the normalised input
    in_hi: np.ndarray
    orders: np.ndarray  # state dimension of each per-joint block (root first)
    k_p: float = 1.0
    k_c: float = 2.0
    footplant: FootplantClassifier | None = None
    meta: dict = field(default_factory=dict)
    ref: np.ndarray = field(default_factory=lambda: rep.IDENTITY_REF.copy())  # (22, 4) per-joint reference rotations
    keep_heading: bool = True  # output yaw change := input yaw change (no heading drift); not stored
    prior_mean: np.ndarray | None = None  # (22, 4) rotation prior (`train.style_prior`): the style's mean per joint
    prior_radii: np.ndarray | None = None  # (2, 22) its inner / outer radius (radians); None: no prior
    raised_arm: StyleCarry | None = None  # a calm raised hand's arm carry (`raised_arm.py`)

    def __post_init__(self) -> None:
        n = self.A.shape[0]
        self.M = np.block([[self.A, self.B], [self.C, self.D]])
        self.n = n

    # ---------------------------------------------------------------- core

    def steady_gain(self) -> np.ndarray:
        """(n, 67) G = (I - A)^-1 B: where sessions start (from 0 every joint swung in over the first frames)."""
        return np.linalg.solve(np.eye(self.n) - self.A, self.B)

    def blend_weight(self, u: np.ndarray) -> np.ndarray:
        """(..., 67) normalised input -> (...,) erf blend weight: 0 within range (+ k_p), -> 1 far outside."""
        dist = np.maximum(np.maximum(u - self.in_hi, self.in_lo - u), 0.0)
        return erf(np.maximum(dist - self.k_p, 0.0) / self.k_c).max(axis=-1)

    def saturated(self, u: np.ndarray) -> np.ndarray:
        """(..., 67) normalised input saturated into the training range (`kernels.saturate`)."""
        hi = self.in_hi + self.k_p * np.tanh(np.maximum(u - self.in_hi, 0.0) / self.k_p)
        lo = self.in_lo - self.k_p * np.tanh(np.maximum(self.in_lo - u, 0.0) / self.k_p)
        return np.where(u > self.in_hi, hi, np.where(u < self.in_lo, lo, u))

    def _finish(self, feats: np.ndarray, u: np.ndarray, y: np.ndarray, blend: bool, read: np.ndarray) -> np.ndarray:
        """The output features from y; the excess of `u` over what the systems `read` passes through."""
        out = y * self.out_std + self.out_mean  # a new array
        out[..., : rep.FEATURE_DIM] += (u - read) * self.in_std
        if blend:
            w = kernels.eased(self.blend_weight(u), ease_keep(LTIStyleModel.fps))[:, None]
            out[..., : rep.FEATURE_DIM] = (1 - w) * out[..., : rep.FEATURE_DIM] + w * feats
            out[..., rep.FEATURE_DIM :] *= 1 - w
        if self.keep_heading:
            out[..., 2] = feats[..., 2]
        return out

    def translate_features(
        self, feats: np.ndarray, blend: bool = True, saturate: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Offline: (F, 67) input features -> ((F, 68) output features, (F, n) states after each frame)."""
        u = (feats - self.in_mean) / self.in_std
        read = self.saturated(u) if saturate else u
        x = self.steady_gain() @ read[0] if len(read) else np.zeros(self.n)
        ys = np.empty((len(u), self.M.shape[0] - self.n))
        xs = np.empty((len(u), self.n))
        for t in range(len(u)):
            z = self.M @ np.concatenate([x, read[t]])
            x, ys[t] = z[: self.n], z[self.n :]
            xs[t] = x
        return self._finish(feats, u, ys, blend and not saturate, read), xs

    def ball(self) -> tuple[np.ndarray, np.ndarray]:
        """(mean (22, 4), radii (2, 22)): the rotation prior for `kernels.pack_styles`; radii inf: none."""
        mean = self.prior_mean if self.prior_mean is not None else np.tile([0.0, 0.0, 0.0, 1.0], (rep.NUM_JOINTS, 1))
        radii = self.prior_radii if self.prior_radii is not None else np.full((2, rep.NUM_JOINTS), np.inf)
        return mean, radii

    # ---------------------------------------------------------------- persistence

    def save(self, path: Path) -> None:
        extra: dict = self.footplant.to_arrays() if self.footplant is not None else {}
        if self.prior_mean is not None and self.prior_radii is not None:
            extra.update(prior_mean=self.prior_mean, prior_radii=self.prior_radii)
        if self.raised_arm is not None:  # an uploaded style's (the built-in ones share raised_arm.FILE)
            extra.update(self.raised_arm.named(ARM_PREFIX))
        np.savez_compressed(
            path,
            style=np.array(self.style),
            **{k: getattr(self, k).astype(np.float32) for k in "ABCD"},
            **{k: getattr(self, k) for k in STORED},
            k=np.array([self.k_p, self.k_c]),
            meta=np.array(repr(self.meta)),
            **extra,
        )

    @classmethod
    def load(cls, path: Path) -> StyleTranslator:
        with np.load(path) as z:
            fp = FootplantClassifier.from_arrays(z) if "fp_w" in z else None
            A, B, C, D = (z[k].astype(np.float64) for k in "ABCD")
            return cls(
                str(z["style"]), A, B, C, D, **{k: z[k] for k in STORED}, k_p=float(z["k"][0]), k_c=float(z["k"][1]),
                footplant=fp, meta={"source": str(path)},
                prior_mean=z["prior_mean"] if "prior_mean" in z else None,
                prior_radii=z["prior_radii"] if "prior_radii" in z else None,
                raised_arm=StyleCarry.read(z, ARM_PREFIX) if f"{ARM_PREFIX}source" in z else None,
            )  # fmt: skip


def ease_keep(fps: float, seconds: float = EASE_S) -> float:
    """Per frame at `fps`, the share of an eased quantity's history kept (time constant `seconds`)."""
    return float(np.exp(-1.0 / (fps * seconds)))


class _Scratch(NamedTuple):
    systems: kernels.Systems  # the style set it was made for
    batch: int
    x: np.ndarray  # (B * N,) room for the styles' LTI states side by side
    work: tuple  # `kernels.Work`, packed
    x_shapes: list[tuple[int, ...]]  # each style's LTI state's
    alone: list[np.ndarray]  # per style s, (S,) int64: where each style's state sits when s's is the only one
    rest: dict[str, np.ndarray]  # each style's LTI state key -> (B, n) read-only zeros: a style no session uses


class _StyleSet(NamedTuple):
    styles: list[str]
    x_keys: list[str]  # state key of each style's LTI state, in style order
    state_keys: frozenset[str]
    systems: kernels.Systems
    ball: kernels.Ball  # the styles' rotation priors
    arm: kernels.RaisedArm  # the styles' raised-arm carries stacked
    constants: tuple  # the step's constant records, packed (`kernels.pack`)


class LTIStyleModel(LTIStyles):
    """Hsu et al. 2005 LTI style translation behind `models/interface.py`; input style BN `normal`.

    State per session: each style's LTI state `x.<style>` (0 while unweighted; weighted in, it starts
    at its input's steady state) and `carry` (`kernels.CARRY`). Weights mix the styles (root features
    linearly, rotations by normalised quaternion blending, 1 - sum(w) of the input passing through);
    one-hot w is the paper's translator. `add_style` / `remove_style` replace, never mutate.
    """

    name = "lti"
    fps = 30.0  # the Bandai Namco rate it was identified at
    controllable = False  # reads frames, not control

    def __init__(
        self,
        translators: dict[str, StyleTranslator] | None = None,
        weights_dir: Path | str = WEIGHTS_DIR,
        blend: bool = True,
        footlock: bool = True,
        keep_heading: bool = True,
        skeleton: Skeleton | None = None,
        off: Collection[str] = (),
    ) -> None:
        if set(off) - set(STAGES):
            raise KeyError(f"undeclared stages {sorted(set(off) - set(STAGES))}: LTI declares {list(STAGES)}")
        self.stages = tuple(s for s in STAGES if s not in off)  # the stages that are on
        self.raised_arms = "raised_arm" in self.stages
        hinge_file = Path(weights_dir) / HINGE_FILE
        self.hinges = Hinges.load(hinge_file) if "hinge_floor" in self.stages and hinge_file.exists() else None
        if translators is None:
            translators = {}
            arms = raised_arm.load(Path(weights_dir)) if self.raised_arms else {}
            for path in sorted(Path(weights_dir).glob("*.npz")):
                if path.name in (raised_arm.FILE, HINGE_FILE):
                    continue
                t = StyleTranslator.load(path)
                t.raised_arm = arms.get(t.style, t.raised_arm)
                translators[t.style] = t
        if not translators:
            raise FileNotFoundError(f"no LTI weights (*.npz) in {weights_dir}")
        self.keep_heading = keep_heading
        self.translators = {name: self._staged(tr) for name, tr in translators.items()}
        self.saturate = "saturation" in self.stages
        self.blend = blend and not self.saturate  # saturated, nothing is out of range to blend
        self.footlock = footlock
        self.foot_pitch = "foot_pitch" in self.stages
        self.skeleton = skeleton if skeleton is not None else bandai_namco_skeleton()
        self.planter = model_rig_planter(
            self.fps,
            hint_speed=HINT_SPEED,
            max_offset=HOLD_CM,
            hint_offset=HINT_HOLD_CM,
            give=GIVE_CM if "root_give" in self.stages else 0.0,
            give_speed=GIVE_SPEED,
        )
        self._hands = HandMeter(self.skeleton)  # the input's hands, for the raised arm (`raised_arm.py`)
        self._scratch = threading.local()  # per thread: step scratch reused between steps (`_workspace`)
        self._set_styles(sorted(translators))
        self._compile_step()

    def _staged(self, tr: StyleTranslator) -> StyleTranslator:
        """`tr` (copied) with this model's heading and without its stages that are off."""
        if "rotation_prior" not in self.stages and tr.prior_mean is not None:
            tr = replace(tr, prior_mean=None, prior_radii=None)
        if not self.raised_arms and tr.raised_arm is not None:
            tr = replace(tr, raised_arm=None)
        tr.keep_heading = self.keep_heading
        return tr

    def _compile_step(self) -> None:
        """One step on the rest pose, so numba compiles (or loads) the step when the model loads."""
        rest = np.zeros((1, rep.NUM_JOINTS, 4))
        rest[..., 3] = 1.0
        self.step_batch(self.init_state(1), FrameBatch(np.zeros((1, 3)), rest), np.zeros((1, len(self._styles))))

    def styles(self) -> list[str]:
        return list(self._styles)

    # ---------------------------------------------------------------- style set

    def _set_styles(self, styles: list[str]) -> None:
        """Everything the step needs per style set, replaced whole so readers see one consistent set."""
        systems, footplant, ball = kernels.pack_styles([self.translators[s] for s in styles], ease_keep(self.fps))
        arm = raised_arm.settings([self.translators[s].raised_arm for s in styles], ease_keep(self.fps, RAISE_EASE_S))
        h = self._hands
        hands = kernels.Hands(
            h.parents, h.offsets, h.chain, h.hands, h.shoulders, self.fps, SWAY_FRAMES, RAISE_RAMP_CM[0]
        )
        switches = (self.blend, self.keep_heading, self.raised_arms, self.footlock, self.saturate, self.foot_pitch)
        bends = kernels.Bends(*kernel_floor(self.skeleton, self.hinges))
        records = [systems, footplant, ball, hands, arm, self.planter._params, switches, bends]
        x_keys = [f"x.{s}" for s in styles]
        self._set = _StyleSet(
            styles,
            x_keys,
            frozenset([CARRY, *x_keys]),
            systems,
            ball,
            arm,
            kernels.pack(records, list(kernels.CONSTANT_SCHEMAS)),
        )

    @property
    def _styles(self) -> list[str]:
        return self._set.styles

    def add_style(self, tr: StyleTranslator) -> None:
        """Append the style of `tr` (a new name) to `styles()`; running sessions are unaffected."""
        if tr.style in self.translators:
            raise ValueError(f"style {tr.style!r} already exists")
        tr = self._staged(tr)
        self.translators = {**self.translators, tr.style: tr}
        self._set_styles(self._styles + [tr.style])

    def remove_style(self, style: str) -> None:
        """Drop `style`; sessions that used it carry on with its share passing the input through."""
        if style not in self.translators:
            raise KeyError(f"no style {style!r}")
        if len(self._styles) == 1:
            raise ValueError("cannot remove the model's last style")
        self._set_styles([s for s in self._styles if s != style])
        self.translators = {k: v for k, v in self.translators.items() if k != style}

    def upgrade_state(self, state: State) -> State:
        """`state` on the current style set, older layouts converted; `state` itself when it already is."""
        if (
            state.keys() == self._set.state_keys
            and state[CARRY].shape[1] == kernels.CARRY_WIDTH
            and all(state[f"x.{s}"].shape[1] == self.translators[s].n for s in self._styles)
        ):
            return state
        batch = len(next(iter(state.values())))
        carry = state.get(CARRY)
        if carry is not None and carry.shape[1] == kernels.CARRY_WIDTH + WAVE_MEANS:
            # saved while a waving arm's running means sat just before the feet: they go
            carry = np.delete(carry, np.s_[kernels.FEET_AT : kernels.FEET_AT + WAVE_MEANS], axis=1)
        if carry is None:
            carry = np.zeros((batch, kernels.CARRY_WIDTH))
            for key in kernels.CARRY:
                if key in state:
                    carry[:, kernels.SPANS[key][0] : kernels.SPANS[key][0] + state[key][0].size] = state[key].reshape(
                        batch, -1
                    )
        out = {CARRY: carry}
        for s in self._styles:
            x, n = state.get(f"x.{s}"), self.translators[s].n
            out[f"x.{s}"] = x if x is not None and x.shape[1] == n else np.zeros((batch, n))
        return out

    def init_state(self, batch: int) -> State:
        return {
            CARRY: np.zeros((batch, kernels.CARRY_WIDTH)),
            **{f"x.{s}": np.zeros((batch, self.translators[s].n)) for s in self._styles},
        }

    def _workspace(self, batch: int) -> _Scratch:
        """This thread's step scratch, reused while the style set and batch stay (page faults otherwise)."""
        held = getattr(self._scratch, "held", None)
        if held is None or held.systems is not self._set.systems or held.batch != batch:
            systems = self._set.systems
            widths = np.diff(systems.x_off).tolist()
            zeros = np.zeros(batch * max(widths))
            zeros.flags.writeable = False
            alone = [np.full(len(widths), -1, np.int64) for _ in widths]
            for s, at in enumerate(alone):
                at[s] = 0
            held = _Scratch(
                systems,
                batch,
                np.empty(batch * int(systems.x_off[-1])),
                kernels.new_work(batch, systems, len(self._set.arm.source)),
                [(batch, n) for n in widths],
                alone,
                {key: zeros[: batch * n].reshape(batch, n) for key, n in zip(self._set.x_keys, widths)},
            )
            self._scratch.held = held
        return held

    @staticmethod
    def _in_use(w: np.ndarray) -> list[int]:
        if len(w) == 1:  # one session's weights, one list
            return [s for s, top in enumerate(w.tolist()[0]) if top > 0.0]
        if len(w) < COMPACT_FROM:  # a few sessions: a Python scan of the weights beats numpy's calls
            return [s for s, column in enumerate(w.T.tolist()) if column and max(column) > 0.0]
        return [s for s, top in enumerate(w.max(axis=0).tolist()) if top > 0.0]

    @staticmethod
    def _side_by_side(
        xs: list[np.ndarray], used: list[int], held: _Scratch, ready: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """The states of the styles in `used` side by side, and where each sits (-1: not in use);
        `ready`: made what the kernel takes (the read-only rest state of a style weighted in)."""
        if len(used) == 1:
            return (_writable(xs[used[0]]) if ready else xs[used[0]]), held.alone[used[0]]
        x_at, width = np.full(len(xs), -1, np.int64), 0
        for s in used:
            x_at[s], width = width, width + xs[s].shape[1]
        x = held.x[: held.batch * width].reshape(held.batch, width)
        for s in used:
            x[:, x_at[s] : x_at[s] + xs[s].shape[1]] = xs[s]
        return x, x_at

    def translate(self, motion: Motion, style: str, timewarp: bool = False) -> tuple[Motion, np.ndarray]:
        """Offline: a `Motion` streamed toward `style`; `timewarp`: resampled by the log time warp."""
        from dataclasses import replace as with_pose

        from .warping import resample_pose

        w = np.zeros((1, len(self._styles)))
        w[0, self._styles.index(style)] = 1.0
        state, root, rots = self.init_state(1), np.empty((motion.num_frames, 3)), np.empty(motion.rotations.shape)
        contacts = np.empty((motion.num_frames, 2), bool)
        for t in range(motion.num_frames):
            frame = FrameBatch(motion.translations[t : t + 1, rep.HIPS], motion.rotations[t : t + 1])
            out, state = self.step_batch(state, frame, w)
            assert out.contacts is not None  # the step always reports them
            root[t], rots[t], contacts[t] = out.root[0], out.rotations[0], out.contacts[0]
        if timewarp:
            tr = self.translators[style]
            out_feats, _ = tr.translate_features(rep.motion_to_features(motion, tr.ref), self.blend, self.saturate)
            rate = np.exp(out_feats[:, rep.FEATURE_DIM])  # output frames per input frame
            clock = np.concatenate([[0.0], np.cumsum(rate[1:])])  # output time of each input frame
            times = np.interp(np.arange(0.0, clock[-1] + 1e-9), clock, np.arange(len(clock)))
            root, rots = resample_pose(root, rots, times)
            contacts = contacts[np.clip(np.round(times).astype(int), 0, len(contacts) - 1)]
        translations = np.broadcast_to(motion.translations[:1], (len(root),) + motion.translations.shape[1:]).copy()
        translations[:, rep.HIPS] = root
        return with_pose(motion, rotations=rots, translations=translations), contacts

    def step_batch(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> Stepped:
        """One frame for every session, in one compiled call (`kernels.step`)."""
        return self._step(state, frames, style_weights, None)

    def step_batch_fading(
        self, state: State, frames: FrameBatch, style_weights: np.ndarray, key: str, reference: tuple
    ) -> Stepped:
        """`step_batch` with the unseen-content fade before the feet, in the same call."""
        return self._step(state, frames, style_weights, (key, reference))

    def _step(self, state: State, frames: FrameBatch, style_weights: np.ndarray, fading: Fading) -> Stepped:
        """The compiled step on the arrays as they come. numba compiles a kernel again for any other
        array type (read-only, strided, float32): ~50 s of a core in which no session on the server
        gets a frame. So the first call copies what the kernel would not take (`_writable`) and
        then bars the kernel from compiling; a later call it has no signature for (a TypeError
        before it runs) is made again on copies. The usual call checks nothing (~2 us at batch 1)."""
        kernel = kernels.step
        if kernel in _LOCKED:
            try:
                return self._step_on(kernel, state, frames, style_weights, fading, ready=False)
            except (TypeError, AttributeError):  # not the kernel's array types (or not arrays)
                pass
        out = self._step_on(kernel, state, frames, style_weights, fading, ready=True)
        kernel.disable_compile()
        _LOCKED.add(kernel)
        return out

    def _step_on(
        self, kernel: Callable[..., None], state: State, frames: FrameBatch, w: np.ndarray, fading: Fading, ready: bool
    ) -> Stepped:
        """`_step` with the inputs as they are, or (`ready`) made what the kernel takes."""
        root, rotations = frames.root, frames.rotations
        if ready:
            root, rotations, w = _writable(root), _writable(rotations), _writable(w)
        styles, x_keys, constants = self._set.styles, self._set.x_keys, self._set.constants
        B = len(root)
        # the kernel trusts every shape (no bounds checks): anything else is a clear error here
        if root.shape != (B, 3) or rotations.shape != (B, rep.NUM_JOINTS, 4):
            raise ValueError(
                f"frames must be root (B, 3) and rotations (B, {rep.NUM_JOINTS}, 4), "
                f"got {root.shape} and {rotations.shape}"
            )
        if w.shape != (B, len(styles)):
            raise ValueError(f"style_weights must be ({B}, {len(styles)}), got {w.shape}")
        held = self._workspace(B)
        try:
            carry, xs = state[CARRY], [state[key] for key in x_keys]
        except KeyError:
            carry, xs = np.empty(0), []
        if carry.shape != (B, kernels.CARRY_WIDTH) or [a.shape for a in xs] != held.x_shapes:
            raise ValueError(
                f"state must hold {CARRY} ({B}, {kernels.CARRY_WIDTH}) and each style's x for this style set: "
                "bring an older state to it with upgrade_state(state)"
            )
        if ready:
            carry = _writable(carry)
        used = self._in_use(w)
        x, x_at = self._side_by_side(xs, used, held, ready)
        new_x, new_carry = np.empty(x.shape), np.empty(carry.shape)
        out = FrameBatch(np.empty((B, 3)), np.empty((B, rep.NUM_JOINTS, 4)), np.empty((B, 2), bool))
        frame, outputs = (root, rotations, w, x_at), (out.root, out.rotations, out.contacts)
        new = {**held.rest, CARRY: new_carry}  # a style no session uses rests at x = 0 (unset)
        if fading is None:
            kernel(*(frame, x, new_x, carry, new_carry, outputs, constants, held.work, NO_FADE))
        else:
            key, reference = fading
            control = _NO_CONTROL if frames.control is None else frames.control
            old = state[key]
            if ready:
                control, old = _writable(control), _writable(old)
            if old.shape[0] != B:
                raise ValueError(f"state[{key!r}] must hold {B} rows, got {old.shape}")
            new[key], out.faded = np.empty(old.shape), np.empty(B)
            fade = (control, old, reference, new[key], out.faded)
            kernel(*(frame, x, new_x, carry, new_carry, outputs, constants, held.work, fade))
        if len(used) == 1:
            new[x_keys[used[0]]] = new_x
        else:
            for s in used:
                new[x_keys[s]] = new_x[:, x_at[s] : x_at[s] + xs[s].shape[1]]
        return out, new
