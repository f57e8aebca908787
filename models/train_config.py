"""Command-line overrides for the trainers' config dataclasses, nanoGPT style: every field of the
config at the top of a train script can be set as `--name=value` (dashes or underscores), typed by
its default. One parser for every trainer, so they accept the same syntax."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    import numpy as np
    import torch

T = TypeVar("T")

TRUE, FALSE = ("1", "true", "yes", "on", ""), ("0", "false", "no", "off")


def parse_overrides(config: T, argv: list[str]) -> T:
    """`config` (a dataclass instance, changed in place and returned) with `--name=value` applied.
    A bare `--flag` sets a bool field. Unknown names and bad values end the program with one line;
    `-h` or `--help` prints the program's docstring and every option with its default, and ends it."""
    known = {f.name for f in fields(config)}  # type: ignore[arg-type]
    if any(arg in ("-h", "--help") for arg in argv):
        print(usage(config))
        raise SystemExit(0)
    for arg in argv:
        key, _, value = arg.lstrip("-").partition("=")
        key = key.replace("-", "_")
        if key not in known:
            raise SystemExit(f"unknown option {key!r}; known: {', '.join(sorted(known))}")
        kind = type(getattr(config, key))
        if kind is bool:
            if value.lower() not in TRUE + FALSE:
                raise SystemExit(f"option {key!r} takes true or false, not {value!r}")
            setattr(config, key, value.lower() in TRUE)
            continue
        try:
            setattr(config, key, kind(value))
        except ValueError:
            raise SystemExit(f"option {key!r} takes a {kind.__name__}, not {value!r}") from None
    return config


def usage(config: object) -> str:
    """The running program's docstring, then each option of `config` as `--name=default`."""
    import sys

    doc = (getattr(sys.modules.get("__main__"), "__doc__", None) or "").strip()
    options = "\n".join(f"  --{f.name}={getattr(config, f.name)}" for f in fields(config))  # type: ignore[arg-type]
    return f"{doc}\n\noptions (--name=value):\n{options}".lstrip()


def use_bf16(setting: str, device: torch.device) -> bool:
    """A trainer's `bf16` setting: whether to autocast to bfloat16; "auto" where it is native
    (CUDA; avx512_bf16 or AMX CPUs)."""
    if setting != "auto":
        return setting.lower() in ("1", "true", "yes", "on")
    if device.type == "cuda":
        return True
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return " avx512_bf16" in flags or " amx_bf16" in flags


def seeded_device(threads: int, seed: int, device: str) -> torch.device:
    """A run's start: its thread count, every random generator seeded (Python's, numpy's global,
    torch's), and its device ("auto": a GPU where there is one)."""
    import random

    import numpy as np
    import torch

    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    return torch.device(("cuda" if torch.cuda.is_available() else "cpu") if device == "auto" else device)


def rng_state(rng: np.random.Generator) -> dict:
    """Every random generator a run draws from (`rng`, torch's CPU and CUDA ones, Python's): what a
    checkpoint holds so that a resumed run continues exactly."""
    import random

    import torch

    cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None
    return {"numpy": rng.bit_generator.state, "torch": torch.get_rng_state(), "cuda": cuda, "python": random.getstate()}


def set_rng_state(rng: np.random.Generator, state: dict) -> None:
    """`rng_state`'s generators back (a checkpoint without CUDA's, or resumed without a GPU, keeps
    CUDA's as they are; `sampler`: an older name of `rng`'s state)."""
    import random

    import torch

    rng.bit_generator.state = state["numpy"] if "numpy" in state else state["sampler"]
    torch.set_rng_state(state["torch"])
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    random.setstate(state["python"])
