"""Semantic class tables: SynWoodScape's 25 classes, CARLA's 0.9.10 and 0.9.14+ tag tables, the
conversions between them and the colour palette (pure JAX lookups)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Int, UInt8

SYNWOODSCAPE_CLASSES: tuple[str, ...] = (
    "unlabeled", "building", "fence", "other", "pedestrian", "pole", "roadline", "road", "sidewalk",
    "vegetation", "vehicle", "wall", "trafficsign", "sky", "ground", "bridge", "railtrack", "guardrail",
    "trafficlight", "water", "terrain", "two_wheeler", "static", "dynamic", "ego_vehicle",
)
"""SynWoodScape class names by id (CONVENTIONS §4): CARLA 0.9.10 ids 0-18 unchanged, then 19 water,
20 terrain, 21 two-wheeler, 22 static, 23 dynamic, 24 ego vehicle."""
CLASS_PEDESTRIAN, CLASS_VEHICLE, CLASS_SKY, CLASS_TWO_WHEELER, CLASS_EGO = 4, 10, 13, 21, 24
"""Class ids used by the instance, motion and box ground truth."""
INSTANCE_CLASSES: tuple[int, ...] = (CLASS_PEDESTRIAN, CLASS_VEHICLE, CLASS_TWO_WHEELER, CLASS_EGO)
"""The SynWoodScape classes that have instances (3D boxes): pedestrian, vehicle, two-wheeler, ego."""

SYNWOODSCAPE_PALETTE: np.ndarray = np.array([
    (0, 0, 0), (70, 70, 70), (100, 40, 40), (55, 90, 80), (220, 20, 60), (153, 153, 153), (157, 234, 50),
    (128, 64, 128), (244, 35, 232), (107, 142, 35), (0, 0, 142), (102, 102, 156), (220, 220, 0),
    (70, 130, 180), (81, 0, 81), (150, 100, 100), (230, 150, 140), (180, 165, 180), (250, 170, 30),
    (45, 60, 150), (145, 170, 100), (119, 11, 32), (110, 190, 160), (170, 120, 50), (0, 110, 130),
], dtype=np.uint8)
"""Colour (RGB uint8) of every SynWoodScape class: CARLA's CityScapes palette for the classes CARLA
has (ids moved with their class), the Cityscapes *bicycle* colour for two-wheelers and a
jaxfish-chosen dark cyan for the ego vehicle."""

CARLA_0914_TAGS: tuple[str, ...] = (
    "unlabeled", "roads", "sidewalks", "building", "wall", "fence", "pole", "trafficlight", "trafficsign",
    "vegetation", "terrain", "sky", "pedestrian", "rider", "car", "truck", "bus", "train", "motorcycle",
    "bicycle", "static", "dynamic", "other", "water", "roadline", "ground", "bridge", "railtrack", "guardrail",
)
"""CARLA 0.9.14+ semantic tags (Cityscapes order) by id."""
CARLA_0910_TAGS: tuple[str, ...] = (
    "unlabeled", "building", "fence", "other", "pedestrian", "pole", "roadline", "road", "sidewalk",
    "vegetation", "vehicle", "wall", "trafficsign", "sky", "ground", "bridge", "railtrack", "guardrail",
    "trafficlight", "static", "dynamic", "water", "terrain",
)
"""CARLA 0.9.10-0.9.13 semantic tags by id (23 tags)."""
CARLA_0910_TO_SYNWOODSCAPE: np.ndarray = np.array(list(range(19)) + [22, 23, 19, 20], dtype=np.int32)
"""CARLA 0.9.10 tag -> SynWoodScape id (0-18 unchanged; 19 static -> 22, 20 dynamic -> 23,
21 water -> 19, 22 terrain -> 20). Two-wheelers and the ego need the instance step."""
CARLA_0914_TO_SYNWOODSCAPE: np.ndarray = np.array(
    [0, 7, 8, 1, 11, 2, 5, 18, 12, 9, 20, 13, 4, 21, 10, 10, 10, 10, 21, 21, 22, 23, 3, 19, 6, 14, 15, 16, 17],
    dtype=np.int32,
)
"""CARLA 0.9.14+ tag -> SynWoodScape id. rider, motorcycle, bicycle -> two-wheeler (21); car, truck,
bus, train -> vehicle (10); the ego needs the instance step."""
CATEGORY_CLASS: dict[str, int] = {
    "four_wheeler": CLASS_VEHICLE, "vehicle": CLASS_VEHICLE, "two_wheeler": CLASS_TWO_WHEELER,
    "pedestrian": CLASS_PEDESTRIAN, "walker": CLASS_PEDESTRIAN, "ego": CLASS_EGO,
}
"""Actor category (as `jaxfish.scene.Actor.category` and the capture's ``actors.json``) -> the
SynWoodScape class of its box."""


def carla_to_synwoodscape(
    tags: Int[ArrayLike, "*batch"],
    *,
    carla_version: str = "0.9.10",
    box_class: Int[ArrayLike, "*batch"] | None = None,
) -> Int[Array, "*batch"]:
    """SynWoodScape class ids of CARLA semantic tags (any shape).

    ``carla_version`` is ``"0.9.10"`` (tables 0.9.10-0.9.13) or ``"0.9.14"`` (0.9.14 and later).
    ``box_class`` (optional, same shape): the class of the 3D box each pixel was assigned to by
    `instance_segmentation` (-1 for none). Pixels of a vehicle-like tag inside a two-wheeler or ego
    box take that box's class (21 or 24): this is how two-wheelers are split off CARLA 0.9.10's
    single vehicle tag, and how the ego body becomes class 24. Unknown tags map to 0 (unlabeled).
    """
    if carla_version not in ("0.9.10", "0.9.14"):
        raise ValueError(f"carla_to_synwoodscape: carla_version must be '0.9.10' or '0.9.14', got {carla_version!r}")
    table = CARLA_0910_TO_SYNWOODSCAPE if carla_version == "0.9.10" else CARLA_0914_TO_SYNWOODSCAPE
    t = jnp.asarray(tags).astype(jnp.int32)
    ok = (t >= 0) & (t < table.shape[0])
    out = jnp.where(ok, jnp.asarray(table)[jnp.clip(t, 0, table.shape[0] - 1)], 0)
    if box_class is not None:
        bc = jnp.asarray(box_class).astype(jnp.int32)
        vehicle_like = (out == CLASS_VEHICLE) | (out == CLASS_TWO_WHEELER)
        out = jnp.where(vehicle_like & ((bc == CLASS_TWO_WHEELER) | (bc == CLASS_EGO)), bc, out)
    return out


def colorize_labels(
    labels: Int[ArrayLike, "*batch"], palette: UInt8[ArrayLike, "K 3"] | None = None
) -> UInt8[Array, "*batch 3"]:
    """RGB rendering of a label map through ``palette`` (default `SYNWOODSCAPE_PALETTE`); labels
    outside the palette are black."""
    pal = jnp.asarray(SYNWOODSCAPE_PALETTE if palette is None else palette, jnp.uint8)
    lab = jnp.asarray(labels).astype(jnp.int32)
    ok = (lab >= 0) & (lab < pal.shape[0])
    return jnp.where(ok[..., None], pal[jnp.clip(lab, 0, pal.shape[0] - 1)], jnp.uint8(0))
