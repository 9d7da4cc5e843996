"""Evaluation: mIoU of the IPM top view and of the camera-fused top view against the true top view,
per class, on embedded-scene samples (the SynWoodScape paper's table compares 61.2 for IPM of a
learned fisheye segmentation with 76.5 for a learned native top-view segmentation; see docs/bev.md
for why these figures are not comparable).

Per sample (scene seed ``s``, frame 0): the four fisheyes of jaxfish's default rig are rendered
directly (the exact oracle, `jaxfish.scene.render_fisheye`) at ``--width`` x 3/4 pixels, and the
true top view by the capture's BEV camera (`jaxfish.scene.simulate_view`) at ``--bev-size`` pixels
and ``--mpp`` metres per pixel. Classes are SynWoodScape's (two-wheelers and the ego split off by
their actors). Three top views: ``fused`` (`jaxfish.bev.fuse_cameras_dense`, what ``jaxfish bev``
writes), ``splat`` (`jaxfish.bev.fuse_cameras` alone, its first stage) and ``ipm``. Each is scored
(`jaxfish.bev.bev_scores`, IoU pooled over all samples) on **all** cells (a cell the method did not
observe is a miss) and on the cells **it observed**, with its coverage. mIoU ignores class 0
(``unlabeled``, void) and averages over the classes present in the (all / observed) truth.

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
    n_cls = len(gt.SYNWOODSCAPE_CLASSES)
    score = jax.jit(lambda p, t: bev.bev_scores(p, t, num_classes=n_cls, void_class=VOID_CLASS))
    methods = ("fused", "splat", "ipm")
    pooled = {m: [np.zeros(n_cls, np.int64) for _ in range(6)] for m in methods}
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
        truth = classes(top.semantic, top.actor_id, actor_class).astype(np.int32)
        rng_a, sem_a, val_a = np.stack(rng), np.stack(sem).astype(np.int32), np.stack(val)
        preds = {
            "fused": bev.fuse_cameras_dense(cams, poses, rng_a, sem_a, bev_cam, bev_pose, valid=val_a, rays=rays).semantic,
            "splat": bev.fuse_cameras(cams, poses, rng_a, sem_a, bev_cam, bev_pose, valid=val_a, rays=rays).semantic,
            "ipm": bev.ipm_semantics(cams, poses, sem_a, bev_cam, bev_pose, valid=val_a).semantic,
        }
        row = {"seed": seed}
        for m in methods:
            s = score(np.asarray(preds[m], np.int32), truth)
            counts = (s.all_cells.intersection, s.all_cells.union, s.truth_count, s.observed_cells.intersection,
                      s.observed_cells.union, s.observed_truth_count)
            for acc, c in zip(pooled[m], counts, strict=True):
                acc += np.asarray(c, np.int64)
            row[m] = float(s.miou_all)
            row[f"{m}_observed"] = float(s.miou_observed)
            row[f"{m}_coverage"] = float(s.coverage)
        per_sample.append(row)
        print(f"seed {seed}: " + "  ".join(f"{m} {100 * row[m]:.1f} / {100 * row[m + '_observed']:.1f} "
                                            f"({100 * row[m + '_coverage']:.0f} %)" for m in methods)
              + f"  {time.perf_counter() - t0:.0f} s", flush=True)
    table, miou, coverage = {}, {}, {}
    for m in methods:
        inter, union, tc, o_inter, o_union, o_tc = pooled[m]
        table[m] = scored_iou(inter, union, tc)
        table[f"{m}_observed"] = scored_iou(o_inter, o_union, o_tc)
        coverage[m] = float(o_tc.sum() / max(tc.sum(), 1))
    for name, per_class in table.items():
        miou[name] = float(np.mean(list(per_class.values()))) if per_class else float("nan")
    cols = ("ipm", "ipm_observed", "splat", "splat_observed", "fused", "fused_observed")
    cls_names = sorted(set().union(*(table[c] for c in cols)), key=gt.SYNWOODSCAPE_CLASSES.index)
    print(f"\n{args.samples} samples, fisheyes {width}x{height}, BEV {args.bev_size}x{args.bev_size} @ {args.mpp} m/px")
    print("IoU % per method on all cells (unobserved = miss) and on the cells it observed; classes present in the "
          "truth, 'unlabeled' ignored")
    print(f"{'class':<14}" + "".join(f"{c:>16}" for c in cols))
    for c in cls_names:
        print(f"{c:<14}" + "".join(f"{100 * table[n][c]:>16.1f}" if c in table[n] else f"{'-':>16}" for n in cols))
    print(f"{'mIoU':<14}" + "".join(f"{100 * miou[n]:>16.1f}" for n in cols))
    print(f"{'coverage':<14}" + "".join(f"{100 * coverage[n.removesuffix('_observed')]:>16.1f}" for n in cols))
    print("paper (SynWoodScape, learned networks): IPM of fisheye segmentation 61.2, native top-view segmentation 76.5")
    if args.json:
        miou_json = {n: v if np.isfinite(v) else None for n, v in miou.items()}
        rows = [{k: v if not isinstance(v, float) or np.isfinite(v) else None for k, v in r.items()} for r in per_sample]
        print(json.dumps({"per_class": table, "miou": miou_json, "coverage": coverage, "per_sample": rows}, indent=1))

if __name__ == "__main__":
    main()
