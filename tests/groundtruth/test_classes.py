"""Semantic class tables and colour codings (labels, flow)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxfish import groundtruth as gt
from tests import tolerances as tol
from tests.conftest import shared_path
from tests.helpers import three_ways

_SYNONYMS = {"roads": "road", "sidewalks": "sidewalk", "car": "vehicle", "truck": "vehicle", "bus": "vehicle",
             "train": "vehicle", "rider": "two_wheeler", "motorcycle": "two_wheeler", "bicycle": "two_wheeler"}


def test_synwoodscape_table():
    names = gt.SYNWOODSCAPE_CLASSES
    assert len(names) == 25 and gt.SYNWOODSCAPE_PALETTE.shape == (25, 3)
    assert names[19:] == ("water", "terrain", "two_wheeler", "static", "dynamic", "ego_vehicle")
    # CARLA 0.9.10 ids 0-18 unchanged, the other tags by name.
    for tag, name in enumerate(gt.CARLA_0910_TAGS):
        assert names[int(gt.CARLA_0910_TO_SYNWOODSCAPE[tag])] == name
    for tag, name in enumerate(gt.CARLA_0914_TAGS):
        assert names[int(gt.CARLA_0914_TO_SYNWOODSCAPE[tag])] == _SYNONYMS.get(name, name)
    assert len({tuple(c) for c in gt.SYNWOODSCAPE_PALETTE}) == 25


def test_two_wheelers_and_ego_split_by_box_class():
    tags = jnp.asarray([10, 10, 10, 4, 7, 99])
    box = jnp.asarray([21, 24, 10, 21, -1, -1])
    out = np.asarray(gt.carla_to_synwoodscape(tags, box_class=box))
    np.testing.assert_array_equal(out, [21, 24, 10, 4, 7, 0])
    out14 = np.asarray(gt.carla_to_synwoodscape(jnp.asarray([18, 14, 14]), carla_version="0.9.14", box_class=jnp.asarray([10, 24, -1])))
    np.testing.assert_array_equal(out14, [21, 24, 10])


def test_colorize_three_ways():
    lab = jnp.asarray(np.random.default_rng(0).integers(-2, 30, (6, 7)))
    e, j, v = three_ways(gt.colorize_labels, lab)
    np.testing.assert_array_equal(e, j)
    np.testing.assert_array_equal(e, v)
    ok = (np.asarray(lab) >= 0) & (np.asarray(lab) < 25)
    np.testing.assert_array_equal(e[ok], gt.SYNWOODSCAPE_PALETTE[np.asarray(lab)[ok]])
    assert np.all(e[~ok] == 0)


def test_flow_colour_wheel_matches_flow_vis_reference():
    data = np.load(shared_path("reference/flow_vis/flow_example_data.npy"))
    from jaxfish.io import read_image

    want = read_image(shared_path("reference/flow_vis/flow_example_output.jpg"))[..., :3].astype(np.float64)
    got = np.asarray(gt.flow_to_color(jnp.asarray(data, jnp.float64))).astype(np.float64)
    assert got.shape == want.shape
    assert np.abs(got - want).mean() < tol.FLOW_COLOR_JPEG
    assert gt.flow_colour_wheel().shape == (55, 3) and sum(gt.WHEEL_SEGMENTS) == 55


def test_flow_colours_jit_vmap_and_invalid_black():
    f = jnp.asarray(np.random.default_rng(2).normal(size=(2, 5, 6, 2)))
    fn = jax.jit(gt.flow_to_color)
    one = np.stack([np.asarray(fn(f[i])) for i in range(2)])
    np.testing.assert_array_equal(np.asarray(jax.vmap(fn)(f)), one)
    np.testing.assert_array_equal(np.asarray(fn(f)), one)  # leading batch axes: one max radius per image
    valid = jnp.zeros((5, 6), bool).at[0, 0].set(True)
    out = np.asarray(fn(f[0], valid=valid))
    assert np.all(out[1:] == 0) and np.any(out[0, 0] > 0)
    # Zero flow is white.
    np.testing.assert_array_equal(np.asarray(fn(jnp.zeros((5, 6, 2))))[0, 0], [255, 255, 255])
