"""The command line: success path, summary, exit codes, safety of files."""

import subprocess
import sys

import numpy as np
import open3d as o3d
import pytest

from o3drbf.cli.commands import main
from o3drbf.io.files import write_points
from o3drbf.synthetic.shapes import Torus


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    p, n = Torus(0.6, 0.25).sample(4000, noise=0.002, seed=1)
    write_points(d / "torus.ply", p, n)
    write_points(d / "torus.xyz", p)
    return d


def test_reconstruct_writes_mesh_model_and_summary(scan, capsys):
    out = scan / "mesh.ply"
    code = main(["reconstruct", str(scan / "torus.ply"), "-o", str(out), "--surface-count", "800",
                 "--resolution", "48", "--save-model", str(scan / "model.npz")])
    assert code == 0
    text = capsys.readouterr().out
    for key in ("points           4,000", "surface", "exterior", "mean spacing", "relative residual", "triangles", "watertight       yes", "fitness error"):
        assert key in text, key
    assert "the final fit's" not in text  # no robust refit: the solve line is the whole fit's
    mesh = o3d.io.read_triangle_mesh(str(out))
    assert len(mesh.triangles) > 1000 and mesh.is_edge_manifold()
    assert (scan / "model.npz").exists()
    leftovers = [f for f in scan.iterdir() if f.name.startswith(".")]
    assert leftovers == []  # atomic writes leave no temporaries


@pytest.mark.parametrize("ext", [".obj", ".stl"])
def test_output_format_follows_extension(scan, ext):
    out = scan / f"mesh{ext}"
    assert main(["reconstruct", str(scan / "torus.ply"), "-o", str(out), "--surface-count", "300", "--resolution", "24", "-q"]) == 0
    assert len(o3d.io.read_triangle_mesh(str(out)).triangles) > 100


def test_surface_radius_and_all_points(scan, capsys):
    out = scan / "radius.ply"
    assert main(["reconstruct", str(scan / "torus.ply"), "-o", str(out), "--surface-radius", "0.1", "--resolution", "24"]) == 0
    text = capsys.readouterr().out
    n = int(text.split("constraints")[1].split("surface")[0].replace(",", ""))
    # torus area in the box ~ 4 pi^2 R r scaled; discs of radius 0.05 are disjoint: n < area / (pi 0.05^2)
    assert 150 < n < 1100
    assert main(["reconstruct", str(scan / "torus.ply"), "-o", str(out), "--all-points", "--resolution", "24", "--solver", "dense"]) == 0
    assert "4,000 surface" in capsys.readouterr().out


def test_points_without_normals(scan, capsys, caplog):
    out = scan / "nonormals.ply"
    assert main(["reconstruct", str(scan / "torus.xyz"), "-o", str(out), "--surface-count", "400", "--resolution", "32"]) == 0
    assert "normals estimated" in capsys.readouterr().out
    assert "has no normals: estimating and orienting" in caplog.text


@pytest.mark.parametrize(
    "args,message",
    [
        (["{d}/missing.ply", "-o", "{d}/x.ply"], "input file not found"),
        (["{d}/torus.ply", "-o", "{d}/torus.ply"], "is the input file"),
        (["{d}/torus.ply", "-o", "{d}/x.docx"], "unsupported extension"),
        (["{d}/torus.ply", "-o", "{d}/nofolder/x.ply"], "output folder does not exist"),
        (["{d}/torus.ply", "-o", "{d}/x.ply", "--delta", "-3"], "delta must be"),
        (["{d}/torus.ply", "-o", "{d}/x.ply", "--lambda-surface", "-1"], "lambda_surface must be"),
        (["{d}/empty.ply", "-o", "{d}/x.ply"], "no points (truncated or empty file)"),
        (["{d}/garbage.ply", "-o", "{d}/x.ply"], "not a PLY file"),
        (["{d}/torus.ply", "-o", "{d}/x.ply", "--save-model", "{d}/m.txt"], "must end in .npz"),
    ],
)
def test_bad_input_exits_2_with_one_line(scan, capsys, args, message):
    (scan / "empty.ply").write_text("")
    (scan / "garbage.ply").write_bytes(b"\x00\x01 not a ply")
    before = (scan / "torus.ply").read_bytes()
    code = main(["reconstruct", *[a.format(d=scan) for a in args], "-q"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert message in err and err.startswith("o3drbf: error:") and "\n" not in err
    assert (scan / "torus.ply").read_bytes() == before  # the input is never touched


def test_usage_errors_and_entry_point(scan):
    with pytest.raises(SystemExit) as e:
        main(["reconstruct", str(scan / "torus.ply")])  # no -o
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        main(["reconstruct", str(scan / "torus.ply"), "-o", "x.ply", "--surface-count", "0"])
    assert e.value.code == 2
    done = subprocess.run([sys.executable, "-m", "o3drbf.cli", "--version"], capture_output=True, text=True)
    assert done.returncode == 0 and "o3drbf" in done.stdout


@pytest.mark.parametrize("argv, expected", [
    (["reconstruct", "x.ply", "--surface-cout", "10"], "o3drbf: error: unknown option --surface-cout; did you mean --surface-count?"),
    (["reconstruct", "x.ply", "-o", "m.ply", "--lamda-surface=0.1"], "o3drbf: error: unknown option --lamda-surface; did you mean --lambda-surface?"),
    (["compare", "x.ply", "--metods", "poisson"], "o3drbf: error: unknown option --metods; did you mean --methods?"),
    (["view", "x.ply", "--resolutoin", "32"], "o3drbf: error: unknown option --resolutoin; did you mean --resolution?"),
    (["reconstruct", "x.ply", "-o", "m.ply", "--zzzz"], "o3drbf: error: unknown option --zzzz (o3drbf reconstruct --help lists the options)"),
])
def test_a_misspelt_option_is_one_line_with_a_suggestion(argv, expected, capsys):
    """Not argparse's whole usage: one line naming the option and the closest valid one, exit 2 (before the missing -o is reported)."""
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.err == expected + "\n" and captured.out == ""


@pytest.mark.parametrize("argv, expected", [
    (["reconstrct", "x.ply", "-o", "m.ply", "--resolution", "64"],
     "o3drbf: error: unknown command reconstrct; did you mean reconstruct? (o3drbf --help lists the commands)"),
    (["veiw", "x.ply"], "o3drbf: error: unknown command veiw; did you mean view? (o3drbf --help lists the commands)"),
    (["zzz"], "o3drbf: error: unknown command zzz (o3drbf --help lists the commands)"),
    (["reconstruct", "x.ply", "-o", "m.ply", "--solver", "dens"],
     "o3drbf: error: argument --solver: invalid choice dens; did you mean dense? (choose from auto, dense, iterative, fast)"),
    (["reconstruct", "x.ply"], "o3drbf: error: the following arguments are required: -o/--output (o3drbf reconstruct --help lists the usage)"),
    ([], "o3drbf: error: no command given: choose from reconstruct, compare, photos, view (o3drbf --help lists the usage)"),
])
def test_usage_errors_are_one_line_with_a_suggestion(argv, expected, capsys):
    """A misspelt command or choice, a missing argument: one line (no usage block), the closest valid word (difflib), exit 2."""
    try:
        code = main(argv)
    except SystemExit as e:  # argparse's errors exit; a misspelt command is caught before argparse, returned
        code = e.code
    assert code == 2
    captured = capsys.readouterr()
    assert captured.err == expected + "\n" and captured.out == ""


def test_a_unique_prefix_of_an_option_is_still_accepted(scan, tmp_path):
    out = tmp_path / "prefix.ply"
    assert main(["reconstruct", str(scan / "torus.ply"), "-o", str(out), "--surface-c", "300", "--resol", "24", "-q"]) == 0


def test_outputs_get_ordinary_permissions(scan):
    import os
    import stat

    out = scan / "perm.ply"
    assert main(["reconstruct", str(scan / "torus.ply"), "-o", str(out), "--surface-count", "300", "--resolution", "24", "-q"]) == 0
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~umask


def test_compare_subcommand(scan, tmp_path, capsys):
    truth = o3d.geometry.TriangleMesh.create_torus(0.6, 0.25, 60, 30)
    o3d.io.write_triangle_mesh(str(tmp_path / "truth.ply"), truth)
    out = tmp_path / "cmp"
    code = main(["compare", str(scan / "torus.ply"), "--truth", str(tmp_path / "truth.ply"), "--methods", "multiorder,poisson",
                 "--resolution", "32", "-o", str(out)])
    assert code == 0
    names = sorted(f.name for f in out.iterdir())
    assert names == ["comparison.csv", "comparison.json", "comparison.md", "comparison.png"]
    table = [line for line in (out / "comparison.md").read_text().splitlines() if line.startswith("|")]
    assert table[0].startswith("| Method |") and len(table) == 4
    assert main(["compare", str(scan / "torus.ply"), "--methods", "poisson,bogus", "-o", str(out)]) == 2
    assert "valid methods" in capsys.readouterr().err


def test_coloured_input_gives_a_coloured_mesh(tmp_path):
    """A point cloud with colours gives a mesh coloured from them (colour = a linear function of position)."""
    import open3d as o3d

    from o3drbf.cli.commands import main
    from o3drbf.synthetic.shapes import Sphere

    pts, nrm = Sphere(1.0).sample(3000, seed=4)
    truth = lambda x: 0.5 + 0.45 * x  # noqa: E731, colour channel = position
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.normals = o3d.utility.Vector3dVector(nrm)
    pcd.colors = o3d.utility.Vector3dVector(truth(pts))
    src = tmp_path / "coloured.ply"
    o3d.io.write_point_cloud(str(src), pcd)
    out = tmp_path / "mesh.ply"
    assert main(["reconstruct", str(src), "-o", str(out), "--resolution", "32", "--surface-count", "600", "-q"]) == 0
    mesh = o3d.io.read_triangle_mesh(str(out))
    assert mesh.has_vertex_colors()
    v = np.asarray(mesh.vertices)
    err = np.abs(np.asarray(mesh.vertex_colors) - truth(v / np.linalg.norm(v, axis=1, keepdims=True)))
    # 3,000 points on the unit sphere are about 0.06 apart; inverse-distance weighting of 8 neighbours
    # blurs a slope of 0.45 over about that distance: a few hundredths.
    assert err.mean() < 0.02, err.mean()
    out2 = tmp_path / "plain.ply"
    assert main(["reconstruct", str(src), "-o", str(out2), "--resolution", "32", "--surface-count", "600", "-q", "--no-color"]) == 0
    assert not o3d.io.read_triangle_mesh(str(out2)).has_vertex_colors()


def test_after_robust_refits_the_summary_says_whose_solve_it_shows(tmp_path):
    """Noisy points with strays: the robust pass refits, and the solve line's time and iterations are
    the final fit's only, so the line says so and gives the fit stage's time, refits included."""
    import o3drbf
    from o3drbf.cli.commands import summary

    p, n = Torus().sample(15_000, noise=0.01, seed=3)
    rng = np.random.default_rng(4)
    strays = rng.choice(len(p), 450, replace=False)
    p[strays] += rng.normal(0.0, 0.08, (len(strays), 3))
    result = o3drbf.reconstruct(p, n, resolution=32)
    rounds = result.report.robust["rounds"]
    assert rounds >= 1
    fit = next(t.seconds for t in result.report.stages if t.name == "fit")
    line = next(x for x in summary(result, p, "in.ply", "out.ply").splitlines() if x.strip().startswith("solve"))
    assert f"(the final fit's; the fit stage, with the first fit and {rounds} robust refits, took {fit:.2f} s)" in line
    assert result.report.solve_seconds < fit
