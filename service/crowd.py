"""A crowd: many characters on one connection (protocol v1.1), held as arrays.

The characters of one model on a connection form a `Troupe`: their model state, rate-adaptation
clocks, held outputs and style weights are arrays with one row per character, so a tick takes all
of them through the model's batcher as one request, with no Python object per character on the
way. Characters that share a rig (model, skeleton and rig options) form a `RigGroup`, whose frames
map onto the model skeleton and back as one array each. Which bytes of a tick belong to whom is
worked out once per list of characters (`Plan`) and reused while the client sends the same list.

Row by row a troupe does what a session does (`service.sessions.Session`): the same clock, the
same held output between model steps, the same style ramp, in the same float64 arithmetic, so a
character's replies in a crowd equal those of the same character streamed alone, bit for bit
(tests/test_crowd.py); the models' steps give each row what it would get in any other batch.
"""

from __future__ import annotations

import asyncio
import json
import secrets
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from models.interface import State, StreamingModel, stack_states, upgrade_state, weight_columns, weight_vector
from models.motion import rate
from models.motion.novelty_stage import faded

from . import pipelines
from . import protocol as P
from .frame_check import check_rows
from .rows import Rows
from .sessions import Held, Snapshot, restored_hinges
from .skeletons import SkeletonAdapter

# (state, root, rotations, weights over names, names, controller rows or None) -> the batcher's step
StepRows = Callable[[State, np.ndarray, np.ndarray, np.ndarray, list[str], np.ndarray | None], Awaitable[tuple]]


class CrowdStep(NamedTuple):
    """A model's batcher entry for a crowd, and the most rows one request of it may hold
    (`Batcher.part_rows`: what a session's frame may wait behind)."""

    step_rows: StepRows
    part_rows: int


def take_rows(state: State, rows: np.ndarray) -> State:
    return {key: value[rows] for key, value in state.items()}


STATE = "state:"  # the model state's keys, among a troupe's per-row arrays
NO_HINGES = np.zeros((0, 4, 4))  # the hinge state passed to an adapter that keeps none


class Troupe:
    """The characters of one model on a connection, one row each. Its per-row arrays live in
    `service.rows.Rows`: a tick, join or leave costs in proportion to the rows it touches, not
    to the troupe (a leave moves the last rows into the freed places: `row_of` follows)."""

    def __init__(self, model: StreamingModel, fps: float, reserve: int = 0) -> None:
        self.model, self.ratio, self.lag = model, model.fps / fps, rate.output_lag(model.fps, fps)
        self._rows = Rows(reserve)  # room for the caller's character cap: a join never copies the troupe
        num_joints = model.skeleton.num_joints
        self.names = list(model.styles())  # what the weight columns stand for
        empty = {
            "ids": np.zeros(0, np.int64),
            "clock": np.zeros(0),  # `Session.clock` per row; < 0 until the first frame
            "held_root": np.zeros((0, rate.HISTORY, 3)),  # the latest model outputs, oldest first
            "held_rot": np.zeros((0, rate.HISTORY, num_joints, 4)),
            "held_input_root": np.zeros((0, 3)),  # the latest input frames (model skeleton)
            "held_input_rot": np.zeros((0, num_joints, 4)),
            "weights": np.zeros((0, len(self.names))),
            "target": np.zeros((0, len(self.names))),
            "left": np.zeros(0, np.int64),  # transition frames left
            "hinges": np.zeros((0, 4, 4)),  # the retargeter's stream state (`Session.hinges`)
        }
        self._rows.append(empty)
        self.row_of: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self._rows)

    # ---- the per-row arrays, as views (written through) ----------------------------------
    @property
    def state(self) -> State:
        """The model state of every row: views, so `state[key][rows] = ...` writes the troupe's."""
        return {key[len(STATE) :]: self._rows.view(key) for key in self._rows.keys() if key.startswith(STATE)}

    @state.setter
    def state(self, state: State) -> None:
        """Every row's state at once (a step of the whole troupe): copied into place."""
        stale = [key for key in self._rows.keys() if key.startswith(STATE) and key[len(STATE) :] not in state]
        for key in stale:
            self._rows.drop(key)
        for key, value in state.items():
            self._rows.replace(STATE + key, value)

    def put_rows(self, rows: np.ndarray, new: State) -> None:
        """`rows`' state replaced by `new`, in place: only those rows are written (the whole
        troupe's copy per partial tick was 130 MB at 16,384 characters). No one else holds these
        arrays: steps and snapshots get gathered copies of their rows."""
        if set(new) - {key[len(STATE) :] for key in self._rows.keys() if key.startswith(STATE)}:
            self.state = upgrade_state(self.model, self.state)  # the model's style set grew meanwhile
        for key, value in new.items():
            self._rows.view(STATE + key)[rows] = value

    ids = property(lambda self: self._rows.view("ids"))
    clock = property(lambda self: self._rows.view("clock"))
    held_root = property(lambda self: self._rows.view("held_root"))
    held_rot = property(lambda self: self._rows.view("held_rot"))
    held_input_root = property(lambda self: self._rows.view("held_input_root"))
    held_input_rot = property(lambda self: self._rows.view("held_input_rot"))
    left = property(lambda self: self._rows.view("left"))
    hinges = property(lambda self: self._rows.view("hinges"))

    @property
    def weights(self) -> np.ndarray:
        return self._rows.view("weights")

    @weights.setter
    def weights(self, value: np.ndarray) -> None:
        self._rows.replace("weights", value)

    @property
    def target(self) -> np.ndarray:
        return self._rows.view("target")

    @target.setter
    def target(self, value: np.ndarray) -> None:
        self._rows.replace("target", value)

    # ---- membership (join, leave, reset: in proportion to the rows touched) ---------------
    def add(
        self,
        ids: Sequence[int],
        weights: Sequence[dict[str, float]],
        resumed: Sequence[Snapshot | None] | None = None,
    ) -> None:
        """New rows for `ids`: fresh, or where `resumed` gives a snapshot, exactly where that
        character (or session: the two snapshot alike) left off."""
        self.sync_styles()
        k = len(ids)
        snaps = list(resumed) if resumed is not None else [None] * k
        if any(s is not None for s in snaps):
            fresh = stack_states(
                [self.model.init_state(1) if s is None else upgrade_state(self.model, s.state) for s in snaps]
            )
        else:
            fresh = self.model.init_state(k)
        if len(self) and set(fresh) != set(self.state):  # the style set changed: every row gets the new keys
            self.state = upgrade_state(self.model, self.state)
            fresh = upgrade_state(self.model, fresh)
        vectors = np.stack([weight_vector(self.names, w) for w in weights]).reshape(k, len(self.names))
        target, clock, left = vectors.copy(), np.full(k, -1.0), np.zeros(k, np.int64)
        hinges = np.zeros((k, 4, 4))
        held = {name: np.zeros((k, *getattr(self, array).shape[1:])) for array, name in HELD_ARRAYS.items()}
        for r, snap in enumerate(snaps):
            if snap is None:
                continue
            vectors[r], target[r] = weight_vector(self.names, snap.weights), weight_vector(self.names, snap.target)
            left[r] = snap.transition_left
            hinges[r] = restored_hinges(snap)[0]
            if (restored := Held.restore(snap.held)) is not None:  # else: the rate starts afresh (`Held.restore`)
                clock[r] = snap.clock
                for name, value in restored._asdict().items():
                    held[name][r] = value
        first = len(self)
        self._rows.append(
            {
                "ids": np.asarray(ids, np.int64),
                "clock": clock,
                **{array: held[name] for array, name in HELD_ARRAYS.items()},
                "weights": vectors,
                "target": target,
                "left": left,
                "hinges": hinges,
                **{STATE + key: value for key, value in fresh.items()},
            }
        )
        for row, i in enumerate(ids, first):
            self.row_of[int(i)] = row

    def snapshot_fields(self, rows: np.ndarray) -> list[dict]:
        """These rows as session snapshots' fields (`Session.snapshot`), one dict per row. Each
        array is copied once for all the rows (one gather per key, not one per row and key: a
        crowd of 2,000 snapshots in a few milliseconds, not 50 of stalled event loop) and every
        row's fields are views of that copy, so rows may step on while the snapshots wait to be
        stored."""
        state = self.state
        keys = list(state)
        # iterating a gathered (n, 1, ...) array yields each row's (1, ...) view without a Python slice per key
        per_row = zip(*(list(state[key][rows][:, None]) for key in keys), strict=True)
        held = {field_name: getattr(self, name)[rows] for name, field_name in HELD_ARRAYS.items()}
        clock, left = self.clock[rows].tolist(), self.left[rows].tolist()
        hinges = self.hinges[rows][:, None]  # each row's (1, 4, 4), a view of this copy
        weights, target = self.weights[rows].tolist(), self.target[rows].tolist()
        names = self.names
        out = []
        for k, values in enumerate(per_row):
            out.append(
                {
                    "state": dict(zip(keys, values, strict=True)),
                    "clock": clock[k],
                    "held": {} if clock[k] < 0 else {name: value[k] for name, value in held.items()},
                    "weights": dict(zip(names, weights[k], strict=True)),
                    "target": dict(zip(names, target[k], strict=True)),
                    "transition_left": left[k],
                    "retarget": {"hinges": hinges[k]},
                }
            )
        return out

    def remove(self, ids: Sequence[int]) -> None:
        """Drop these characters' rows; the last rows move into their places."""
        gone = np.array([self.row_of.pop(int(i)) for i in ids], np.int64)
        moved_from, moved_to = self._rows.remove(gone)
        ids_now = self.ids
        for row in moved_to.tolist():
            self.row_of[int(ids_now[row])] = row
        if not moved_from.size and not len(self):
            self.row_of.clear()

    def rows(self, ids: Sequence[int]) -> np.ndarray:
        return np.array([self.row_of[i] for i in ids], np.int64)

    def reset(self, rows: np.ndarray) -> None:
        """Recurrent state back to its start (`Session.reset`, per row)."""
        self.put_rows(rows, self.model.init_state(len(rows)))
        self.clock[rows] = -1.0

    def set_style(self, rows: np.ndarray, target: dict[str, float], transition_frames: int) -> None:
        """`Session.set_style` for these rows."""
        self.sync_styles()
        vector = weight_vector(self.names, target)
        self.target[rows] = vector
        self.left[rows] = transition_frames
        if transition_frames == 0:
            self.weights[rows] = vector

    def style_rows(self, rows: np.ndarray) -> list[dict[str, float]]:
        """The current weights of these rows as {style: weight} (for replies)."""
        return [{n: float(self.target[r, j]) for j, n in enumerate(self.names)} for r in rows]

    def sync_styles(self) -> np.ndarray:
        """Follow a change of the model's style set: columns of deleted styles go (their share
        passes the input through, as `Session.drop_deleted`), new styles get a zero column.
        Returns the ids of characters that had weight on a deleted style."""
        names = list(self.model.styles())
        if names == self.names:
            return np.zeros(0, np.int64)
        old = {n: j for j, n in enumerate(self.names)}
        gone = [old[n] for n in self.names if n not in names]
        had = (self.weights[:, gone] > 0).any(1) | (self.target[:, gone] > 0).any(1) if gone else None
        self.weights = weight_columns(self.weights, self.names, names)
        self.target = weight_columns(self.target, self.names, names)
        self.names = names
        return self.ids[had] if had is not None else np.zeros(0, np.int64)

    # ---- one tick (arrays only) ---------------------------------------------------------
    def model_inputs(self, rows: np.ndarray, root: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, list]:
        """`Session.model_inputs` for each row, in the same float64 arithmetic: (steps due per
        row, per k-th step the input poses of the rows that take one)."""
        clock, steps, weights = rate.steps_due(self.clock[rows], self.ratio)
        self.clock[rows] = clock
        inputs = []
        for k in range(int(steps.max(initial=0))):
            due = steps > k
            w, prev = weights[due, k], rows[due]  # a row's first frame: weight 1, itself
            inputs.append(rate.blend(self.held_input_root[prev], self.held_input_rot[prev], root[due], rot[due], w))
        self.held_input_root[rows], self.held_input_rot[rows] = root, rot
        return steps, inputs

    def advance_style(self, rows: np.ndarray) -> np.ndarray:
        """`Session.advance_style` for each row: one step of the linear ramp where a transition runs."""
        moving = rows[self.left[rows] > 0]
        if len(moving):
            cur, tgt = self.weights[moving], self.target[moving]
            self.weights[moving] = cur + (tgt - cur) / self.left[moving, None]
            self.left[moving] -= 1
        return self.weights[rows]

    async def step(
        self,
        step: CrowdStep,
        rows: np.ndarray,
        root: np.ndarray,
        rot: np.ndarray,
        control: np.ndarray | None = None,
    ) -> None:
        """The model steps each row owes for this frame (rate adaptation), holding the outputs;
        `control`: the rows' controller input (`FrameBatch.control`), for a controller tick.

        At most `step.part_rows` rows go to the batcher at a time, one part after the other: a
        session's frame that comes meanwhile is stepped before the next part instead of waiting
        behind the whole troupe (a 712-row LTI step held the model thread ~20 ms; the neighbour's
        frames waited that long on every tick). Rows are independent in every model's step
        (tests/test_rowwise.py), so the replies are the same whatever the parts."""
        first = rows[self.clock[rows] < 0]
        steps, inputs = self.model_inputs(rows, root, rot)
        for k, (sel_root, sel_rot) in enumerate(inputs):
            due = steps > k
            sel = rows if due.all() else rows[due]
            sel_control = control if control is None or due.all() else control[due]
            weights = self.advance_style(sel)
            for start in range(0, len(sel), step.part_rows):
                part = slice(start, start + step.part_rows)
                some = sel[part]
                whole = len(some) == len(self) and np.array_equal(some, np.arange(len(self)))
                out_root, out_rot, new_state = await step.step_rows(
                    self.state if whole else take_rows(self.state, some),
                    sel_root[part],
                    sel_rot[part],
                    weights[part],
                    self.names,
                    None if sel_control is None else sel_control[part],
                )
                if whole:
                    self.state = new_state
                else:
                    self.put_rows(some, new_state)
                self.held_root[some] = rate.push(self.held_root[some], out_root)
                self.held_rot[some] = rate.push(self.held_rot[some], out_rot)
            if k == 0 and len(first):  # a row's first output stands for the earlier ones too
                self.held_root[first] = self.held_root[first, -1:]
                self.held_rot[first] = self.held_rot[first, -1:]

    def held_output(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`Session.held_output` for each row."""
        u = rate.output_weight(self.clock[rows], self.lag)
        return rate.interpolate(self.held_root[rows], self.held_rot[rows], u)


HELD_ARRAYS = {  # a troupe's rate arrays: the `Held` field each row's snapshot keeps it under
    "held_root": "outputs_root",
    "held_rot": "outputs_rotations",
    "held_input_root": "input_root",
    "held_input_rot": "input_rotations",
}


@dataclass(eq=False)  # one object per rig: grouped by identity
class RigGroup:
    """Characters of one model sharing one rig: their frames convert as one array."""

    model: str
    adapter: SkeletonAdapter

    @property
    def frame_floats(self) -> int:
        return 3 + 4 * self.adapter.num_joints


@dataclass
class Part:
    """The characters of one rig group in one tick's layout."""

    group: RigGroup
    troupe: Troupe
    positions: np.ndarray  # places in the tick's list of characters
    offsets: np.ndarray  # float offsets of their frames in the tick's payload
    rows: np.ndarray  # their troupe rows
    ids: np.ndarray  # their character ids


@dataclass
class Plan:
    """Where each character's frame lies in a tick with this list of characters."""

    ids: np.ndarray  # (count,) uint32, as sent
    sizes: np.ndarray  # (count,) floats of each character's frame
    parts: list[Part]

    @property
    def floats(self) -> int:
        return int(self.sizes.sum())


@dataclass
class Character:
    id: int
    group: RigGroup
    spec: P.CrowdCharacter
    skeleton: str  # the rig as opened (kept in its snapshots, so a resume maps frames the same way)
    bvh_header: str | None
    rig: dict
    session_id: str = field(default_factory=lambda: secrets.token_hex(16))  # as uuid4().hex, at 1/10 the cost
    token: str = field(default_factory=lambda: secrets.token_urlsafe(24))
    # a resumed character's place (its snapshot's `last_seq`), kept until the crowd answers a tick
    resumed_seq: int | None = None
    joined_at: int = 0  # the crowd's answered ticks when it joined


@dataclass
class Joining:
    """A character about to join, its request checked: model, rig and starting style weights."""

    spec: P.CrowdCharacter
    model: StreamingModel
    rig_key: tuple  # (skeleton, bvh_header, rig options as JSON)
    adapter: SkeletonAdapter
    weights: dict[str, float]
    resumed: Snapshot | None = None  # where it left off, when it joins with a resume token


@dataclass
class TickResult:
    reply: bytes  # the binary reply (characters whose frame was refused left out)
    errors: list[P.ProtocolError] = field(default_factory=list)  # one per refused character frame
    frames: dict[str, int] = field(default_factory=dict)  # character frames stylised, by model


class Crowd:
    """The characters of one crowd connection, by model (troupes) and rig (groups)."""

    def __init__(self, fps: float, reserve: int = 0, faded: bool = False) -> None:
        self.fps, self.reserve = fps, reserve  # reserve: rows each troupe has room for from the start
        self.faded = faded  # replies end in each character's `faded`
        self.characters: dict[int, Character] = {}
        self.troupes: dict[str, Troupe] = {}
        self.groups: dict[tuple, RigGroup] = {}
        self._plan: Plan | None = None
        self._plan_key = b""
        self.answered = 0  # ticks answered

    def __len__(self) -> int:
        return len(self.characters)

    # ---- membership -------------------------------------------------------------------
    def add(self, joining: Sequence[Joining]) -> None:
        """Add characters (ids not in the crowd yet), each troupe's in one go."""
        by_model: dict[str, list[Joining]] = {}
        for j in joining:
            by_model.setdefault(j.model.name, []).append(j)
        for name, members in by_model.items():
            troupe = self.troupes.get(name)
            if troupe is None:
                troupe = self.troupes[name] = Troupe(members[0].model, self.fps, self.reserve)
            troupe.add([j.spec.id for j in members], [j.weights for j in members], [j.resumed for j in members])
            for j in members:
                group = self.groups.setdefault((name, *j.rig_key), RigGroup(name, j.adapter))
                skeleton, bvh_header, rig = j.rig_key[0] or "custom", j.rig_key[1], json.loads(j.rig_key[2])
                character = Character(j.spec.id, group, j.spec, skeleton, bvh_header, rig)
                if j.resumed is not None:
                    character.session_id, character.token = j.resumed.session_id, j.resumed.token
                    character.resumed_seq = j.resumed.last_seq
                character.joined_at = self.answered
                self.characters[j.spec.id] = character
        self._plan = None

    def remove(self, ids: Sequence[int]) -> None:
        """Drop these characters."""
        by_model: dict[str, list[int]] = {}
        for i in ids:
            character = self.characters.pop(i)
            by_model.setdefault(character.group.model, []).append(i)
        for name, gone in by_model.items():
            troupe = self.troupes[name]
            troupe.remove(gone)
            if not len(troupe):
                del self.troupes[name]
        used = {(c.group.model, id(c.group)) for c in self.characters.values()}
        self.groups = {k: g for k, g in self.groups.items() if (g.model, id(g)) in used}
        self._plan = None

    def snapshots(self, owner: str, last_seq: int | None, ids: Sequence[int] | None = None) -> list[Snapshot]:
        """Each character (or those in `ids`) as a session snapshot under its own resume token:
        resumable in a crowd, or alone as a session. `last_seq` is the crowd's last answered tick;
        a character resumed since the last tick keeps the place it was resumed at (its client would
        otherwise replay every frame). The reply to it is not kept per character (a resumed
        crowd's client asks again)."""
        now, out = time.time(), []
        by_troupe: dict[str, list[Character]] = {}
        for i in self.characters if ids is None else ids:
            c = self.characters[i]
            by_troupe.setdefault(c.group.model, []).append(c)
        for name, members in by_troupe.items():
            troupe = self.troupes[name]
            model, pipeline = pipelines.split(name)
            fields = troupe.snapshot_fields(np.array([troupe.row_of[c.id] for c in members], np.int64))
            for c, f in zip(members, fields, strict=True):
                out.append(
                    Snapshot(
                        session_id=c.session_id,
                        token=c.token,
                        model=model,
                        pipeline=pipeline,
                        skeleton=c.skeleton,
                        bvh_header=c.bvh_header,
                        fps=self.fps,
                        encoding="binary",
                        last_seq=last_seq if c.joined_at < self.answered else c.resumed_seq,
                        saved_at=now,
                        rig=dict(c.rig),
                        owner=owner,
                        **f,
                    )
                )
        return out

    def troupe_rows(self, ids: Sequence[int]) -> dict[str, tuple[Troupe, np.ndarray, list[int]]]:
        """The named characters by troupe: (troupe, their rows, their ids)."""
        grouped: dict[str, list[int]] = {}
        for i in ids:
            grouped.setdefault(self.characters[i].group.model, []).append(i)
        return {name: (self.troupes[name], self.troupes[name].rows(m), m) for name, m in grouped.items()}

    # ---- a tick -------------------------------------------------------------------------
    def plan(self, ids_raw: bytes, seq: int) -> Plan:
        """The layout of a tick listing these characters (bytes as sent); reused while the list
        is unchanged, so a steady stream pays one bytes comparison for it."""
        if self._plan is not None and ids_raw == self._plan_key:
            return self._plan
        ids = np.frombuffer(ids_raw, "<u4")
        unknown = [int(i) for i in ids if int(i) not in self.characters]
        if unknown:
            raise P.ProtocolError(
                "unknown_character", f"no character {', '.join(map(str, unknown[:10]))} in this crowd", seq
            )
        if len(np.unique(ids)) != len(ids):
            raise P.ProtocolError("bad_frame", "a character appears twice in the tick", seq)
        groups = [self.characters[int(i)].group for i in ids]
        sizes = np.array([g.frame_floats for g in groups], np.int64)
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        parts = []
        for group in dict.fromkeys(groups):  # first-seen order
            positions = np.array([k for k, g in enumerate(groups) if g is group], np.int64)
            troupe = self.troupes[group.model]
            members = [int(ids[k]) for k in positions]
            parts.append(
                Part(group, troupe, positions, starts[positions], troupe.rows(members), np.array(members, np.int64))
            )
        self._plan, self._plan_key = Plan(ids.copy(), sizes, parts), bytes(ids_raw)
        return self._plan

    async def tick(
        self,
        seq: int,
        ids_raw: bytes,
        payload: np.ndarray,
        step: Callable[[str], CrowdStep],
        dropped: int = 0,
        control: bool = False,
    ) -> TickResult:
        """Stylise one tick: every listed character's frame through its model, a refused frame
        costing only its own character's reply. `step(model)` gives that model's batcher entry.
        A controller tick (`control`) carries each character's desired motion instead of a
        frame, as a session's `control` message does (the input pose is the rest pose)."""
        plan = self.plan(ids_raw, seq)
        want = len(plan.ids) * P.CONTROL_FLOATS if control else plan.floats
        if len(payload) != want:
            raise P.ProtocolError(
                "bad_frame",
                f"tick payload holds {len(payload)} floats, its {len(plan.ids)} characters' "
                f"{'controls' if control else 'frames'} take {want}",
                seq,
            )
        result = TickResult(b"")
        ok = np.ones(len(plan.ids), bool)
        inputs = []  # per part: (rows ok, client rotations, model root, model rotations, controller rows, hinges)
        for part in plan.parts:
            if control:
                good, root, rot, rows_control = self._controls(part, payload, seq, result)
            else:
                good, root, rot = self._frames(part, payload, seq, result)
                rows_control = None
            ok[part.positions[~good]] = False
            adapter = part.group.adapter
            hinges = part.troupe.hinges[part.rows[good]] if adapter.keeps_state else NO_HINGES  # a copy
            model_root, model_rot = adapter.to_model_rows(root, rot, hinges) if len(root) else (root, rot)
            if adapter.keeps_state:
                part.troupe.hinges[part.rows[good]] = hinges
            inputs.append((good, rot, model_root, model_rot, rows_control, hinges))
        outputs = await self._step(plan, inputs, step, result)
        out = np.empty(int(plan.sizes[ok].sum()), "<f4")
        starts = np.concatenate([[0], np.cumsum(plan.sizes[ok])[:-1]])
        place = np.full(len(plan.ids), -1, np.int64)
        place[ok] = starts
        for part, (good, rot, _, _, _, hinges), (out_root, out_rot) in zip(plan.parts, inputs, outputs, strict=True):
            if not len(out_root):
                continue
            client_root, client_rot = part.group.adapter.from_model_rows(out_root, out_rot, rot, hinges)
            at = place[part.positions[good]]
            n = len(at)
            rows = np.concatenate([client_root, client_rot.reshape(n, -1)], 1)
            out[at[:, None] + np.arange(rows.shape[1])] = rows
            result.frames[part.group.model] = result.frames.get(part.group.model, 0) + n
        result.reply = P.encode_tick(
            seq, plan.ids[ok], out, dropped, self._fades(plan, inputs)[ok] if self.faded else None
        )
        self.answered += 1
        return result

    @staticmethod
    def _fades(plan: Plan, inputs: list) -> np.ndarray:
        """Each listed character's `faded` after this tick (0 where its pipeline has no fade)."""
        out = np.zeros(len(plan.ids))
        for part, (good, *_) in zip(plan.parts, inputs, strict=True):
            fade = faded(part.troupe.state)
            if fade is not None:
                out[part.positions[good]] = fade[part.rows[good]]
        return out

    @staticmethod
    def _frames(part: Part, payload: np.ndarray, seq: int, result: TickResult) -> tuple:
        """A part's frames, checked in one compiled pass: (valid rows, roots, rotations) of the
        valid ones; each refused frame's error in `result`."""
        n, num_joints = len(part.positions), part.group.adapter.num_joints
        root, rot, status = np.empty((n, 3)), np.empty((n, num_joints, 4)), np.empty(n, np.int64)
        check_rows(payload, part.offsets, root, rot, status)
        good = status == 0
        for k in np.flatnonzero(~good):
            result.errors.append(
                P.ProtocolError("bad_frame", P.FRAME_CHECK_ERRORS[int(status[k])], seq, character=int(part.ids[k]))
            )
        return good, root[good], rot[good]

    @staticmethod
    def _controls(part: Part, payload: np.ndarray, seq: int, result: TickResult) -> tuple:
        """A part's controller input: (valid rows, rest-pose roots and rotations, (m, 5) control
        rows) of the valid ones; a non-controller model's characters are refused."""
        num_joints = part.group.adapter.num_joints
        values = payload.reshape(-1, P.CONTROL_FLOATS)[part.positions]
        rows, good = P.control_rows(values)
        if not part.troupe.model.controllable:
            for character in part.ids:
                result.errors.append(
                    P.ProtocolError(
                        "control_unsupported",
                        f"model {part.troupe.model.name!r} is not a character controller: send it frames",
                        seq,
                        character=int(character),
                    )
                )
            good[:] = False
        else:
            for k in np.flatnonzero(~good):
                result.errors.append(
                    P.ProtocolError(
                        "bad_frame",
                        f"controller values out of range (speeds within ±{P.MAX_CONTROL_SPEED:g} m/s, "
                        "facing within ±1e4 rad, gait 0 or 1)",
                        seq,
                        character=int(part.ids[k]),
                    )
                )
        m = int(good.sum())
        rest = np.zeros((m, num_joints, 4))
        rest[..., 3] = 1.0
        return good, np.zeros((m, 3)), rest, rows[good]

    async def _step(
        self, plan: Plan, inputs: list, step: Callable[[str], CrowdStep], result: TickResult
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each troupe's characters of this tick as one batcher request (all troupes at once)."""
        by_troupe: dict[str, list[int]] = {}
        for k, part in enumerate(plan.parts):
            by_troupe.setdefault(part.group.model, []).append(k)

        async def run(name: str, members: list[int]) -> None:
            troupe = self.troupes[name]
            for i in troupe.sync_styles():
                result.errors.append(
                    P.ProtocolError(
                        "style_deleted",
                        "a style of this character's mix was deleted; its share now passes the input through",
                        None,
                        character=int(i),
                    )
                )
            rows = np.concatenate([plan.parts[k].rows[inputs[k][0]] for k in members])
            if not len(rows):
                return
            root = np.concatenate([inputs[k][2] for k in members])
            rot = np.concatenate([inputs[k][3] for k in members])
            given = [inputs[k][4] for k in members]
            control = None if given[0] is None else np.concatenate(given)  # a tick is all frames or all controls
            await troupe.step(step(name), rows, root, rot, control)
            held_root, held_rot = troupe.held_output(rows)
            start = 0
            for k in members:
                n = len(inputs[k][2])
                outputs[k] = (held_root[start : start + n], held_rot[start : start + n])
                start += n

        outputs: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros((0, 3)), np.zeros((0, 0, 4))) for _ in plan.parts]
        await asyncio.gather(*(run(name, members) for name, members in by_troupe.items()))
        return outputs
