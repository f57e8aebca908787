"""LPN-FiLM's arm coupling: a style's forearms moved with its upper arms, shoulders and chest as
they move together in the style's real clips (`ARM_COUPLING_FILE` beside the weights, written by
`python -m models.lpn.arm_coupling [STYLE ...]`; `runtime.LPNModel` applies it after the output
prior and before the rotation balls).

After the output prior (`output_prior.py`), LPN-FiLM's active walks swung their upper arms as the
real active walks do (mean deviation 31.6 against 33.0 degrees) but did not pump their forearms:
driven by the `normal` TRAIN walks, the forearm turned at 73 degrees/s where the real active
forearm turns at 180, the hands' vertical speed varied half as much as the real ones' (std 81-94
against 139-159 cm/s on the validation walks and turns), and the position judge read 2 of the 13
validation locomotion inputs as exhausted. The output prior maps each joint on its own, so it can
widen a forearm's spread but not put a pump in step with the swing the network keeps still. In
the real active clips the forearm's deviation from its mean is, to R^2 0.81 and 0.74 on its two
main axes, a linear function of the deviations of its upper arm, its shoulder and the chest
(`DRIVERS`); in the network's output the same regression has other coefficients. The coupling
swaps the network's for the real ones:

    d_f' = d_f + (B_real - B_made)^T [d_u, d_s, d_c, 1]

every d a joint's rotation vector away from the style's real mean (in the joint's own frame, as
the output prior reads it), B fitted by least squares on the style's real TRAIN locomotion and on
the network's output (its carriage and output prior in place, driven by the `normal` TRAIN
locomotion), on walks and on runs apart and mixed by the control's gait share, as the output
prior is. What the network's forearm does apart from its drivers stays. A style mix blends the
corrections as the output prior does (q' = q exp(sum_s w_s log(q^-1 f_s(q)))); a row that weighs
no coupled style, and every joint but the forearms, is left exactly as it was.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..motion.rotations import quat_inv, quat_mean, quat_mul
from ..motion.style_carry import quat_exp, quat_log
from .carriage import LOCOMOTION, SKIP_FRAMES, train_clips

ARM_COUPLING_FILE = "arm_coupling.npz"
COUPLED = ("active",)  # the styles validation chose (model card)
SIDES = ("L", "R")
DRIVERS = ("UpperArm", "Shoulder", "Chest")  # a side's joints the forearm follows (Chest: both sides)
COUPLING_ROWS = ("couple_mean", "couple_walk", "couple_run", "couple_on")  # its style-table rows
FIT_FRAMES = 300


def side_joints(names: list[str] | tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(drivers (2, len(DRIVERS)), forearms (2,)): joint indices per side, left then right."""
    drivers = [[list(names).index(j if j == "Chest" else f"{j}_{s}") for j in DRIVERS] for s in SIDES]
    return np.array(drivers), np.array([list(names).index(f"LowerArm_{s}") for s in SIDES])


def deviations(q: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """(..., K, 3) rotation vectors of rotations (..., K, 4) away from means (K, 4), in each joint's frame."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return quat_log(quat_mul(quat_inv(mean), q))


def design(d: np.ndarray) -> np.ndarray:
    """(N, 3K + 1): the drivers' deviations (N, K, 3), flattened, and a constant."""
    return np.concatenate([d.reshape(len(d), -1), np.ones((len(d), 1))], axis=1)


@dataclass(frozen=True)
class ArmCoupling:
    """Per coupled style (S) and side (2): the real means of the drivers and the forearm
    (S, 2, len(DRIVERS) + 1, 4), and the regression's difference, real minus made, for walking
    and running frames (S, 2, 3 len(DRIVERS) + 1, 3)."""

    styles: tuple[str, ...]
    mean: np.ndarray
    walk: np.ndarray
    run: np.ndarray

    def rows(self, names: list[str]) -> dict[str, np.ndarray]:
        """The style table's rows aligned with `names` (`style_table.PLAIN` for a style without one)."""
        from .style_table import PLAIN

        shapes = {"couple_mean": self.mean.shape[1:], "couple_walk": self.walk.shape[1:]}
        shapes["couple_run"], shapes["couple_on"] = self.run.shape[1:], ()
        rows = {key: PLAIN[key]((len(names), *shapes[key])) for key in COUPLING_ROWS}
        for i, name in enumerate(names):
            if name in self.styles:
                k = self.styles.index(name)
                rows["couple_mean"][i], rows["couple_walk"][i], rows["couple_run"][i] = (
                    self.mean[k],
                    self.walk[k],
                    self.run[k],
                )
                rows["couple_on"][i] = 1.0
        return rows

    def save(self, path: Path) -> Path:
        np.savez(path, styles=np.array(self.styles), mean=self.mean, walk=self.walk, run=self.run)
        return path

    @classmethod
    def load(cls, path: Path) -> ArmCoupling:
        with np.load(path) as z:
            return cls(
                tuple(str(s) for s in z["styles"]), *(np.asarray(z[k], np.float64) for k in ("mean", "walk", "run"))
            )

    def with_styles_of(self, other: ArmCoupling) -> ArmCoupling:
        """This coupling with `other`'s styles added or replacing this one's (a refit of some styles)."""
        keep = [k for k, s in enumerate(self.styles) if s not in other.styles]
        return ArmCoupling(
            tuple(self.styles[k] for k in keep) + other.styles,
            *(np.concatenate([getattr(self, f)[keep], getattr(other, f)]) for f in ("mean", "walk", "run")),
        )


def couple_rows(
    table, rotations: np.ndarray, weights: np.ndarray, gait: np.ndarray, joints: tuple[np.ndarray, np.ndarray]
) -> np.ndarray:
    """The rotations (B, J, 4) with the forearms of the rows that weigh a coupled style moved with
    their drivers (`table`: a `StyleTable` with the coupling's rows; `joints`: `side_joints`);
    walking and running gains mixed by each row's gait share (B,). Other rows and joints exactly
    as they were. Compiled (`kernels.couple_arms`): the numpy reference (`couple_rows_numpy`)
    took ~0.3 ms a step at batch 1, a sixth of the whole LPN-FiLM step."""
    from .kernels import couple_arms

    coupled = _coupled(table, weights, gait)
    if coupled is None:
        return rotations
    rows, w, share = coupled
    out = np.array(rotations, np.float64)
    mean, walk, run = (table.get(k) for k in COUPLING_ROWS[:3])
    couple_arms(np.asarray(rotations, np.float64), rows, w, share, *joints, mean, walk, run, out)
    return out.astype(rotations.dtype)


def _coupled(table, weights: np.ndarray, gait: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(the rows that weigh a coupled style, every row's weights on coupled styles (B, S), every
    row's gait share (B,)), or None when no row weighs one."""
    on = table.get("couple_on")
    if on is None:
        return None
    w = np.asarray(weights, np.float64) * on[None]
    rows = np.flatnonzero(w.any(axis=1))
    return (rows, w, np.clip(np.asarray(gait, np.float64), 0.0, 1.0)) if len(rows) else None


def couple_rows_numpy(
    table, rotations: np.ndarray, weights: np.ndarray, gait: np.ndarray, joints: tuple[np.ndarray, np.ndarray]
) -> np.ndarray:
    """The numpy reference of `couple_rows`."""
    coupled = _coupled(table, weights, gait)
    if coupled is None:
        return rotations
    rows, w, share = coupled
    w, share = w[rows], share[rows][:, None, None]
    mean, walk, run = (table.get(k) for k in COUPLING_ROWS[:3])
    drivers, forearms = joints  # both sides at once: (2, D) and (2,)
    q = np.asarray(rotations[rows], np.float64)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    arm = q[:, forearms]  # (R, 2, 4)
    correction = np.zeros(arm.shape[:-1] + (3,))
    for s in np.flatnonzero(w.any(axis=0)):
        d = deviations(q[:, drivers], mean[s, :, :-1])  # (R, 2, D, 3)
        x = np.concatenate([d.reshape(*d.shape[:2], -1), np.ones(d.shape[:2] + (1,))], axis=-1)
        gains = walk[s] + share[..., None] * (run[s] - walk[s])  # (R, 2, 3D + 1, 3)
        moved = deviations(arm, mean[s, :, -1]) + np.einsum("nki,nkij->nkj", x, gains)
        styled = quat_mul(mean[s, :, -1], quat_exp(moved))
        correction += w[:, s, None, None] * quat_log(quat_mul(quat_inv(arm), styled))
    out = np.array(rotations, copy=True)
    out[rows[:, None], forearms[None]] = quat_mul(arm, quat_exp(correction))
    return out


def regression(clips: list[np.ndarray], means: np.ndarray, joints: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(2, 3 len(DRIVERS) + 1, 3): per side, the least-squares map from the drivers' deviations
    to the forearm's over every frame of `clips` (each (F, J, 4))."""
    q = np.concatenate(clips)
    drivers, forearms = joints
    return np.stack(
        [
            np.linalg.lstsq(
                design(deviations(q[:, ins], means[k, :-1])), deviations(q[:, j], means[k, -1]), rcond=None
            )[0]
            for k, (ins, j) in enumerate(zip(drivers, forearms))
        ]
    )


def fit(model, styles: list[str], dataset: str = "bandai-namco-2") -> ArmCoupling:
    """The coupling of `styles` from `model` (its carriage and output prior in place, no coupling)."""
    from ..eval.run import stylise

    clips = train_clips(dataset)
    model = model.with_own_styles()
    model.arm_coupling = None
    joints = side_joints(model.skeleton.names)
    order = np.concatenate([joints[0], joints[1][:, None]], axis=1)  # per side: drivers, then the forearm
    means, gains = [], {"walk": [], "run": []}
    for style in styles:
        real = {g: [m.rotations.astype(np.float64) for m in clips(style, c)] for g, c in LOCOMOTION.items()}
        mean = quat_mean(np.concatenate(real["walk"] + real["run"])[:, order], axis=0)  # (2, D + 1, 4)
        means.append(mean)
        for gait, contents in LOCOMOTION.items():
            inputs = [m.slice(0, FIT_FRAMES) for m in clips("normal", contents)]
            made = stylise(model, inputs, [model.styles().index(style)] * len(inputs))
            gains[gait].append(
                regression(real[gait], mean, joints)
                - regression([o.rotations[SKIP_FRAMES:].astype(np.float64) for o in made], mean, joints)
            )
    return ArmCoupling(tuple(styles), np.stack(means), np.stack(gains["walk"]), np.stack(gains["run"]))


def main(argv: list[str]) -> None:
    """`STYLE ...` (default: `COUPLED`): refits those, keeping the file's other styles."""
    import time

    import torch

    from ..settings import get_settings
    from .runtime import load

    torch.set_num_threads(1)
    t0 = time.time()
    folder = get_settings().weights_dir / "lpn"
    coupling = fit(load(folder), argv or list(COUPLED))
    if argv and (folder / ARM_COUPLING_FILE).exists():
        coupling = ArmCoupling.load(folder / ARM_COUPLING_FILE).with_styles_of(coupling)
    print(
        f"wrote {coupling.save(folder / ARM_COUPLING_FILE)} for {', '.join(coupling.styles)} in {time.time() - t0:.0f} s"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
