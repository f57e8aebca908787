"""Writes models/weights/lti/MODEL_CARD.md from training_report.json and a fresh benchmark."""

from __future__ import annotations

import json
from pathlib import Path

from .model import WEIGHTS_DIR

TEMPLATE = """# LTI style translation (Hsu, Pulli & Popović 2005) — model card

Per-style linear time-invariant translators from the Bandai Namco dataset-2 style `normal` to each
other dataset-2 style, for the stylestream service (`models.lti.LTIStyleModel`, name `lti`).
One `<style>.npz` per output style (float32 matrices, compressed), {size_kb:.0f} KiB in all.

## Data and licence

* Bandai Namco Research Motion Dataset, **dataset 2** (`bandai-namco-2`), 30 fps, 22-joint skeleton.
  Pairs: every `train`-split clip of the output style is paired with the `normal` train clip of the
  same content (walk, walk-turn-left/right, run, wave-*-hand, raise-up-*-hand) whose length is
  closest, within the time warp's slope limits ([1/3, 2] output frames per input frame; clips
  outside are skipped). Held-out evaluation uses the same pairing on the `val` split.
  Dataset 1 has no `normal`→style pairs with matching content and was not used.
* Licence: the Bandai Namco data are **CC BY-NC 4.0**; these weights are derived from them and
  inherit **CC BY-NC 4.0** (non-commercial use, attribution to Bandai Namco Studios Inc.).

## Method (what the weights contain)

* Correspondence: iterative motion warping (time warp by dynamic programming over the output
  upsampled ×3 with slope in [1/3, 2], alternated with a per-DOF smooth scale/offset space warp
  solved in closed form, until the objective stops decreasing). The space warp only aids the
  alignment; the training output is the time-warped output clip.
* Representation (67 DOFs in, 68 out): root ground-plane displacement and yaw change in the
  previous frame's facing, root height, yaw-free hips tilt and 20 joint rotations as exponential
  maps relative to a per-joint reference rotation (mean training pose, stored as `ref`), per-DOF
  normalisation (input and output separately); extra output: log of the differential time warp.
* 21 per-joint LTI systems (root: 7 inputs → 7 outputs + log time warp; each other joint 3 → 3),
  identified by PO-MOESP subspace identification (horizon {horizon} block rows, order from the
  singular values: an obvious gap, else {energy:.0%} of the energy, capped at {max_root} for the
  root and {max_joint} per joint), B and D fitted for simulation from x0 = 0; combined block-
  diagonally into one system `[x'; y] = [[A, B], [C, D]] [x; u]`.
* **Unstable A:** every block's A is made stable before B and D are fitted. Eigenvalues with
  modulus ≥ {max_radius} are reflected into the unit circle (λ → 1/λ̄, keeping the frequency and
  turning growth into decay) and capped at modulus {max_radius}; A is rebuilt from the modified
  eigen-decomposition (real). If that reconstruction were ill-conditioned, A would be scaled by
  {max_radius}/ρ(A) instead. The largest spectral radius as identified and the number of moved
  eigenvalues are listed below; every stored A has ρ(A) ≤ {max_radius}.
* Footplant: per foot, a 1-D Fisher/MDA projection of the state with one Gaussian per class
  (planted / not), fitted to ankle contacts of the time-warped output examples. Contacts are
  returned every frame and drive the IK foot lock (see Runtime options).
* Generalisation blend: per DOF the distance d of the normalised input outside its training range;
  w = max over DOFs of erf(max(0, d − k_p) / k_c), k_p = {k_p}, k_c = {k_c}; output ← (1 − w)·output + w·input.

## Training

Command: `{command}` (config: `models/lti/train.py` CONFIG; deterministic).
Time on the 2-core shared CPU machine: {train_time}.

## Held-out validation pairs (no blend; errors against the IMW-aligned real output)

`rmse` is over all 68 normalised output DOFs; `angle` the mean geodesic error of the 20 joint
rotations; `speed` the mean absolute root-speed error. "identity" is the do-nothing baseline
(output = input). Contact accuracy is per foot and frame.

| style | val pairs | rmse (identity) | angle deg (identity) | speed cm/s (identity) | contacts | train pairs / frames | state dim | ρ(A) identified → stored | eigenvalues moved |
|---|---|---|---|---|---|---|---|---|---|
{rows}

State dimensions per block (root, then joints 2..21 Spine … Toes_R):

{orders}

## Dataset 1 (trained, not shipped)

Dataset 1 has one take per (style, content), so each `normal`→style model gets 1–8 training pairs
(a few hundred to ~1000 frames) and at most 2 validation pairs. They were trained with the same
configuration (`python -m models.lti train --styles bn1-old ...`, ~5 s each) but are **not**
shipped: on the few held-out pairs they are often worse than doing nothing; a trial with much
smaller state dimensions (root ≤ 4, joints ≤ 2) helped some (active, chimpira, tired) but left
happy, proud and feminine worse than the identity. Numbers (rmse, joint angle
error in degrees; identity baseline in brackets):

| model | train pairs | val pairs | rmse (identity) | angle deg (identity) |
|---|---|---|---|---|
{bn1}

## Streaming cost (`python -m models.lti bench`, this machine, float64 numpy)

```
{bench}
```

## Looked at

`python -m models.lti render --styles elderly exhausted` (validation walk
`dataset-2_walk_normal_021`): the elderly translation leans forward, shortens the stride and
reduces the arm swing, close to real elderly takes (validation walks: forward lean 8–10° vs 10°
real and 2° input; left-hand swing 24–26 cm vs 25–26 cm real and 47–49 cm input; speed 78–86 cm/s vs
71–78 cm/s real and 105–108 cm/s input). The path keeps its direction, and at the elderly speed it
is shorter. The exhausted translation is subtler (slightly slower, a little more forward lean of
the head and chest); it does not reproduce the larger, forward arm swing of the real exhausted
takes. The per-frame root-speed error is no better than the identity baseline (it is dominated by
within-step speed fluctuations and alignment jitter), although the mean speed is translated.

## Runtime options (not part of the weights)

* `keep_heading` (default on): the output's yaw change is the input's. The model's own yaw output
  drifts slowly for some styles (exhausted: ~0.05°/frame on a straight walk, a full turn in ~4
  minutes of streaming), which a live stream cannot afford. `--model-heading` in the CLI turns it off.
* Foot lock (default on): two-bone leg IK holds a planted ankle at its touch-down point, the
  anchor being dragged along when it lags the animated ankle by more than 5 cm; the root and the
  path are untouched. The translated root slightly outpaces the translated strides, so a hard
  lock straightens the knees (elderly knee flexion 42° → 32°, the real elderly take has 42°); with
  the 5 cm limit the knee keeps 40° and the ankle speed while planted drops from 43–46 to 28–32 cm/s
  (elderly; exhausted 30 → 16 cm/s). A hard lock reaches ~5 cm/s. An earlier root-shifting lock
  kept the legs but shortened the path (811 → 459 cm on the same walk) and was dropped.
* Erf blend (default on): see above; contacts are returned with every frame either way.
* Time warp: offline only (`translate --timewarp`), the log-rate output is ignored online.
"""


def write_model_card(bench: str, train_time: str, command: str, out: Path = WEIGHTS_DIR / "MODEL_CARD.md") -> Path:
    report = json.loads((WEIGHTS_DIR / "training_report.json").read_text())
    cfg, styles = report["config"], report["styles"]
    rows, orders, bn1 = [], [], []
    for style in sorted(styles):
        r = styles[style]
        if not (WEIGHTS_DIR / f"{style}.npz").exists():
            bn1.append(
                f"| {style} | {r['train_pairs']} | {r['pairs']} | "
                + (
                    f"{r['rmse_norm']:.3f} ({r['rmse_norm_identity']:.3f}) | {r['joint_angle_deg']:.2f} ({r['joint_angle_deg_identity']:.2f}) |"
                    if r.get("pairs")
                    else "— | — |"
                )
            )
            continue
        orders.append(f"* {style}: {r['orders']}")
        if not r.get("pairs"):
            rows.append(
                f"| {style} | 0 | — | — | — | — | {r['train_pairs']} / {r['train_frames']} | {r['state_dim']} | "
                f"{r.get('raw_spectral_radius_max', float('nan')):.3f} → {r['spectral_radius']:.3f} | {r.get('eigenvalues_moved', '?')} |"
            )
            continue
        rows.append(
            f"| {style} | {r['pairs']} | {r['rmse_norm']:.3f} ({r['rmse_norm_identity']:.3f}) | "
            f"{r['joint_angle_deg']:.2f} ({r['joint_angle_deg_identity']:.2f}) | "
            f"{r['root_speed_cm_s']:.1f} ({r['root_speed_cm_s_identity']:.1f}) | {r['contact_accuracy']:.1%} | "
            f"{r['train_pairs']} / {r['train_frames']} | {r['state_dim']} | "
            f"{r.get('raw_spectral_radius_max', float('nan')):.3f} → {r['spectral_radius']:.3f} | {r.get('eigenvalues_moved', '?')} |"
        )
    size = sum(p.stat().st_size for p in WEIGHTS_DIR.glob("*.npz")) / 1024  # the translators and the raised arm
    text = TEMPLATE.format(
        size_kb=size,
        horizon=cfg["horizon"],
        energy=cfg["energy"],
        max_root=cfg["max_order_root"],
        max_joint=cfg["max_order_joint"],
        max_radius=cfg["max_radius"],
        k_p=cfg["k_p"],
        k_c=cfg["k_c"],
        command=command,
        train_time=train_time,
        rows="\n".join(rows),
        orders="\n".join(orders),
        bench=bench,
        bn1="\n".join(bn1) or "| (none trained) | | | | |",
    )
    out.write_text(text)
    return out
