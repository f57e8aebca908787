"""The trainers' one command-line parser: `--name=value` typed by the config's defaults."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from models.erd.train import parse_args as erd_args
from models.lpn.train import parse_args as lpn_args
from models.train_config import parse_overrides


@dataclass
class Config:
    steps: int = 10
    lr: float = 1e-3
    name: str = "run"
    compile: bool = True


def test_values_take_the_type_of_the_defaults():
    cfg = parse_overrides(Config(), ["--steps=30", "--lr=0.5", "--name=x", "--compile=false"])
    assert (cfg.steps, cfg.lr, cfg.name, cfg.compile) == (30, 0.5, "x", False)
    assert parse_overrides(Config(compile=False), ["--compile"]).compile is True


@pytest.mark.parametrize(
    "argv,says",
    [
        (["--stepz=3"], "unknown option 'stepz'"),
        (["--steps=ten"], "takes a int"),
        (["--compile=maybe"], "true or false"),
    ],
)
def test_bad_options_end_the_program_with_one_line(argv, says):
    with pytest.raises(SystemExit, match=says):
        parse_overrides(Config(), argv)


@pytest.mark.parametrize("parse", [erd_args, lpn_args])
def test_every_trainer_parses_the_same_way(parse):
    defaults = vars(parse([]))
    for key, value in defaults.items():
        if isinstance(value, bool):
            assert getattr(parse([f"--{key}=false"]), key) is False
        elif isinstance(value, int):
            assert getattr(parse([f"--{key.replace('_', '-')}={value + 1}"]), key) == value + 1
    with pytest.raises(SystemExit, match="unknown option"):
        parse(["--no-such-option=1"])
