"""The constraint-count sweeps kept in docs/data (benchmarks/paper/count_rule.py): the pages quote their rows."""

import sys

import pytest
from conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks" / "paper"))
import count_rule  # noqa: E402

DATA = REPO / "docs" / "data"


def row(chamfer, study_chamfer, constraints, study_constraints, watertight=True, fit=1.0):
    return {"chamfer_l1": chamfer, "study_chamfer": study_chamfer, "surface_constraints": constraints,
            "study_constraints": study_constraints, "watertight": watertight, "seconds": 2.0, "study_seconds": 3.0, "fit_seconds": fit}


def test_summary_counts_and_ratios_by_hand():
    rows = [row(1.2, 1.0, 60, 100), row(1.0, 1.0, 100, 100), row(0.9, 1.0, 70, 100, watertight=False), {"error": "x"}]
    m = count_rule.summary(rows)
    assert m["cells"] == 4 and m["failed"] == 1
    assert m["constraints"] == 230 and m["study_constraints"] == 300
    assert m["fewer_median"] == pytest.approx(0.3)  # fewer: 0.4, 0.0, 0.3
    assert m["chamfer_median"] == pytest.approx(1.0) and m["chamfer_max"] == pytest.approx(1.2)
    assert (m["worse_5"], m["worse_10"], m["watertight"]) == (1, 1, 2)
    assert m["fit_seconds"] == pytest.approx(3.0)


def test_the_adaptive_page_quotes_its_rows():
    runs = count_rule.runs_of([str(DATA / "adaptive-constraints.jsonl")])
    page = (DATA / "adaptive-constraints.md").read_text()
    assert count_rule.table(runs) in page
