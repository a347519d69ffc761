"""``o3dvis normals | reconstruct | shadow | best-view | render``: the applications on files."""

from __future__ import annotations

import argparse

from .._optional import figure_class
from ._common import add_method_flags, add_vector, check_output, stages, visibility_method, write_image

__all__ = ["register"]

_EPILOG = "example:\n  "
# o3dvis.apps.views.SEARCHES (a test checks they agree), kept here so that the parser imports no torch
_SEARCHES = ("candidates", "gradient")


def _add_view_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--views", type=int, default=26, help="cameras for the normals (default 26)")
    parser.add_argument("--refine-views", type=int, default=0,
                        help="more cameras for the points the first leave uncovered (default 0: none)")
    parser.add_argument("--knn", type=int, default=None, metavar="K",
                        help="fit each normal to its K nearest neighbours, weighted by the views that see "
                             "them with it, instead of triangulating: faster (16 is a good start)")


def _search(args: argparse.Namespace):
    """The Open3D search parameter ``--knn`` names (None: triangulate)."""
    import open3d as o3d

    return None if args.knn is None else o3d.geometry.KDTreeSearchParamKNN(args.knn)


def _parser(subparsers, name: str, help: str, description: str, example: str) -> argparse.ArgumentParser:
    return subparsers.add_parser(name, help=help, description=description, epilog=_EPILOG + example,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)


def register(subparsers) -> None:
    """Adds the application subcommands."""
    p = _parser(subparsers, "normals", "estimate oriented normals from visibility",
                "Estimates oriented normals of the input cloud from the surface seen by --views cameras around it "
                "(or, with --orient-only, orients the normals it already has) and writes the cloud.",
                "o3dvis normals scan.ply -o scan_normals.ply --views 26")
    p.add_argument("input", help="point cloud file readable by Open3D (.ply, .pcd, .xyz, ...)")
    p.add_argument("-o", "--output", required=True, help="output point cloud file")
    _add_view_flags(p)
    p.add_argument("--orient-only", action="store_true", help="keep the normals of the input, only orient them")
    add_method_flags(p)
    p.set_defaults(func=_normals)

    p = _parser(subparsers, "reconstruct", "mesh a cloud: Poisson, or the surface one camera sees",
                "Without --camera: screened Poisson reconstruction on visibility-oriented normals. "
                "With --camera: the mesh of the surface that camera sees (projected Delaunay).",
                "o3dvis reconstruct scan.ply -o mesh.ply --depth 8 --trim 0.02")
    p.add_argument("input", help="point cloud file readable by Open3D")
    p.add_argument("-o", "--output", required=True, help="output mesh file (.ply, .obj, ...)")
    add_vector(p, "--camera", "view-dependent mesh from this position")
    p.add_argument("--depth", type=int, default=8,
                   help="Poisson octree depth (default 8; at most 16, and what the cloud and memory allow)")
    p.add_argument("--trim", type=float, default=0.0,
                   help="drop Poisson vertices below this density quantile, e.g. 0.02 (default 0)")
    _add_view_flags(p)
    add_method_flags(p)
    p.set_defaults(func=_reconstruct)

    p = _parser(subparsers, "shadow", "render a cloud with the shadows a point light casts",
                "Renders the input cloud from --camera lit by a point light at --light, shadowed points dark, "
                "and optionally saves the light's shadow map (float depth, .npy).",
                "o3dvis shadow scan.ply --light 0 0 3 --camera 2 -2 1 -o shadows.png")
    p.add_argument("input", help="point cloud file readable by Open3D")
    add_vector(p, "--light", "light position", required=True)
    add_vector(p, "--camera", "camera position", required=True)
    p.add_argument("-o", "--output", required=True, help="output image (.png, .jpg)")
    p.add_argument("--width", type=int, default=640, help="image width (default 640)")
    p.add_argument("--height", type=int, default=480, help="image height (default 480)")
    p.add_argument("--shadow-map", default=None, metavar="FILE.npy", help="also save the light's depth map")
    p.add_argument("--resolution", type=int, default=512, help="shadow map size (default 512)")
    add_method_flags(p)
    p.set_defaults(func=_shadow)

    p = _parser(subparsers, "best-view", "find the camera position that sees the most points",
                "Scores --candidates views spread on the sphere of radius = bbox diagonal from one encoding "
                "of the cloud, refines the best by a compass search (or, with --search gradient, runs "
                "gradient descent on the network's soft visibility); prints the position X Y Z.",
                "o3dvis best-view scan.ply -o best.png")
    p.add_argument("input", help="point cloud file readable by Open3D")
    p.add_argument("--worst", action="store_true", help="find the view that sees the fewest points")
    p.add_argument("--search", choices=_SEARCHES, default=_SEARCHES[0],
                   help="candidates (default): a scored lattice refined by compass search; gradient: "
                        "Adam on the soft visibility (much slower)")
    p.add_argument("--candidates", type=int, default=200, help="views scored first (default 200)")
    p.add_argument("--steps", type=int, default=None,
                   help="refinement rounds (default 10), or optimisation steps with --search gradient "
                        "(default 300)")
    p.add_argument("--starts", type=int, default=None,
                   help="views refined (default 4), or starting directions with --search gradient (default 8)")
    p.add_argument("-o", "--output", default=None, help="also render the view to this image")
    p.add_argument("--plot", default=None, help="save the loss curve to this image (matplotlib)")
    add_method_flags(p, choices=("neural",))
    p.set_defaults(func=_best_view)

    p = _parser(subparsers, "render", "render a cloud to an image, hidden points removed",
                "Renders the points of the input cloud that --camera sees (z-buffered splats, no display needed), "
                "coloured by their colours or shaded by their normals.",
                "o3dvis render scan.ply --camera 2 -2 1 -o scan.png --depth-output depth.npy")
    p.add_argument("input", help="point cloud file readable by Open3D")
    add_vector(p, "--camera", "camera position", required=True)
    p.add_argument("-o", "--output", required=True, help="output image (.png, .jpg)")
    p.add_argument("--width", type=int, default=640, help="image width (default 640)")
    p.add_argument("--height", type=int, default=480, help="image height (default 480)")
    p.add_argument("--all", action="store_true", help="splat every point (no visibility)")
    p.add_argument("--depth-output", default=None, metavar="FILE.npy",
                   help="also save the float depth image")
    add_method_flags(p)
    p.set_defaults(func=_render)


def _normals(args: argparse.Namespace) -> int:
    import open3d as o3d

    from ..apps.normals import estimate_normals_neural, orient_normals_neural
    from ..io import read_point_cloud

    check_output(args.output, "-o", "point cloud")
    pcd = read_point_cloud(args.input)
    method = visibility_method(args)
    if args.orient_only:
        if args.knn is not None:
            raise ValueError("--knn estimates normals; --orient-only keeps the input's")
        orient_normals_neural(pcd, args.views, method, refine_views=args.refine_views)
    else:
        estimate_normals_neural(pcd, _search(args), args.views, method, refine_views=args.refine_views,
                                progress=True)
    if not o3d.io.write_point_cloud(args.output, pcd):
        raise RuntimeError(f"could not write {args.output}")
    print(f"{len(pcd.points)} oriented normals -> {args.output}")
    return 0


def _reconstruct(args: argparse.Namespace) -> int:
    import numpy as np
    import open3d as o3d

    from ..apps.reconstruction import reconstruct_poisson, reconstruct_view_dependent
    from ..io import read_point_cloud

    check_output(args.output, "-o", "mesh")
    pcd = read_point_cloud(args.input)
    method = visibility_method(args)
    if args.camera is not None:
        if args.knn is not None:
            raise ValueError("--knn estimates the normals of a Poisson reconstruction; --camera needs none")
        mesh = reconstruct_view_dependent(pcd, args.camera, method)
    else:
        if not 0 <= args.trim < 1:
            raise ValueError(f"--trim must be a quantile in [0, 1), got {args.trim}")
        mesh, densities = reconstruct_poisson(pcd, args.depth, method, num_views=args.views,
                                              refine_views=args.refine_views, progress=True,
                                              search_param=_search(args))
        if args.trim > 0:
            densities = np.asarray(densities)
            mesh.remove_vertices_by_mask(densities < np.quantile(densities, args.trim))
    if not o3d.io.write_triangle_mesh(args.output, mesh):
        raise RuntimeError(f"could not write {args.output}")
    print(f"{len(mesh.vertices)} vertices, {len(mesh.triangles)} triangles -> {args.output}")
    return 0


def _shadow(args: argparse.Namespace) -> int:
    import numpy as np

    from ..apps.shadows import points_in_shadow, render_with_shadows, shadow_map
    from ..io import read_point_cloud

    check_output(args.output, "-o", "image")
    check_output(args.shadow_map, "--shadow-map", "array")
    pcd = read_point_cloud(args.input)
    method = visibility_method(args)
    with stages(3 if args.shadow_map else 2, "shadow") as bar:
        shadowed = points_in_shadow(pcd, args.light, method)
        bar.update()
        write_image(args.output, render_with_shadows(pcd, args.light, args.camera, args.width,
                                                      args.height, method))
        bar.update()
        if args.shadow_map:
            np.save(args.shadow_map, np.asarray(shadow_map(pcd, args.light, args.resolution, method)))
            bar.update()
    print(f"{int(shadowed.sum())} of {len(shadowed)} points in shadow -> {args.output}")
    return 0


def _best_view(args: argparse.Namespace) -> int:
    from ..apps.render import render_points
    from ..apps.views import best_view
    from ..io import read_point_cloud

    figure = figure_class("--plot") if args.plot else None
    check_output(args.output, "-o", "image")
    if figure is not None:
        plots = tuple(f".{s}" for s in figure().canvas.get_supported_filetypes())
        check_output(args.plot, "--plot", "plot", plots)
    pcd = read_point_cloud(args.input)
    method = visibility_method(args)
    camera, losses = best_view(pcd, maximize=not args.worst, steps=args.steps, model=method, starts=args.starts,
                               candidates=args.candidates, search=args.search)
    fraction = -losses.min() if not args.worst else losses.min()
    print(f"{'worst' if args.worst else 'best'} view: {camera[0]:.6g} {camera[1]:.6g} {camera[2]:.6g} "
          f"(sees {100 * fraction:.1f}% of the points, soft count)")
    if args.output:
        write_image(args.output, render_points(pcd, camera, model=method))
    if figure is not None:
        fig = figure(figsize=(5, 3))
        ax = fig.subplots()
        ax.plot(losses)
        ax.set_xlabel("step" if args.search == "gradient" else "round (0: the best candidate)")
        ax.set_ylabel("loss (- visible fraction)" if not args.worst else "loss (visible fraction)")
        fig.tight_layout()
        fig.savefig(args.plot)
    return 0


def _render(args: argparse.Namespace) -> int:
    import numpy as np

    from ..apps.render import depth_image, render_points
    from ..io import read_point_cloud

    check_output(args.output, "-o", "image")
    check_output(args.depth_output, "--depth-output", "array")
    pcd = read_point_cloud(args.input)
    method = None if args.all else visibility_method(args)
    with stages(2 if args.depth_output else 1, "render") as bar:
        write_image(args.output, render_points(pcd, args.camera, not args.all, args.width,
                                                args.height, method))
        bar.update()
        if args.depth_output:
            depth = depth_image(pcd, args.camera, width=args.width, height=args.height,
                                visible_only=not args.all, model=method)
            np.save(args.depth_output, np.asarray(depth))
            bar.update()
    print(f"{args.width}x{args.height} render -> {args.output}")
    return 0
