"""All ground truth of a camera rig, batched: the cameras of one sample (leading axis ``C``) or of
several samples (leading axes ``(N, C)``) in one call.

The batch is mapped either by `jax.vmap` (``batch="vmap"``: one program per stage for the whole
batch, one host round trip for the static sizes of the instance segmentation, the largest over
the batch) or by a loop dispatching each camera's compiled programs asynchronously
(``batch="loop"``: static sizes per camera). Both give the same values (tested).
``batch="auto"`` loops on the CPU backend (XLA:CPU lowers batched gathers slowly and schedules one
large program worse than one small program per camera) and vmaps on accelerators, where one wide
program keeps the device busy. Timings of both modes: ``docs/performance.md``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ..cameras import AbstractCamera
from ..reprojection import Lut
from ..transforms import Pose
from ._boxes3d import Boxes3D
from ._fisheye import (
    CameraGroundTruth,
    FisheyeImages,
    camera_to_world,
    fisheye_images,
    fisheye_images_pair,
    ground_truth_from_images,
    ground_truth_from_plan,
    ground_truth_plan,
    rest_statics,
)
from ._flow import pixel_rays
from ._instances import BOX_MARGIN_M, FALLBACK_DISTANCE_M, MOTION_THRESHOLD_M, InstanceMap

BatchMode = Literal["auto", "vmap", "loop"]


def resolve_batch_mode(batch: str) -> str:
    """``"vmap"`` or ``"loop"`` for a requested mode (``"auto"``: loop on CPU, vmap elsewhere)."""
    if batch == "auto":
        return "loop" if jax.default_backend() == "cpu" else "vmap"
    if batch not in ("vmap", "loop"):
        raise ValueError(f"batch must be 'auto', 'vmap' or 'loop', got {batch!r}")
    return batch


def _at(tree, i: int):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


def _stack(trees):
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)


def map_rig(fn, per_camera, per_sample, per_item):
    """``fn(per_camera[j], per_sample[i], per_item[i, j])`` over ``n`` samples x ``c`` cameras by
    nested `jax.vmap` (call it inside `jax.jit`): pytrees whose leaves carry the camera axis, the
    sample axis or both ``(n, c)``; returns a pytree with leading axes ``(n, c)``."""
    over_cameras = jax.vmap(fn, in_axes=(0, None, 0))
    return jax.vmap(over_cameras, in_axes=(None, 0, 0))(per_camera, per_sample, per_item)


def stack_rig(rows):
    """A nested list ``[i][j]`` of equal pytrees as one pytree with leading axes ``(n, c)`` (one copy)."""
    n, c = len(rows), len(rows[0])
    flat = [x for row in rows for x in row]
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs).reshape((n, c) + xs[0].shape), *flat)


def _plan_one(cam, smp, item, carla_version: str, reach: float):
    """One camera of one sample: fisheye images at t-1 and t, camera -> world poses, the culling
    plan; and ``[max candidates, busy tiles, many-candidate tiles]``."""
    lut, camera, c2v, ray = cam
    bp, bc, vp, vc = smp
    (rgb_p, dep_p, tag_p), (rgb, dep, tag) = item
    img_p, img = fisheye_images(lut, rgb_p, dep_p, tag_p), fisheye_images(lut, rgb, dep, tag)
    c2w_p, c2w = camera_to_world(vp, c2v), camera_to_world(vc, c2v)
    k, busy, many, cands, points = ground_truth_plan(camera, ray, img_p, img, c2w_p, c2w, bp, bc, carla_version, reach)
    return (img_p, img, c2w_p, c2w, cands, points), jnp.stack([k, busy, many]).astype(jnp.int32)


def _rest_one(cam, smp, item, statics):
    camera, ray = cam
    bp, bc = smp
    img_p, img, c2w_p, c2w, cands, points = item
    return ground_truth_from_plan(camera, ray, img_p, img, c2w_p, c2w, bp, bc, cands, points, *statics)


@functools.partial(jax.jit, static_argnums=(10, 11))
def _vmap_plan(luts, cameras, cameras_to_vehicle, rays, faces_prev, faces, boxes_prev, boxes, v2w_prev, v2w,
               carla_version: str, reach: float):
    fn = functools.partial(_plan_one, carla_version=carla_version, reach=reach)
    return map_rig(fn, (luts, cameras, cameras_to_vehicle, rays), (boxes_prev, boxes, v2w_prev, v2w), (faces_prev, faces))


@functools.partial(jax.jit, static_argnums=(5,))
def _vmap_rest(cameras, rays, planned, boxes_prev, boxes, statics):
    return map_rig(functools.partial(_rest_one, statics=statics), (cameras, rays), (boxes_prev, boxes), planned)


_jit_fisheye_images = jax.jit(fisheye_images)
_jit_pixel_rays = jax.jit(functools.partial(pixel_rays, dtype=jnp.float32))
_vmap_pixel_rays = jax.jit(jax.vmap(functools.partial(pixel_rays, dtype=jnp.float32)))


def _per_camera(x, c: int, what: str, mode: str):
    """A list of per-camera pytrees in loop mode (slicing a stacked input), a stacked pytree in
    vmap mode (stacking a list)."""
    if isinstance(x, list):
        if len(x) != c:
            raise ValueError(f"rig_ground_truth: {len(x)} entries in '{what}' for {c} cameras")
        return list(x) if mode == "loop" else _stack(list(x))
    leaves = jax.tree_util.tree_leaves(x)
    if not leaves or any(jnp.ndim(leaf) == 0 or jnp.shape(leaf)[0] != c for leaf in leaves):
        raise ValueError(f"rig_ground_truth: '{what}' must be stacked over the {c} cameras (leading axis) or a list, "
                         f"got leading sizes {sorted({jnp.shape(leaf)[:1] for leaf in leaves})}")
    return [_at(x, j) for j in range(c)] if mode == "loop" else x


def _array(x):
    return x if isinstance(x, (np.ndarray, jax.Array)) else np.asarray(x)


def _faces_tuple(faces: Any, where: str) -> tuple:
    """``(rgb, depth_m, semantic)`` of ``faces``: each an array stacked over the cameras, or a list
    of per-camera arrays of one sample, held as a `_PerCamera` (not copied)."""
    try:
        # NumPy faces stay on the host until each camera's program reads them (slices are views).
        fields = tuple(getattr(faces, k) for k in ("rgb", "depth_m", "semantic"))
    except AttributeError as e:
        raise ValueError(f"rig_ground_truth: {where} needs fields rgb, depth_m and semantic ({e})") from e
    out = []
    for k, f in zip(("rgb", "depth_m", "semantic"), fields, strict=True):
        if isinstance(f, (list, tuple)):
            parts = [_array(a) for a in f]
            if not parts or len({(a.shape, a.dtype) for a in parts}) != 1 or parts[0].ndim != (4 if k == "rgb" else 3):
                raise ValueError(f"rig_ground_truth: {where}.{k} as a list needs one (F, S, S{', 3' if k == 'rgb' else ''}) "
                                 f"array per camera, all of one shape and dtype, got {[a.shape for a in parts]}")
            out.append(_PerCamera(parts))
        else:
            out.append(_array(f))
    return tuple(out)


class _PerCamera:
    """Per-camera arrays of one sample handed over as a list: shaped and indexed like their stack
    ``(C, ...)`` without the copy stacking costs (`stack` makes it for the vmap mode)."""

    def __init__(self, parts: list):
        self.parts = parts
        self.shape = (len(parts),) + parts[0].shape
        self.ndim = len(self.shape)

    def __getitem__(self, index: tuple):
        (j,) = index
        return self.parts[j]

    def stack(self):
        return np.stack(self.parts) if isinstance(self.parts[0], np.ndarray) else jnp.stack(self.parts)


def rig_ground_truth(
    luts: Lut | Sequence[Lut],
    cameras: AbstractCamera | Sequence[AbstractCamera],
    cameras_to_vehicle: Pose,
    faces_prev: Any,
    faces: Any,
    boxes_prev: Boxes3D,
    boxes: Boxes3D,
    vehicle_to_world_prev: Pose,
    vehicle_to_world: Pose,
    *,
    carla_version: str = "0.9.10",
    motion_threshold_m: float = MOTION_THRESHOLD_M,
    backward_flow: bool = False,
    margin_m: float = BOX_MARGIN_M,
    fallback_m: float = FALLBACK_DISTANCE_M,
    max_candidates: int | None = None,
    surface_samples: int = 12,
    rays: tuple[Float[ArrayLike, "C H W 3"], Bool[ArrayLike, "C H W"]] | Sequence[tuple] | None = None,
    batch: BatchMode = "auto",
    stacked: bool = True,
    images_prev: Sequence[FisheyeImages | None] | None = None,
    labels_prev: Sequence[tuple[InstanceMap, Array] | None] | None = None,
) -> CameraGroundTruth | list:
    """`fisheye_ground_truth` for every camera of a rig at once, for one sample or a batch of samples.

    Per camera (leading axis ``C``): ``luts`` (cube -> fisheye `Lut`\\ s), ``cameras`` (fisheye
    models of one type and image size) and ``rays`` (each camera's `pixel_rays`; computed when
    omitted), each either stacked leaf by leaf (`jaxfish.reprojection.stack_luts`) or a list with
    one entry per camera (cheapest for ``batch="loop"``, which would otherwise slice copies);
    ``cameras_to_vehicle`` (batched `Pose` ``(C,)``).

    Per sample: ``faces_prev`` / ``faces`` carry ``rgb``, ``depth_m`` and ``semantic`` with leading
    axes ``(C, F, S, S)`` for one sample (or, each field, a list of one ``(F, S, S)`` array per
    camera: with ``batch="loop"`` the cameras' faces are read where they are, never copied into
    one stack), or ``(N, C, F, S, S)`` for ``N`` samples; the boxes
    (same actors at t-1 and t) and the ego poses are then unbatched, or carry a leading ``N``
    (boxes padded to one size with ``boxes_from_actors(..., pad_to=)``).

    Returns a `CameraGroundTruth` whose arrays have leading axes ``(C,)`` or ``(N, C)``; entry
    ``[c]`` (``[n, c]``) equals `fisheye_ground_truth` of that camera and sample (labels
    identical; flow within float32 rounding of differently fused pose products).
    ``max_candidates`` and the tile capacities of the instance segmentation are the largest over
    the batch with ``batch="vmap"`` (one host round trip), per camera and sample with
    ``batch="loop"`` (each camera's program is compiled on its own anyway). ``batch``: how the
    cameras and samples are mapped (module docstring). ``stacked=False`` returns a list with one
    `CameraGroundTruth` per camera (a list of such lists for ``N`` samples) instead: with
    ``batch="loop"`` it skips the copy of every output that stacking costs.

    ``images_prev`` (one sample, ``batch="loop"``): per camera, its `FisheyeImages` at t-1 when
    they are already known, or None. A sequence's previous sample computed them as its images at
    t when its faces at t are this sample's faces at t-1: the same program on the same faces, so
    the same bits. Those cameras resample only their faces at t (``faces_prev`` is not read).
    ``labels_prev`` (with ``images_prev``): per camera, its ``(instances, semantic)`` at t-1 when
    already known for those images, these ``boxes_prev`` and ``vehicle_to_world_prev`` and the
    same options (the previous sample's labels at t), or None; those cameras plan and label only
    the instant t."""
    mode = resolve_batch_mode(batch)
    fp, fc = _faces_tuple(faces_prev, "faces_prev"), _faces_tuple(faces, "faces")
    single = fc[0].ndim == 5
    if fc[0].ndim not in (5, 6):
        raise ValueError(f"rig_ground_truth: faces.rgb must be (C, F, S, S, 3) or (N, C, F, S, S, 3), got {fc[0].shape}")
    for a, b in zip(fp, fc, strict=True):
        if a.shape != b.shape:
            raise ValueError(f"rig_ground_truth: faces_prev {a.shape} and faces {b.shape} differ")
    samples = (boxes_prev, boxes, vehicle_to_world_prev, vehicle_to_world)
    n, c = (1, fc[0].shape[0]) if single else fc[0].shape[:2]
    if images_prev is not None and (mode != "loop" or not single or len(images_prev) != c):
        raise ValueError(f"rig_ground_truth: images_prev needs batch='loop' and one sample, with one entry per camera "
                         f"({c}); got batch={mode!r}, faces {fc[0].shape}, {len(images_prev)} entries")
    if labels_prev is not None and (images_prev is None or len(labels_prev) != c
                                    or any(lab is not None and im is None for lab, im in zip(labels_prev, images_prev, strict=True))):
        raise ValueError(f"rig_ground_truth: labels_prev needs images_prev, with one entry per camera ({c}) and images "
                         "wherever labels are given")
    luts, cameras = _per_camera(luts, c, "luts", mode), _per_camera(cameras, c, "cameras", mode)
    if rays is not None:
        rays = _per_camera([tuple(r) for r in rays] if isinstance(rays, list) else tuple(rays), c, "rays", mode)
    for leaf in () if single else jax.tree_util.tree_leaves(samples):
        if leaf.shape[:1] != (n,):
            raise ValueError(f"rig_ground_truth: {n} samples in the faces, but a box / pose array of shape {leaf.shape}")
    c2v = Pose(jnp.asarray(cameras_to_vehicle.rotation_matrix, jnp.float32), jnp.asarray(cameras_to_vehicle.translation, jnp.float32))
    if c2v.rotation_matrix.shape != (c, 3, 3):
        raise ValueError(f"rig_ground_truth: cameras_to_vehicle must be a batch of {c} poses, got {c2v.rotation_matrix.shape}")
    if rays is None:
        rays = [_jit_pixel_rays(cam) for cam in cameras] if mode == "loop" else _vmap_pixel_rays(cameras)
    elif mode == "loop":
        rays = [(jnp.asarray(r[0], jnp.float32), jnp.asarray(r[1], bool)) for r in rays]
    else:
        rays = (jnp.asarray(rays[0], jnp.float32), jnp.asarray(rays[1], bool))
    reach = float(max(margin_m, fallback_m))
    if mode == "vmap":
        fp, fc = (tuple(x.stack() if isinstance(x, _PerCamera) else x for x in xs) for xs in (fp, fc))
        if single:
            fp, fc = (tuple(x[None] for x in fp), tuple(x[None] for x in fc))
            samples = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], samples)
        planned, sizes = _vmap_plan(luts, cameras, c2v, rays, fp, fc, *samples, carla_version, reach)
        k_host, busy_host, many_host = (int(v) for v in jax.device_get(jnp.max(sizes.reshape(-1, 3), axis=0)))
        statics = rest_statics(carla_version, motion_threshold_m, backward_flow, margin_m, fallback_m, max_candidates,
                               surface_samples, k_host, busy_host, many_host)
        out = _vmap_rest(cameras, rays, planned, samples[0], samples[1], statics)
        if not stacked:
            rows = [[_at(_at(out, i), j) for j in range(c)] for i in range(n)]
            return rows[0] if single else rows
        return _at(out, 0) if single else out

    # Loop: camera by camera, exactly `fisheye_ground_truth`'s programs (images, plan, read the static
    # sizes back, queue the rest asynchronously), then the next camera. Interleaving keeps one
    # camera's intermediates alive at a time, which is faster on CPU than planning every camera first
    # with one shared round trip, or than fusing the images into the plan program.
    def one(cam, smp, item, known_prev, known_labels):
        lut, camera, c2v_j, ray = cam
        (rgb_p, dep_p, tag_p), (rgb, dep, tag) = item
        if known_prev is None:
            img_p, img = fisheye_images_pair(lut, rgb_p, dep_p, tag_p, rgb, dep, tag)
        else:
            img_p, img = known_prev, _jit_fisheye_images(lut, rgb, dep, tag)
        return ground_truth_from_images(
            camera, ray, img_p, img, c2v_j, *smp, carla_version=carla_version, motion_threshold_m=motion_threshold_m,
            backward_flow=backward_flow, margin_m=margin_m, fallback_m=fallback_m, max_candidates=max_candidates,
            surface_samples=surface_samples, labels_prev=known_labels)

    # Each camera's faces in one indexing step (a view of NumPy faces, one slice of device faces).
    per_camera = [(luts[j], cameras[j], _at(c2v, j), rays[j]) for j in range(c)]
    rows = []
    known = images_prev or [None] * c
    known_labels = labels_prev or [None] * c
    for i in range(n):
        smp = samples if single else _at(samples, i)
        index = [(j,) if single else (i, j) for j in range(c)]
        rows.append([one(per_camera[j], smp, tuple(tuple(x[index[j]] for x in xs) for xs in (fp, fc)), known[j],
                         known_labels[j]) for j in range(c)])
    if not stacked:
        return rows[0] if single else rows
    return _stack(rows[0]) if single else stack_rig(rows)  # one copy of every output
