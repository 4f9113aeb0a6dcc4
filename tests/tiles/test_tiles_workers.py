"""A tiled run on a separate Dask scheduler and two worker processes that read a shared tile folder (docs/tiles.md).

The commands of docs/tiles.md, in small: ``python -m distributed.cli.dask_scheduler``,
two ``python -m distributed.cli.dask_worker --nthreads 1`` processes, then
``o3drbf reconstruct`` on a binary PLY with ``--scheduler ADDR`` and the
tile files in a folder given by TMPDIR that every worker reads.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("distributed")

pytestmark = pytest.mark.slow


def _start(args, log):
    return subprocess.Popen([sys.executable, "-m", *args], stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def test_two_worker_processes_on_a_scheduler_with_a_shared_tile_folder(tmp_path):
    import open3d as o3d

    from o3drbf.io.files import write_points
    from o3drbf.synthetic.shapes import Torus

    shape = Torus(0.7, 0.25)
    pts, nrm = shape.sample(6000, seed=2)
    write_points(tmp_path / "t.ply", pts, nrm)
    shared = tmp_path / "shared"
    shared.mkdir()
    info = tmp_path / "scheduler.json"
    log = open(tmp_path / "dask.log", "w")
    procs = [_start(["distributed.cli.dask_scheduler", "--scheduler-file", str(info), "--port", "0", "--dashboard-address", ":0"], log)]
    try:
        for _ in range(2):
            procs.append(_start(["distributed.cli.dask_worker", "--scheduler-file", str(info), "--nthreads", "1", "--nworkers", "1",
                                 "--memory-limit", "2GiB", "--dashboard-address", ":0"], log))
        from distributed import Client

        deadline = time.time() + 60
        while not info.exists() and time.time() < deadline:
            time.sleep(0.2)
        address = json.loads(info.read_text())["address"]
        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=60)
        out = tmp_path / "m.ply"
        env = {**os.environ, "TMPDIR": str(shared)}
        cmd = [sys.executable, "-m", "o3drbf", "reconstruct", str(tmp_path / "t.ply"), "-o", str(out), "--tiles", "4",
               "--scheduler", address, "--resolution", "48", "-v"]
        done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
        log.flush()
        assert done.returncode == 0, done.stderr[-3000:] + "\n--- dask.log ---\n" + (tmp_path / "dask.log").read_text()[-4000:]
        text = done.stdout
        assert "memory-mapped, spread to per-tile files" in text and "tiles            4;" in text
        workers = [line for line in text.splitlines() if line.startswith("  workers ")]
        assert workers and workers[0].startswith("  workers          2: tcp://"), text  # both worker processes ran tiles
        assert "watertight       yes" in text and "1 component(s)" in text
        mesh = o3d.io.read_triangle_mesh(str(out))
        assert mesh.is_watertight() and mesh.euler_poincare_characteristic() == 0
        assert np.abs(shape.signed_distance(np.asarray(mesh.vertices))).max() < 0.03
        assert f"files in {shared}{os.sep}o3drbf-tiles-" in done.stderr  # the per-tile files went to the shared folder ...
        assert not any(shared.iterdir())  # ... and were removed after the fit
    finally:
        for p in procs[::-1]:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        log.close()
