"""CARLA 0.9.10 - 0.9.13 semantic tags (the 23-tag table SynWoodScape was captured with)."""

from __future__ import annotations

CARLA_SEMANTIC_TAGS: dict[str, int] = {
    "unlabeled": 0,
    "building": 1,
    "fence": 2,
    "other": 3,
    "pedestrian": 4,
    "pole": 5,
    "roadline": 6,
    "road": 7,
    "sidewalk": 8,
    "vegetation": 9,
    "vehicle": 10,
    "wall": 11,
    "trafficsign": 12,
    "sky": 13,
    "ground": 14,
    "bridge": 15,
    "railtrack": 16,
    "guardrail": 17,
    "trafficlight": 18,
    "static": 19,
    "dynamic": 20,
    "water": 21,
    "terrain": 22,
}
"""CARLA 0.9.10 semantic tag of each class name (red channel of the semantic camera)."""
