"""Time and memory of one drop-in call from 2 k to 10 M points, against Open3D's HPR in the same run.

    python3 benchmarks/bench_scaling.py --points 2048,8192,32768,200000,1000000,3000000,10000000 \\
        --out benchmarks/results/scaling.md
    python3 benchmarks/bench_scaling.py --scene rooms --points 200000,1000000 --rounds 5 \\
        --out benchmarks/results/scaling_inside.md
    python3 benchmarks/bench_scaling.py --scene rooms --points 10000000 --rounds 1 \\
        --out benchmarks/results/scaling_inside_10m.md
    python3 benchmarks/bench_scaling.py --scene rooms --points 200000,1000000 --rotations 2 \\
        --out benchmarks/results/scaling_inside_x2.md

For each size, one procedural cloud and one camera (as ``o3dvis bench``), or with ``--scene``
a procedural scene (furnished rooms or a street, sampled uniformly, fixed seed) and a camera
inside it, whose drop-in answers with the ``scene`` model (and ``encode``/``query`` are that
model's); with ``--rotations K``, the model answers with the mean over K rotations of the
cloud (``NeuralVisibility.pretrained(num_rotations=K)``, passed as ``model=``); and
interleaved rounds of ``o3dvis.hidden_point_removal_neural`` (its kept encoding
cleared first, so that it encodes), its two stages alone (``encode`` and one
``query``) and Open3D's ``hidden_point_removal``. The peak memory is what one call
of the drop-in (or of HPR) adds to the resident memory of a fresh process (Linux). Medians of the rounds
(``--rounds``, one above ``--few-above`` points). The thread policy is o3dvis's
automatic one: on a busy machine that is one thread.
"""

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import o3dvis  # noqa: E402
from o3dvis import encodings  # noqa: E402
from o3dvis.neural import NeuralVisibility  # noqa: E402
from o3dvis.threads import cpu_pressure, plan_threads  # noqa: E402
from o3dvis.evaluation.speed import bench_cloud  # noqa: E402


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def _mib(value: float | None) -> str:
    return "" if value is None else f"{value:.0f}"


def _scene(points: int, kind: str | None = None):
    """A cloud of ``points``, a camera (inside a procedural scene of ``kind`` if given) and
    Open3D's documented HPR radius (diameter x 100)."""
    if kind is None:
        cloud = bench_cloud(points, 1)
        xyz, camera = cloud.points, cloud.cameras[0]
    else:
        from o3dvis.training.data.scenes import free_positions, random_scene, sample_uniform
        rng = np.random.default_rng(0)
        scene = random_scene(kind, rng)
        xyz, camera = sample_uniform(scene, points, rng)[0], free_positions(scene, 1, rng)[0]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    return pcd, camera, 100.0 * float(np.linalg.norm(np.ptp(xyz, axis=0)))


def _status_kib(field: str) -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(field + ":"))


def _dropin_model(rotations: int) -> NeuralVisibility | None:
    """What the drop-in is given as ``model=``: None (its default) or the shipped models with
    ``num_rotations`` (the scene model answers a camera inside)."""
    return None if rotations == 1 else NeuralVisibility.pretrained(num_rotations=rotations)


def child_peak_mib(way: str, points: int, kind: str | None, rotations: int) -> None:
    """Prints the peak resident memory (MiB) one call of ``way`` adds to this fresh process, above its
    level with the cloud built and the model loaded and run once on a small cloud (Linux)."""
    pcd, camera, radius = _scene(points, kind)
    small, small_camera, _ = _scene(2048, kind)
    model = _dropin_model(rotations)
    o3dvis.hidden_point_removal_neural(small, small_camera, model=model)
    encodings.clear()
    with open("/proc/self/clear_refs", "w") as f:  # resets the peak (VmHWM) to the current level
        f.write("5")
    before = _status_kib("VmRSS")
    if way == "drop-in":
        o3dvis.hidden_point_removal_neural(pcd, camera, model=model)
    else:
        pcd.hidden_point_removal(camera, radius)
    print((_status_kib("VmHWM") - before) / 1024)


def _peak_mib(way: str, points: int, kind: str | None, rotations: int) -> float | None:
    """:func:`child_peak_mib` in a fresh process; None where it cannot tell."""
    run = subprocess.run([sys.executable, __file__, "--child", way, str(points), "--rotations", str(rotations)]
                         + (["--scene", kind] if kind else []), capture_output=True, text=True)
    try:
        return float(run.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return None


def measure(points: int, rounds: int, kind: str | None = None, rotations: int = 1) -> dict:
    pcd, camera, radius = _scene(points, kind)
    name = "scene" if kind else "default"
    vis = NeuralVisibility.pretrained(name, num_rotations=rotations)
    model = _dropin_model(rotations)

    def dropin():
        encodings.clear()
        o3dvis.hidden_point_removal_neural(pcd, camera, model=model)

    field = vis.encode(pcd)
    ways = {"drop-in": dropin, "encode": lambda: vis.encode(pcd), "query": lambda: field.query(camera),
            "Open3D HPR": lambda: pcd.hidden_point_removal(camera, radius)}
    ways["Open3D HPR"]()  # warm
    times = {name: [] for name in ways}
    for _ in range(rounds):  # interleaved: a burst of load hits every way alike
        for name, way in ways.items():
            times[name].append(_timed(way))
    del field
    encodings.clear()
    medians = {name: statistics.median(t) for name, t in times.items()}
    return {"points": points, "rounds": rounds, "median_s": medians,
            "rotations": rotations,
            "peak_mib": {way: _peak_mib(way, points, kind, rotations) for way in ("drop-in", "Open3D HPR")},
            "speedup_vs_hpr": medians["Open3D HPR"] / medians["drop-in"],
            "threads_planned": plan_threads(points, 1), "cpu_pressure": cpu_pressure()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", default="2048,8192,32768,200000,1000000,3000000,10000000")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--few-above", type=int, default=1_000_000)
    parser.add_argument("--scene", choices=("rooms", "street"), help="a procedural scene, the camera inside")
    parser.add_argument("--rotations", type=int, default=1, help="the model's num_rotations (default 1)")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--child", nargs=2, metavar=("WAY", "POINTS"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child_peak_mib(args.child[0], int(args.child[1]), args.scene, args.rotations)
        return 0
    rows = []
    for n in (int(p) for p in args.points.split(",")):
        rows.append(measure(n, args.rounds if n <= args.few_above else 1, args.scene, args.rotations))
        print(json.dumps(rows[-1]), flush=True)
    lines = ["| points | drop-in (ms) | encode (ms) | query, one view (ms) | drop-in peak memory (MiB) | "
             "Open3D HPR (ms) | HPR peak memory (MiB) | speed-up vs HPR |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m, p = r["median_s"], r["peak_mib"]
        lines.append(f"| {r['points']:,} | {1e3 * m['drop-in']:.1f} | {1e3 * m['encode']:.1f} | {1e3 * m['query']:.1f} | "
                     f"{_mib(p['drop-in'])} | {1e3 * m['Open3D HPR']:.1f} | {_mib(p['Open3D HPR'])} | "
                     f"{r['speedup_vs_hpr']:.2f}x |")
    faster = [r["points"] for r in rows if r["speedup_vs_hpr"] >= 1]
    slower = [r["points"] for r in rows if r["speedup_vs_hpr"] < 1 and (not faster or r["points"] < min(faster))]
    crossover = ("never faster than HPR here" if not faster else f"faster than HPR from {min(faster):,} points"
                 + (f" (slower at {max(slower):,})" if slower else ""))
    pressure = [r["cpu_pressure"] for r in rows if r["cpu_pressure"] is not None]
    scene = (f" --scene {args.scene}" if args.scene else "") + (f" --rotations {args.rotations}"
                                                                 if args.rotations != 1 else "")
    lines = [f"`python3 benchmarks/bench_scaling.py{scene} --points {args.points}`: medians of {args.rounds} interleaved "
             f"rounds (one above {args.few_above:,} points), o3dvis's automatic threads "
             f"(planned: {sorted({r['threads_planned'] for r in rows})}"
             + (f", CPU pressure {min(pressure):.2f}-{max(pressure):.2f}" if pressure else "")
             + f"); peak memory: what one call adds to a fresh process. The drop-in is {crossover}.", ""] + lines
    table = "\n".join(lines) + "\n"
    print(table)
    if args.out:
        args.out.write_text(table)
        args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
