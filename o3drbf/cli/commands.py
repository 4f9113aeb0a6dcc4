"""The ``o3drbf`` command line.

    o3drbf reconstruct INPUT -o OUTPUT [options]
    o3drbf compare INPUT [--cameras F] [--truth MESH] [--methods ...] [-o DIR]
    o3drbf view INPUT [--cameras F] [--screenshot PNG]
    o3drbf photos IMAGES_DIR --calibration FILE -o MODEL.ply

Exit status 0 on success; 2 with a one-line reason on bad input or usage;
1 on an unexpected failure.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from o3drbf.pipeline import DEFAULTS

__all__ = ["main", "build_parser", "check_reconstruct_files"]

log = logging.getLogger("o3drbf")


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a number >= 1, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="o3drbf",
        description="Smooth, closed surfaces from sparse, noisy 3-D points (multi-order RBF volumetric regularization).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    rec = sub.add_parser(
        "reconstruct",
        help="point cloud -> closed mesh",
        description="Reconstruct a closed mesh from a point cloud (PLY, PCD, XYZ, XYZN, ...). "
        "Lengths (offsets, radii, delta, tau, lambda) refer to the data normalized into a 2x2x2 box.",
    )
    rec.add_argument(
        "input",
        help="point cloud file (normals used when present), or a file that holds points and cameras: "
        "Stanford .conf (range scans), COLMAP text folder, Bundler bundle.out, o3drbf scan .json",
    )
    rec.add_argument("-o", "--output", required=True, help="output mesh (.ply, .obj, .stl, .off, .gltf, .glb)")
    g = rec.add_argument_group("basis")
    g.add_argument("--basis", default=DEFAULTS["basis"], choices=["multiorder", "thinplate", "gaussian"])
    g.add_argument(
        "--auto",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="choose delta, tau and lambda-surface from the data's spacing and noise (default); "
        f"--no-auto: the paper's fixed values delta {DEFAULTS['delta']:g}, tau {DEFAULTS['tau']:g}, lambda-surface {DEFAULTS['lambda_surface']:g}. "
        "An explicit --delta, --tau or --lambda-surface overrides only that one",
    )
    g.add_argument("--delta", type=float, default=None, help=f"multi-order: first-order weight, enters squared (default: --auto, or {DEFAULTS['delta']:g})")
    g.add_argument("--tau", type=float, default=None, help=f"multi-order: third-order weight (default: --auto, or {DEFAULTS['tau']:g})")
    g.add_argument("--sigma", type=float, default=DEFAULTS["sigma"], help="gaussian: width (default %(default)s)")
    g = rec.add_argument_group("cameras and outliers")
    g.add_argument("--cameras", metavar="FILE", help="cameras that saw the points (JSON, Middlebury *_par.txt, COLMAP folder, bundle.out, .conf): exterior constraints go toward them")
    g.add_argument("--outliers", default="none", choices=["none", "largest", "statistical"], help="keep the largest connected component (or Open3D statistical removal) first (default %(default)s)")
    g.add_argument("--outlier-radius", type=float, default=None, help="neighbourhood radius for --outliers largest, data units (default: 3 mean spacings)")
    g.add_argument("--keep-components", type=_positive_int, default=1, help="components kept by --outliers largest (default %(default)s)")
    g = rec.add_argument_group("constraints")
    g.add_argument("--lambda-surface", type=float, default=None, help=f"smoothing of surface constraints, >= 0 (default: --auto, or {DEFAULTS['lambda_surface']:g})")
    g.add_argument("--lambda-exterior", type=float, default=DEFAULTS["lambda_exterior"], help="smoothing of exterior constraints (default %(default)s)")
    g.add_argument("--surface-count", type=_positive_int, default=DEFAULTS["surface_count"], help="Poisson-disc subsample to about N surface constraints (default %(default)s)")
    g.add_argument("--surface-radius", type=float, default=None, help="Poisson-disc radius (box units) instead of --surface-count")
    g.add_argument("--all-points", action="store_true", help="use every point as a surface constraint (no subsampling)")
    g.add_argument("--exterior-ratio", type=float, default=DEFAULTS["exterior_ratio"], help="exterior constraints per surface constraint (default %(default)s)")
    g.add_argument("--exterior-offset", type=float, default=DEFAULTS["exterior_offset"], help="distance of exterior constraints from the surface (default %(default)s)")
    g.add_argument("--sphere-count", type=int, default=DEFAULTS["sphere_count"], help="exterior constraints on a sphere around the data (default %(default)s)")
    g = rec.add_argument_group("solve and mesh")
    g.add_argument("--solver", default="auto", choices=["auto", "dense", "iterative", "fast"])
    g.add_argument("--resolution", type=_positive_int, default=DEFAULTS["resolution"], help="marching-cubes cells along the longest side (default %(default)s)")
    g.add_argument("--voxel-size", type=float, default=None, help="grid spacing in data units (overrides --resolution)")
    g.add_argument("--save-model", metavar="FILE.npz", help="also save the implicit function (evaluate it later with o3drbf.ImplicitSurface.load)")
    g.add_argument("--seed", type=int, default=0, help="seed for sampling (default %(default)s)")
    g = rec.add_argument_group("output")
    g.add_argument("--no-color", action="store_true", help="do not colour the mesh from the input points' colours (used when the input has colours)")
    g.add_argument("-q", "--quiet", action="store_true", help="no progress bars or summary")
    g.add_argument("-v", "--verbose", action="store_true", help="log each step")

    from o3drbf.evaluation.compare import add_compare_arguments

    add_compare_arguments(
        sub.add_parser(
            "compare",
            help="run several methods on the same points: tables and a picture",
            description="Run o3drbf's bases and Open3D's Poisson, ball pivoting and alpha shapes on the same data; "
            "write comparison.md/.csv/.json and comparison.png.",
        )
    )

    from o3drbf.photo.pipeline import add_photos_arguments

    add_photos_arguments(
        sub.add_parser(
            "photos",
            help="calibrated photographs -> closed, coloured mesh",
            description="Carve a voxel shell from calibrated photographs, fit the surface to it and colour it from the photographs.",
        )
    )

    view = sub.add_parser(
        "view",
        help="interactive viewer (PyVista): points, constraints, surface, sliders",
        description="Show the input points, the constraints, the cameras and the iso-surface beside Open3D Poisson; "
        "sliders refit.  --screenshot renders offscreen without a display.",
    )
    _add_view_arguments(view)
    return parser


def _add_view_arguments(parser: argparse.ArgumentParser) -> None:
    """The viewer's arguments, without importing PyVista (``o3drbf --help`` stays fast)."""
    try:
        from o3drbf.viewers.app import add_view_arguments
    except ImportError:  # viewers/ not installed: keep the CLI usable
        parser.add_argument("input", nargs="?")
        return
    add_view_arguments(parser)


def _version() -> str:
    from o3drbf import __version__

    return __version__


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status.

    0 success; 2 bad input or usage (one line naming the problem); 1 an
    unexpected failure (one line, the traceback with ``-v``); 130 interrupted
    (Ctrl-C); 128 + N on signal N (SIGTERM: 143).  Outputs are atomic: on
    any failure or interruption no partial file is left and an existing
    output is unchanged.
    """
    from o3drbf.io.files import signal_cleanup

    try:
        with signal_cleanup():
            return _main(argv)
    except KeyboardInterrupt:
        print("o3drbf: interrupted", file=sys.stderr)
        return 130


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _reconstruct(args) -> int:
    from o3drbf.io import files as io
    from o3drbf.pipeline import reconstruct

    t0 = time.perf_counter()
    out = io.check_output(args.output, inputs=[args.input])
    if args.save_model:
        model = Path(args.save_model)
        if model.suffix != ".npz":
            raise ValueError(f"--save-model must end in .npz, got {args.save_model!r}")
        if model.resolve() == Path(args.input).resolve():
            raise ValueError("--save-model is the input file; choose another name (inputs are never overwritten)")
    points, normals, cameras, point_camera = _read_input(args.input)
    if args.cameras:
        if cameras is not None:
            raise ValueError(f"{args.input} already holds cameras; drop --cameras")
        from o3drbf.cameras.model import load_cameras

        cameras = load_cameras(args.cameras)
    if normals is None and cameras is None:
        log.warning("%s has no normals: estimating and orienting them with Open3D", args.input)
    progress = not args.quiet
    result = reconstruct(
        points,
        normals,
        cameras=cameras,
        point_camera=point_camera,
        outliers=args.outliers,
        outlier_radius=args.outlier_radius,
        keep_components=args.keep_components,
        basis=args.basis,
        delta=args.delta,
        tau=args.tau,
        sigma=args.sigma,
        lambda_surface=args.lambda_surface,
        auto=args.auto,
        lambda_exterior=args.lambda_exterior,
        surface_count=None if args.all_points else args.surface_count,
        surface_radius=args.surface_radius,
        exterior_ratio=args.exterior_ratio,
        exterior_offset=args.exterior_offset,
        sphere_count=args.sphere_count,
        solver=args.solver,
        resolution=args.resolution,
        voxel_size=args.voxel_size,
        seed=args.seed,
        progress=progress,
    )
    colored = ""
    if not args.no_color:
        colors = _input_colors(args.input, cameras if not args.cameras else None)
        if colors is not None and len(colors) == len(points):
            from o3drbf.mesh.color import color_mesh

            result.mesh = color_mesh(result.mesh, points=points, colors=colors)
            colored = "coloured from the input points' colours"
    io.write_mesh(out, result.mesh, inputs=[args.input])
    if args.save_model:
        result.surface.save(args.save_model)
    if not args.quiet:
        text = summary(result, points, args.input, out, args.save_model, time.perf_counter() - t0)
        if colored:
            text = text.replace("\n  watertight", f"\n  colour           {colored}\n  watertight", 1)
        print(text)
    return 0


_CAMERA_INPUTS = (".conf", ".out", ".json")


def _read_input(path: str):
    """Points, normals, cameras and the per-point camera index from INPUT."""
    from o3drbf.io import files as io

    p = Path(path)
    if p.is_dir() or p.suffix.lower() in _CAMERA_INPUTS:
        from o3drbf.cameras.model import load_cameras

        if not p.exists():
            raise FileNotFoundError(f"input not found: {p}")
        cams = load_cameras(p, read_scans=True) if p.suffix.lower() == ".conf" else load_cameras(p)
        if cams.points is None or len(cams.points) == 0:
            raise ValueError(f"{p} holds cameras but no points; give a point cloud as INPUT and this file as --cameras")
        pc = cams.point_camera
        if pc is not None and (pc < 0).all():
            pc = None
        return cams.points, None, cams, pc
    points, normals, _ = io.read_points(p)
    return points, normals, None, None


def _input_colors(path: str, cameras) -> "np.ndarray | None":
    """Per-point colours of INPUT (a coloured point cloud, or a scan JSON / COLMAP model with colours)."""
    from o3drbf.io import files as io

    if cameras is not None and getattr(cameras, "colors", None) is not None:
        return cameras.colors
    p = Path(path)
    if p.is_dir() or p.suffix.lower() in _CAMERA_INPUTS:
        return None
    return io.read_points(p)[2]


def _parameters_line(stats) -> str:
    """The parameters used, where each came from, and the automatic rule's reason."""
    params, source = stats.get("parameters", {}), stats.get("parameter_source", {})
    parts = [f"{name} {params[name]:.4g} ({source.get(name, 'given')})" for name in ("delta", "tau", "lambda_surface") if name in params]
    line = ", ".join(parts)
    if stats.get("auto"):
        line += f"\n  auto because     {stats['auto']['reason']}"
    return line


def summary(result, points, input_path, output_path, model_path=None, seconds=None) -> str:
    """The closing summary: what went in, what came out, and how well it fits."""
    from o3drbf.mesh.metrics import fitness_error, mesh_report

    s = result.stats
    fit = fitness_error(points, result.mesh)
    rep = mesh_report(result.mesh)
    scale = result.surface.normalization.scale
    lines = [
        f"o3drbf reconstruct: {input_path} -> {output_path}",
        f"  points           {s['points']:,}" + ("  (normals estimated)" if s["normals_estimated"] else "")
        + (f", {s['outliers_removed']:,} outliers removed" if s.get("outliers_removed") else ""),
        f"  constraints      {s['surface_constraints']:,} surface, {s['exterior_constraints']:,} exterior, {s['sphere_constraints']:,} sphere",
        f"  mean spacing     {s['mean_spacing']:.4g} (data units), {s['mean_spacing_box']:.4f} in the 2x2x2 box",
        f"  basis            {s['basis']}",
        f"  parameters       {_parameters_line(s)}",
        f"  solve            {s['solver']}, {s['solve_seconds']:.2f} s, relative residual {s['residual']:.1e}"
        + (f", {s['iterations']} iterations" if s["iterations"] else ""),
        f"  mesh             {s['triangles']:,} triangles, {s['vertices']:,} vertices, extracted in {s['extract_seconds']:.2f} s",
        f"  watertight       {'yes' if rep['watertight'] else 'NO'} (edge-manifold, closed), Euler characteristic {rep['euler_characteristic']}, {rep['components']} component(s)",
        f"  fitness error    mean {fit['mean']:.3g}, RMS {fit['rms']:.3g}, max {fit['max']:.3g} (data units; mean {fit['mean'] * scale:.2e} in the box)",
    ]
    if s.get("cameras"):
        seen = s["points_seen_per_camera"]
        shown = ", ".join(f"{v:,}" for v in seen[:12]) + (", ..." if len(seen) > 12 else "")
        lines.insert(3, f"  cameras          {s['cameras']}; surface constraints seen per camera: {shown}")
    if model_path:
        lines.append(f"  model            {model_path}")
    if seconds is not None:
        lines.append(f"  total time       {seconds:.1f} s")
    return "\n".join(lines)


# -- argument and failure helpers (used by main) ---------------------------------------


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _check_args(parser, args)
    logging.basicConfig(
        level=logging.INFO if getattr(args, "verbose", False) else logging.WARNING,
        format="o3drbf: %(message)s",
        stream=sys.stderr,
    )
    try:
        if args.command == "reconstruct":
            return _reconstruct(args)
        if args.command == "compare":
            from o3drbf.evaluation.compare import main_compare

            return main_compare(args)
        if args.command == "photos":
            from o3drbf.photo.pipeline import main_photos

            return main_photos(args)
        if args.command == "view":
            try:
                from o3drbf.viewers.app import main_view
            except ImportError as exc:
                raise ImportError(f"o3drbf view needs the viewers package and PyVista ({exc}); pip install 'o3drbf[view]'") from None
            return main_view(args)
    except MemoryError as exc:
        print(f"o3drbf: error: {_memory_message(exc)}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError, RuntimeError, OSError, ImportError) as exc:
        print(f"o3drbf: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # a bug: one line, the traceback with -v
        if getattr(args, "verbose", False):
            import traceback

            traceback.print_exc()
        print(
            f"o3drbf: internal error: {type(exc).__name__}: {_one_line(exc)} (run with -v for the traceback; please report it)",
            file=sys.stderr,
        )
        return 1
    parser.error(f"unknown command {args.command!r}")
    return 2


def _check_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse values argparse's types let through, naming the option (exit 2).

    NaN or infinite numbers for any option, and a negative ``--seed`` or
    ``--sphere-count``.
    """
    import math

    for dest, value in sorted(vars(args).items()):
        option = "--" + dest.replace("_", "-")
        if isinstance(value, float) and not math.isfinite(value):
            parser.error(f"argument {option}: expected a finite number, got {value!r}")
        if dest in ("seed", "sphere_count") and isinstance(value, int) and not isinstance(value, bool) and value < 0:
            parser.error(f"argument {option}: expected a whole number >= 0, got {value}")
        if dest == "seed" and isinstance(value, int) and value >= 2**63:
            parser.error(f"argument {option}: expected a number below 2**63, got {value}")


def _memory_message(exc: MemoryError) -> str:
    """One line: how much memory was asked for, how much is free, and what to change."""
    text = _one_line(exc) if str(exc) else "out of memory"
    free = ""
    try:
        from o3drbf.solvers.base import available_memory

        free = f" ({available_memory() / 2**30:.2f} GiB available)"
    except Exception:  # noqa: BLE001 - the message must not fail
        pass
    return (
        f"out of memory: {text}{free}; use fewer constraints (--surface-count), a coarser --resolution, "
        "or --solver fast, or free memory (nothing was written)"
    )


def check_reconstruct_files(args: argparse.Namespace, points=None) -> "Path":
    """All the file checks of ``reconstruct``, for ``_reconstruct`` to call before any costly step.

    Parameters
    ----------
    args : argparse.Namespace
        ``output``, ``input``, and optionally ``save_model`` and ``cameras``.
    points : (N, 3) array, optional
        The input points, once read: the output format must hold their
        coordinates (:func:`o3drbf.io.files.check_mesh_precision`).

    Returns
    -------
    Path
        The output mesh path.

    Raises
    ------
    ValueError, FileNotFoundError, PermissionError
        One line naming the option and the fix.
    """
    from o3drbf.io import files as io

    out = io.check_output(args.output)
    model = getattr(args, "save_model", None)
    if model and Path(model).suffix != ".npz":
        raise ValueError(f"--save-model must end in .npz, got {model!r}")
    io.check_outputs([out, model], [args.input, getattr(args, "cameras", None)])
    if points is not None:
        io.check_mesh_precision(out, points)
    return out


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
