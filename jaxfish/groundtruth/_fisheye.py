"""Fisheye images, depth and labels from cube faces (through the reprojection kernels), and the
whole per-camera ground truth of one sample."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._constants import FAR_DEPTH_M
from .._numerics import materialize
from ..cameras import AbstractCamera
from ..reprojection import Lut, resample_bilinear, resample_depth, resample_nearest
from ..transforms import Pose
from ._boxes2d import Boxes2D, boxes_from_instances, boxes_from_surfaces
from ._boxes3d import Boxes3D
from ._classes import carla_to_synwoodscape
from ._flow import FlowField, analytic_flow, apply_pose, pixel_points, pixel_rays, rigid_motion
from ._instances import (
    BOX_MARGIN_M,
    FALLBACK_DISTANCE_M,
    MOTION_THRESHOLD_M,
    TILE_SIZE,
    InstanceMap,
    assign_instances,
    box_displacements,
    instance_plan,
    motion_segmentation,
    tile_capacity,
)


class FisheyeImages(eqx.Module):
    """One fisheye camera at one instant, resampled from its cube faces: `rgb` ``(H, W, 3)``
    (source dtype, bilinear, seam-free), `range_m` (Euclidean range along the fisheye ray, metres;
    sky/far exactly 1000; 0 outside the lens domain), `tag` (CARLA semantic tag, nearest, never
    mixed), `valid` (the pixel has a ray seen by a face)."""

    rgb: Array
    range_m: Float[Array, "H W"]
    tag: Int[Array, "H W"]
    valid: Bool[Array, "H W"]


def fisheye_images(
    lut: Lut, faces_rgb: ArrayLike, faces_depth_m: Float[ArrayLike, "F S S"], faces_tag: Int[ArrayLike, "F S S"]
) -> FisheyeImages:
    """Resample one camera's faces ``(F, S, S[, 3])`` (RGB, CARLA planar depth in metres, CARLA
    tags) to the fisheye through ``lut`` with `resample_bilinear`, `resample_depth` and
    `resample_nearest` (``reduce="centre"`` for labels so they match the depth's centre sample)."""
    rgb, valid = resample_bilinear(jnp.asarray(faces_rgb), lut)
    rng, _ = resample_depth(jnp.asarray(faces_depth_m, jnp.float32), lut, far_m=FAR_DEPTH_M)
    tag, _ = resample_nearest(jnp.asarray(faces_tag), lut, reduce="centre")
    return FisheyeImages(rgb=rgb, range_m=rng, tag=tag.astype(jnp.int32), valid=valid)


def range_to_z_depth(
    camera: AbstractCamera, range_m: Float[ArrayLike, "H W"], *,
    rays: tuple[Float[ArrayLike, "H W 3"], Bool[ArrayLike, "H W"]] | None = None,
) -> Float[Array, "H W"]:
    """Planar z-depth (along the camera's optical axis, metres) of a range map; far/sky pixels
    (range >= 1000) stay 1000, pixels without a ray 0. Beyond 90 degrees z is negative. ``rays``:
    the camera's `pixel_rays`, when already computed (saves the unprojection)."""
    r = jnp.asarray(range_m)
    if rays is None:
        rays, ok = camera.unproject(camera.pixel_grid(r.dtype))
    else:
        rays, ok = jnp.asarray(rays[0]), jnp.asarray(rays[1], bool)
    z = r * rays[..., 2].astype(r.dtype)
    z = jnp.where(r >= FAR_DEPTH_M, jnp.asarray(FAR_DEPTH_M, r.dtype), z)
    return jnp.where(ok, z, 0.0)


class CameraGroundTruth(eqx.Module):
    """All ground truth of one fisheye camera for one sample (t, with its previous frame t-1).

    - `images_prev`, `images`: `FisheyeImages` at t-1 and t;
    - `semantic_prev`, `semantic`: SynWoodScape class ids ``(H, W)`` (two-wheelers and the ego
      split off by their boxes);
    - `instances_prev`, `instances`: `InstanceMap` at t-1 and t;
    - `motion`: moving-object mask at t; `displacement_m` ``(B,)`` per box;
    - `flow`: forward flow on the t-1 grid (t-1 -> t); `flow_backward` (t grid, t -> t-1) or None;
    - `boxes_2d`: visible boxes (from the instance mask at t); `boxes_2d_full`: full extent from
      the box surfaces at t.
    """

    images_prev: FisheyeImages
    images: FisheyeImages
    semantic_prev: Int[Array, "H W"]
    semantic: Int[Array, "H W"]
    instances_prev: InstanceMap
    instances: InstanceMap
    motion: Bool[Array, "H W"]
    displacement_m: Float[Array, " B"]
    flow: FlowField
    flow_backward: FlowField | None
    boxes_2d: Boxes2D
    boxes_2d_full: Boxes2D


@jax.jit
def camera_to_world(vehicle_to_world: Pose, camera_to_vehicle: Pose) -> Pose:
    """OpenCV camera -> CARLA world: ``vehicle_to_world @ camera_to_vehicle`` (float32; one compiled
    program, so that a call dispatches once instead of once per operation)."""
    v = Pose(vehicle_to_world.rotation_matrix, vehicle_to_world.translation, dtype=jnp.float32)
    c = Pose(camera_to_vehicle.rotation_matrix, camera_to_vehicle.translation, dtype=jnp.float32)
    return v @ c


def instant_labels(images: FisheyeImages, boxes: Boxes3D, cand: Bool[Array, "T B"],
                   points: tuple[Float[Array, "H W 3"], Int[Array, "H W"]], carla_version: str, margin_m: float,
                   fallback_m: float, k: int, capacity: int, capacity_many: int) -> tuple[InstanceMap, Int[Array, "H W"]]:
    """The labels of one instant (traceable; the arguments from ``carla_version`` on static,
    `rest_statics`): `assign_instances` on `instant_plan`'s ``cand`` and ``points``, and the
    SynWoodScape semantics with two-wheelers and the ego split off by their boxes. Returns
    ``(instances, semantic)``; the values do not depend on ``k`` and the capacities as long as
    they hold the plan's counts."""
    world, base = points  # world points and base classes, from the planning step
    inst = assign_instances(world, base, boxes, margin_m, fallback_m, TILE_SIZE, k, capacity, cand, capacity_many)
    sem = carla_to_synwoodscape(images.tag, carla_version=carla_version, box_class=inst.class_id)
    return inst, sem


def fisheye_ground_truth(
    lut: Lut,
    camera: AbstractCamera,
    camera_to_vehicle: Pose,
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
    rays: tuple[Float[ArrayLike, "H W 3"], Bool[ArrayLike, "H W"]] | None = None,
) -> CameraGroundTruth:
    """Everything for one fisheye camera: ``faces_prev`` / ``faces`` carry ``rgb (F, S, S, 3)``,
    ``depth_m (F, S, S)`` (CARLA planar depth, metres) and ``semantic (F, S, S)`` (CARLA tags) at
    t-1 and t (e.g. `jaxfish.scene.CameraImages` stacked over faces); ``boxes_prev`` / ``boxes``
    the same actors in the same order at t-1 and t; ``vehicle_to_world*`` the ego's ISO vehicle
    frame -> CARLA world (`vehicle_to_world_from_carla`). Flow uses the instance assignment at
    t-1 (each point moves with its box) and the range map at t for occlusions. ``rays``: the
    camera's `pixel_rays` (a per-calibration constant; computed here when omitted)."""
    img_p, img = fisheye_images_pair(lut, *(jnp.asarray(getattr(f, k)) for f in (faces_prev, faces) for k in ("rgb", "depth_m", "semantic")))
    rays = _jit_rays(camera) if rays is None else (jnp.asarray(rays[0], jnp.float32), jnp.asarray(rays[1], bool))
    return ground_truth_from_images(
        camera, rays, img_p, img, camera_to_vehicle, boxes_prev, boxes, vehicle_to_world_prev, vehicle_to_world,
        carla_version=carla_version, motion_threshold_m=motion_threshold_m, backward_flow=backward_flow,
        margin_m=margin_m, fallback_m=fallback_m, max_candidates=max_candidates, surface_samples=surface_samples)


def ground_truth_from_images(
    camera: AbstractCamera,
    rays: tuple[Float[Array, "H W 3"], Bool[Array, "H W"]],
    images_prev: FisheyeImages,
    images: FisheyeImages,
    camera_to_vehicle: Pose,
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
    labels_prev: tuple[InstanceMap, Int[Array, "H W"]] | None = None,
) -> CameraGroundTruth:
    """`fisheye_ground_truth` from the camera's images at t-1 and t (`fisheye_images`, or a
    directly captured view's): per instant `instant_plan` and `instant_labels` (one host round
    trip between them for the static sizes, `rest_statics`), then `truth_from_labels` (its
    compiled motion, flow and boxes, with the images and labels passed through as they are).
    ``rays``: the camera's float32 `pixel_rays`; the options are `fisheye_ground_truth`'s.
    ``labels_prev``: ``(instances, semantic)`` at t-1 when already known for these images,
    boxes, poses and options (a sequence's previous sample computed them as its labels at t:
    the same programs on the same inputs, so the same bits); the planning and labelling of t-1 are
    then skipped. Not traceable (it reads the plans' sizes back)."""
    c2w_p = camera_to_world(vehicle_to_world_prev, camera_to_vehicle)
    c2w = camera_to_world(vehicle_to_world, camera_to_vehicle)
    reach = max(margin_m, fallback_m)
    todo = [(images, c2w, boxes)] if labels_prev is not None else [(images_prev, c2w_p, boxes_prev), (images, c2w, boxes)]
    plans = [_jit_instant_plan(camera, rays, im, c2w_, bx, carla_version, reach) for im, c2w_, bx in todo]
    per_instant = [] if labels_prev is None else [labels_prev]
    for (im, _, bx), (k_host, n_host, m_host, cand, points) in zip(todo, plans, strict=True):
        statics = rest_statics(carla_version, motion_threshold_m, backward_flow, margin_m, fallback_m, max_candidates,
                               surface_samples, k_host, n_host, m_host)
        version, _, _, margin, fallback, k, capacity, many, _ = statics
        per_instant.append(_jit_instant_labels(im, bx, cand, points, version, margin, fallback, k, capacity, many))
    (inst_p, sem_p), (inst, sem) = per_instant
    labels = (inst_p, sem_p, inst, sem)
    rest = _jit_motion_flow_boxes(camera, rays, images_prev, images, c2w_p, c2w, boxes_prev, boxes, labels,
                                  float(motion_threshold_m), bool(backward_flow), int(surface_samples))
    return _camera_truth(images_prev, images, labels, rest)  # the inputs as they are: no copies


def rest_statics(carla_version, motion_threshold_m, backward_flow, margin_m, fallback_m, max_candidates, surface_samples,
                 k, busy, many) -> tuple:
    """The static arguments of the second stage (`ground_truth_from_plan`'s ``carla_version`` to
    ``surface_samples``), from the options and the host values of the planning stage
    (`ground_truth_plan`): most candidates per tile ``k`` (rounded up to a power of two unless
    ``max_candidates`` is given, so that frames and cameras of similar content share one
    compilation), and the tile capacities for the ``busy`` and ``many``-candidate tiles."""
    if max_candidates is None:
        max_candidates = 1 << max(int(k) - 1, 0).bit_length()
    return (carla_version, float(motion_threshold_m), bool(backward_flow), float(margin_m), float(fallback_m),
            int(max_candidates), tile_capacity(int(busy)), tile_capacity(int(many)), int(surface_samples))


def view_ground_truth(
    camera: AbstractCamera,
    camera_to_vehicle: Pose,
    view_prev: Any,
    view: Any,
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
    rays: tuple[Float[ArrayLike, "H W 3"], Bool[ArrayLike, "H W"]] | None = None,
    images_prev: FisheyeImages | None = None,
    labels_prev: tuple[InstanceMap, Int[Array, "H W"]] | None = None,
) -> CameraGroundTruth:
    """The same ground truth as `fisheye_ground_truth` for a camera captured directly (no cube
    faces): the BEV top view (`Orthographic`) or the front perspective camera (`Pinhole`).
    ``view_prev`` / ``view`` carry ``rgb (H, W, 3)``, ``depth_m (H, W)`` (CARLA planar depth along the
    optical axis; for the orthographic view the distance from the image plane) and ``semantic``
    (CARLA tags); planar depth becomes range along each ray (far stays 1000). ``images_prev``: the
    view's images at t-1 when already known (a sequence's previous sample computed them as its
    images at t; ``view_prev`` is then not read); ``labels_prev``: its labels at t-1 likewise
    (`ground_truth_from_images`)."""
    if labels_prev is not None and images_prev is None:
        raise ValueError("view_ground_truth: labels_prev needs images_prev (the images they were computed from)")
    rays = _jit_rays(camera) if rays is None else (jnp.asarray(rays[0], jnp.float32), jnp.asarray(rays[1], bool))
    img_p = images_prev if images_prev is not None else \
        _jit_view_images(camera, rays, *(jnp.asarray(getattr(view_prev, k)) for k in ("rgb", "depth_m", "semantic")))
    img = _jit_view_images(camera, rays, *(jnp.asarray(getattr(view, k)) for k in ("rgb", "depth_m", "semantic")))
    return ground_truth_from_images(
        camera, rays, img_p, img, camera_to_vehicle, boxes_prev, boxes, vehicle_to_world_prev, vehicle_to_world,
        carla_version=carla_version, motion_threshold_m=motion_threshold_m, backward_flow=backward_flow,
        margin_m=margin_m, fallback_m=fallback_m, max_candidates=max_candidates, surface_samples=surface_samples,
        labels_prev=labels_prev)


@jax.jit
def _jit_view_images(camera, rays, rgb, depth_m, tag):
    r, ok = rays
    z = depth_m.astype(jnp.float32)
    rz = r[..., 2]
    good = ok & (rz > 0)
    rng = jnp.where(good, z / jnp.where(good, rz, 1.0), 0.0)
    rng = jnp.where(z >= FAR_DEPTH_M, FAR_DEPTH_M, rng)
    return FisheyeImages(rgb=rgb, range_m=rng.astype(jnp.float32), tag=tag.astype(jnp.int32), valid=good)


@jax.jit
def fisheye_images_pair(
    lut: Lut,
    rgb_prev: Array, depth_prev_m: Float[Array, "F S S"], tag_prev: Int[Array, "F S S"],
    rgb: Array, depth_m: Float[Array, "F S S"], tag: Int[Array, "F S S"],
) -> tuple[FisheyeImages, FisheyeImages]:
    """`fisheye_images` of one camera's faces at t-1 and at t in one compiled program: the faces'
    RGB ``(F, S, S, 3)``, CARLA planar depth (metres) and CARLA tags at each instant."""
    return fisheye_images(lut, rgb_prev, depth_prev_m, tag_prev), fisheye_images(lut, rgb, depth_m, tag)


@jax.jit
def _jit_rays(camera):
    return pixel_rays(camera, dtype=jnp.float32)


def _world_points(camera, rays, images: FisheyeImages, cam_to_world: Pose):
    pts, ok = pixel_points(camera, images.range_m, dtype=jnp.float32, rays=rays)
    return apply_pose(cam_to_world, pts), ok & images.valid


def instant_plan(
    camera: AbstractCamera,
    rays: tuple[Float[Array, "H W 3"], Bool[Array, "H W"]],
    images: FisheyeImages,
    c2w: Pose,
    boxes: Boxes3D,
    carla_version: str,
    reach: float,
) -> tuple[Int[Array, ""], Int[Array, ""], Int[Array, ""], Bool[Array, "T B"], tuple[Float[Array, "H W 3"], Int[Array, "H W"]]]:
    """The planning of one instant (traceable; ``carla_version`` and ``reach`` static): each
    pixel's CARLA world point and base SynWoodScape class (-1: no pixel) from ``images`` and the
    camera -> world pose ``c2w`` (`camera_to_world`), and `instance_plan` against ``boxes``.
    Returns ``(k, busy, many, candidates, (world points, base classes))``, which
    `instant_labels` consumes. ``reach``: max(margin_m, fallback_m) in metres."""
    world, ok = _world_points(camera, rays, images, c2w)
    base = jnp.where(ok, carla_to_synwoodscape(images.tag, carla_version=carla_version), -1)
    k, n, m, c = instance_plan(world, base, boxes, TILE_SIZE, reach)
    return k, n, m, c, (world, base)


def ground_truth_plan(
    camera: AbstractCamera,
    rays: tuple[Float[Array, "H W 3"], Bool[Array, "H W"]],
    img_p: FisheyeImages,
    img: FisheyeImages,
    c2w_p: Pose,
    c2w: Pose,
    boxes_prev: Boxes3D,
    boxes: Boxes3D,
    carla_version: str,
    reach: float,
) -> tuple[Int[Array, ""], Int[Array, ""], Int[Array, ""], tuple[Bool[Array, "T B"], Bool[Array, "T B"]],
           tuple[tuple[Float[Array, "H W 3"], Int[Array, "H W"]], tuple[Float[Array, "H W 3"], Int[Array, "H W"]]]]:
    """The first stage of a camera's ground truth (traceable; ``carla_version`` and ``reach``
    static): `instant_plan` at t-1 (images ``img_p``, camera -> world pose ``c2w_p``, boxes
    ``boxes_prev``) and at t. Returns ``(k, busy, many, candidates, points)``: the larger of the
    two instants' counts, the two ``(T, B)`` candidate masks and the two ``(world points, base
    classes)`` pairs, which `ground_truth_from_plan` consumes."""
    p = instant_plan(camera, rays, img_p, c2w_p, boxes_prev, carla_version, reach)
    q = instant_plan(camera, rays, img, c2w, boxes, carla_version, reach)
    return jnp.maximum(p[0], q[0]), jnp.maximum(p[1], q[1]), jnp.maximum(p[2], q[2]), (p[3], q[3]), (p[4], q[4])


_jit_instant_plan = jax.jit(instant_plan, static_argnums=(5, 6))


def ground_truth_from_plan(
    camera: AbstractCamera,
    rays: tuple[Float[Array, "H W 3"], Bool[Array, "H W"]],
    img_p: FisheyeImages,
    img: FisheyeImages,
    c2w_p: Pose,
    c2w: Pose,
    boxes_prev: Boxes3D,
    boxes: Boxes3D,
    cands: tuple[Bool[Array, "T B"], Bool[Array, "T B"]],
    points: tuple[tuple[Float[Array, "H W 3"], Int[Array, "H W"]], tuple[Float[Array, "H W 3"], Int[Array, "H W"]]],
    carla_version: str,
    motion_threshold_m: float,
    backward_flow: bool,
    margin_m: float,
    fallback_m: float,
    k: int,
    capacity: int,
    capacity_many: int,
    surface_samples: int,
) -> CameraGroundTruth:
    """The second stage of a camera's ground truth (traceable; the arguments from
    ``carla_version`` on are static, `rest_statics`): semantic and instance labels at t-1 and t
    (`assign_instances` on `ground_truth_plan`'s ``cands`` and ``points``), motion, forward (and
    with ``backward_flow`` backward) flow, and the 2D boxes, as one `CameraGroundTruth`:
    `labels_from_plan`, then `truth_from_labels`."""
    labels = labels_from_plan(img_p, img, boxes_prev, boxes, cands, points, carla_version, margin_m, fallback_m, k,
                              capacity, capacity_many)
    # Materialise the labels: otherwise XLA fuses their tile scatters and transposes into the flow's
    # and the boxes' consumers.
    inst_p, inst = materialize((labels[0], labels[2]), img.range_m.reshape(-1)[0])
    return truth_from_labels(camera, rays, img_p, img, c2w_p, c2w, boxes_prev, boxes, (inst_p, labels[1], inst, labels[3]),
                             motion_threshold_m, backward_flow, surface_samples)


def labels_from_plan(img_p: FisheyeImages, img: FisheyeImages, boxes_prev: Boxes3D, boxes: Boxes3D, cands, points,
                     carla_version: str, margin_m: float, fallback_m: float, k: int, capacity: int,
                     capacity_many: int) -> tuple:
    """The labels of `ground_truth_from_plan` (the arguments from ``carla_version`` on static):
    ``(instances_prev, semantic_prev, instances, semantic)``."""
    inst_p, sem_p = instant_labels(img_p, boxes_prev, cands[0], points[0], carla_version, margin_m, fallback_m, k,
                                   capacity, capacity_many)
    inst, sem = instant_labels(img, boxes, cands[1], points[1], carla_version, margin_m, fallback_m, k, capacity,
                               capacity_many)
    return inst_p, sem_p, inst, sem


def truth_from_labels(camera: AbstractCamera, rays: tuple[Float[Array, "H W 3"], Bool[Array, "H W"]],
                      img_p: FisheyeImages, img: FisheyeImages, c2w_p: Pose, c2w: Pose, boxes_prev: Boxes3D,
                      boxes: Boxes3D, labels: tuple, motion_threshold_m: float, backward_flow: bool,
                      surface_samples: int) -> CameraGroundTruth:
    """The rest of `ground_truth_from_plan` from its ``labels`` (`labels_from_plan`'s; the
    arguments from ``motion_threshold_m`` on static): motion, flow and 2D boxes. Independent of
    the planning stage's sizes, so that one compiled program serves every camera of a rig."""
    rest = _motion_flow_boxes(camera, rays, img_p, img, c2w_p, c2w, boxes_prev, boxes, labels, motion_threshold_m,
                              backward_flow, surface_samples)
    return _camera_truth(img_p, img, labels, rest)


def _motion_flow_boxes(camera, rays, img_p: FisheyeImages, img: FisheyeImages, c2w_p: Pose, c2w: Pose,
                       boxes_prev: Boxes3D, boxes: Boxes3D, labels: tuple, motion_threshold_m: float,
                       backward_flow: bool, surface_samples: int) -> tuple:
    """What `truth_from_labels` computes: ``(motion, displacements, flow, backward flow or None,
    2D boxes, full 2D boxes)``. Its compiled program returns only these: an input handed back
    as an output would be copied into a buffer of its own."""
    inst_p, _, inst, _ = labels
    disp = box_displacements(boxes_prev, boxes)
    motion = motion_segmentation(inst.box_index, disp, boxes.class_id, threshold_m=motion_threshold_m)
    fwd_motion = rigid_motion(boxes_prev.box_to_world, boxes.box_to_world)
    flow = analytic_flow(camera, img_p.range_m, inst_p.box_index, fwd_motion, c2w_p, c2w, target_range_m=img.range_m,
                         valid=img_p.valid, rays=rays)
    back = None
    if backward_flow:
        bwd_motion = rigid_motion(boxes.box_to_world, boxes_prev.box_to_world)
        back = analytic_flow(camera, img.range_m, inst.box_index, bwd_motion, c2w, c2w_p, target_range_m=img_p.range_m,
                             valid=img.valid, rays=rays)
    b2d = boxes_from_instances(inst.box_index, boxes.num_boxes)
    full = boxes_from_surfaces(boxes, camera, c2w.inverse(), samples=surface_samples)
    return motion, disp, flow, back, b2d, full


def _camera_truth(img_p: FisheyeImages, img: FisheyeImages, labels: tuple, rest: tuple) -> CameraGroundTruth:
    inst_p, sem_p, inst, sem = labels
    motion, disp, flow, back, b2d, full = rest
    return CameraGroundTruth(
        images_prev=img_p, images=img, semantic_prev=sem_p, semantic=sem, instances_prev=inst_p, instances=inst,
        motion=motion, displacement_m=disp, flow=flow, flow_backward=back, boxes_2d=b2d, boxes_2d_full=full,
    )


_jit_instant_labels = jax.jit(instant_labels, static_argnums=tuple(range(4, 10)))
_jit_motion_flow_boxes = jax.jit(_motion_flow_boxes, static_argnums=(9, 10, 11))
