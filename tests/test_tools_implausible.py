"""`tools.implausible` counts failing clips by joint the way the evaluation judges them: a joint
turned away from every real frame of the style is named on every clip, and nothing else moves."""

from __future__ import annotations

from collections import Counter
from dataclasses import replace

import numpy as np

from models.data import build_index, load_motions, select
from models.eval.physical import Input
from models.eval.sealed import real_clips
from models.eval.sources import D2, Source
from models.motion.rotations import quat_exp, quat_mul
from tools.implausible import tally


def test_a_joint_turned_out_of_the_style_is_the_one_named():
    index = build_index([D2])
    ref = real_clips(index, ["feminine"], final=False, quick=False)[0]
    clips = select(index, split="val", style="feminine")[1::2][:4]  # not the half the radii come from
    real = load_motions(clips)
    source = Source(D2, real, [c.name for c in clips], [c.content for c in clips])
    head = real[0].skeleton.index("Head")
    turned = []
    for m in real:
        rotations = m.rotations.copy()
        rotations[:, head] = quat_mul(rotations[:, head], quat_exp(np.array([np.radians(70.0), 0.0, 0.0])))
        turned.append(replace(m, rotations=rotations))
    inputs = [Input.of(m, ref) for m in real]
    as_is, broken = tally(ref, "feminine", real, source, inputs), tally(ref, "feminine", turned, source, inputs)
    others = lambda t: {k: n for k, n in t.joints.items() if k != "Head"}  # noqa: E731
    assert broken.joints["Head"] == broken.clips == 4 and broken.plausible == 0
    assert broken.contents == Counter(c.content for c in clips)
    assert others(broken) == others(as_is)
