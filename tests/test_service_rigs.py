"""Any humanoid rig through the live service: rigs made from a Bandai Namco walk (tests/rigs.py)
stream through a session of every model (LTI, Style-ERD, and LPN-FiLM following the input's root
motion) and come back on their own hierarchy, upright, feet on their own floor, matching what the
same walk gives on the model's own skeleton; a rig written in a left-handed frame comes back as
its right-handed twin does; bad rigs are refused with typed errors; POST /v1/skeletons."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from models.motion import bvh
from models.motion.humanoid import BN_ROLES
from models.motion.skeleton import Motion, fk, to_bvh
from models.registry import load_models
from models.settings import get_settings

from .clips import angle_deg
from .live_server import UPLOAD_TIMEOUT_S, live_server
from .rigs import SPECS, as_bvh_file, bn_positions, make_rig, mapped_error, mirrored, stream, stream_made_rig

FRAMES = 45
STYLE = "elderly"
RIGS = ["mixamo", "ue5", "smplx", "unity", "bvh", "blender"]
MODELS = ("lti", "erd", "lpn")
LEG = 80.0  # BN thigh + shin, cm


@pytest.fixture(scope="module")
def server():
    models = load_models(get_settings().weights_dir)
    with live_server({m: models[m] for m in MODELS}, idle_timeout_s=30) as (base, _):
        yield base


@pytest.fixture(scope="module")
def walk(bn_walk) -> Motion:
    return bn_walk.slice(0, FRAMES)


def _made(walk: Motion, name: str) -> tuple[str, Motion]:
    return as_bvh_file(make_rig(walk, SPECS[name]))


@pytest.fixture(scope="module")
def bn_outputs(server, walk) -> dict[str, np.ndarray]:
    """Per model, world positions of the stylised walk on the model skeleton (streamed on first use)."""

    class Outputs(dict):
        def __missing__(self, model: str) -> np.ndarray:
            _, root, rot = stream(
                server, {"skeleton": "bandai-namco"}, walk.translations[:, 1], walk.rotations, model, STYLE
            )
            trans = walk.translations.copy()
            trans[:, 1] = root
            self[model] = fk(rot, trans, walk.skeleton.parents)[1]
            return self[model]

    return Outputs()


@pytest.mark.parametrize("model, name", [(m, n) for m in MODELS for n in RIGS])
def test_made_rig_comes_back_as_the_model_rig_does(server, walk, bn_outputs, model, name):
    """Root-relative positions of the mapped joints and the hips height within 3 % of the leg of
    what the same walk gives on the model rig (LPN-FiLM, a controller, follows the input's root
    motion: the same root motion in gives the same walk out); upright and feet on the floor in
    the rig's own world (its up axis, its units)."""
    spec = SPECS[name]
    motion = make_rig(walk, spec)
    started, styled = stream_made_rig(server, motion, spec, model, STYLE)
    assert started["rig"]["root_joint"] == spec.rename["Hips"]  # the hips move: the header gives them position channels
    assert started["joints"] == list(motion.skeleton.names) and started["rig"]["retargeted"]
    assert started["rig"]["up"] == spec.up and started["rig"]["units"] == ("m" if spec.metres else "cm")
    assert set(started["rig"]["unmapped"]) >= {n for n, _ in spec.fingers}
    bn_output, sk = bn_outputs[model], walk.skeleton
    err = mapped_error(styled, spec, bn_output, sk)
    assert np.median(err) / LEG < 0.03, (name, np.median(err))
    # feet on the client's floor as the model puts them on its own: the hips height agrees too
    got = bn_positions(styled, spec)
    hips_c, hips_b = motion.skeleton.index(spec.rename["Hips"]), sk.index("Hips")
    assert np.median(np.abs(got[:, hips_c, 1] - bn_output[:, hips_b, 1])) / LEG < 0.03
    # and the style is there: the output differs from the input well beyond the errors above
    mapped = [motion.skeleton.index(spec.rename[b]) for b in BN_ROLES if b != "Hips"]
    moved = np.linalg.norm(got - bn_positions(motion, spec), axis=-1)[:, mapped]
    assert np.median(moved) > 2 * np.median(err)
    # in the rig's own world: head above the hips every frame, the lower toe at the floor (0)
    own = styled.global_positions() / spec.unit
    up = "xyz".index(spec.up)
    head, toes = (
        motion.skeleton.index(spec.rename["Head"]),
        [motion.skeleton.index(spec.rename[f"Toes_{s}"]) for s in "LR"],
    )
    assert (own[:, head, up] - own[:, hips_c, up]).min() > 0.5 * LEG
    lowest = own[:, toes, up].min(axis=1)
    bn_lowest = bn_output[:, [sk.index("Toes_L"), sk.index("Toes_R")], 1].min(axis=1)
    assert abs(np.median(lowest) - np.median(bn_lowest)) < 0.03 * LEG and lowest.min() > -0.03 * LEG, (lowest.min(),)


@pytest.mark.parametrize("name", ["mixamo", "ue5"])
def test_left_handed_rig_comes_back_as_its_right_handed_twin(server, walk, name):
    """A made rig written in a left-handed frame (Y up: Z flipped, as Unity; Z up: Y flipped, as
    Unreal), streamed with `handedness: "left"`, comes back as the right-handed rig does, mirrored."""
    spec = SPECS[name]
    reflection = np.diag([1.0, 1.0, -1.0]) if spec.up == "y" else np.diag([1.0, -1.0, 1.0])
    made = make_rig(walk, spec)
    out = {}
    for hand, motion in (("right", made), ("left", mirrored(made, reflection))):
        started, styled = stream_made_rig(server, motion, spec, "lti", STYLE, handedness=hand)
        assert started["rig"]["handedness"] == hand and started["rig"]["up"] == spec.up
        out[hand] = (styled.translations[:, motion.skeleton.index(spec.rename["Hips"])], styled.rotations)
    root_l, rot_l = out["left"]  # written right-handed again:
    rot_back = mirrored(Motion(made.skeleton, rot_l, made.translations, made.fps), reflection).rotations
    np.testing.assert_allclose(root_l @ reflection.T, out["right"][0], atol=1e-3 * spec.unit)  # float32 on the wire
    assert angle_deg(rot_back, out["right"][1]).max() < 0.05
    assert angle_deg(out["left"][1], out["right"][1]).max() > 1.0  # the left-handed numbers do differ


def test_left_handed_model_rig_is_retargeted_not_passed_through(server, walk, bn_outputs):
    """The model's own joint names in a left-handed frame: mapped through its world like any rig
    (before, a Bandai Namco-named header skipped the mapping and `handedness` was ignored)."""
    reflection = np.diag([1.0, 1.0, -1.0])
    header, m = as_bvh_file(mirrored(walk, reflection))
    hips = m.skeleton.index("Hips")
    started, root, rot = stream(
        server, {"bvh_header": header, "handedness": "left"}, m.translations[:, hips], m.rotations
    )
    assert started["rig"]["retargeted"] and started["rig"]["handedness"] == "left"
    trans = m.translations.copy()
    trans[:, hips] = root
    got = Motion(m.skeleton, rot, trans, m.fps).global_positions() @ reflection.T  # back to right-handed
    want = bn_outputs["lti"][:, [walk.skeleton.index(n) for n in m.skeleton.names]]
    hips = m.skeleton.index("Hips")  # as for every made rig: joints relative to the hips, and the hips height
    err = np.linalg.norm((got - got[:, [hips]]) - (want - want[:, [hips]]), axis=-1)[:, hips + 1 :]
    assert np.median(err) / LEG < 0.03, np.median(err)
    assert np.median(np.abs(got[:, hips, 1] - want[:, hips, 1])) / LEG < 0.03


@pytest.mark.parametrize("name", ["ue5", "smplx"])
def test_intensity_zero_gives_the_input_back(server, walk, name):
    spec = SPECS[name]
    header, motion = _made(walk, name)
    hips = motion.skeleton.index(spec.rename["Hips"])
    started, root, rot = stream(
        server, {"bvh_header": header, "intensity": 0.0}, motion.translations[:, hips], motion.rotations
    )
    assert started["rig"]["root_joint"] == spec.rename["Hips"]
    np.testing.assert_allclose(root, motion.translations[:, hips], atol=1e-3 * (0.01 if spec.metres else 1.0))
    assert angle_deg(rot, motion.rotations).max() < 0.05  # float32 on the wire


def test_preset_with_its_joints_in_any_order(server, walk):
    from models.motion.humanoid_presets import PRESETS

    names = [
        n
        for n in PRESETS["mixamo"].skeleton().names
        if "Index" not in n and "Thumb" not in n and "Pinky" not in n and "Ring" not in n and "Middle" not in n
    ][::-1]
    rest = np.tile([0.0, 0.0, 0.0, 1.0], (3, len(names), 1))
    started, root, rot = stream(server, {"skeleton": "mixamo", "joints": names}, np.array([[0.0, 95.0, 0.0]] * 3), rest)
    assert started["joints"] == names and started["rig"]["preset"] == "mixamo"
    assert started["rig"]["mapping"]["hand_l"] == "LeftHand" and rot.shape == (3, len(names), 4)


@pytest.mark.parametrize(
    "start, code, words",
    [
        (
            {
                "bvh_header": "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Zrotation Xrotation Yrotation\n"
                " JOINT Head\n {\n  OFFSET 0 50 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n  End Site\n  {\n"
                "   OFFSET 0 10 0\n  }\n }\n}\n"
            },
            "unsupported_skeleton",
            ["missing_roles", "spine1", "hand_l", "foot_r"],
        ),
        ({"skeleton": "ue5", "joint_map": {"wing_l": "hand_l"}}, "bad_skeleton", ["bad_joint_map", "wing_l"]),
        ({"skeleton": "mixamo", "joints": ["Hips", "Tail"]}, "bad_skeleton", ["Tail"]),
        (
            {"skeleton": "smpl", "joints": ["pelvis", "spine1", "head"]},
            "unsupported_skeleton",
            ["upperarm_l", "foot_r"],
        ),
    ],
)
def test_bad_and_partial_rigs_are_refused_with_typed_errors(server, start, code, words):
    with connect(server.replace("http", "ws") + "/v1/stream") as ws:
        ws.send(json.dumps({"type": "start", "model": "lti", "style": STYLE, **start}))
        reply = json.loads(ws.recv(timeout=20))
        assert reply["type"] == "error" and reply["code"] == code, reply
        for w in words:
            assert w in reply["message"]
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=10)


def test_post_skeletons_reports_the_mapping_or_what_is_missing(server, walk):
    header, _ = _made(walk, "ue5")
    r = httpx.post(f"{server}/v1/skeletons", json={"bvh_header": header}, timeout=30)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["mapping"]["upperleg_l"] == "thigh_l" and body["up"] == "z" and "index_01_l" in body["unmapped"]
    r = httpx.post(
        f"{server}/v1/skeletons", json={"skeleton": "smpl", "joints": ["pelvis", "spine1", "head"]}, timeout=30
    )
    assert r.status_code == 422 and r.json()["code"] == "missing_roles"
    assert set(r.json()["missing"]) >= {"upperarm_l", "hand_r", "foot_l"}
    r = httpx.post(f"{server}/v1/skeletons?preview=true", json={"skeleton": "unity"}, timeout=60)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png" and r.content[:4] == b"\x89PNG"


def test_style_upload_takes_a_made_rig_clip(server, bn_walk):
    """A made-rig BVH passes validation (retargeted); without fine_tune the LTI model says why not."""
    motion = make_rig(bn_walk.slice(0, 90), SPECS["unity"])
    motion.euler_orders = tuple("ZXY" for _ in motion.skeleton.names)
    text = bvh.dumps(to_bvh(motion))
    r = httpx.post(
        f"{server}/v1/styles",
        files={"file": ("walk.bvh", text.encode())},
        data={"name": "unity-walk", "model": "lti"},
        timeout=UPLOAD_TIMEOUT_S,
    )
    assert r.status_code == 422 and r.json()["code"] == "fine_tune_required", r.text
