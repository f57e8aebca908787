"""The training scripts' run folder and log: one line per event, on stderr beside the progress bar
and appended to `run_dir/train.log`, so a long run can be followed and read back afterwards."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

from tqdm import tqdm


def start_run(run_dir: Path, out_dir: Path) -> Callable[[str], None]:
    """Create the run (checkpoints, log) and output (renders) folders; return the logger."""
    run_dir.mkdir(parents=True, exist_ok=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    logf = open(run_dir / "train.log", "a")  # noqa: SIM115 - open for the life of the run

    def log(msg: str) -> None:
        line = f"[{time.strftime('%H:%M:%S')}] {msg}"
        tqdm.write(line, file=sys.stderr)  # above the progress bar, not through it
        logf.write(line + "\n")
        logf.flush()

    return log
