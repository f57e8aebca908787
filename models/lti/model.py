"""Trained LTI style translators and the streaming interface the service calls.

One `StyleTranslator` per output style holds the block-diagonal LTI system (all per-joint
systems combined), the per-DOF normalisation, the input's training range (for the erf blend)
and the footplant classifier. Every frame, per session:

    u = (features(frame) - in_mean) / in_std          (features: representation.py)
    v = u saturated into the training range           (`saturation`: hi + k_p tanh((u - hi) / k_p) past it)
    [x'; y] = M [x; v]     with M = [[A, B], [C, D]]   (block-diagonal per joint)
    out = y * out_std + out_mean + (u - v) in_std     (the input's excess passes through)
    or, the stage off (the paper's core), v = u and
    out = (1 - w) out + w in,  w = max_d erf(max(0, dist_d - k_p) / k_c)   (generalisation blend,
                                                                          eased over time: `kernels.ease`)
    pose = inverse representation(out); rotation prior (`train.style_prior`); hinge joints kept on
    their hinge at no less than their least real bend (`models.motion.hinge_kernels`, `hinges.npz`); contacts
    then the stages, each measured on the input and fitted per style the same way: a raised,
    calm hand's arm (raised_arm.py), the planted feet

Heading: the translated yaw drifts slowly for some styles, so by default the output takes the
input's yaw change (`keep_heading=True`); speed, posture and timing stay translated. The feet are
planted (`footlock`) by `models.motion.feet.FootPlanter`, shared by every method, with the
classifier's contacts as hints for feet slower than `HINT_SPEED`, the root giving way past
`GIVE_CM` (`root_give`); `FrameBatch.contacts` are the planted legs, or the classifier's.

The streaming step (`LTIStyleModel.step_batch`) is one compiled call for every session and stage
(`kernels.step`); the offline path (`LTIStyleModel.translate`) streams a whole clip through it,
and takes the log-time-warp output (last DOF) where asked (`timewarp=True`): online it would break
synchrony. `tests/reference/lti_offline.py` is the numpy reference the step is tested against.
"""

from __future__ import annotations

import threading
from collections.abc import Collection
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.special import erf

from models.interface import FrameBatch
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

# The stages around the identified systems, in the order the compiled step runs them (`kernels.step`),
# each fitted from real clips the same way for every style: the input saturated into each
# system's training range (`kernels.saturate`, the ranges in each translator's file; off, the
# paper's erf blend hands the input back instead), the rotation prior (`train.style_prior`, in
# each translator's file), the hinge floor (`python -m models.lti hinges`), the raised arm
# (`raised_arm.py`) and, in the foot planter, the root giving way to held feet (`GIVE_CM`). Any
# can be switched off
# (`LTIStyleModel(off=...)`, `Settings.stages_off` as `lti.<name>`); the offline path
# (`LTIStyleModel.translate`) runs the stream's.
STAGES = ("saturation", "rotation_prior", "hinge_floor", "raised_arm", "root_give")
CARRY = "carry"  # the state's packed carry (`kernels.CARRY`); each style's LTI state is its x.<style>
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights" / "lti"
ARM_PREFIX = "arm_"  # key prefix of a translator file's raised-arm carry (`StyleCarry.named`)
STORED = ("in_mean", "in_std", "out_mean", "out_std", "in_lo", "in_hi", "orders", "ref")  # saved as they are
EASE_S = 0.1  # time constant of each of the two followers easing the erf blend weight (`kernels.ease`)
RAISE_EASE_S = 0.05  # and the raised-arm shares: at 0.1 s a raise-up's arm came late enough to cost content reads
HINT_SPEED = 120.0  # cm/s: a foot the footplant classifier calls planted plants when slower (`FootPlanter.hint_speed`)
# cm: a hold that needs the leg moved further from the translator's lets the foot go
# (`FootPlanter.max_offset`; 15 for the networks). Longer holds turn the translated thighs out of
# the style's real frames (docs/eval/ablation.md); shorter ones let more feet slide.
HOLD_CM = 8.0
# cm: ... but a foot the footplant classifier calls planted (the paper's footplant constraint)
# is held to this (`FootPlanter.hint_offset`): the translated foot often lands still moving,
# and let go at HOLD_CM it skidded forward in 3-4 cm steps. Chosen on validation among 12, 16
# and 24 with the earlier two-feet move (docs/eval/ablation.md).
HINT_HOLD_CM = 12.0
# cm, cm/s (the `root_give` stage): past GIVE_CM a held foot's hold moves the root instead, at
# most GIVE_SPEED (`FootPlanter.give`, `give_speed`). LTI's joints, each its own system, slide a
# planted foot under a body that does not follow; let go at HOLD_CM, such a foot snapped back
# over the ground (on other performers' walks, where the saturated input no longer hands the
# legs back). Both chosen on validation (docs/eval/ablation.md).
GIVE_CM = 5.0
GIVE_SPEED = 30.0
_NO_CONTROL = np.zeros((0, 5))  # the fade's control rows when a frame carries none
WAVE_MEANS = 32  # carry columns of the removed waving arm's running means (input and output, 2 sides x 2 joints x 4)
COMPACT_FROM = 16  # sessions in a step from which numpy, not a Python loop, finds the styles in use (`_side_by_side`)


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
    prior_mean: np.ndarray | None = (
        None  # (22, 4) rotation prior (`train.style_prior`): the real style's mean per joint
    )
    prior_radii: np.ndarray | None = None  # (2, 22) its inner / outer radius (radians); None: no prior
    raised_arm: StyleCarry | None = None  # a calm raised hand's arm carry (`raised_arm.py`)

    def __post_init__(self) -> None:
        n = self.A.shape[0]
        self.M = np.block([[self.A, self.B], [self.C, self.D]])
        self.n = n

    # ---------------------------------------------------------------- core

    def steady_gain(self) -> np.ndarray:
        """(n, 67) G = (I - A)^-1 B: the state x = G u a constant input u would settle in. A
        session starts each system there, on its first frame's input, and its output on that
        input's own steady output: started from x = 0 (the mean input's), every joint swung from
        the mean pose toward the input's over the first frames, an acceleration several times the
        clip's own p99 on other performers' motion (the systems' poles lie within 0.9)."""
        return np.linalg.solve(np.eye(self.n) - self.A, self.B)

    def blend_weight(self, u: np.ndarray) -> np.ndarray:
        """(..., 67) normalised input -> (...,) erf blend weight: 0 within the training range
        (plus k_p standard deviations), -> 1 far outside."""
        dist = np.maximum(np.maximum(u - self.in_hi, self.in_lo - u), 0.0)
        return erf(np.maximum(dist - self.k_p, 0.0) / self.k_c).max(axis=-1)

    def saturated(self, u: np.ndarray) -> np.ndarray:
        """(..., 67) normalised input saturated into the training range (`kernels.saturate`)."""
        hi = self.in_hi + self.k_p * np.tanh(np.maximum(u - self.in_hi, 0.0) / self.k_p)
        lo = self.in_lo - self.k_p * np.tanh(np.maximum(self.in_lo - u, 0.0) / self.k_p)
        return np.where(u > self.in_hi, hi, np.where(u < self.in_lo, lo, u))

    def _finish(self, feats: np.ndarray, u: np.ndarray, y: np.ndarray, blend: bool, read: np.ndarray) -> np.ndarray:
        """The output features from the systems' y; `read`: the normalised input the systems read
        (`u` saturated or not), whose excess over it passes through."""
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
        """Offline: (F, 67) input features -> ((F, 68) output features, (F, n) states after each
        frame); `saturate`: the systems read the input saturated into range, not blended back."""
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
        """(mean (22, 4), radii (2, 22)): this style's rotation prior as the compiled step reads it
        (`kernels.pack_styles`); without a prior the radii are infinite and nothing is held."""
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
                str(z["style"]),
                A,
                B,
                C,
                D,
                **{k: z[k] for k in STORED},
                k_p=float(z["k"][0]),
                k_c=float(z["k"][1]),
                footplant=fp,
                meta={"source": str(path)},
                prior_mean=z["prior_mean"] if "prior_mean" in z else None,
                prior_radii=z["prior_radii"] if "prior_radii" in z else None,
                raised_arm=StyleCarry.read(z, ARM_PREFIX) if f"{ARM_PREFIX}source" in z else None,
            )


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
    """Hsu et al. 2005 LTI style translation behind the project's streaming interface
    (`models/interface.py`); the input style is Bandai Namco `normal`.

    State per session (all arrays, session axis first): the LTI state of each style in its own
    array `x.<style>` (a style whose weight is 0 is held at x = 0, unset: weighted in, it starts at its
    input's steady state, `kernels.start_state`),
    and `carry`, one float64 row of everything else (`kernels.CARRY`: the input's and the
    output's root transforms, the hands' measures, the running means, the foot planter's memory).
    A style weight vector w mixes the styles: the root displacement features are blended
    linearly, joint rotations by normalised quaternion blending, and 1 - sum(w) of the input
    passes through (intensity < 1). With a one-hot w this is exactly the paper's translator.

    The style set can change while sessions run: `add_style(translator)` appends a style to
    `styles()`, `remove_style(name)` drops one, and `upgrade_state` brings a state made before
    (a live session's, a snapshot's) to the current set: a new style's `x.<style>` starts at 0, a
    removed style's is dropped, nothing else changes. Both replace (never mutate) `translators`
    and the style list, so readers on other threads see a consistent set and `copy.copy(model)`
    is a model whose style set changes independently of this one.
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
        """`tr` with this model's heading and without its stages that are off (a copy, then)."""
        if "rotation_prior" not in self.stages and tr.prior_mean is not None:
            tr = replace(tr, prior_mean=None, prior_radii=None)
        if not self.raised_arms and tr.raised_arm is not None:
            tr = replace(tr, raised_arm=None)
        tr.keep_heading = self.keep_heading
        return tr

    def _compile_step(self) -> None:
        """One step of one session on the rest pose: numba compiles the step, every stage of it
        (or loads it from its cache) here, when the model loads, instead of on a live session's
        first frame."""
        rest = np.zeros((1, rep.NUM_JOINTS, 4))
        rest[..., 3] = 1.0
        self.step_batch(self.init_state(1), FrameBatch(np.zeros((1, 3)), rest), np.zeros((1, len(self._styles))))

    def styles(self) -> list[str]:
        return list(self._styles)

    # ---------------------------------------------------------------- style set

    def _set_styles(self, styles: list[str]) -> None:
        """Everything the step needs per style set, computed here once (the state keys, the
        kernel's records) and replaced whole, so a reader sees one consistent set."""
        systems, footplant, ball = kernels.pack_styles([self.translators[s] for s in styles], ease_keep(self.fps))
        arm = raised_arm.settings([self.translators[s].raised_arm for s in styles], ease_keep(self.fps, RAISE_EASE_S))
        h = self._hands
        hands = kernels.Hands(
            h.parents, h.offsets, h.chain, h.hands, h.shoulders, self.fps, SWAY_FRAMES, RAISE_RAMP_CM[0]
        )
        switches = (self.blend, self.keep_heading, self.raised_arms, self.footlock, self.saturate)
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

    def upgrade_state(self, state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """`state` on the current style set: added styles at x = 0, removed ones dropped (see
        `models.interface`); `state` itself when it already is (one key-set comparison). A state
        from before the carry was packed (its entries under their own keys; those it lacks,
        from before a stage, start again) is packed; one saved with the removed waving arm's
        running means loses them, so a session resumed across a rolling upgrade goes on."""
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

    def init_state(self, batch: int) -> dict[str, np.ndarray]:
        return {
            CARRY: np.zeros((batch, kernels.CARRY_WIDTH)),
            **{f"x.{s}": np.zeros((batch, self.translators[s].n)) for s in self._styles},
        }

    def _workspace(self, batch: int) -> _Scratch:
        """This thread's scratch for steps of `batch` sessions, reused while the style set and the
        batch stay: at batch 256 fresh ~4 MB per step cost more in page faults than the step."""
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
        """The styles some session's weight (B, S) uses."""
        if len(w) == 1:  # one session's weights, one list
            return [s for s, top in enumerate(w.tolist()[0]) if top > 0.0]
        if len(w) < COMPACT_FROM:  # a few sessions: a Python scan of the weights beats numpy's calls
            return [s for s, column in enumerate(w.T.tolist()) if column and max(column) > 0.0]
        return [s for s, top in enumerate(w.max(axis=0).tolist()) if top > 0.0]

    @staticmethod
    def _side_by_side(xs: list[np.ndarray], used: list[int], held: _Scratch) -> tuple[np.ndarray, np.ndarray]:
        """The LTI states of the styles in `used` side by side for the kernel, and where each sits
        (`kernels.Frame`; -1: not in use). One style's own array when it is the only one (a
        session streams one style most of the time), else a copy of those in use (with six
        styles at batch 256 the rest is ~2 MB copied for nothing)."""
        if len(used) == 1 and xs[used[0]].flags.c_contiguous and xs[used[0]].dtype == np.float64:
            return xs[used[0]], held.alone[used[0]]
        x_at, width = np.full(len(xs), -1, np.int64), 0
        for s in used:
            x_at[s], width = width, width + xs[s].shape[1]
        x = held.x[: held.batch * width].reshape(held.batch, width)
        for s in used:
            x[:, x_at[s] : x_at[s] + xs[s].shape[1]] = xs[s]
        return x, x_at

    def translate(self, motion: Motion, style: str, timewarp: bool = False) -> tuple[Motion, np.ndarray]:
        """Offline: a whole `Motion` (BN skeleton) streamed toward `style` by this model's step and
        stages; with `timewarp`, resampled by the translator's log-time-warp output (which would
        break a stream's synchrony). Returns (Motion, contacts (F', 2))."""
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

    def step_batch(
        self, state: dict[str, np.ndarray], frames: FrameBatch, style_weights: np.ndarray
    ) -> tuple[FrameBatch, dict[str, np.ndarray]]:
        """One frame for every session: one compiled call (`kernels.step`) on the packed carry
        and the styles' LTI states laid side by side."""
        return self._step(state, frames, style_weights, None)

    def step_batch_fading(
        self, state: dict[str, np.ndarray], frames: FrameBatch, style_weights: np.ndarray, key: str, reference: tuple
    ) -> tuple[FrameBatch, dict[str, np.ndarray]]:
        """`step_batch` with the unseen-content fade (`models.motion.novelty_stage`, which calls
        this) between the translator and the feet, in one compiled call (`kernels.step_fading`): the fade's state is
        `state[key]`, its reference `reference` (`NoveltyReference.arrays`)."""
        return self._step(state, frames, style_weights, (key, reference))

    def _step(
        self,
        state: dict[str, np.ndarray],
        frames: FrameBatch,
        style_weights: np.ndarray,
        fading: tuple[str, tuple] | None,
    ) -> tuple[FrameBatch, dict[str, np.ndarray]]:
        root = np.ascontiguousarray(frames.root, dtype=np.float64)
        rotations = np.ascontiguousarray(frames.rotations, dtype=np.float64)
        w = np.ascontiguousarray(style_weights, dtype=np.float64)
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
            carry, xs = np.ascontiguousarray(state[CARRY], dtype=np.float64), [state[key] for key in x_keys]
        except KeyError:
            carry, xs = np.empty(0), []
        if carry.shape != (B, kernels.CARRY_WIDTH) or [a.shape for a in xs] != held.x_shapes:
            raise ValueError(
                f"state must hold {CARRY} ({B}, {kernels.CARRY_WIDTH}) and each style's x for this style set: "
                "bring an older state to it with upgrade_state(state)"
            )
        used = self._in_use(w)
        x, x_at = self._side_by_side(xs, used, held)
        new_x, new_carry = np.empty(x.shape), np.empty(carry.shape)
        out = FrameBatch(np.empty((B, 3)), np.empty((B, rep.NUM_JOINTS, 4)), np.empty((B, 2), bool))
        frame, outputs = (root, rotations, w, x_at), (out.root, out.rotations, out.contacts)
        new = {**held.rest, CARRY: new_carry}  # a style no session uses rests at x = 0 (unset)
        if fading is None:
            kernels.step(*(frame, x, new_x, carry, new_carry, outputs, constants, held.work))
        else:
            key, reference = fading
            control = _NO_CONTROL if frames.control is None else np.ascontiguousarray(frames.control, np.float64)
            old = state[key]
            if old.shape[0] != B:
                raise ValueError(f"state[{key!r}] must hold {B} rows, got {old.shape}")
            new[key], out.faded = np.empty(old.shape), np.empty(B)
            fade = (control, old, *reference, new[key], out.faded)
            kernels.step_fading(*(frame, x, new_x, carry, new_carry, outputs, constants, held.work, fade))
        if len(used) == 1:
            new[x_keys[used[0]]] = new_x
        else:
            for s in used:
                new[x_keys[s]] = new_x[:, x_at[s] : x_at[s] + xs[s].shape[1]]
        return out, new
