"""``o3dvis shapes``, ``o3dvis prepare``, ``o3dvis train``, ``o3dvis calibrate``, ``o3dvis fuse`` and
``o3dvis publish``."""

from __future__ import annotations

import argparse
import json
import time

from ._common import check_folder, check_output, positive_ints


def _shapes(args) -> int:
    from ..training.data.shapes import DEFAULT_PRIMITIVES, PRIMITIVES, write_shapes

    if args.primitives is None:
        names = DEFAULT_PRIMITIVES
    else:
        names = tuple(PRIMITIVES) if args.primitives == "all" else tuple(args.primitives.split(","))
    if not set(names) <= set(PRIMITIVES):
        raise ValueError(f"--primitives: unknown {', '.join(sorted(set(names) - set(PRIMITIVES)))}; "
                         f"choose from {', '.join(PRIMITIVES)}")
    check_folder(args.out_dir, "OUT_DIR")
    paths = write_shapes(args.out_dir, args.count, args.seed, names, args.enclosed)
    print(f"wrote {len(paths)} meshes to {args.out_dir}")
    return 0


def _prepare(args) -> int:
    from ..training.data.prepare import prepare, prepare_scenes

    check_folder(args.out_dir, "OUT_DIR")
    t = time.time()
    if args.scenes is None:
        result, what = prepare(args.mesh_dir, args.out_dir, args.points, args.views, args.workers,
                               args.seed), "meshes"
    else:
        result, what = prepare_scenes(args.out_dir, args.scenes, args.mesh_dir, args.points, args.views,
                                      args.workers, args.seed, tuple(args.kinds.split(",")),
                                      tuple(args.samplings.split(",")), args.max_range), "scenes"
    print(f"labelled {result['done']} {what}, skipped {result['skipped']} finished, "
          f"{len(result['failed'])} failed, in {time.time() - t:.1f} s")
    return 1 if result["failed"] and not result["done"] else 0


def _train(args) -> int:
    import torch

    from ..training.train import TrainConfig, train

    check_folder(args.out, "-o")
    if args.threads:
        torch.set_num_threads(args.threads)
    network = {"use_normals": args.normals, "noise_cues": args.noise_cues, "footprints": args.footprints}
    if args.depth:
        network["depth"] = args.depth
    if args.channels:
        network["channels"] = tuple(args.channels)
    if args.frequencies is not None:
        network["num_frequencies"] = args.frequencies
    cfg = TrainConfig(
        data=args.data, out=args.out, val=args.val, steps=args.steps, batch_size=args.batch_size,
        lr=args.lr, val_every=args.val_every, workers=args.workers, seed=args.seed, device=args.device,
        network=network, init=args.init, time_limit=args.time_limit, orientation_weight=args.orientation_weight,
        augmentation={"min_points": args.min_points, "max_points": args.max_points,
                      "views": args.views, "noise": args.noise, "noise_prob": args.noise_prob,
                      "estimated_normals": args.estimated_normals})
    best = train(cfg)
    print(json.dumps({"checkpoint": str(best)}))
    return 0


def _calibrate(args) -> int:
    import torch

    from ..training.calibrate import calibrate
    from ..training.data.dataset import Augmentation

    check_output(args.out, "-o")
    if args.threads:
        torch.set_num_threads(args.threads)
    summary = calibrate(args.checkpoint, args.data, args.out, args.clouds, args.keep, args.seed,
                        Augmentation(max_points=args.max_points, estimated_normals=args.estimated_normals))
    print(json.dumps({k: summary[k] for k in ("u", "w", "samples", "cross_entropy_before",
                                              "cross_entropy_after")}))
    return 0


def _fuse(args) -> int:
    import torch

    from ..training.fuse import fuse

    check_output(args.out, "-o")
    if args.threads:
        torch.set_num_threads(args.threads)
    summary = fuse(args.checkpoint, args.data, args.out, args.clouds, args.keep, args.seed, args.min_points,
                   args.max_points, args.noise, args.noise_prob, args.steps, args.hidden)
    print(json.dumps({k: summary[k] for k in ("samples", "cross_entropy_before", "cross_entropy_after")}))
    return 0


def _publish(args) -> int:
    from ..training.publish import publish

    entry = publish(args.checkpoint, args.name, args.run, args.manifest, args.eval, args.command_line,
                    root=args.root)
    print(json.dumps({args.name: {k: entry[k] for k in ("file", "sha256", "bytes")}}))
    return 0


def _fit_arguments(p: argparse.ArgumentParser, data: str, out: str, clouds: int) -> None:
    """The arguments of the commands that fit a part of a trained network (calibrate, fuse)."""
    p.add_argument("checkpoint", metavar="CHECKPOINT", help=".safetensors file written by o3dvis train")
    p.add_argument("data", nargs="+", help=data)
    p.add_argument("-o", "--out", required=True, help=out)
    p.add_argument("--clouds", type=int, default=clouds, help=f"clouds drawn (default {clouds})")
    p.add_argument("--keep", type=int, default=20000, help="(point, view) pairs kept per cloud (default 20000)")
    p.add_argument("--seed", type=int, default=1, help="seed of the draw and of the fit (default 1)")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: default)")


_FORMAT = argparse.RawDescriptionHelpFormatter


def _add_shapes(sub: argparse._SubParsersAction) -> None:
    """``o3dvis shapes``: random procedural training meshes."""
    p = sub.add_parser("shapes", help="write random procedural training meshes", formatter_class=_FORMAT,
                       description="Write random unions of primitives as PLY meshes.\n\n"
                                   "example:\n  o3dvis shapes data/proc_meshes --count 600")
    p.add_argument("out_dir", metavar="OUT_DIR", help="folder for the meshes (created)")
    p.add_argument("--count", type=int, default=100, help="number of meshes (default 100)")
    p.add_argument("--seed", type=int, default=0, help="seed; mesh i depends on (seed, i) only (default 0)")
    p.add_argument("--primitives", default=None,
                   help="comma-separated parts to draw from (o3dvis.training.data.shapes.PRIMITIVES), or 'all' "
                        "(default: all but the thick-walled ones)")
    p.add_argument("--enclosed", action="store_true",
                   help="put each shape inside a closed shell (half of them with a hole cut in it)")
    p.set_defaults(func=_shapes)


def _add_prepare(sub: argparse._SubParsersAction) -> None:
    """``o3dvis prepare``: meshes or procedural scenes labelled with ray-cast visibility."""
    p = sub.add_parser("prepare", help="label meshes with ray-cast visibility", formatter_class=_FORMAT,
                       description="Sample points on every mesh (ply/obj/off/stl) below MESH_DIR and label\n"
                                   "them from random viewpoints; resumable, parallel. With --scenes N,\n"
                                   "label N procedural scenes instead (furnished rooms, streets; metres),\n"
                                   "with furniture and objects drawn from MESH_DIR, cameras inside (3/4)\n"
                                   "and outside (1/4): one file {kind}-{sampling}__{index}.npz per sampling.\n\n"
                                   "examples:\n  o3dvis prepare meshes/train data/train --workers 2\n"
                                   "  o3dvis prepare meshes/train data/scenes --scenes 400 --points 200000")
    p.add_argument("mesh_dir", metavar="MESH_DIR", help="folder of meshes (searched recursively)")
    p.add_argument("out_dir", metavar="OUT_DIR", help="folder for one .npz per mesh or scene (created)")
    p.add_argument("--scenes", type=int, metavar="N", help="label N procedural scenes (see above)")
    p.add_argument("--kinds", default="rooms,street",
                   help="scene kinds, scene i being the (i mod count)-th (default rooms,street)")
    p.add_argument("--samplings", default="uniform,lidar",
                   help="samplings written per scene: uniform (area-weighted), lidar (rays from 1-5 "
                        "sensors) (default uniform,lidar)")
    p.add_argument("--max-range", type=float, help="range limit of the lidar sampling, metres (default none)")
    p.add_argument("--points", type=int, default=100_000, help="points per mesh (default 100000)")
    p.add_argument("--views", type=int, default=16, help="viewpoints per mesh (default 16)")
    p.add_argument("--workers", type=int, default=1, help="parallel processes (default 1)")
    p.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    p.set_defaults(func=_prepare)


def _add_train(sub: argparse._SubParsersAction) -> None:
    """``o3dvis train``: a visibility network trained on prepared folders."""
    p = sub.add_parser("train", help="train a visibility network", formatter_class=_FORMAT,
                       description="Train on prepared folders; resumes when OUT holds a run.\n"
                                   "Several GPUs: torchrun --nproc_per_node=N -m o3dvis train ... --device cuda\n\n"
                                   "example:\n  o3dvis train data/train data/proc --val data/val --out runs/default")
    p.add_argument("data", nargs="+", help="folders of prepared .npz files")
    p.add_argument("-o", "--out", required=True, help="run folder (checkpoints, log)")
    p.add_argument("--val", help="folder of prepared validation files")
    p.add_argument("--steps", type=int, default=10_000, help="optimiser steps in all (default 10000)")
    p.add_argument("--batch-size", type=int, default=4, help="clouds per step and process (default 4)")
    p.add_argument("--lr", type=float, default=2e-3, help="peak AdamW learning rate (default 2e-3)")
    p.add_argument("--val-every", type=int, default=500, help="validate every this many steps (default 500)")
    p.add_argument("--min-points", type=int, default=2048, help="smallest subsample per cloud (default 2048)")
    p.add_argument("--max-points", type=int, default=16384, help="largest subsample per cloud (default 16384)")
    p.add_argument("--views", type=int, default=4, help="viewpoints per cloud and step")
    p.add_argument("--noise", type=float, default=0.02, help="largest noise level, share of the bbox diagonal")
    p.add_argument("--noise-prob", type=float, default=0.5, help="share of clouds that get noise (default 0.5)")
    p.add_argument("--normals", action="store_true", help="train a model that takes normals")
    p.add_argument("--estimated-normals", type=float, default=0.0, metavar="SHARE",
                   help="share of clouds given the normals normals='estimate' computes instead of exact ones")
    p.add_argument("--noise-cues", action="store_true",
                   help="the U-Net also reads two per-cloud noise statistics (o3dvis.nn.noise)")
    p.add_argument("--footprints", action="store_true",
                   help="also read depth buffers with each point splatted over its footprint as its plane "
                        "(o3dvis.nn.cues)")
    p.add_argument("--depth", type=int, help="octree depth (default: the network's)")
    p.add_argument("--channels", type=positive_ints, help="comma-separated stage widths")
    p.add_argument("--frequencies", type=int, help="view-embedding frequencies (default: the network's)")
    p.add_argument("--workers", type=int, default=0, help="DataLoader worker processes")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: default)")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cuda (default: cpu)")
    p.add_argument("--seed", type=int, default=0, help="seed of the network and the sampling (default 0)")
    p.add_argument("--init", help="start from this checkpoint (extra input channels start at zero)")
    p.add_argument("--time-limit", type=float, metavar="SECONDS",
                   help="checkpoint and stop after this many seconds of training (run again to resume)")
    p.add_argument("--orientation-weight", type=float, default=0.0, metavar="W",
                   help="also train a linear head on the U-Net's point features to give each point's "
                        "oriented normal, with this weight on its 1 - cos loss (the head is not saved "
                        "with the network; default 0: none)")
    p.set_defaults(func=_train)


def _add_calibrate(sub: argparse._SubParsersAction) -> None:
    """``o3dvis calibrate``: a trained network's per-cloud calibration."""
    p = sub.add_parser("calibrate", help="fit a trained network's per-cloud calibration", formatter_class=_FORMAT,
                       description="Fit, on training clouds drawn as training draws them, the map of the\n"
                                   "network's margins that depends on each cloud's noise and size\n"
                                   "(o3dvis.nn.calibration), and write the calibrated network.\n\n"
                                   "example:\n  o3dvis calibrate runs/default/best.safetensors data/train "
                                   "data/proc -o default-calibrated.safetensors")
    _fit_arguments(p, "folders of prepared .npz training files", "the calibrated .safetensors file to write", 2000)
    p.add_argument("--max-points", type=int, default=81920, help="largest cloud drawn (default 81920)")
    p.add_argument("--estimated-normals", type=float, default=0.0, metavar="SHARE",
                   help="share of clouds given the normals normals='estimate' computes (as in train)")
    p.set_defaults(func=_calibrate)


def _add_fuse(sub: argparse._SubParsersAction) -> None:
    """``o3dvis fuse``: a scene network's fusion with the surfel z-buffer."""
    p = sub.add_parser("fuse", help="fit a scene network's fusion with the surfel z-buffer", formatter_class=_FORMAT,
                       description="Fit, on scene clouds seen from cameras inside them, the MLP that fuses the\n"
                                   "network's margins with the surfel z-buffer's test (o3dvis.nn.fusion), and\n"
                                   "write the fused network.\n\n"
                                   "example:\n  o3dvis fuse o3dvis/weights/scene.safetensors data/sctrain "
                                   "-o scene-fused.safetensors")
    _fit_arguments(p, "folders of prepared scene .npz files (o3dvis prepare --scenes)",
                   "the fused .safetensors file to write", 400)
    p.add_argument("--min-points", type=int, default=8192, help="smallest cloud drawn (default 8192)")
    p.add_argument("--max-points", type=int, default=65536, help="largest cloud drawn (default 65536)")
    p.add_argument("--noise", type=float, default=0.02,
                   help="largest noise, a fraction of the median camera distance (default 0.02)")
    p.add_argument("--noise-prob", type=float, default=0.5, help="share of clouds with noise (default 0.5)")
    p.add_argument("--steps", type=int, default=3000, help="Adam steps of the fit (default 3000)")
    p.add_argument("--hidden", type=int, default=32, help="width of the fusion's hidden layer (default 32)")
    p.set_defaults(func=_fuse)


def _add_publish(sub: argparse._SubParsersAction) -> None:
    """``o3dvis publish``: a checkpoint installed as a shipped model."""
    p = sub.add_parser("publish", help="install a checkpoint as a shipped model", formatter_class=_FORMAT,
                       description="Copy a checkpoint into o3dvis/weights/ and write its model-card entry\n"
                                   "(architecture, data licences, steps, validation, sha256).\n\n"
                                   "example:\n  o3dvis publish runs/default/best.safetensors --name default "
                                   "--run runs/default --manifest meshes/MANIFEST.csv")
    p.add_argument("checkpoint", metavar="CHECKPOINT", help=".safetensors file written by o3dvis train")
    p.add_argument("--name", required=True, help="model name, e.g. default or normals")
    p.add_argument("--run", help="the training run folder (config.json, log.jsonl)")
    p.add_argument("--manifest", help="MANIFEST.csv of the training meshes (licences)")
    p.add_argument("--eval", help="JSON written by 'o3dvis eval' to record as the validation table")
    p.add_argument("--command-line", action="append",
                   help="a command that made the model, for the card; repeat it for each, oldest first")
    p.add_argument("--root", help="folder the card's paths are made relative to "
                                  "(default: the current directory)")
    p.set_defaults(func=_publish)


def register(sub: argparse._SubParsersAction) -> None:
    """Adds the commands that make models: shapes, prepare, train, calibrate, fuse, publish."""
    for add in (_add_shapes, _add_prepare, _add_train, _add_calibrate, _add_fuse, _add_publish):
        add(sub)
