"""Events: face events land on the fisheye pixels whose rays pass through their face pixel, counts
follow the documented fan-out rule, time order is kept."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfish import groundtruth as gt


@pytest.fixture(scope="module")
def event_map(sample):
    return gt.event_map_from_lut(sample.lut)


def _random_events(rng, n, faces, size, t0=1_000_000_000):
    return (rng.integers(0, faces, n), rng.integers(0, size, n), rng.integers(0, size, n),
            np.sort(rng.integers(t0, t0 + 100_000_000, n)).astype(np.int64), rng.random(n) < 0.5)


def test_events_land_where_the_fisheye_ray_meets_the_face_pixel(sample, event_map, jit_unproject):
    rng = np.random.default_rng(0)
    fi, x, y, t, p = _random_events(rng, 4000, sample.lut.num_faces, sample.face_size)
    out = gt.compact_events(jax.jit(gt.map_events)(event_map, fi, x, y, t, p))
    assert out["x"].size > 100
    # Each output pixel's centre ray, projected into the rig, falls in the event's face pixel.
    from jaxfish.reprojection import CubeRig

    rig = CubeRig(sample.face_size, dtype=jnp.float32)
    uv = np.stack([out["x"], out["y"]], -1).astype(np.float32)
    rays, ok = jit_unproject(sample.camera, jnp.asarray(uv))
    face, fuv, fok = rig.project_faces(rays)
    assert np.all(np.asarray(ok) & np.asarray(fok))
    np.testing.assert_array_equal(np.asarray(face), out["face"])
    src = {}
    for k in range(fi.size):
        src.setdefault((int(fi[k]), int(x[k]), int(y[k])), []).append(k)
    fx = np.floor(np.asarray(fuv)[:, 0] + 0.5).astype(int)
    fy = np.floor(np.asarray(fuv)[:, 1] + 0.5).astype(int)
    for j in range(out["x"].size):
        assert (int(out["face"][j]), fx[j], fy[j]) in src


def _inverse_reference(nearest, valid, n_src, m):
    """Per face pixel its first ``m`` fisheye pixels in index order: a stable sort, by NumPy."""
    key = np.where(np.asarray(valid).reshape(-1), np.asarray(nearest).reshape(-1), n_src)
    order = np.argsort(key, kind="stable")
    fanout = np.bincount(key, minlength=n_src + 1)[:n_src]
    start = np.cumsum(fanout) - fanout
    targets = np.full((n_src, m), -1, np.int64)
    for j in range(m):
        has = fanout > j
        targets[has, j] = order[start[has] + j]
    return targets, fanout


@pytest.mark.parametrize("max_fanout", [None, 1, 4])
def test_event_map_is_the_stable_inverse_of_the_lut(sample, max_fanout):
    from jaxfish.reprojection import centre_sample

    lut = sample.lut
    k = centre_sample(lut.supersample)
    f, s_h, s_w = lut.source_shape
    emap = gt.event_map_from_lut(lut, max_fanout=max_fanout)
    want, fanout = _inverse_reference(lut.nearest_index[..., k], lut.valid[..., k], f * s_h * s_w,
                                      emap.max_fanout)
    assert emap.max_fanout == (int(fanout.max()) if max_fanout is None else max_fanout)
    np.testing.assert_array_equal(np.asarray(emap.targets), want)
    np.testing.assert_array_equal(np.asarray(emap.fanout), np.minimum(fanout, emap.max_fanout))


def test_event_map_inverse_with_fanouts_up_to_four():
    from jaxfish.groundtruth._events import _inverse

    rng = np.random.default_rng(3)
    n_src, shape = 50, (9, 11)
    nearest = rng.integers(0, n_src, shape).astype(np.int32)  # several pixels per face pixel, some none
    valid = rng.random(shape) < 0.8
    want, fanout = _inverse_reference(nearest, valid, n_src, 6)
    assert fanout.max() >= 4
    key = np.where(valid, nearest, n_src).reshape(-1)
    for m in (1, 3, 6):
        targets, fan = _inverse(key, fanout, n_src, m)
        np.testing.assert_array_equal(np.asarray(targets), want[:, :m])
        np.testing.assert_array_equal(np.asarray(fan), np.minimum(fanout, m))


def test_counts_follow_the_fanout_rule_and_time_order_is_kept(sample, event_map):
    rng = np.random.default_rng(1)
    s = sample.face_size
    fi, x, y, t, p = _random_events(rng, 3000, sample.lut.num_faces, s)
    ev = jax.jit(gt.map_events)(event_map, fi, x, y, t, p)
    fan = np.asarray(event_map.fanout)[(fi * s + y) * s + x]
    assert int(ev.count) == fan.sum()
    out = gt.compact_events(ev)
    assert np.all(np.diff(out["t"]) >= 0)
    # Polarity and time are copied from the source event; every source event with fan-out f appears f times.
    assert sorted(zip(out["t"].tolist(), out["polarity"].tolist(), strict=True)) == sorted(
        [(int(tk), bool(pk)) for tk, pk, f in zip(t, p, fan, strict=True) for _ in range(f)])
    # The whole fisheye is fed: every valid fisheye pixel has exactly one source face pixel.
    assert int(np.asarray(event_map.fanout).sum()) == int(np.asarray(sample.lut.valid[..., 0]).sum())


def test_out_of_range_events_are_dropped(event_map):
    ev = gt.map_events(event_map, jnp.asarray([0, 9, 0]), jnp.asarray([-1, 0, 0]), jnp.asarray([0, 0, 10**6]),
                       jnp.asarray([1, 2, 3]), jnp.asarray([True, True, False]))
    assert int(ev.count) == 0


def test_event_colours():
    img = np.asarray(gt.events_to_color(jnp.asarray([0, 1, 1, 2]), jnp.asarray([0, 0, 0, 1]),
                                        jnp.asarray([True, True, False, False]), width=3, height=2))
    np.testing.assert_array_equal(img[0, 0], [0, 0, 255])  # positive: blue
    np.testing.assert_array_equal(img[0, 1], [255, 255, 255])  # tie: white
    np.testing.assert_array_equal(img[1, 2], [255, 0, 0])  # negative: red
    np.testing.assert_array_equal(img[1, 0], [255, 255, 255])


def test_unsorted_input_and_ties_follow_the_stable_rule(sample, event_map):
    """Against a NumPy reference of the rule: events in stable time order (ties keep input order),
    each expanded to its fisheye pixels in `EventMap.targets` order."""
    rng = np.random.default_rng(2)
    s, n = sample.face_size, 2000
    fi, x, y = rng.integers(0, sample.lut.num_faces, n), rng.integers(0, s, n), rng.integers(0, s, n)
    t, p = rng.integers(0, 50, n).astype(np.int64), rng.random(n) < 0.5  # unsorted, many ties
    out = gt.compact_events(jax.jit(gt.map_events)(event_map, fi, x, y, t, p))
    targets = np.asarray(event_map.targets)
    ref = [(int(t[k]), int(tg), int(fi[k]), bool(p[k])) for k in np.argsort(t, kind="stable")
           for tg in targets[(fi[k] * s + y[k]) * s + x[k]] if tg >= 0]
    got = list(zip(out["t"].tolist(), (out["y"] * event_map.width + out["x"]).tolist(), out["face"].tolist(),
                   out["polarity"].tolist(), strict=True))
    assert got == ref


def test_host_times_beyond_int32_raise_without_x64_instead_of_wrapping(event_map):
    rng = np.random.default_rng(3)
    face, x, y, t, pol = _random_events(rng, 50, event_map.num_faces, event_map.face_size, t0=10**10)
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match="jax_enable_x64"):
            gt.map_events(event_map, face, x, y, t, pol)
        relative = gt.map_events(event_map, face, x, y, t - t.min(), pol)  # the documented way
    full = gt.map_events(event_map, face, x, y, t, pol)  # x64 on (the test suite's setting)
    n = int(full.count)
    assert n == int(relative.count) > 0
    np.testing.assert_array_equal(np.asarray(relative.t)[:n] + t.min(), np.asarray(full.t)[:n])
    np.testing.assert_array_equal(np.asarray(relative.x)[:n], np.asarray(full.x)[:n])
