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
import re
import sys
import time
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import NoReturn

from o3drbf.cli.arguments import add_options, non_negative_int, options_from_args
from o3drbf.io.files import MESH_FORMATS

__all__ = ["main", "run", "build_parser", "check_reconstruct_files", "tiled_summary", "options_from_args", "add_option_arguments"]

log = logging.getLogger("o3drbf")


def add_option_arguments(parser: argparse.ArgumentParser) -> None:
    """The reconstruction options (:func:`o3drbf.cli.arguments.add_options` of ``reconstruct``), and ``--all-points``."""
    groups = add_options(parser, "reconstruct")
    groups["constraints"].add_argument("--all-points", action="store_true", help="use every point as a surface constraint (no subsampling)")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(  # its subcommands' parsers are OneLineParsers too
        prog="o3drbf",
        description="Smooth, closed surfaces from sparse, noisy 3-D points (multi-order RBF volumetric regularization).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    rec = sub.add_parser(
        "reconstruct",
        help="point cloud -> closed mesh",
        description="Reconstruct a closed mesh from a point cloud (PLY, PCD, XYZ, XYZN, LAS, LAZ, E57, ...). "
        "Lengths (offsets, radii, delta, tau, lambda) refer to the data normalized into a 2x2x2 box.",
    )
    rec.add_argument(
        "input",
        help="point cloud file (normals used when present; LAS/LAZ lidar points), or a file that holds points and cameras: "
        "Stanford .conf (range scans), COLMAP text folder, Bundler bundle.out, o3drbf scan .json, E57 scans with poses",
    )
    rec.add_argument("-o", "--output", required=True, help=f"output mesh ({', '.join(MESH_FORMATS)})")
    add_option_arguments(rec)
    g = rec.add_argument_group("input and output")
    g.add_argument("--cameras", metavar="FILE", help="cameras that saw the points (JSON, Middlebury *_par.txt, COLMAP folder, "
                   "bundle.out, .conf): exterior constraints go toward them and points in their observed free space are outliers")
    g.add_argument("--save-model", metavar="FILE.npz", help="also save the implicit function (evaluate it later with o3drbf.ImplicitSurface.load)")
    g.add_argument("--report", metavar="FILE.json", help="also write the closing summary as JSON: counts, parameters, seconds and peak memory per stage")
    g.add_argument("--seed", type=non_negative_int, default=0, help="seed for every random choice (default %(default)s)")
    g.add_argument("--no-color", action="store_true", help="do not colour the mesh from the input points' colours (used when the input has colours)")
    g.add_argument("-q", "--quiet", action="store_true", help="no progress bars or summary")
    g.add_argument("-v", "--verbose", action="store_true", help="log each step")

    from o3drbf.cli.compare import add_compare_arguments
    from o3drbf.cli.photos import add_photos_arguments
    from o3drbf.cli.view import add_view_arguments

    add_compare_arguments(
        sub.add_parser(
            "compare",
            help="run several methods on the same points: tables and a picture",
            description="Run o3drbf's bases and Open3D's Poisson, ball pivoting and alpha shapes on the same data; "
            "write comparison.md/.csv/.json and comparison.png.",
        )
    )

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
    add_view_arguments(view)
    return parser


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

    Examples
    --------
    >>> import contextlib, io, pathlib, tempfile
    >>> from o3drbf.cli.commands import main
    >>> from o3drbf.io.files import write_points
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> _ = write_points(folder / 'sphere.ply', *Sphere(1.0).sample(600, noise=0.002, seed=0))
    >>> main(['reconstruct', str(folder / 'sphere.ply'), '-o', str(folder / 'mesh.ply'), '--resolution', '20', '-q'])
    0
    >>> err = io.StringIO()
    >>> with contextlib.redirect_stderr(err):
    ...     main(['reconstruct', str(folder / 'sphere.ply'), '-o', str(folder / 'mesh.ply'), '--resolutoin', '20'])
    2
    >>> print(err.getvalue().strip())
    o3drbf: error: unknown option --resolutoin; did you mean --resolution?
    """
    from o3drbf.io.files import signal_cleanup

    if argv is None:
        _collect_less()
    try:
        with signal_cleanup():
            return _main(argv)
    except KeyboardInterrupt:
        print("o3drbf: interrupted", file=sys.stderr)
        return 130
    finally:
        if argv is None:
            _leave_for_exit()


def run() -> NoReturn:
    """The console script ``o3drbf`` and ``python -m o3drbf``: :func:`main` on the process's arguments, then
    the end of the process.

    Once the command is done, ``atexit`` handlers run and stdout and stderr are flushed as at any exit; the
    process then ends at once (:func:`os._exit`) instead of tearing the interpreter down, which frees every
    module's objects and runs Open3D's and Numba's library destructors for nothing.  Outputs are closed and
    renamed into place before :func:`main` returns.  Where a thread other than a daemon is still alive, the
    interpreter ends as usual (it waits for that thread).
    """
    code = main()
    import atexit
    import os
    import threading

    if any(t.is_alive() and not t.daemon for t in threading.enumerate() if t is not threading.main_thread()):
        sys.exit(code)
    atexit._run_exitfuncs()  # what the interpreter runs first at its end
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (``| head``): nothing more can be written there
            pass
    os._exit(code)


#: The garbage collector's thresholds in the process of the command line (:func:`gc.set_threshold`;
#: Python's are 700, 10, 10).
COLLECTOR_THRESHOLDS = (20_000, 10, 10)


def _collect_less() -> None:
    """Called when ``main`` runs the process's own command line: the garbage collector's youngest
    generation is collected after :data:`COLLECTOR_THRESHOLDS` new objects instead of 700.

    A command builds few objects that refer to each other but imports many modules (SciPy, Numba,
    Open3D) whose objects each collection walks again; the arrays that hold the data are freed when
    their last reference goes, whatever the collector does.  An in-process caller passes ``argv`` and
    keeps its own thresholds."""
    import gc

    gc.set_threshold(*COLLECTOR_THRESHOLDS)


def _leave_for_exit() -> None:
    """Called when ``main`` ran the process's own command line (``argv=None``: the console script and
    ``python -m o3drbf``), which ends next: every object still alive is moved out of the garbage collector's
    reach (:func:`gc.freeze`), so the interpreter's closing collections do not walk the many objects that
    Numba and SciPy leave behind.  Outputs are already closed and renamed into place by then; ``atexit``
    handlers and the flush of stdout and stderr still run.  An in-process caller passes ``argv`` and keeps a
    collector that frees as usual."""
    import gc

    gc.freeze()


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _reconstruct(args) -> int:
    from dataclasses import replace

    from o3drbf.io import files as io
    from o3drbf.pipeline import reconstruct
    from o3drbf.pointset import read_input

    t0 = time.perf_counter()
    options = options_from_args(args).validate()
    out = check_reconstruct_files(args)
    tiles_auto = args.tiles == "auto"
    if tiles_auto:
        _untiled_if_it_fits(args, io.point_count(args.input))  # from the file header, before reading
    if args.tiles is not None and args.cameras is None:
        vertices = _mapped_input(args.input)
        if vertices is not None:  # a binary PLY with normals, or a lidar file: never read whole
            check_reconstruct_files(args, next(vertices.chunks(100_000))[1])
            return _reconstruct_tiled(args, vertices, options, out, t0)
    from o3drbf.options import check_untiled_fits

    if args.tiles is None:
        check_untiled_fits(io.point_count(args.input))  # from the file header, before reading
    data = read_input(args.input, cameras=args.cameras)
    if tiles_auto and args.tiles is not None:
        _untiled_if_it_fits(args, len(data.points))
    if args.tiles is None:
        check_untiled_fits(len(data.points))
    check_reconstruct_files(args, data.points)
    if args.no_color:
        data = replace(data, colors=None)
    if data.normals is None and data.cameras is None:
        log.warning("%s has no normals: estimating and orienting them with Open3D", args.input)
    if args.tiles is not None:
        return _reconstruct_tiled(args, data, options, out, t0)
    result = reconstruct(data, options=options, seed=args.seed, progress=not args.quiet)
    t_write = time.perf_counter()
    fields = None if result.confidence is None or out.suffix.lower() != ".ply" else {"confidence": result.confidence.confidence}
    io.write_mesh(out, result.mesh_arrays, inputs=[args.input], vertex_fields=fields)
    if args.save_model:
        result.surface.save(args.save_model)
    from o3drbf.pipeline import StageTiming, peak_rss_mb

    result.report.stages.append(StageTiming("write", time.perf_counter() - t_write, peak_rss_mb()))
    checks = None
    if not args.quiet:  # the summary's checks of the mesh, timed as a stage of their own
        t_checks = time.perf_counter()
        checks = summary_checks(result, data.points)
        result.report.stages.append(StageTiming("checks", time.perf_counter() - t_checks, peak_rss_mb()))
    if args.report:
        write_report(args.report, result.report, time.perf_counter() - t0)
    if not args.quiet:
        print(summary(result, data.points, args.input, out, args.save_model, time.perf_counter() - t0, checks))
    return 0


def write_report(path, report, seconds: float) -> None:
    """The report of a run as JSON (NaN as null), ``total_seconds`` from the command's start, written atomically."""
    import json
    import math

    from o3drbf.io.files import atomic_path

    def clean(x):
        if isinstance(x, float):
            return x if math.isfinite(x) else None
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if hasattr(x, "tolist"):
            return clean(x.tolist())
        return x if x is None or isinstance(x, (bool, int, str)) else str(x)

    data = report.as_dict()
    if data.get("robust"):
        data["robust"].pop("constraints", None)  # arrays, not a summary
    data["command_seconds"] = seconds
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(clean(data), indent=1))


def _untiled_if_it_fits(args, n_points) -> None:
    """``--tiles auto`` on an input the untiled path holds: run untiled (``args.tiles = None``), said in one line."""
    if n_points is None:
        return
    from o3drbf.options import untiled_fits, untiled_memory
    from o3drbf.solvers.base import available_memory

    available = available_memory()
    if untiled_fits(n_points, available):
        log.warning("--tiles auto: %s points fit in memory without tiles (about %.1f GiB of %.1f GiB available): running untiled",
                    f"{int(n_points):,}", untiled_memory(n_points) / 2**30, available / 2**30)
        args.tiles = None


def _mapped_input(path):
    """The memory-mapped vertices of a binary PLY with normals, a LAS, LAZ or E57 file read chunk by chunk, else None (read it into memory)."""
    from o3drbf.io.lidar import LIDAR_FORMATS

    if str(path).lower().endswith(LIDAR_FORMATS):
        from o3drbf.cameras.lidar import LidarPoints

        return LidarPoints(path)
    if not str(path).lower().endswith(".ply"):
        return None
    from o3drbf.io.files import open_ply_vertices

    try:
        vertices = open_ply_vertices(path)
    except (ValueError, FileNotFoundError):
        return None  # ascii, lists, no vertices...: read_input reads it or names the problem
    return vertices if vertices.has_normals else None


def _reconstruct_tiled(args, data, options, out, t0) -> int:
    """``--tiles``: the tiled fit and tiled marching cubes (:mod:`o3drbf.tiles`), with the untiled path's stages in every fit."""
    from o3drbf.io import files as io
    from o3drbf.io.files import PlyVertices
    from o3drbf.tiles.run import reconstruct_tiled

    from o3drbf.cameras.lidar import LidarPoints

    mapped = "memory-mapped" if isinstance(data, PlyVertices) else "read chunk by chunk" if isinstance(data, LidarPoints) else ""
    surface, mesh, stats = reconstruct_tiled(data, options=options, seed=args.seed, progress=not args.quiet)
    io.write_mesh(out, mesh, inputs=[args.input])
    if args.save_model:
        surface.save(args.save_model)
    if not args.quiet:
        from o3drbf.mesh.metrics import mesh_report

        print(tiled_summary(stats, args.input, out, time.perf_counter() - t0, mapped, mesh_report(mesh)))
    return 0


def _refits_note(s) -> str:
    """After robust refits, what the solve line's figures are: the final fit's, not the whole fit stage's."""
    rounds = int((s.robust or {}).get("rounds", 0))
    if not rounds:
        return ""
    fit = next((t.seconds for t in s.stages if t.name == "fit"), None)
    return (f" (the final fit's; the fit stage, with the first fit and {rounds} robust refit{'s' if rounds > 1 else ''}, "
            + (f"took {fit:.2f} s)" if fit is not None else "is in the time per stage)"))


def _watertight_line(rep: dict) -> str:
    """The summary's watertight line (from :func:`o3drbf.mesh.metrics.mesh_report`): Open3D's test, topology, pieces."""
    return (f"  watertight       {'yes' if rep['watertight'] else 'NO'} (Open3D's is_watertight: closed, manifold, "
            f"{rep['self_intersections'] or 'no'} self-intersecting triangle pair(s)), "
            f"Euler characteristic {rep['euler_characteristic']}, {rep['components']} component(s)")


def tiled_summary(stats: dict, input_path, output_path, seconds: float, mapped: str = "", report: dict | None = None) -> str:
    """The closing summary of ``reconstruct --tiles``.

    Parameters
    ----------
    stats : dict
        From :func:`o3drbf.tiles.run.reconstruct_tiled`.
    input_path, output_path : path-like
    seconds : float
        Wall time of the whole command.
    mapped : str
        How the points were read without loading the file ("memory-mapped", "read chunk by chunk"), or "".
    report : dict, optional
        :func:`o3drbf.mesh.metrics.mesh_report` of the mesh: adds the
        watertight line of the untiled summary.
    """
    c = stats["constraints"]
    workers = stats["workers"]
    lines = [
        f"o3drbf reconstruct --tiles: {input_path} -> {output_path}",
        f"  points           {stats['points']:,} read, {stats.get('kept', stats['points']):,} kept"
        + (f" ({stats['outliers']:,} removed as outliers)" if stats.get("outliers") else "")
        + (f" ({mapped}, spread to per-tile files)" if mapped else ""),
        *([f"  cameras          {stats['cameras']}: exterior constraints toward them and the free-space outlier test in every tile"]
          if stats.get("cameras") else []),
        *([f"  denoised         in {stats['denoised_tiles']} of {stats['tiles']} tiles (surface constraints moved onto local fits "
           "of the points)"] if stats.get("denoised_tiles") else []),
        f"  tiles            {stats['tiles']}; constraints per tile min {c['min']:,}, median {c['median']:,.0f}, max {c['max']:,}"
        + (f"; {stats['subsampled_tiles']} fitted from a uniform subsample of their points (denser than their constraints need)"
           if stats.get("subsampled_tiles") else ""),
        f"  blend overlap    {stats['overlap']:.0%} of each cell's half-size on every side (at least {stats['min_overlap']:g} box units)",
        f"  mesh             {stats['triangles']:,} triangles, {stats['vertices']:,} vertices",
        *([_watertight_line(report)] if report is not None else []),
        f"  time             fit {stats['fit_seconds']:.1f} s, mesh {stats['extract_seconds']:.1f} s, total {seconds:.1f} s",
        f"  workers          {len(workers)}: " + "; ".join(
            f"{name} {w['tasks']} tasks, {w['seconds']:.1f} s, peak {w['peak_rss'] / 2**30:.2f} GiB" for name, w in workers.items()),
    ]
    return "\n".join(lines)


def _parameters_line(report) -> str:
    """The parameters used, where each came from, and the automatic rule's reason."""
    params, source = report.parameters, report.parameter_source
    parts = [f"{name} {params[name]:.4g} ({source.get(name, 'given')})" for name in ("delta", "tau", "sigma", "lambda_surface") if name in params]
    line = ", ".join(parts)
    if report.auto:
        line += f"\n  auto because     {report.auto['reason']}"
    return line


def summary_checks(result, points) -> dict:
    """The summary's checks of a reconstruction's mesh: ``fitness`` (:func:`o3drbf.mesh.metrics.fitness_error`
    over the kept points) and ``report`` (:func:`o3drbf.mesh.metrics.mesh_report`)."""
    from o3drbf.mesh.metrics import fitness_error, mesh_report

    kept = points if getattr(result, "points", None) is None else result.points  # outliers removed, repeats merged
    mesh = result.mesh_arrays
    return {"fitness": fitness_error(kept, mesh), "report": mesh_report(mesh)}


def summary(result, points, input_path, output_path, model_path=None, seconds=None, checks=None) -> str:
    """The closing summary: what went in, what came out, how well it fits, and where the time went.

    ``checks``: :func:`summary_checks` of ``result`` and ``points`` when already made (else they are made here).
    """
    s = result.report
    kept = points if getattr(result, "points", None) is None else result.points  # outliers removed, repeats merged
    checks = summary_checks(result, points) if checks is None else checks
    fit, rep = checks["fitness"], checks["report"]
    removed = [f"{s.outliers_removed:,} removed as outliers"] * bool(s.outliers_removed) + [
        f"{s.duplicates_merged:,} repeated points merged"] * bool(s.duplicates_merged)
    scale = result.surface.normalization.scale
    colored = result.mesh_arrays.has_vertex_colors()
    lines = [
        f"o3drbf reconstruct: {input_path} -> {output_path}",
        f"  points           {s.input_points or s.points:,} read, {s.points:,} kept" + (f" ({', '.join(removed)})" if removed else "")
        + ("  (normals estimated)" if s.normals_estimated else ""),
        *([f"  normals          {s.normals_repaired}"] if getattr(s, "normals_repaired", "") else []),
        *([f"  registration     {s.registration['reason']}"] if s.registration else []),
        f"  outliers         {s.outliers_removed:,} removed ({s.outlier_method}: {s.outlier_reason})",
        f"  constraints      {s.surface_constraints:,} surface, {s.exterior_constraints:,} exterior, {s.sphere_constraints:,} sphere",
        f"  mean spacing     {s.mean_spacing:.4g} (data units), {s.mean_spacing_box:.4f} in the 2x2x2 box",
        *([f"  denoised         {s.denoised:,} surface constraints moved onto local fits of the points "
           f"(noise {s.noise:.2g} -> {s.constraint_noise:.2g} data units)"] if s.denoised else []),
        f"  basis            {s.basis}",
        f"  parameters       {_parameters_line(s)}",
        f"  solve            {s.solver}, {s.solve_seconds:.2f} s, relative residual {s.residual:.1e}"
        + (f", {s.iterations} iterations" if s.iterations else "") + _refits_note(s),
    ]
    if s.robust:
        r = s.robust
        lines.append(f"  robust fit       {r.get('rounds', 0)} round(s), {r.get('downweighted', 0):,} constraints down-weighted, "
                     f"{r.get('dropped', 0):,} dropped (residual scale {r.get('scale', float('nan')):.2g} box units)")
    lines += [
        f"  mesh             {s.triangles:,} triangles, {s.vertices:,} vertices"
        + (f", {s.resolution} cells on the longest side" if s.resolution else "") + f", extracted in {s.extract_seconds:.2f} s"
        + (f"; {s.specks_removed} speck(s) under two constraint spacings across removed" if s.specks_removed else ""),
        _watertight_line(rep),
        f"  fitness error    over the {len(kept):,} kept points: mean {fit['mean']:.3g}, RMS {fit['rms']:.3g}, max {fit['max']:.3g} "
        f"(data units; mean {fit['mean'] * scale:.2e} in the box)",
    ]
    if colored:
        lines.insert(-2, "  colour           from the input points' colours")
    if s.confidence:
        c = s.confidence
        line = (f"  confidence       mean {c['mean']:.3f}, median {c['median']:.3f}, min {c['min']:.3f} per vertex"
                + (" (PLY vertex property 'confidence')" if str(output_path).lower().endswith(".ply") else ""))
        if c.get("trim") is not None:
            line += (f"\n  trimmed          {c['triangles_removed']:,} triangles with a vertex below {c['trim']:g} removed: "
                     "an open surface where nothing was seen")
        lines.insert(-2, line)
    if s.cameras:
        seen = s.points_seen_per_camera or []
        shown = ", ".join(f"{v:,}" for v in seen[:12]) + (", ..." if len(seen) > 12 else "")
        dropped = getattr(s, "cameras_dropped", None) or []
        lines.insert(2, f"  cameras          {s.cameras}; surface constraints seen per camera: {shown}"
                     + (f"; {len(dropped)} more dropped, inside the data: {', '.join(dropped)}" if dropped else ""))
    if model_path:
        lines.append(f"  model            {model_path}")
    stages = ", ".join(f"{t.name} {t.seconds:.2f}" for t in s.stages)
    lines.append(f"  time per stage   {stages} s; peak memory {max((t.peak_mb for t in s.stages), default=0) / 1024:.2f} GB")
    if seconds is not None:
        lines.append(f"  total time       {seconds:.1f} s")
    return "\n".join(lines)


# -- argument and failure helpers (used by main) ---------------------------------------


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    misspelt = unknown_option_message(parser, argv)  # before argparse's own errors, which print the whole usage
    if misspelt:
        print(f"o3drbf: error: {misspelt}", file=sys.stderr)
        return 2
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        print(f"o3drbf: error: unexpected argument(s) {' '.join(unknown)} (o3drbf {args.command} --help lists the usage)", file=sys.stderr)
        return 2
    _check_args(parser, args)
    logging.basicConfig(level=logging.WARNING, format="o3drbf: %(message)s", stream=sys.stderr)
    from o3drbf.progress import logs_above_bars

    verbose = getattr(args, "verbose", False)
    try:
        # log lines (warnings too) never break into a progress bar; without -v
        # only o3drbf's own lines are shown (not Dask's nor Open3D's chatter)
        with logs_above_bars(), _only_o3drbf_logs(verbose), _open3d_quiet(verbose), _warnings_as_log_lines(), _verbose(verbose):
            return _dispatch(parser, args)
    except MemoryError as exc:
        print(f"o3drbf: error: {_memory_message(exc, getattr(args, 'solver', None))}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError, RuntimeError, OSError, ImportError) as exc:
        print(f"o3drbf: error: {getattr(exc, 'cli_message', None) or _one_line(exc)}", file=sys.stderr)
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
    return 2


def unknown_option_message(parser: argparse.ArgumentParser, argv: list[str]) -> str | None:
    """One line for the first ``--option`` of ``argv`` the command does not know, with the closest valid one; None if all are known.

    ``reconstruct x.ply --surface-cout 10`` -> "unknown option --surface-cout; did you mean --surface-count?"
    (:func:`difflib.get_close_matches` over the command's options).  A unique prefix of an
    option is known, as argparse takes it; everything after ``--`` is a value.
    """
    import difflib

    command = parser
    sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
    name = next((a for a in argv if not a.startswith("-")), None)
    if sub is not None and name in sub.choices:
        command = sub.choices[name]
    elif sub is not None and name is not None:  # a misspelt command: its options would be judged against the wrong parser
        return f"unknown command {name}{did_you_mean(name, list(sub.choices))} ({parser.prog} --help lists the commands)"
    options = sorted({o for a in command._actions for o in a.option_strings if o.startswith("--")})
    for arg in argv:
        if arg == "--":
            break
        if not arg.startswith("--"):
            continue
        word = arg.split("=", 1)[0]
        if word in options or sum(o.startswith(word) for o in options) == 1:
            continue
        if sum(o.startswith(word) for o in options) > 1:
            continue  # ambiguous: argparse names the candidates
        close = difflib.get_close_matches(word, options, n=1, cutoff=0.6)
        if close:
            return f"unknown option {word}; did you mean {close[0]}?"
        return f"unknown option {word} ({command.prog} --help lists the options)"
    return None


def did_you_mean(word: str, choices: list[str]) -> str:
    """``"; did you mean CLOSEST?"`` for the choice :func:`difflib.get_close_matches` finds closest to ``word``, else ``""``."""
    import difflib

    close = difflib.get_close_matches(word, choices, n=1, cutoff=0.6)
    return f"; did you mean {close[0]}?" if close else ""


#: argparse's message for a value outside ``choices=`` (quotes around the words in Python 3.11-3.13, none in 3.14).
_INVALID_CHOICE = re.compile(r"^(argument (?P<argument>[^:]+): )?invalid choice: '?(?P<value>[^']*?)'? \(choose from (?P<choices>.*)\)$")


class OneLineParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose usage errors are one line on stderr, exit 2.

    argparse prints the whole usage above its message; here the message alone, the closest valid
    value for an invalid choice (``argument --solver: invalid choice dens; did you mean dense?``,
    ``unknown command reconstrct; did you mean reconstruct?``), and where the usage is.

    Examples
    --------
    >>> import contextlib, io
    >>> parser = OneLineParser(prog="tool")
    >>> _ = parser.add_argument("--solver", choices=["dense", "fast"])
    >>> err = io.StringIO()
    >>> with contextlib.redirect_stderr(err):
    ...     try:
    ...         parser.parse_args(["--solver", "dens"])
    ...     except SystemExit as exit:
    ...         print(exit.code)
    2
    >>> print(err.getvalue().strip())
    o3drbf: error: argument --solver: invalid choice dens; did you mean dense? (choose from dense, fast)
    """

    def error(self, message: str):
        self.exit(2, f"o3drbf: error: {self.one_line(message)}\n")

    def one_line(self, message: str) -> str:
        """argparse's ``message`` as the line :meth:`error` prints (without the ``o3drbf: error:`` prefix)."""
        message = " ".join(str(message).split())
        commands = next((list(a.choices) for a in self._actions if isinstance(a, argparse._SubParsersAction)), None)
        if commands and message == "the following arguments are required: COMMAND":
            return f"no command given: choose from {', '.join(commands)} ({self.prog} --help lists the usage)"
        bad = _INVALID_CHOICE.match(message)
        if bad is None:
            return f"{message} ({self.prog} --help lists the usage)"
        value, argument = bad["value"], bad["argument"]
        choices = [c.strip().strip("'") for c in bad["choices"].split(",")]
        if argument in (None, "COMMAND"):
            return f"unknown command {value}{did_you_mean(value, choices)} ({self.prog} --help lists the commands)"
        return f"argument {argument}: invalid choice {value}{did_you_mean(value, choices)} (choose from {', '.join(choices)})"


class _OnlyO3drbf(logging.Filter):
    """Pass o3drbf's own records, and other libraries' errors."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.name == "o3drbf" or record.name.startswith("o3drbf.") or record.levelno >= logging.ERROR


@contextmanager
def _only_o3drbf_logs(verbose: bool):
    """Without -v, the log handlers show only o3drbf's lines: Dask's cluster start and stop
    (some 30 INFO and WARNING lines) and other libraries' records that propagate to the root
    logger are dropped; with -v everything is shown."""
    handlers = [] if verbose else list(logging.getLogger().handlers)
    only = _OnlyO3drbf()
    for handler in handlers:
        handler.addFilter(only)
    try:
        yield
    finally:
        for handler in handlers:
            handler.removeFilter(only)


@contextmanager
def _open3d_quiet(verbose: bool):
    """Open3D's own messages (printed straight to stdout, e.g. "Write OBJ can not include triangle
    normals") at Error level while a command runs, Warning with -v; restored after.  Set when the command
    imports Open3D (:func:`o3drbf.startup.when_imported`): a reconstruction of a scan to a .ply never does."""
    from o3drbf.startup import when_imported

    before = []

    def quiet(o3d):
        before.append((o3d, o3d.utility.get_verbosity_level()))
        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Warning if verbose else o3d.utility.VerbosityLevel.Error)

    try:
        with when_imported("open3d", quiet):
            yield
    finally:
        for o3d, level in before:
            o3d.utility.set_verbosity_level(level)


@contextmanager
def _verbose(on: bool):
    """o3drbf's logger at INFO while a command runs (restored after: main() may be called again)."""
    previous = log.level
    if on:
        log.setLevel(logging.INFO)
    try:
        yield
    finally:
        log.setLevel(previous)


@contextmanager
def _warnings_as_log_lines():
    """Python warnings as one log line each (``o3drbf: ConvergenceWarning: ...``), through the logging the bars respect."""
    previous = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        log.warning("%s: %s", category.__name__, _one_line(message) if isinstance(message, BaseException) else " ".join(str(message).split()))

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = previous


def _dispatch(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from o3drbf.options import PARAMETER_RANGES, check_parameter_range

    for name in PARAMETER_RANGES:  # before any file is read, for every command that has the option
        value = getattr(args, name, None)
        if isinstance(value, (int, float)) and value > 0:  # zero and negatives: the kernel's own message
            check_parameter_range(name, value)
    if args.command == "reconstruct":
        return _reconstruct(args)
    if args.command == "compare":
        from o3drbf.cli.compare import main_compare

        return main_compare(args)
    if args.command == "photos":
        from o3drbf.cli.photos import main_photos

        return main_photos(args)
    if args.command == "view":
        from o3drbf.cli.view import main_view

        return main_view(args)
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


def _memory_message(exc: MemoryError, solver: str | None = None) -> str:
    """One line: how much memory was asked for, how much is free, and what to change.

    A refusal made up front (:class:`o3drbf.solvers.MemoryRefusal`) says what
    it knows: the need, the limit, and its own command-line fix; any other
    MemoryError gets the general advice (``--solver fast`` only when the
    solver was ``dense``)."""
    free = ""
    try:
        from o3drbf.solvers.base import available_memory

        free = f" ({available_memory() / 2**30:.2f} GiB available)"
    except Exception:  # noqa: BLE001 - the message must not fail
        pass
    from o3drbf.solvers.base import MemoryRefusal

    if isinstance(exc, MemoryRefusal) and exc.cli_hint:
        return f"out of memory: {exc.message(exc.cli_hint, free)} (refused before the fit; nothing was written)"
    text = _one_line(exc) if str(exc) else "out of memory"
    solver_hint = ", --solver fast" if solver == "dense" else ""
    return (
        f"out of memory: {text}{free}; use fewer constraints (--surface-count), a coarser --resolution{solver_hint}, "
        "--tiles auto, or free memory (nothing was written)"
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
    if getattr(args, "confidence", False) and out.suffix.lower() != ".ply":
        raise ValueError(f"--confidence writes a PLY vertex property, but the output is {out.suffix or 'without extension'}; use a .ply output")
    model = getattr(args, "save_model", None)
    if model and Path(model).suffix != ".npz":
        raise ValueError(f"--save-model must end in .npz, got {model!r}")
    report = getattr(args, "report", None)
    if report and Path(report).suffix.lower() != ".json":
        raise ValueError(f"--report must end in .json, got {report!r}")
    io.check_outputs([out, model, report], [args.input, getattr(args, "cameras", None)])
    if points is not None:
        io.check_mesh_precision(out, points)
    return out


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
