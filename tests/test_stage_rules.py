"""No correction stage holds a rule that names a style, a side or a content.

A stage is fitted from a style's clips the same way for every style, and measures from the motion
what the body is doing (its gait, a raised hand, which side moves), so a style uploaded from a
clip gets the same treatment as a built-in one. A rule table keyed by a name (`("active",)`, a
side `"R"`, a content `"wave-left-hand"`) gives one style, side or content a behaviour the others
never get. This test reads the stage modules' source: every string constant that is not a
docstring must name no style or content of the data index (nor a hyphen-prefix of one, such as
`"raise-up"`), no side on its own (`"L"`, `"left"`, ...), and a joint of one side only if the same
module also names its mirror (`TWIST_JOINTS` lists both arms: a symmetric set is no side rule).

To cover another method's stages, add its modules to `STAGE_MODULES`."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STAGE_MODULES = (
    "models/erd/stages.py",
    "models/erd/rotation_prior.py",
    "models/erd/slow_carry.py",
    "models/erd/twist_range.py",
    "models/erd/gait.py",
    "models/erd/upload_stages.py",
    "models/erd/uploads.py",
    "models/erd/finetune.py",
    "models/lpn/output_prior.py",
    "models/lpn/arm_coupling.py",
    "models/lpn/carriage.py",
    "models/stages.py",
    "models/motion/rotation_ball.py",
    "models/motion/hinge_floor.py",
    "models/lti/model.py",
    "models/lti/kernels.py",
    "models/lti/footplant.py",
    "models/lti/raised_arm.py",
)
SIDE_WORDS = {"l", "r", "left", "right"}
SIDE_SUFFIXES = {"_l": "_r", "_r": "_l"}


def _docstrings(tree: ast.AST) -> set[int]:
    """The ids of the constant nodes that are docstrings (a module's, class's or function's first statement)."""
    out = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body:
            first = body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    return out


def string_constants(source: str) -> list[tuple[int, str]]:
    """(line, text) of every string constant in `source` that is not a docstring, the literal parts
    of f-strings included."""
    tree = ast.parse(source)
    docs = _docstrings(tree)
    return [
        (node.lineno, node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs
    ]


def _prefixes(name: str) -> set[str]:
    """`name` and each of its hyphen-prefixes: "raise-up-left-hand" -> raise, raise-up, ..."""
    parts = name.lower().split("-")
    return {"-".join(parts[:k]) for k in range(1, len(parts) + 1)}


def named_rules(source: str, names: set[str]) -> list[str]:
    """What in `source` names one of `names` (styles and contents), a side, or a one-sided joint."""
    words = set().union(*(_prefixes(n) for n in names))
    found, joints = [], {}
    for line, text in string_constants(source):
        low = text.strip().lower()
        if not low:
            continue
        if low in words or (low.endswith("-") and low.rstrip("-") in words):
            found.append(f"line {line}: {text!r} names a style or content")
        elif low in SIDE_WORDS:
            found.append(f"line {line}: {text!r} names a side")
        elif low[-2:] in SIDE_SUFFIXES and len(low) > 2:
            joints[low] = line
    for joint, line in joints.items():
        if joint[:-2] + SIDE_SUFFIXES[joint[-2:]] not in joints:
            found.append(f"line {line}: {joint!r} names a joint of one side only")
    return found


@pytest.fixture(scope="module")
def names() -> set[str]:
    """Every style and content of the data index (both Bandai Namco datasets and the others), and
    the dataset-1 prefix LPN-FiLM gives its styles."""
    from models.data import build_index

    index = build_index()
    styles = {c.style for c in index}
    return styles | {f"d1-{s}" for s in styles} | {c.content for c in index}


@pytest.mark.parametrize("module", STAGE_MODULES)
def test_no_stage_names_a_style_a_side_or_a_content(module, names):
    assert named_rules((ROOT / module).read_text(), names) == []


def test_the_scan_finds_each_kind_of_rule():
    """The detector itself: a style tuple, a content prefix, a side and a one-sided joint are
    found; docstrings, a symmetric joint set and names built over both sides are not."""
    names = {"active", "normal", "raise-up-left-hand", "walk", "d1-sad"}
    source = '''"""Toward active, a raise-up walk."""
STYLES = ("active",)
PREFIX = c.startswith("raise-up")
SIDES = ("R",)
ONE = ("Hand_R",)
D1 = s.startswith("d1-sad")
'''
    found = named_rules(source, names)
    assert sorted(f.split(":")[0] for f in found) == [f"line {k}" for k in range(2, 7)]
    clean = '''"""A walk toward active, the left arm."""
BOTH = ("UpperArm_L", "UpperArm_R")
JOINTS = tuple(f"Hand_{s}" for s in "LR")
def f():
    """active"""
    return "prior_on"
'''
    assert named_rules(clean, names) == []
