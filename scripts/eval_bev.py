"""Evaluation: mIoU of the IPM top view and of the camera-fused top view against the true top view,
per class, on embedded-scene samples (the SynWoodScape paper's comparison: 61.2 IPM vs 76.5
native top view).

Per sample (scene seed ``s``, frame 0): the four fisheyes of jaxfish's default rig are rendered
directly (the exact oracle, `jaxfish.scene.render_fisheye`) at ``--width`` x 3/4 pixels, and the
true top view by the capture's BEV camera (`jaxfish.scene.simulate_view`) at ``--bev-size`` pixels
and ``--mpp`` metres per pixel. Classes are SynWoodScape's (two-wheelers and the ego split off by
their actors). IoU is pooled over all samples, over all BEV cells (a cell the fusion did not
observe counts as a miss) and over the cells the fusion observed (both methods on the same cells).
mIoU ignores class 0 (``unlabeled``, void) and averages over the classes present in the truth, the
same classes for both methods.

    uv run python scripts/eval_bev.py [--samples 4] [--width 320] [--bev-size 256] [--mpp 0.08]
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxfish as jf
from jaxfish import bev
from jaxfish import groundtruth as gt
from jaxfish.scene import CaptureConfig, bev_camera, generate_street, render_fisheye, sensor_mounts, simulate_view

F32 = jnp.float32
VOID_CLASS = 0  # SynWoodScape "unlabeled": not scored


def scored_iou(inter, union, truth_count) -> dict[str, float]:
    """IoU per scored class (present in the truth, not void) by name."""
    return {gt.SYNWOODSCAPE_CLASSES[k]: float(inter[k] / union[k]) for k in np.nonzero(truth_count)[0] if k != VOID_CLASS}


def classes(tags, actor_id, actor_class: dict[int, int]) -> np.ndarray:
    """SynWoodScape classes of CARLA 0.9.10 tags, vehicle pixels of two-wheelers / the ego split off."""
    ids = np.asarray(actor_id)
    box_class = np.full(ids.shape, -1, np.int32)
    for a, c in actor_class.items():
        box_class[ids == a] = c
    return np.asarray(gt.carla_to_synwoodscape(np.asarray(tags), box_class=box_class))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=4, help="number of scenes (seeds 0..N-1)")
    ap.add_argument("--width", type=int, default=320, help="fisheye width (height = 3/4)")
    ap.add_argument("--bev-size", type=int, default=256)
    ap.add_argument("--mpp", type=float, default=0.08, help="BEV metres per pixel")
    ap.add_argument("--json", action="store_true", help="also print the table as JSON")
    args = ap.parse_args()
    width, height = args.width, round(args.width * 3 / 4)
    rig = {k: c.astype(F32) for k, c in jf.default_rig(width=width, height=height, dtype=F32).items()}
    names = list(rig)
    config = CaptureConfig(bev_size=args.bev_size, bev_metres_per_pixel=args.mpp)
    mounts = sensor_mounts(rig, config)
    bev_cam, bev_pose = bev_camera(config), mounts.bev_camera_to_vehicle
    cams = bev.stack_cameras([rig[n].camera for n in names])
    poses = bev.stack_poses([rig[n].camera_to_vehicle for n in names])
    rays = jax.jit(bev.rig_rays)(cams)
    iou = jax.jit(lambda p, t: bev.semantic_iou(p, t, num_classes=len(gt.SYNWOODSCAPE_CLASSES)))
    pooled = {"fused": [0, 0, 0], "ipm": [0, 0, 0], "fused_observed": [0, 0, 0], "ipm_observed": [0, 0, 0]}
    n_cls = len(gt.SYNWOODSCAPE_CLASSES)
    per_sample = []
    t0 = time.perf_counter()
    for seed in range(args.samples):
        frame = generate_street(seed, frame=0, rig=rig)
        actor_class = {a.id: gt.CATEGORY_CLASS[a.category] for a in frame.actors}
        rng, sem, val = [], [], []
        for n in names:
            o = render_fisheye(frame, rig[n])
            rng.append(np.asarray(o.range_m, np.float32))
            sem.append(classes(o.semantic, o.actor_id, actor_class))
            val.append(np.asarray(o.valid) & np.asarray(o.hit))
        _, top, _ = simulate_view(frame, bev_cam, bev_pose, config)
        truth = classes(top.semantic, top.actor_id, actor_class)
        rng_a, sem_a, val_a = np.stack(rng), np.stack(sem).astype(np.int32), np.stack(val)
        fused = bev.fuse_cameras(cams, poses, rng_a, sem_a, bev_cam, bev_pose, valid=val_a, rays=rays)
        ipm = bev.ipm_semantics(cams, poses, sem_a, bev_cam, bev_pose, valid=val_a)
        row = {"seed": seed, "observed": float(np.mean(np.asarray(fused.observed)))}
        obs = np.asarray(fused.observed)
        t_obs = np.where(obs, truth, -1).astype(np.int32)  # only the cells the fusion observed
        for name, pred, t in (("fused", fused.semantic, truth), ("ipm", ipm.semantic, truth),
                              ("fused_observed", fused.semantic, t_obs), ("ipm_observed", ipm.semantic, t_obs)):
            s = iou(np.asarray(pred, np.int32), t.astype(np.int32))
            t_flat = t.reshape(-1)
            counts = np.bincount(t_flat[(t_flat >= 0) & (t_flat < n_cls)], minlength=n_cls)
            pooled[name][0] = pooled[name][0] + np.asarray(s.intersection, np.int64)
            pooled[name][1] = pooled[name][1] + np.asarray(s.union, np.int64)
            pooled[name][2] = pooled[name][2] + counts
            per_class = scored_iou(np.asarray(s.intersection), np.asarray(s.union), counts)
            row[name] = float(np.mean(list(per_class.values()))) if per_class else float("nan")
        per_sample.append(row)
        print(f"seed {seed}: fused mIoU {100 * row['fused']:.1f}  IPM mIoU {100 * row['ipm']:.1f}  "
              f"(fusion observed {100 * row['observed']:.0f} % of the cells)  {time.perf_counter() - t0:.0f} s", flush=True)
    table = {}
    for name, (inter, union, counts) in pooled.items():
        table[name] = scored_iou(inter, union, counts)
    cls_names = sorted(set(table["fused"]) | set(table["ipm"]), key=gt.SYNWOODSCAPE_CLASSES.index)
    print(f"\n{args.samples} samples, fisheyes {width}x{height}, BEV {args.bev_size}x{args.bev_size} @ {args.mpp} m/px")
    cols = ("ipm", "fused", "ipm_observed", "fused_observed")
    print("all cells: IPM, fused; cells observed by the fusion: IPM, fused (IoU %; classes present in the truth, "
          "'unlabeled' ignored)")
    print(f"{'class':<14}" + "".join(f"{c:>16}" for c in cols))
    for c in cls_names:
        print(f"{c:<14}" + "".join(f"{100 * table[n].get(c, 0.0):>16.1f}" for n in cols))
    miou = {n: float(np.mean(list(table[n].values()))) if table[n] else float("nan") for n in table}
    print(f"{'mIoU':<14}" + "".join(f"{100 * miou[n]:>16.1f}" for n in cols))
    print("paper (SynWoodScape): IPM 61.2, native top view 76.5")
    if args.json:
        miou_json = {n: v if np.isfinite(v) else None for n, v in miou.items()}
        rows = [{k: v if not isinstance(v, float) or np.isfinite(v) else None for k, v in r.items()} for r in per_sample]
        print(json.dumps({"per_class": table, "miou": miou_json, "per_sample": rows}, indent=1))


if __name__ == "__main__":
    main()
