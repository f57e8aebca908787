"""BVH reading and writing. The MOTION block (~99 % of a file) is parsed in one vectorised call;
channel order is kept, so a round trip reproduces the file's numbers; errors name file and line.
(The PyPI BVH packages parse value by value, drop channel order, or cannot write.)
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")
ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")


class BvhError(ValueError):
    """A malformed BVH file; the message names the file and the 1-based line."""

    def __init__(self, source: str, line: int, message: str) -> None:
        super().__init__(f"{source}:{line}: {message}")
        self.source, self.line, self.reason = source, line, message


@dataclass
class BvhJoint:
    name: str
    parent: int  # index into BvhFile.joints, -1 for the root
    offset: np.ndarray  # (3,)
    channels: list[str]  # e.g. ["Xposition", ..., "Zrotation", ...] in file order
    end_site: np.ndarray | None = None  # offset of the End Site, if any


@dataclass
class BvhFile:
    """A BVH file as written: hierarchy plus the raw (frames, channels) motion matrix."""

    joints: list[BvhJoint]
    frame_time: float
    motion: np.ndarray  # (F, C) float64, channels in hierarchy order
    source: str = "<memory>"
    decimals: int | None = None  # fixed decimal places the file was printed with, if it used them
    channel_slices: list[slice] = field(init=False)

    def __post_init__(self) -> None:
        start, self.channel_slices = 0, []
        for joint in self.joints:
            self.channel_slices.append(slice(start, start + len(joint.channels)))
            start += len(joint.channels)
        if self.motion.ndim != 2 or self.motion.shape[1] != start:
            raise ValueError(f"{self.source}: motion has shape {self.motion.shape}, hierarchy has {start} channels")

    @property
    def names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def num_frames(self) -> int:
        return self.motion.shape[0]

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time


_VALID_CHANNELS = set(POSITION_CHANNELS + ROTATION_CHANNELS)
_MOTION = re.compile(r"^[ \t]*MOTION[ \t]*\r?$", re.M)
_NUMBER = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


def _floats(tokens: list[str], n: int, source: str, lineno: int, what: str) -> np.ndarray:
    if len(tokens) != n or not all(_NUMBER.match(t) for t in tokens):
        raise BvhError(source, lineno, f"{what} needs {n} numbers, got {' '.join(tokens)!r}")
    return np.array([float(t) for t in tokens])


def parse(text: str, source: str = "<memory>") -> BvhFile:
    """Parse BVH text (LF or CRLF, spaces or tabs)."""
    motion_at = _MOTION.search(text)
    lines = text[: motion_at.end() if motion_at else len(text)].splitlines()
    # the Frames: and Frame Time: lines (blank lines allowed); the rows are never split into a list
    lines += text[motion_at.end() :].split("\n", 6)[1:6] if motion_at else []
    joints: list[BvhJoint] = []
    stack: list[int] = []  # open joints; -2 marks an open End Site
    pending: tuple[str, int] | None = None  # a JOINT/ROOT/End Site line awaiting its '{'
    i = 0
    while i < len(lines):
        lineno, tokens = i + 1, lines[i].split()
        i += 1
        if not tokens:
            continue
        key = tokens[0]
        if key == "HIERARCHY" and not joints and pending is None:
            continue
        if key in ("ROOT", "JOINT"):
            if (key == "ROOT") != (not stack) or len(tokens) < 2:
                raise BvhError(source, lineno, f"unexpected {key}")
            pending = (" ".join(tokens[1:]), lineno)
        elif key == "End" and len(tokens) >= 2 and tokens[1] == "Site":
            if not stack or stack[-1] < 0:
                raise BvhError(source, lineno, "End Site outside a joint")
            pending = ("", lineno)
        elif key == "{":
            if pending is None:
                raise BvhError(source, lineno, "'{' without a joint")
            name, _ = pending
            pending = None
            if name:
                parent = stack[-1] if stack else -1
                joints.append(BvhJoint(name, parent, np.zeros(3), []))
                stack.append(len(joints) - 1)
            else:
                stack.append(-2)
        elif key == "}":
            if not stack:
                raise BvhError(source, lineno, "unbalanced '}'")
            stack.pop()
        elif key == "OFFSET":
            if not stack:
                raise BvhError(source, lineno, "OFFSET outside a joint")
            offset = _floats(tokens[1:], 3, source, lineno, "OFFSET")
            if stack[-1] == -2:
                joints[stack[-2]].end_site = offset
            else:
                joints[stack[-1]].offset = offset
        elif key == "CHANNELS":
            if not stack or stack[-1] < 0:
                raise BvhError(source, lineno, "CHANNELS outside a joint")
            if len(tokens) < 2 or not tokens[1].isdigit() or int(tokens[1]) != len(tokens) - 2:
                raise BvhError(source, lineno, "CHANNELS count does not match the channel names")
            bad = [c for c in tokens[2:] if c not in _VALID_CHANNELS]
            if bad:
                raise BvhError(source, lineno, f"unknown channel {bad[0]!r}")
            joints[stack[-1]].channels = tokens[2:]
        elif key == "MOTION":
            if stack or pending or not joints:
                raise BvhError(source, lineno, "MOTION before the hierarchy is complete")
            return _parse_motion(lines, i, joints, source, text)
        else:
            raise BvhError(source, lineno, f"unexpected token {key!r}")
    raise BvhError(source, len(lines), "no MOTION section")


def _parse_motion(lines: list[str], i: int, joints: list[BvhJoint], source: str, text: str) -> BvhFile:
    def header(prefix: str) -> str:
        nonlocal i
        while i < len(lines) and not lines[i].strip():
            i += 1
        norm = " ".join(lines[i].split()) if i < len(lines) else ""  # tabs or spaces
        if not norm.startswith(prefix):
            raise BvhError(source, min(i + 1, len(lines)), f"expected '{prefix}'")
        value = norm[len(prefix) :].strip()
        i += 1
        return value

    frames_text, time_text = header("Frames:"), header("Frame Time:")
    if not frames_text.isdigit():
        raise BvhError(source, i - 1, f"bad frame count {frames_text!r}")
    if not _NUMBER.match(time_text) or float(time_text) <= 0:
        raise BvhError(source, i, f"bad frame time {time_text!r}")
    num_frames, num_channels = int(frames_text), sum(len(j.channels) for j in joints)
    parts = text.split("\n", i)
    body_text = parts[i] if len(parts) > i else ""
    num_rows = body_text.rstrip().count("\n") + 1 if body_text.strip() else 0
    if num_rows != num_frames:
        raise BvhError(
            source, i + min(num_rows, num_frames) + 1, f"header says {num_frames} frames, file has {num_rows} rows"
        )
    try:  # numpy < 2.3 warns and stops at a bad token (the size check catches it), later ones raise
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            values = np.fromstring(body_text, dtype=np.float64, sep=" ")
    except ValueError:
        values = np.empty(0)
    if values.size != num_frames * num_channels or not np.isfinite(values).all():
        _locate_bad_row(body_text.rstrip().splitlines(), i, num_channels, source)
    decimals = _printed_decimals(body_text[:4096])
    return BvhFile(joints, float(time_text), values.reshape(num_frames, num_channels), source, decimals)


def _printed_decimals(sample: str) -> int | None:
    """Decimal places of fixed-point numbers in the first rows; None when they use exponents."""
    if "e" in sample or "E" in sample:
        return None
    places = [len(frac) for frac in re.findall(r"\.(\d+)", sample)]
    return max(places) if places else 0


def _locate_bad_row(body: list[str], first: int, num_channels: int, source: str) -> None:
    """Slow path, only on error: find the first row that is not `num_channels` finite numbers."""
    for k, row in enumerate(body):
        tokens = row.split()
        if len(tokens) != num_channels:
            raise BvhError(source, first + k + 1, f"expected {num_channels} values, got {len(tokens)}")
        try:
            vals = np.array(tokens, dtype=np.float64)
        except ValueError:
            bad = next(t for t in tokens if not _NUMBER.match(t))
            raise BvhError(source, first + k + 1, f"not a number: {bad!r}") from None
        if not np.isfinite(vals).all():
            raise BvhError(source, first + k + 1, "non-finite value")
    raise BvhError(source, first, "malformed MOTION block")


def read(path: str | Path) -> BvhFile:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError as exc:
        raise BvhError(str(path), 1, f"not UTF-8 text ({exc.reason})") from None
    return parse(text, str(path))


def _fmt(values: np.ndarray, precision: int) -> str:
    return " ".join(f"{v:.{precision}g}" for v in values)


def _fmt_rows(motion: np.ndarray, decimals: int | None, precision: int) -> list[str]:
    spec = f"%.{decimals}f" if decimals is not None else f"%.{precision}g"
    return [" ".join(spec % v for v in row) for row in motion.tolist()]


def dumps(bvh: BvhFile, precision: int = 6) -> str:
    """Serialise to BVH text, keeping the decimals read (else `precision` significant digits)."""
    out = ["HIERARCHY"]
    children: dict[int, list[int]] = {}
    for idx, joint in enumerate(bvh.joints):
        children.setdefault(joint.parent, []).append(idx)

    def emit(idx: int, depth: int) -> None:
        joint, pad = bvh.joints[idx], "  " * depth
        out.append(f"{pad}{'ROOT' if joint.parent < 0 else 'JOINT'} {joint.name}")
        out.append(f"{pad}{{")
        out.append(f"{pad}  OFFSET {_fmt(joint.offset, precision)}")
        if joint.channels:
            out.append(f"{pad}  CHANNELS {len(joint.channels)} {' '.join(joint.channels)}")
        for child in children.get(idx, []):
            emit(child, depth + 1)
        if joint.end_site is not None:
            out.extend(
                [f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {_fmt(joint.end_site, precision)}", f"{pad}  }}"]
            )
        out.append(f"{pad}}}")

    for root in children.get(-1, []):
        emit(root, 0)
    out += ["MOTION", f"Frames: {bvh.num_frames}", f"Frame Time: {bvh.frame_time:.{precision}g}"]
    out += _fmt_rows(bvh.motion, bvh.decimals, precision)
    return "\n".join(out) + "\n"


def write(bvh: BvhFile, path: str | Path, precision: int = 6) -> None:
    Path(path).write_text(dumps(bvh, precision), encoding="utf-8")
