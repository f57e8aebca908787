"""The few OSC 1.0 pieces a VMC bridge needs, on raw bytes: split packets, decode pose messages,
encode bundles.

Why not python-osc for the hot path: building one 56-bone VMC frame with its message builders
costs ~1.4 ms and parsing one ~0.3 ms, most of the bridge's 2 ms budget. Here a VMC pose message
(`,sfffffff`: name, px, py, pz, qx, qy, qz, qw) is decoded with one `struct` call, every other
message is kept as its raw bytes (so a pass-through is byte-exact, whatever its type tags), and
a frame's bone messages are encoded from one (N, 7) float array with per-name byte prefixes
cached. python-osc stays the reference the tests check this codec against.

OSC layout: a string is ASCII, NUL-terminated and padded to a multiple of 4 bytes; a message is
address, type tags (`,` then one letter per argument), arguments big-endian; a bundle is
`#bundle\\0`, an 8-byte time tag, then elements, each an int32 size and a message or bundle.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Sequence

import numpy as np

BUNDLE_TAG = b"#bundle\x00"
IMMEDIATELY = b"\x00\x00\x00\x00\x00\x00\x00\x01"  # the OSC time tag meaning "now"
MAX_DATAGRAM = 65000  # bundles larger than this are split (a UDP datagram holds 65507 bytes)
_POSE = struct.Struct(">7f")
_SIZE = struct.Struct(">i")
# bytes each argument type takes (strings and blobs are variable)
_FIXED = {
    "i": 4,
    "f": 4,
    "c": 4,
    "r": 4,
    "m": 4,
    "h": 8,
    "d": 8,
    "t": 8,
    "T": 0,
    "F": 0,
    "N": 0,
    "I": 0,
    "[": 0,
    "]": 0,
}


class OscError(ValueError):
    """A datagram that is not well-formed OSC (the bridge drops it and counts it)."""


def osc_string(text: str | bytes) -> bytes:
    """`text` NUL-terminated and padded to a multiple of 4 bytes."""
    raw = text.encode() if isinstance(text, str) else text
    return raw + b"\x00" * (4 - len(raw) % 4)


def _read_string(data: bytes, start: int) -> tuple[bytes, int]:
    """(string, offset after its padding) of the OSC string at `start`."""
    end = data.find(b"\x00", start)
    if end < 0:
        raise OscError("unterminated OSC string")
    return data[start:end], (end + 4) & ~3


def elements(data: bytes) -> Iterator[bytes]:
    """The messages of a packet, nested bundles flattened, each as its raw bytes."""
    if not data.startswith(BUNDLE_TAG):
        if data[:1] != b"/" or len(data) % 4 or b"\x00" not in data:
            raise OscError("neither an OSC message nor a bundle")
        yield data
        return
    i, n = 16, len(data)
    while i < n:
        if i + 4 > n:
            raise OscError("truncated bundle element size")
        size = int.from_bytes(data[i : i + 4], "big", signed=True)
        if size < 0 or i + 4 + size > n or size % 4:
            raise OscError("bad bundle element size")
        part = data[i + 4 : i + 4 + size]
        if part.startswith(BUNDLE_TAG):
            yield from elements(part)
        elif part[:1] == b"/":
            yield part
        else:
            raise OscError("a bundle element that is not an OSC message")
        i += 4 + size


def pose_head(address_: str) -> bytes:
    """The first 32 bytes of a VMC pose message to `address_` in its usual shape (`,sfffffff`)."""
    return osc_string(address_) + osc_string(",sfffffff")


def split_pose(message: bytes, head_size: int) -> tuple[bytes, bytes]:
    """(name, the 28 bytes of its seven big-endian floats) of a pose message known to start with a
    `pose_head` of `head_size` bytes: no decoding, the caller converts many at once."""
    end = message.find(b"\x00", head_size)
    k = (end + 4) & ~3
    if end < 0 or k + 28 > len(message):
        raise OscError("truncated pose message")
    return message[head_size:end], message[k : k + 28]


def address(message: bytes) -> bytes:
    """A message's address pattern."""
    return _read_string(message, 0)[0]


def decode_pose(message: bytes) -> tuple[str, tuple[float, ...]] | None:
    """(name, (px, py, pz, qx, qy, qz, qw)) of a VMC pose message (`/VMC/Ext/Bone/Pos`,
    `/VMC/Ext/Root/Pos`: a string then at least seven numbers; extra arguments, such as
    Root/Pos's scale in VMC 2.1, are ignored), or None when its arguments are not that."""
    _, i = _read_string(message, 0)
    tags, i = _read_string(message, i)
    if tags[:9] == b",sfffffff":  # the usual shape: one struct call
        name, i = _read_string(message, i)
        if i + 28 > len(message):
            raise OscError("truncated pose message")
        return name.decode("utf-8", "replace"), _POSE.unpack_from(message, i)
    args = decode_args(message)
    if len(args) >= 8 and isinstance(args[0], str) and all(isinstance(a, (int, float)) for a in args[1:8]):
        return args[0], tuple(float(a) for a in args[1:8])
    return None


def decode_args(message: bytes) -> list:
    """Every argument of a message (i, f, d, h, s, S, b, T, F, N, I, c, r, m, t; arrays flattened)."""
    _, i = _read_string(message, 0)
    tags, i = _read_string(message, i)
    if not tags.startswith(b","):
        raise OscError("message without type tags")
    out: list = []
    for tag in tags[1:].decode("ascii", "replace"):
        if tag in "sS":
            text, i = _read_string(message, i)
            out.append(text.decode("utf-8", "replace"))
        elif tag == "b":
            (size,) = _SIZE.unpack_from(message, i)
            out.append(message[i + 4 : i + 4 + size])
            i += 4 + ((size + 3) & ~3)
        elif tag in _FIXED:
            width = _FIXED[tag]
            if i + width > len(message):
                raise OscError("truncated message")
            if tag == "i":
                out.append(struct.unpack_from(">i", message, i)[0])
            elif tag == "f":
                out.append(struct.unpack_from(">f", message, i)[0])
            elif tag == "d":
                out.append(struct.unpack_from(">d", message, i)[0])
            elif tag == "h":
                out.append(struct.unpack_from(">q", message, i)[0])
            elif tag in "TF":
                out.append(tag == "T")
            elif tag != "[" and tag != "]":
                out.append(message[i : i + width] if width else None)
            i += width
        else:
            raise OscError(f"unknown OSC type tag {tag!r}")
    return out


def encode_message(address_: str, args: Sequence) -> bytes:
    """One message from Python values: str -> s, bool -> T/F, int -> i, float -> f, bytes -> b."""
    tags, body = [","], []
    for a in args:
        if isinstance(a, bool):
            tags.append("T" if a else "F")
        elif isinstance(a, str):
            tags.append("s")
            body.append(osc_string(a))
        elif isinstance(a, (int, np.integer)):
            tags.append("i")
            body.append(struct.pack(">i", int(a)))
        elif isinstance(a, (float, np.floating)):
            tags.append("f")
            body.append(struct.pack(">f", float(a)))
        elif isinstance(a, bytes):
            tags.append("b")
            body.append(_SIZE.pack(len(a)) + a + b"\x00" * (-len(a) % 4))
        else:
            raise TypeError(f"cannot encode {type(a).__name__} as an OSC argument")
    return osc_string(address_) + osc_string("".join(tags)) + b"".join(body)


def pack_pose(values: Sequence[float]) -> bytes:
    """Seven numbers as the 28 bytes `split_pose` gives."""
    return _POSE.pack(*values[:7])


class PoseEncoder:
    """Encodes pose messages of one address for many names from an (N, 7) array: each name's
    element prefix (size, address, `,sfffffff`, name) is built once, the numbers are one
    big-endian float32 conversion of the whole array."""

    def __init__(self, address_: str) -> None:
        self._head = osc_string(address_) + osc_string(",sfffffff")
        self._prefix: dict[str, bytes] = {}

    def prefix(self, name: str) -> bytes:
        """The bundle-element prefix of `name`'s message: int32 size, address, tags, name."""
        p = self._prefix.get(name)
        if p is None:
            body = self._head + osc_string(name)
            p = self._prefix[name] = _SIZE.pack(len(body) + 28) + body
        return p

    def elements(self, names: Sequence[str], values: np.ndarray) -> list[bytes]:
        """Bundle elements (size-prefixed messages), one per name, values (N, 7)."""
        return self.join([self.prefix(n) for n in names], values)

    @staticmethod
    def join(prefixes: Sequence[bytes], values: np.ndarray) -> list[bytes]:
        """Bundle elements from prefixes already looked up (`prefix`) and values (N, 7)."""
        raw = np.ascontiguousarray(values, dtype=">f4").tobytes()
        return [p + raw[28 * k : 28 * k + 28] for k, p in enumerate(prefixes)]


def element(message: bytes) -> bytes:
    """A raw message as a bundle element (int32 size first)."""
    return _SIZE.pack(len(message)) + message


def bundles(elements_: Sequence[bytes], limit: int = MAX_DATAGRAM) -> list[bytes]:
    """Bundles (time tag: immediately) holding the size-prefixed `elements_` in order, as few as
    fit in `limit` bytes each (one, for any usual VMC frame)."""
    out: list[bytes] = []
    part: list[bytes] = []
    size = 16
    for e in elements_:
        if part and size + len(e) > limit:
            out.append(BUNDLE_TAG + IMMEDIATELY + b"".join(part))
            part, size = [], 16
        part.append(e)
        size += len(e)
    if part or not out:
        out.append(BUNDLE_TAG + IMMEDIATELY + b"".join(part))
    return out
