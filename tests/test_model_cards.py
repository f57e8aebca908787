"""The model cards under models/weights (issue 46): short enough to read, carrying the licence the
Bandai Namco data passes on to weights trained on it, and citing only commands that exist."""

from __future__ import annotations

import ast
import importlib.util
import re
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CARDS = sorted((REPO / "models" / "weights").glob("*/MODEL_CARD.md"))
MAX_LINES = 200
BANDAI_NAMCO = re.compile(r"bandai[ -]namco", re.I)
# `python -m module [args]` up to the end of the code span, table cell, comment or line
COMMAND = re.compile(r"python -m ([A-Za-z_][\w.]*)([^`|#\n]*)")
OPTION = re.compile(r"(?<!\S)--([A-Za-z][\w-]*)")


def commands(text: str) -> list[tuple[str, list[str]]]:
    """Each cited `python -m` command: its module and the names of its `--options`."""
    text = text.replace("\\\n", " ")  # a shell line continued on the next
    return [(m[1].rstrip("."), OPTION.findall(m[2])) for m in COMMAND.finditer(text)]


def _is_dataclass(node: ast.ClassDef) -> bool:
    for d in node.decorator_list:
        target = d.func if isinstance(d, ast.Call) else d
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name == "dataclass":
            return True
    return False


@cache
def known_options(folder: Path) -> frozenset[str]:
    """Option names the modules of `folder` accept: string literals such as "--minutes" or
    "--runs=" (argparse and hand-read argv), and the fields of its dataclasses, which
    `models.training.parse_overrides` takes as `--field=value`."""
    names: set[str] = set()
    for path in folder.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                if m := re.fullmatch(r"--([A-Za-z][\w-]*)=?", node.value):
                    names.add(m[1])
            elif isinstance(node, ast.ClassDef) and _is_dataclass(node):
                names.update(
                    s.target.id for s in node.body if isinstance(s, ast.AnnAssign) and isinstance(s.target, ast.Name)
                )
    return frozenset(names)


def card_id(path: Path) -> str:
    return path.parent.name


def test_every_method_has_a_card() -> None:
    assert {card_id(p) for p in CARDS} >= {"lti", "erd", "lpn", "eval"}


@pytest.mark.parametrize("card", CARDS, ids=card_id)
def test_a_card_is_at_most_200_lines(card: Path) -> None:
    lines = len(card.read_text().splitlines())
    assert lines <= MAX_LINES, f"{card.relative_to(REPO)}: {lines} lines (history belongs in git)"


@pytest.mark.parametrize("card", CARDS, ids=card_id)
def test_weights_from_bandai_namco_data_name_their_licence(card: Path) -> None:
    """The Bandai Namco datasets are CC BY-NC 4.0, and weights trained on them inherit it."""
    text = card.read_text()
    records = [p.read_text() for p in card.parent.glob("*.json")]
    if not any(BANDAI_NAMCO.search(t) for t in [text, *records]):
        pytest.skip("weights not trained on Bandai Namco data")
    assert "CC BY-NC 4.0" in text, "the card must name the CC BY-NC 4.0 licence"
    assert "non-commercial" in text.lower(), "the card must say the weights are for non-commercial use"


@pytest.mark.parametrize("card", CARDS, ids=card_id)
def test_every_cited_command_exists(card: Path) -> None:
    cited = commands(card.read_text())
    missing = sorted({module for module, _ in cited if importlib.util.find_spec(module) is None})
    assert not missing, f"modules that do not exist: {missing}"
    unknown = []
    for module, options in cited:
        spec = importlib.util.find_spec(module)
        assert spec is not None and spec.origin is not None
        accepted = known_options(Path(spec.origin).parent)
        unknown += [f"python -m {module} --{o}" for o in options if o not in accepted]
    assert not unknown, f"options no command of the module's package reads: {unknown}"


def test_the_command_reader_sees_what_a_card_cites() -> None:
    """What the checks above rest on: continued lines, several commands on a line, options with
    values, and table cells."""
    text = (
        "`python -m models.eval --split val --methods lti` and `.venv/bin/python -m models.lti train`\n"
        "OMP_NUM_THREADS=1 .venv/bin/python -m models.erd.train --init_weights=models/weights/erd \\\n"
        "    --minutes=30   # stage 3 --not-an-option\n"
        "| 1 | network | `python -m models.lpn train` | – |\n"
    )
    assert commands(text) == [
        ("models.eval", ["split", "methods"]),
        ("models.lti", []),
        ("models.erd.train", ["init_weights", "minutes"]),
        ("models.lpn", []),
    ]
    assert "split" not in known_options(REPO / "models" / "eval")  # the old `--split val` is gone
    assert {"final", "quick", "methods"} <= known_options(REPO / "models" / "eval")
    assert {"minutes", "init_weights", "export"} <= known_options(REPO / "models" / "erd")
