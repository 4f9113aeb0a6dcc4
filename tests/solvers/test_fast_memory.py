"""Memory of the fast path: budgets follow the memory available, the plan is honest, refusals come first.

Independent truths: the bytes of the arrays a grid sum really allocates
(its kernel transform, its near-field matrix), and psutil's own report,
replaced here by a fake machine.
"""

from __future__ import annotations

import re
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import psutil
import pytest

from o3drbf.cli.commands import main
from o3drbf.io.files import write_points
from o3drbf.rbf.kernels import MultiOrder
from o3drbf.solvers import MemoryRefusal, Refitter, fast, resolve_method
from o3drbf.solvers.base import available_memory, memory_limit_or_default
from o3drbf.synthetic.shapes import Sphere, Torus

GB = 2**30
#: Names a command-line user cannot act on, and must never read in a refusal.
API_WORDS = ("backend", "memory_limit", "method=", "surface_count", "'fmm'", "'fast'")


def torus_centres(n, seed=0):
    p, nrm = Torus().sample(int(n / 1.1), seed=seed)
    k = n - len(p)
    idx = np.random.default_rng(seed + 1).choice(len(p), k, replace=False)
    return np.vstack([p, p[idx] + 0.05 * nrm[idx]])


@pytest.fixture
def machine(monkeypatch):
    """A fake machine: ``machine(bytes)`` makes psutil report that much available memory
    (and no address-space or cgroup limit below it)."""
    real = psutil.virtual_memory

    def set_available(nbytes):
        fake = real()._replace(available=int(nbytes))
        monkeypatch.setattr(psutil, "virtual_memory", lambda: fake)
        import resource

        monkeypatch.setattr(resource, "getrlimit", lambda which: (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
        monkeypatch.setattr("builtins.open", _no_cgroup(open))

    return set_available


def _no_cgroup(real_open):
    def fake_open(path, *a, **k):
        if str(path).startswith("/sys/fs/cgroup"):
            raise OSError("no cgroup here")
        return real_open(path, *a, **k)

    return fake_open


def test_budgets_follow_available_memory(machine):
    """The solve's limit and a grid's budget are 80 % of what psutil says is available, whatever that is."""
    for avail in (3 * GB, 40 * GB):
        machine(avail)
        assert available_memory() == avail
        assert memory_limit_or_default() == int(0.8 * avail)
        assert fast.grid_budget() == int(0.8 * avail)
    # A grid that needs more than the fixed 2 GB of old is built when the machine has room ...
    c = torus_centres(3000)
    need = fast.GridSum(MultiOrder(10.0, 0.01), c, eps=1e-6).info["grid_bytes"]
    machine(need / 0.8 * 1.05)
    assert fast.GridSum(MultiOrder(10.0, 0.01), c, eps=1e-6).info["grid_bytes"] == need
    # ... and refused, naming sizes not API names, when it has not.
    machine(need / 0.8 * 0.95)
    with pytest.raises(MemoryError, match=r"needs ~.* GB of FFT arrays \(budget") as info:
        fast.GridSum(MultiOrder(10.0, 0.01), c, eps=1e-6)
    assert not any(w in str(info.value) for w in API_WORDS)


def test_stored_near_fields_follow_available_memory(machine):
    """Whether the products keep their near fields is 30 % of the memory limit (80 % of what is available),
    with no fixed cap: 6 GB of near fields are stored on a machine with 40 GB free, not on one with 16 GB."""
    from o3drbf.solvers.fast import neighbours

    entries = 6 * GB / (neighbours.NNZ_BYTES * (1 + neighbours.COMPANION_SHARE))
    machine(40 * GB)
    assert neighbours.store_near(entries)  # 6 GB <= 0.3 * 32 GB
    machine(16 * GB)
    assert not neighbours.store_near(entries)  # 6 GB > 0.3 * 12.8 GB
    assert neighbours.store_near(entries, limit=int(20.1 * GB)) and not neighbours.store_near(entries, limit=int(19.9 * GB))


def test_plan_matches_the_arrays_a_grid_allocates():
    """memory_plan's pieces against the real arrays: the kernel transform of the grid and the
    near-field matrix of the products at the centres (within 15 %)."""
    kernel = MultiOrder(9.92, 0.005)
    c = torus_centres(20000)
    from scipy.spatial import cKDTree

    tree = cKDTree(c)
    plan = fast.grid_plan(kernel, c, tree, 1e-7)
    op = fast.GridSum(kernel, c, eps=1e-7, tree=tree)
    near = op.near
    assert plan["grid"] == pytest.approx(op.mesh.khat.nbytes, rel=0.15)
    assert plan["near"] == pytest.approx(near.data.nbytes + near.indices.nbytes + near.indptr.nbytes, rel=0.15)
    whole = fast.memory_plan(kernel, c)
    assert whole["total"] >= whole["fit"] > plan["grid"] + plan["near"]


def test_plan_counts_the_coarse_rows_grid_where_the_second_correction_runs():
    """With the second coarse correction (a capped coarse level, from about 48,000 centres) the preconditioner
    sums the product's rows at the coarse centres on a looser companion grid (``post_eps``): the plan counts
    that grid's kernel transform (within 15 %) there, and no such grid below."""
    from o3drbf.solvers.fast.precondition import TwoLevelSettings, second_correction

    kernel = MultiOrder(9.92, 0.005)
    st = TwoLevelSettings()
    key = f"grid {st.post_eps:g}"
    small, large = torus_centres(20000), torus_centres(60000)
    assert not second_correction(len(small), st) and second_correction(len(large), st)
    assert key not in fast.memory_plan(kernel, small, eps=1e-7, evaluation=False)["parts"]
    parts = fast.memory_plan(kernel, large, eps=1e-7, evaluation=False)["parts"]
    op = fast.GridSum(kernel, large, eps=1e-7, store=False)
    op.rows(np.arange(0, len(large), 100), eps=st.post_eps)
    assert parts[key] == pytest.approx(op._tier(st.post_eps).mesh.khat.nbytes, rel=0.15)


def test_far_centres_block_is_stored_within_its_share_of_the_memory_limit(monkeypatch):
    """The kernel block between the centres and the far ones the grid leaves out (an exterior sphere) is
    stored when it fits in OUTSIDE_BLOCK_SHARE of the limit (the grid's budget), else summed directly at
    every product; the memory plan counts the block's real bytes exactly when it is stored."""
    from o3drbf.solvers.fast import grid

    kernel = MultiOrder(10.0, 0.01)
    far = np.random.default_rng(4).normal(size=(12, 3))
    c = np.vstack([torus_centres(3000), 6.0 * far / np.linalg.norm(far, axis=1, keepdims=True)])
    budget = 4 * GB
    monkeypatch.setattr(grid, "OUTSIDE_BLOCK_MIN", 0)
    block = 8 * len(c) * 12
    for share, stored in ((1.01 * block / budget, True), (0.99 * block / budget, False)):
        monkeypatch.setattr(grid, "OUTSIDE_BLOCK_SHARE", share)
        assert grid.outside_block_bytes(budget) == int(share * budget)
        op = fast.GridSum(kernel, c, eps=1e-6, budget=budget)
        assert len(op.outside) == 12
        held = op._outside_block()
        assert (held is not None) == stored
        plan = fast.memory_plan(kernel, c, limit=budget)["parts"]
        assert plan.get("far centres", 0) == (sum(a.nbytes for a in held) if stored else 0)
    monkeypatch.setattr(grid, "OUTSIDE_BLOCK_MIN", 256 * 2**20)
    assert grid.outside_block_bytes(budget) == 256 * 2**20  # a floor on small machines


def test_looser_companions_never_take_a_finer_grid():
    """The looser companions (relaxed products at 1e-3 and 1e-4, the preconditioner's sums at 1e-2) have
    grids no finer than the product's own: at 300,000 constraints a 300-neighbour companion needed more
    FFT memory than the product."""
    kernel = MultiOrder(9.92, 0.005)
    c = torus_centres(40000)
    op = fast.GridSum(kernel, c, eps=1e-7)
    for tol in (1e-2, 1e-3, 1e-4):
        tier = op._tier(tol)
        assert tier is not op and tier.eps == tol
        assert tier.h >= op.h * (1 - 1e-12)
        assert tier.info["grid_bytes"] <= op.info["grid_bytes"]
        w = np.random.default_rng(0).normal(size=len(c))
        rows = np.random.default_rng(1).choice(len(c), 200, replace=False)
        from o3drbf.rbf.sums import kernel_matrix

        ref = kernel_matrix(kernel, c[rows], c) @ w
        assert np.linalg.norm(tier.matvec(w)[rows] - ref) / np.linalg.norm(ref) < tol


def test_fast_refusal_is_up_front_and_names_a_count_that_fits(machine):
    """A fast solve over the limit is refused before any product is built, with the share
    of the constraints that would fit, and that share does fit."""
    kernel = MultiOrder(9.92, 0.005)
    c = torus_centres(20000)
    # (at a limit this small the near fields are summed on the fly: the leanest plan, still over the limit)
    limit = int(0.5 * fast.memory_plan(kernel, c, evaluation=False, limit=2**20)["total"])
    need = fast.memory_plan(kernel, c, evaluation=False, limit=limit)["total"]  # (the near field follows the limit)
    assert need > limit
    session = Refitter(kernel, c, np.zeros(len(c)), 1e-3, method="fast", memory_limit=limit)
    with pytest.raises(MemoryRefusal) as info:
        session.solve()
    assert session.operator is None
    exc = info.value
    assert exc.need == need and 0 < exc.fraction < 1
    assert "--surface-count" in exc.cli_hint and not any(w in exc.cli_hint for w in API_WORDS)
    sub = c[np.sort(np.random.default_rng(3).permutation(len(c))[: int(exc.fraction * len(c))])]
    assert fast.memory_plan(kernel, sub, evaluation=False, limit=limit)["total"] <= limit


def test_dense_refusals_point_to_the_fast_solver():
    """--solver dense above its size or memory: the command line is told --solver fast / auto."""
    with pytest.raises(ValueError) as info:
        resolve_method("dense", 20000, 1, 10**12)
    assert "--solver auto" in info.value.cli_message and "method=" not in info.value.cli_message
    with pytest.raises(MemoryRefusal) as info:
        resolve_method("dense", 8000, 1, 10**6)
    assert "--solver fast" in info.value.cli_hint and not any(w in info.value.cli_hint for w in API_WORDS)


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    d = tmp_path_factory.mktemp("fast_memory_cli")
    p, n = Sphere(1.0).sample(3000, seed=4)
    write_points(d / "in.ply", p, n)
    return d


def _refused(cloud, capsys, monkeypatch, machine, available, extra=()):
    """Run the command line on a fake machine; the fit must never start."""
    import o3drbf.options
    import o3drbf.pipeline.run  # where reconstruct looks its stages up

    monkeypatch.setattr(o3drbf.options, "check_untiled_fits", lambda *a, **k: None)  # the reading side is not the question
    monkeypatch.setattr(o3drbf.pipeline.run, "fit_surface", lambda *a, **k: pytest.fail("the fit started"))
    machine(available)
    t0 = time.perf_counter()
    code = main(["reconstruct", str(cloud / "in.ply"), "-o", str(cloud / "o.ply"), "--solver", "fast", "--resolution", "24", "-q",
                 *extra])
    seconds = time.perf_counter() - t0
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert not any(w in err for w in API_WORDS), err
    assert not (cloud / "o.ply").exists()
    return err, seconds


def test_cli_refuses_a_fast_fit_before_it_starts(cloud, capsys, monkeypatch, machine):
    """Too little memory for any fit: refused in seconds, pointing to --tiles auto."""
    err, seconds = _refused(cloud, capsys, monkeypatch, machine, 2 * 2**20)
    assert re.search(r"out of memory: a fast fit of [\d,]+ constraints .* needs about .* but the limit is .*--tiles auto", err), err
    assert "--solver fast" not in err  # the solver already chosen
    assert seconds < 30


def test_cli_refusal_suggests_a_surface_count_that_fits(cloud, capsys, monkeypatch, machine):
    """Somewhat too little memory: the refusal names a smaller --surface-count; with it the
    memory check passes on the same machine."""
    import o3drbf.pipeline
    from o3drbf.pipeline import build_constraints, choose_parameters
    from o3drbf.options import Options

    opts = Options.create(solver="fast", resolution=24, surface_count=1000)
    data = SimpleNamespace()
    from o3drbf.pointset import read_input

    data = read_input(str(cloud / "in.ply"))
    cset = build_constraints(data, opts.constraints)
    params = choose_parameters(data, cset, opts.parameters)
    plan = o3drbf.pipeline.check_fit_memory(cset, params, opts.fit, opts.extract)
    available = 0.7 * plan["total"] / 0.8
    err, _ = _refused(cloud, capsys, monkeypatch, machine, available, ["--surface-count", "1000"])
    found = re.search(r"--surface-count (\d+)", err)
    assert found, err
    count = int(found.group(1))
    assert count < 1000
    opts = Options.create(solver="fast", resolution=24, surface_count=count)
    cset = build_constraints(data, opts.constraints)
    params = choose_parameters(data, cset, opts.parameters)
    o3drbf.pipeline.check_fit_memory(cset, params, opts.fit, opts.extract)  # does not raise


def test_cli_general_memory_error_does_not_suggest_the_chosen_solver(cloud, capsys, monkeypatch):
    import o3drbf.pipeline

    def boom(*a, **k):
        raise MemoryError("Unable to allocate 3.1 GiB for an array")

    monkeypatch.setattr(o3drbf.pipeline, "reconstruct", boom)
    code = main(["reconstruct", str(cloud / "in.ply"), "-o", str(cloud / "o.ply"), "--solver", "fast", "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "3.1 GiB" in err and "--surface-count" in err and "--solver fast" not in err


def test_cli_refuses_a_large_fit_right_after_reading(tmp_path, capsys, monkeypatch, machine):
    """Every point as a constraint (66,000 of them) on a machine with 300 MB: refused by the early
    estimate, before outliers, normals or constraints are computed, in seconds."""
    import o3drbf.options
    import o3drbf.pipeline.run  # where reconstruct looks its stages up

    p, n = Sphere(1.0).sample(60000, seed=5)
    write_points(tmp_path / "big.ply", p, n)
    monkeypatch.setattr(o3drbf.options, "check_untiled_fits", lambda *a, **k: None)
    monkeypatch.setattr(o3drbf.pipeline.run, "remove_outliers", lambda *a, **k: pytest.fail("a costly stage started"))
    machine(300 * 2**20)
    t0 = time.perf_counter()
    code = main(["reconstruct", str(tmp_path / "big.ply"), "-o", str(tmp_path / "o.ply"), "--all-points", "-q"])
    seconds = time.perf_counter() - t0
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert re.search(r"out of memory: a fast fit of about 66,064 constraints \(60,000 surface\) and its mesh needs about .*--tiles auto", err), err
    assert not any(w in err for w in API_WORDS), err
    assert seconds < 60


_MEASURE = r"""
import json, sys
import numpy as np
from o3drbf.rbf.kernels import MultiOrder
from o3drbf.solvers import fast
from o3drbf.solvers.fast import neighbours
from o3drbf.synthetic.shapes import Torus

def status(field):
    for line in open("/proc/self/status"):
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024

n, store = int(sys.argv[1]), sys.argv[2] == "stored"
if not store:
    neighbours.NEAR_STORE_BYTES = 0  # the near fields summed on the fly, as at a million constraints
p, nrm = Torus().sample(int(n / 1.1), seed=0)
idx = np.random.default_rng(1).choice(len(p), n - len(p), replace=False)
c = np.vstack([p, p[idx] + 0.05 * nrm[idx]])
y = np.r_[np.zeros(len(p)), -np.ones(n - len(p))]
lam = np.r_[np.full(len(p), 1e-3), np.full(n - len(p), 2.0)]
kernel = MultiOrder(10.0, 0.01)
plan = fast.memory_plan(kernel, c, evaluation=False)
fast.solve(kernel, c[:500], y[:500], lam[:500])  # compiled kernels loaded before the baseline
open("/proc/self/clear_refs", "w").write("5")
base = status("VmRSS")
sol = fast.solve(kernel, c, y, lam)
print(json.dumps({"plan": plan["fit"], "used": status("VmHWM") - base, "store": sol.info["split"]["near_field"]}))
"""


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux's /proc/self/clear_refs")
@pytest.mark.parametrize("near", ["stored", "summed on the fly"])
def test_plan_is_within_a_factor_of_the_measured_peak(near):
    """The up-front estimate of a fit against the resident memory the fit really takes (the peak
    of a fresh process over its resident memory before the fit, read from the kernel), with the
    near fields stored and summed on the fly: within a factor of 1.5 either way."""
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _MEASURE, "30000", near.split()[0]], capture_output=True, text=True,
                         check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["store"] == near
    ratio = got["used"] / got["plan"]
    assert 1 / 1.5 < ratio < 1.5, f"measured {got['used'] / GB:.2f} GB, planned {got['plan'] / GB:.2f} GB"
