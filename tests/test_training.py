"""The trainers' shared pieces (`models/training.py`): one command-line parser (`--name=value`
typed by the config's defaults), the random state and the schedule a checkpoint holds."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from models.erd.train import parse_args as erd_args
from models.lpn.train import parse_args as lpn_args
from models.training import parse_overrides


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


@pytest.mark.parametrize("flag", ["-h", "--help"])
def test_help_lists_every_option_with_its_default_and_ends_the_program(flag, capsys):
    with pytest.raises(SystemExit) as ended:
        parse_overrides(Config(), ["--steps=3", flag])
    said = capsys.readouterr().out
    assert ended.value.code == 0
    assert "--steps=10" in said and "--lr=0.001" in said and "--name=run" in said and "--compile=True" in said


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


def test_a_checkpoints_random_state_replays_every_generator_exactly():
    """`rng_state` then `set_rng_state`: numpy's generator, torch's and Python's draw again what
    they drew after the checkpoint (a resumed run continues exactly); an older checkpoint naming
    the numpy state `sampler` restores too."""
    import random

    import numpy as np
    import torch

    from models.training import rng_state, set_rng_state

    rng = np.random.default_rng(3)
    state = rng_state(rng)
    draws = lambda: (rng.random(3).tolist(), torch.rand(3).tolist(), random.random())  # noqa: E731
    first = draws()
    set_rng_state(rng, state)
    assert draws() == first
    older = {("sampler" if k == "numpy" else k): v for k, v in state.items()}
    set_rng_state(rng, older)
    assert draws() == first


def test_a_schedule_resumes_from_either_trainers_checkpoints():
    """A checkpoint's schedule keeps its span unless the session sets one; LPN's older checkpoints
    (a learning rate and `total_s` in the schedule) resume as the same cosine."""
    from dataclasses import asdict

    from models.training import Schedule

    older = Schedule.resumed({"lr": 7e-4, "decay_to": 0.05, "total_s": 600.0, "elapsed_s": 120.0}, None)
    assert older == Schedule(0.05, 600.0, by_steps=False, elapsed_s=120.0)
    assert Schedule.resumed(asdict(older), 900.0).total == 900.0
    steps = Schedule(0.2, 20.0, by_steps=True, elapsed_s=5.0)
    assert steps.factor(0) == 1.0 and steps.factor(20) == pytest.approx(0.2) and steps.progress(10) == 0.5
