"""What the trainers (`erd/train.py`, `lpn/train.py`) share, nanoGPT style: the command line
(every config field as `--name=value`), the run's start, what a checkpoint holds to resume
exactly, and the loop: steps within a wall-clock budget under a cosine learning rate."""

from __future__ import annotations

import math
import random
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np
import torch
from tqdm import tqdm

T = TypeVar("T")
Log = Callable[[str], None]

# --------------------------------------------------------------------------- command line

TRUE, FALSE = ("1", "true", "yes", "on", ""), ("0", "false", "no", "off")


def parse_overrides(config: T, argv: list[str]) -> T:
    """`config` (changed in place) with `--name=value` applied (typed by the default; a bare `--flag`
    sets a bool). Unknown names and bad values end the program with one line; `-h`/`--help` prints
    the program's docstring and every option with its default."""
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
    doc = (getattr(sys.modules.get("__main__"), "__doc__", None) or "").strip()
    options = "\n".join(f"  --{f.name}={getattr(config, f.name)}" for f in fields(config))  # type: ignore[arg-type]
    return f"{doc}\n\noptions (--name=value):\n{options}".lstrip()


class TrainConfig(Protocol):
    """The fields of a trainer's config that this file reads."""

    run_dir: str  # checkpoints and log
    resume: bool  # continue run_dir/ckpt.pt
    minutes: float  # this session's wall-clock budget
    max_iters: int  # steps in all
    eval_every: int
    ckpt_every: int  # run_dir/ckpt.pt, what --resume continues
    snapshot_every: int  # also keep ckpt_<iter>.pt, not resumable (0: only the latest)


C = TypeVar("C", bound=TrainConfig)


def resume_config(default: C, argv: list[str]) -> tuple[C, dict | None]:
    """The command line's config, or with `--resume` the run's own, then the command line's overrides."""
    cfg = parse_overrides(default, argv)
    path = Path(cfg.run_dir) / "ckpt.pt"
    if not cfg.resume or not path.exists():
        return cfg, None
    ck = torch.load(path, map_location="cpu", weights_only=False)
    known = {f.name for f in fields(cfg)}  # type: ignore[arg-type]
    saved = type(cfg)(**{k: v for k, v in ck["train_config"].items() if k in known})
    return parse_overrides(saved, argv), ck


# --------------------------------------------------------------------------- a run's start


def seeded_device(threads: int, seed: int, device: str) -> torch.device:
    """A run's start: its threads, every random generator seeded, its device ("auto": a GPU if any)."""
    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    return torch.device(("cuda" if torch.cuda.is_available() else "cpu") if device == "auto" else device)


def use_bf16(setting: str, device: torch.device) -> bool:
    """Whether to autocast to bfloat16; "auto": where native (CUDA; avx512_bf16 or AMX CPUs)."""
    if setting != "auto":
        return setting.lower() in ("1", "true", "yes", "on")
    if device.type == "cuda":
        return True
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return " avx512_bf16" in flags or " amx_bf16" in flags


def autocast(device: torch.device, bf16: bool) -> torch.autocast:
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16)


def start_run(run_dir: Path, out_dir: Path) -> Log:
    """Create the run and output folders; the logger writes each line to stderr and `run_dir/train.log`."""
    run_dir.mkdir(parents=True, exist_ok=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    logf = open(run_dir / "train.log", "a")  # noqa: SIM115 - open for the life of the run

    def log(msg: str) -> None:
        line = f"[{time.strftime('%H:%M:%S')}] {msg}"
        tqdm.write(line, file=sys.stderr)
        logf.write(line + "\n")
        logf.flush()

    return log


# --------------------------------------------------------------------------- what resumes


def rng_state(rng: np.random.Generator) -> dict:
    """Every random generator a run draws from, so a resumed run continues exactly."""
    cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None
    return {"numpy": rng.bit_generator.state, "torch": torch.get_rng_state(), "cuda": cuda, "python": random.getstate()}


def set_rng_state(rng: np.random.Generator, state: dict) -> None:
    """`rng_state`'s generators back (CUDA's kept where the checkpoint or machine lacks it)."""
    rng.bit_generator.state = state["numpy"] if "numpy" in state else state["sampler"]
    torch.set_rng_state(state["torch"])
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    random.setstate(state["python"])


@dataclass
class Schedule:
    """Cosine learning-rate factor over `total` seconds across sessions, or steps when `by_steps`."""

    decay_to: float
    total: float
    by_steps: bool = False
    elapsed_s: float = 0.0

    def progress(self, it: int) -> float:
        done = it if self.by_steps else self.elapsed_s
        return min(done / max(self.total, 1e-9), 1.0)

    def factor(self, it: int) -> float:
        return self.decay_to + (1 - self.decay_to) * 0.5 * (1 + math.cos(math.pi * self.progress(it)))

    @staticmethod
    def resumed(saved: dict, total: float | None) -> Schedule:
        """A checkpoint's schedule, over `total` where given; older LPN checkpoints say `total_s`."""
        saved = {k: v for k, v in saved.items() if k != "lr"}
        if "total_s" in saved:
            saved["total"] = saved.pop("total_s")
        return Schedule(**{**saved, "total": saved["total"] if total is None else total})


def save_checkpoint(state: dict, path: Path) -> None:
    """Written beside `path` and renamed over it, so a run killed mid-write keeps its last one."""
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


# --------------------------------------------------------------------------- the loop


class Run(Protocol):
    """A trainer's networks and state: `step` one update, `report` and `postfix` its figures."""

    it: int
    history: list[dict]
    schedule: Schedule

    def step(self) -> dict[str, float]: ...
    def validate(self) -> dict[str, Any]: ...
    def report(self, terms: dict[str, float], factor: float, steps_per_s: float) -> dict[str, Any]: ...
    def postfix(self, terms: dict[str, float]) -> dict[str, str]: ...
    def checkpoint(self, path: Path, resumable: bool = True) -> None: ...


def train(
    run: Run,
    cfg: TrainConfig,
    optimizers: Sequence[tuple[torch.optim.Optimizer | None, float]],
    log: Log,
    desc: str,
    every: Sequence[tuple[int, Callable[[int], None]]] = (),
) -> float:
    """Step `run` until the budget or schedule ends; validate, checkpoint and call `every` along the way."""
    sched, run_dir = run.schedule, Path(cfg.run_dir)
    t0, first_it, seconds0 = time.time(), run.it, sched.elapsed_s

    def steps_per_s() -> float:
        return (run.it - first_it) / max(sched.elapsed_s - seconds0, 1e-9)

    bar = tqdm(total=cfg.max_iters, initial=run.it, desc=desc, mininterval=10, file=sys.stderr)
    last = time.time()
    while run.it < cfg.max_iters and time.time() - t0 < cfg.minutes * 60 and sched.progress(run.it) < 1.0:
        factor = sched.factor(run.it)
        for opt, base in optimizers:
            for group in opt.param_groups if opt is not None else ():
                group["lr"] = base * factor
        terms = run.step()
        run.it += 1
        now = time.time()
        sched.elapsed_s += now - last
        last = now
        bar.update(1)
        if run.it % 50 == 0:
            bar.set_postfix(run.postfix(terms))
        if run.it % cfg.eval_every == 0:
            v = run.validate()
            v.update(iter=run.it, minutes=round(sched.elapsed_s / 60, 2), **run.report(terms, factor, steps_per_s()))
            run.history.append(v)
            log("val " + " ".join(f"{k}={x:.4g}" if isinstance(x, float) else f"{k}={x}" for k, x in v.items()))
            last = time.time()
        if run.it % cfg.ckpt_every == 0:
            run.checkpoint(run_dir / "ckpt.pt")
        if cfg.snapshot_every and run.it % cfg.snapshot_every == 0:
            run.checkpoint(run_dir / f"ckpt_{run.it:06d}.pt", resumable=False)
        for period, action in every:
            if period and run.it % period == 0:
                action(run.it)
    bar.close()
    v = run.validate()
    v.update(iter=run.it, minutes=round(sched.elapsed_s / 60, 2))
    run.history.append(v)
    log("final val " + " ".join(f"{k}={x:.4g}" for k, x in v.items()))
    run.checkpoint(run_dir / "ckpt.pt")
    return steps_per_s()
