"""Start-up and machine-readable reports: what a user's first seconds and a benchmark rely on."""

import json
import os
import subprocess
import sys

import pytest

from o3drbf.cli.commands import main
from o3drbf.io.files import write_points
from o3drbf.synthetic.shapes import Sphere


def _python(code: str) -> str:
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def test_importing_o3drbf_and_open3d_leaves_dash_and_plotly_unloaded_until_used():
    out = _python(
        "import sys, o3drbf, open3d\n"
        "print('dash' in sys.modules, 'plotly' in sys.modules)\n"
        "from o3drbf.startup import PLOTLY_MODULE\n"
        "stand_in = sys.modules[PLOTLY_MODULE]\n"
        "go = stand_in.go  # first use: the real module\n"
        "real = sys.modules[PLOTLY_MODULE]\n"
        "print('dash' in sys.modules, real is not stand_in, open3d.visualization.draw_plotly is real.draw_plotly,\n"
        "      getattr(real, '__o3drbf_stand_in__', False))\n"
    )
    assert out.split() == ["False", "False", "True", "True", "True", "False"], out


def test_open3d_imported_first_is_left_alone():
    out = _python(
        "import sys, open3d, o3drbf\n"
        "from o3drbf.startup import PLOTLY_MODULE, defer_open3d_plotly\n"
        "print('dash' in sys.modules, defer_open3d_plotly(), getattr(sys.modules[PLOTLY_MODULE], '__o3drbf_stand_in__', False))\n"
    )
    assert out.split() == ["True", "False", "False"], out


def test_report_json_has_the_summary_and_every_stage(tmp_path):
    p, n = Sphere(1.0).sample(1200, seed=3)
    write_points(tmp_path / "sphere.ply", p, n)
    report = tmp_path / "run.json"
    assert main(["reconstruct", str(tmp_path / "sphere.ply"), "-o", str(tmp_path / "m.ply"), "-q", "--report", str(report)]) == 0
    data = json.loads(report.read_text())
    names = [s["name"] for s in data["stages"]]
    assert names[0] == "read" and names[-1] == "write" and {"fit", "extract"} <= set(names)
    assert all(s["seconds"] >= 0 and s["peak_mb"] > 0 for s in data["stages"])
    assert data["points"] == 1200 and data["surface_constraints"] > 0 and data["triangles"] > 0
    assert data["command_seconds"] >= sum(s["seconds"] for s in data["stages"])


def test_summary_checks_are_a_stage_of_their_own(tmp_path, capsys):
    """Without ``-q`` the closing summary's checks of the mesh are timed as the last stage, in the report and the summary."""
    p, n = Sphere(1.0).sample(1200, seed=3)
    write_points(tmp_path / "sphere.ply", p, n)
    report = tmp_path / "run.json"
    assert main(["reconstruct", str(tmp_path / "sphere.ply"), "-o", str(tmp_path / "m.ply"), "--report", str(report)]) == 0
    names = [s["name"] for s in json.loads(report.read_text())["stages"]]
    assert names[-2:] == ["write", "checks"]
    line = next(x for x in capsys.readouterr().out.splitlines() if "time per stage" in x)
    assert ", write " in line and ", checks " in line


@pytest.mark.parametrize("name", ["run.txt", "sphere.ply"])
def test_report_must_be_a_new_json_file(tmp_path, capsys, name):
    p, n = Sphere(1.0).sample(300, seed=3)
    write_points(tmp_path / "sphere.ply", p, n)
    before = (tmp_path / "sphere.ply").read_bytes()
    code = main(["reconstruct", str(tmp_path / "sphere.ply"), "-o", str(tmp_path / "m.ply"), "--report", str(tmp_path / name)])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ("--report" in err[0] or "input" in err[0]), err
    assert (tmp_path / "sphere.ply").read_bytes() == before and not (tmp_path / "m.ply").exists()


def test_set_up_warm_up_leaves_nothing_to_compile_on_a_first_run(tmp_path):
    """``scripts/warm_up.py`` (run by ``make setup``) caches every kernel a default run with its summary uses:
    points with normals on the dense solver and on the fast one (larger clouds), and a range scan with cameras."""
    from pathlib import Path

    import open3d as o3d

    from o3drbf.synthetic.scans import range_scans, write_scan_json

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    warm = subprocess.run([sys.executable, str(root / "scripts" / "warm_up.py")], capture_output=True, text=True, env=env, timeout=900)
    assert warm.returncode == 0, warm.stderr[-2000:]
    p, n = Sphere(1.0).sample(2000, seed=5)
    write_points(tmp_path / "sphere.ply", p, n)
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.8, 30)
    points, owner, cameras = range_scans(sphere, n_views=3, width=60, height=45, seed=2)
    scan = write_scan_json(tmp_path / "scan.json", points, cameras, point_camera=owner)
    runs = [[str(tmp_path / "sphere.ply")], [str(tmp_path / "sphere.ply"), "--solver", "fast"], [str(scan)]]
    code = (
        "import gc, sys\n"
        "from numba.core.registry import CPUDispatcher\n"
        "from o3drbf.cli import main\n"
        f"for args in {runs!r}:\n"
        f"    assert main(['reconstruct', *args, '-o', {str(tmp_path / 'm.ply')!r}]) == 0, args\n"
        "compiled = sorted(f'{d.py_func.__module__}.{d.__name__}' for d in gc.get_objects()\n"
        "                  if isinstance(d, CPUDispatcher) and d.py_func.__module__.startswith('o3drbf') and d.stats.cache_misses)\n"
        "print('COMPILED', *compiled, file=sys.stderr)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    compiled = run.stderr.rsplit("COMPILED", 1)[1].split()
    assert compiled == [], f"compiled on the first run after set-up: {compiled}"
    # Nor does Python compile o3drbf's sources (which it cannot cache itself where PYTHONDONTWRITEBYTECODE is set):
    # every module has bytecode stamped with its source's current modification time and size.
    import importlib.util

    stale = []
    for source in [*(root / "o3drbf").rglob("*.py"), *(root / "viewers").rglob("*.py")]:
        cached = Path(importlib.util.cache_from_source(str(source)))
        head = cached.read_bytes()[:16] if cached.exists() else b""
        stat = source.stat()
        if len(head) < 16 or int.from_bytes(head[8:12], "little") != int(stat.st_mtime) & 0xFFFFFFFF \
                or int.from_bytes(head[12:16], "little") != stat.st_size & 0xFFFFFFFF:
            stale.append(str(source.relative_to(root)))
    assert stale == [], f"no current bytecode after set-up: {stale[:5]} ({len(stale)} modules)"


def test_import_o3drbf_is_light_and_every_public_name_resolves():
    out = _python(
        "import sys, o3drbf\n"
        "print(*(m in sys.modules for m in ('scipy', 'numba', 'open3d')))\n"
        "missing = [n for n in o3drbf.__all__ if getattr(o3drbf, n, None) is None]\n"
        "print(len(o3drbf.__all__), missing, set(o3drbf.__all__) <= set(dir(o3drbf)))\n"
        "from o3drbf import reconstruct, MultiOrder\n"
        "print(reconstruct.__module__.startswith('o3drbf.pipeline'), MultiOrder is o3drbf.MultiOrder)\n"
    )
    lines = out.splitlines()
    assert lines[0].split() == ["False", "False", "False"], out
    assert lines[1].endswith("[] True") and int(lines[1].split()[0]) > 20, out
    assert lines[2].split() == ["True", "True"], out


def test_help_loads_no_compiled_kernels_nor_scipy():
    """``o3drbf --help`` and ``o3drbf reconstruct --help`` build every parser (their help names the code's
    constants, e.g. the solver switch) without importing Numba, SciPy or Open3D: it answers at once."""
    out = _python(
        "import contextlib, io, sys\n"
        "from o3drbf.cli import main\n"
        "for argv in (['--help'], ['reconstruct', '--help']):\n"
        "    with contextlib.redirect_stdout(io.StringIO()) as text, contextlib.suppress(SystemExit):\n"
        "        main(argv)\n"
        "    assert 'usage' in text.getvalue()\n"
        "print(*(m in sys.modules for m in ('numba', 'scipy', 'open3d')))\n"
    )
    assert out.split() == ["False", "False", "False"], out


def test_log_lines_go_above_the_bars_without_tqdms_notebook_parts(tmp_path):
    """The command line writes its log lines through ``tqdm.write`` (above any bar) and, outside IPython,
    draws plain tqdm bars: neither tqdm's notebook module nor asyncio is imported."""
    p, _ = Sphere(1.0).sample(800, seed=3)
    write_points(tmp_path / "s.ply", p)  # no normals: a warning line
    code = (
        "import sys\n"
        "import tqdm.std as T\n"
        "write = T.tqdm.write.__func__\n"
        "T.tqdm.write = classmethod(lambda cls, s, file=None, end='\\n', nolock=False: write(cls, '[tqdm] ' + s, file, end, nolock))\n"
        "from o3drbf.cli.commands import main\n"
        f"rc = main(['reconstruct', {str(tmp_path / 's.ply')!r}, '-o', {str(tmp_path / 'm.ply')!r}])\n"
        "print(rc, 'asyncio' in sys.modules, 'tqdm.auto' in sys.modules)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "O3DRBF_NO_PROGRESS": "0"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split()[-3:] == ["0", "False", "False"], proc.stdout[-500:]
    assert any(x.startswith("[tqdm] o3drbf: ") and "no normals" in x for x in proc.stderr.splitlines()), proc.stderr[-2000:]


def test_the_process_command_line_collects_less_and_freezes_the_collector_at_the_end_an_in_process_call_does_not(tmp_path):
    # argv=None (the console script, python -m o3drbf): the collector's thresholds raised for the command,
    # gc.freeze() once it is done, and the outputs are whole; an in-process call with argv leaves the
    # collector as it was.
    p, n = Sphere(1.0).sample(300, seed=3)
    write_points(tmp_path / "sphere.ply", p, n)
    args = ["reconstruct", str(tmp_path / "sphere.ply"), "-o", str(tmp_path / "m.ply"), "--resolution", "16", "-q"]
    args2 = ["o3drbf"] + args[:3] + [str(tmp_path / "m2.ply")] + args[4:]
    out = _python(
        "import gc, sys\n"
        "from o3drbf.cli.commands import main\n"
        f"print(main({args!r}), gc.get_freeze_count(), gc.get_threshold() == (700, 10, 10))\n"
        f"sys.argv = {args2!r}\n"
        "code = main()\n"
        "from o3drbf.cli.commands import COLLECTOR_THRESHOLDS\n"
        "print(code, gc.get_freeze_count() > 0, gc.get_threshold() == COLLECTOR_THRESHOLDS != (700, 10, 10))\n"
    )
    assert out.split() == ["0", "0", "True", "0", "True", "True"], out
    import open3d as o3d

    for name in ("m.ply", "m2.ply"):
        mesh = o3d.io.read_triangle_mesh(str(tmp_path / name))
        assert len(mesh.triangles) > 0 and mesh.is_watertight()


@pytest.mark.parametrize("thread", [False, True])
def test_the_console_script_ends_the_process_after_atexit_without_tearing_the_interpreter_down(tmp_path, thread):
    # run(): atexit handlers run and the output is whole, but the interpreter's teardown (which flushes a file
    # object left open) is skipped; with a non-daemon thread still alive the interpreter ends as usual.
    p, n = Sphere(1.0).sample(300, seed=3)
    write_points(tmp_path / "sphere.ply", p, n)
    argv = ["o3drbf", "reconstruct", str(tmp_path / "sphere.ply"), "-o", str(tmp_path / "m.ply"), "--resolution", "16", "-q"]
    left_open = tmp_path / "left_open.txt"
    code = (
        "import atexit, os, sys, threading, time\n"
        f"left_open = open({str(left_open)!r}, 'w')\n"
        "left_open.write('teardown')\n"
        "atexit.register(print, 'atexit')\n"
        + (f"threading.Thread(target=lambda: [time.sleep(0.05) for _ in iter(lambda: os.path.exists({str(tmp_path / 'm.ply')!r}), True)]).start()\n"
           if thread else "")  # alive until the command has written its output
        + f"sys.argv = {argv!r}\n"
        "from o3drbf.cli import run\n"
        "run()\n"
        "print('after run')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["atexit"], proc.stdout
    assert left_open.read_text() == "teardown" * thread
    import open3d as o3d

    assert o3d.io.read_triangle_mesh(str(tmp_path / "m.ply")).is_watertight()
    bad = subprocess.run([sys.executable, "-m", "o3drbf", "reconstruct", str(tmp_path / "none.ply"), "-o", str(tmp_path / "n.ply")],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and bad.stderr.strip().startswith("o3drbf: error: input file not found"), bad.stderr


def test_the_command_line_turns_numpys_huge_page_advice_off_unless_the_user_set_it():
    code = "import o3drbf.cli, numpy, os; print(numpy._core.multiarray._get_madvise_hugepage(), os.environ.get('NUMPY_MADVISE_HUGEPAGE'))"
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    off = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    kept = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**env, "NUMPY_MADVISE_HUGEPAGE": "1"}, timeout=120)
    first = subprocess.run([sys.executable, "-c", "import numpy\n" + code.replace("; print", "\nprint")], capture_output=True, text=True, env=env,
                           timeout=120)
    assert off.stdout.split() == ["False", "0"], off.stderr[-500:]
    assert kept.stdout.split() == ["True", "1"], kept.stderr[-500:]
    assert first.stdout.split() == ["True", "None"], first.stderr[-500:]  # NumPy imported first: left alone


@pytest.mark.parametrize("numba_first", [False, True])
def test_numba_runs_on_its_workqueue_whichever_compiled_module_runs_first(numba_first):
    """The self-intersection count (parallel Numba) run before any RBF module: Numba's default order
    tries TBB first, and an old system TBB prints a warning to the user's terminal; o3drbf's order
    is set at ``import o3drbf``, also when the program imported Numba before it."""
    out = _python(
        "import warnings\n"
        "warnings.simplefilter('error')\n"  # any warning (the TBB one included) fails the run
        + ("import numba\n" if numba_first else "")
        + "import numpy as np\n"
        "from o3drbf.mesh.intersections import self_intersecting_pairs\n"
        "import numba\n"
        "v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)\n"
        "t = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])\n"
        "print(len(self_intersecting_pairs(v, t)), numba.threading_layer())\n"
    )
    assert out.split() == ["0", "workqueue"], out


def test_a_users_threading_layer_is_kept():
    proc = subprocess.run([sys.executable, "-c", "import o3drbf, os; print(os.environ['NUMBA_THREADING_LAYER_PRIORITY'])"],
                          capture_output=True, text=True, timeout=300,
                          env={**os.environ, "NUMBA_THREADING_LAYER_PRIORITY": "omp workqueue tbb"})
    assert proc.returncode == 0 and proc.stdout.split() == ["omp", "workqueue", "tbb"], proc.stderr[-2000:]


def test_numbas_set_up_runs_in_a_thread_once_started_by_the_pipeline(monkeypatch):
    # In a new process the thread installs Numba's registries (numba.np.arraymath is one of the modules it
    # imports), is a daemon, and is the same thread on a second call.
    out = _python(
        "import sys, numba, o3drbf\n"
        "from o3drbf.startup import ready_numba_in_background\n"
        "before = 'numba.np.arraymath' in sys.modules\n"
        "t = ready_numba_in_background(); t.join()\n"
        "print(before, 'numba.np.arraymath' in sys.modules, ready_numba_in_background() is t, t.daemon)\n"
    )
    assert out.split() == ["False", "True", "True", "True"], out
    import o3drbf
    import o3drbf.pipeline.run as run

    calls = []
    monkeypatch.setattr(run, "ready_numba_in_background", lambda: calls.append(1))
    p, n = Sphere(1.0).sample(400, seed=1)
    o3drbf.reconstruct(p, n, surface_count=150, resolution=12)
    assert calls == [1]


def test_a_scan_reconstructed_to_a_ply_never_imports_open3d_and_gives_the_apis_mesh(tmp_path):
    """``o3drbf reconstruct scan.json -o mesh.ply`` (with its summary) never imports Open3D (a large part of a
    short run's start-up); the file holds, to the bit, the mesh ``reconstruct`` gives a Python caller as an
    Open3D mesh, and Open3D reads it back so."""
    import numpy as np
    import open3d as o3d

    import o3drbf
    from o3drbf.pointset import read_input
    from o3drbf.synthetic.scans import range_scans, write_scan_json

    sphere = o3d.geometry.TriangleMesh.create_sphere(0.8, 30)
    points, owner, cameras = range_scans(sphere, n_views=3, width=60, height=45, seed=2)
    scan = write_scan_json(tmp_path / "scan.json", points, cameras, point_camera=owner)
    out = tmp_path / "m.ply"
    code = (
        "import sys\n"
        "from o3drbf.cli import main\n"
        f"assert main(['reconstruct', {str(scan)!r}, '-o', {str(out)!r}]) == 0\n"
        "print('OPEN3D', 'open3d' in sys.modules)\n"
    )
    printed = _python(code)
    assert "watertight       yes" in printed and printed.split("OPEN3D")[1].split() == ["False"], printed[-1500:]
    mesh = o3drbf.reconstruct(read_input(str(scan))).mesh
    assert isinstance(mesh, o3d.geometry.TriangleMesh)
    back = o3d.io.read_triangle_mesh(str(out))
    for name in ("vertices", "triangles", "vertex_normals"):
        assert np.array_equal(np.asarray(getattr(back, name)), np.asarray(getattr(mesh, name))), name


def test_when_imported_runs_its_callback_once_the_module_has_run(tmp_path, monkeypatch):
    """The hook the command line sets Open3D's verbosity with: the callback sees the module after its code ran,
    at once when it is imported already, and not after the block."""
    from o3drbf.startup import when_imported

    (tmp_path / "o3drbf_probe_a.py").write_text("VALUE = 7\n")
    (tmp_path / "o3drbf_probe_b.py").write_text("VALUE = 8\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    seen = []
    with when_imported("o3drbf_probe_a", lambda m: seen.append(("a", m.VALUE))):
        assert seen == []
        import o3drbf_probe_a  # noqa: F401
    assert seen == [("a", 7)]
    with when_imported("o3drbf_probe_a", lambda m: seen.append(("again", m.VALUE))):
        pass
    with when_imported("o3drbf_probe_b", lambda m: seen.append(("b", m.VALUE))):
        pass
    import o3drbf_probe_b  # noqa: F401
    assert seen == [("a", 7), ("again", 7)]
    monkeypatch.delitem(sys.modules, "o3drbf_probe_a")
    monkeypatch.delitem(sys.modules, "o3drbf_probe_b")
