"""The skeletons the project serves, from small committed BVH files (hierarchy + one frame), so
nothing at serving time needs the mocap data."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from .skeleton import Motion, Skeleton, load

ASSETS = Path(__file__).resolve().parent / "assets"

# A BN foot's toe height on the ground (`retarget.contact_height` of dataset-2_walk_normal_001)
BANDAI_NAMCO_TOE_FLOOR = 4.248
BANDAI_NAMCO_ANKLE_FLOOR = 11.739  # the same for the ankles (`feet.FootPlanter` holds either on the ground)


@lru_cache(maxsize=1)
def bandai_namco_pose() -> Motion:
    """One frame: the models' skeleton in a natural standing pose."""
    return load(ASSETS / "bandai_namco.bvh")


def bandai_namco_skeleton() -> Skeleton:
    return bandai_namco_pose().skeleton


@lru_cache(maxsize=1)
def cmu_pose() -> Motion:
    return load(ASSETS / "cmu.bvh")


def cmu_skeleton() -> Skeleton:
    """The CMU skeleton with cgspeed joint names (sessions that say `skeleton: "cmu"`)."""
    return cmu_pose().skeleton
