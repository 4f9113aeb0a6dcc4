"""The recorded benchmark runs (benchmarks/recorded/) and docs/benchmarks.md agree (`make bench-check`)."""

import json
import sys

from conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
import check_recorded  # noqa: E402


def test_docs_quote_every_recorded_run():
    assert check_recorded.problems() == []


def test_a_page_that_drifted_from_its_run_is_caught(tmp_path):
    run = {"date": "x", "machine": {}, "rows": [{"case": "scan 27k", "tool": "o3drbf", "rc": 2}],
           "tables": "| case | tool |\n| scan 27k | o3drbf | 12.3 |"}
    (tmp_path / "run.json").write_text(json.dumps(run))
    page = tmp_path / "page.md"
    page.write_text("| case | tool |\n| scan 27k | o3drbf | 12.4 |\n")
    found = check_recorded.problems(tmp_path, page)
    assert len(found) == 2 and "12.3" in found[0] and "exited 2" in found[1]
    page.write_text("| case | tool |\n| scan 27k | o3drbf | 12.3 |\n(exit 2: the scan was refused)\n")
    assert check_recorded.problems(tmp_path, page) == []


def test_a_tiles_page_without_its_run_is_caught(tmp_path):
    (tmp_path / "run.json").write_text(json.dumps({"date": "x", "machine": {}, "rows": [], "tables": ""}))
    (tmp_path / "tiles_1m.md").write_text("| method | seconds |\n|---|---|\n| o3drbf tiles | 69.4 |\n")
    page = tmp_path / "benchmarks.md"
    page.write_text("")
    (tmp_path / "tiles.md").write_text("| o3drbf tiles | 70.1 |\n")
    found = check_recorded.problems(tmp_path, page)
    assert len(found) == 1 and "69.4" in found[0]
    (tmp_path / "tiles.md").write_text("| o3drbf tiles | 69.4 |\n")
    assert check_recorded.problems(tmp_path, page) == []


def test_the_user_path_tables_say_which_targets_are_met():
    import user_path

    row = {"tool": "o3drbf", "rc": 0, "cpu": 1.0, "detail": "", "stages": []}
    rows = [dict(row, case="torus 1M, --all-points", seconds=578.9, gb=5.71)]
    text = user_path.tables(rows, 0.2)
    assert "| torus 1M, --all-points: seconds | 578.90 | 300 | no |" in text
    assert "| torus 1M, --all-points: peak GB | 5.71 | 8 | yes |" in text
    assert "o3drbf / peer" not in text  # no peer ran: no empty ratio table
    rows += [dict(row, case="scan 27k", seconds=4.0, gb=0.6), dict(row, case="scan 27k", tool="Poisson d8", seconds=2.0, gb=0.3)]
    text = user_path.tables(rows, 0.2)
    assert "| scan 27k vs Poisson d8 | 2.00 | 1.5 | no |" in text


def test_the_user_path_keeps_each_tools_median_run():
    import user_path

    runs = [{"seconds": s, "rc": 0, "cpu": s, "gb": 0.5} for s in (5.0, 3.0, 4.0)]
    mid = user_path.median_run(runs)
    assert mid["seconds"] == 4.0 and mid["cpu"] == 4.0 and mid["runs"] == [5.0, 3.0, 4.0]
    assert user_path.median_run(runs[:2])["seconds"] == 3.0  # an even count: the lower middle
    failed = dict(runs[0], rc=1, seconds=0.1)
    assert user_path.median_run([failed, *runs[1:]])["seconds"] == 3.0  # a failed run is not a time
    assert user_path.runs_note(mid) == "; median of 3 runs: 3.0, 4.0, 5.0 s" and user_path.runs_note(runs[0]) == ""
