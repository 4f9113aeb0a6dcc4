"""Check that the recorded benchmark runs and the pages that quote them agree.

Each file in ``benchmarks/recorded/`` is one run of a benchmark (``user_path.py
--record``): its rows, the machine and load, and the markdown tables it printed.
``docs/benchmarks.md`` quotes each table verbatim, ``docs/tiles.md`` the table rows of
each ``tiles_*.md`` (the output of ``tiles.py``); this script fails (exit 1,
naming the file and the first line that differs) when a page no longer shows
what its run printed, or when a row in the run failed without the page saying
so.

    python benchmarks/check_recorded.py
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
RECORDED = HERE / "recorded"
PAGE = HERE.parent / "docs" / "benchmarks.md"


def problems(recorded: Path = RECORDED, page: Path = PAGE) -> list[str]:
    """What does not agree, one line each (empty when all do)."""
    out = []
    text = page.read_text() if page.exists() else ""
    runs = sorted(recorded.glob("*.json"))
    if not runs:
        return [f"{recorded}: no recorded run"]
    tiles_page = page.parent / "tiles.md"
    tiles_text = tiles_page.read_text() if tiles_page.exists() else ""
    for run in sorted(recorded.glob("tiles_*.md")):  # a benchmarks/tiles.py run's output: its table rows quoted on tiles.md
        for line in run.read_text().splitlines():
            if line.startswith("| ") and not line.startswith("| method") and line not in tiles_text:
                out.append(f"{tiles_page.name} does not quote {run.name}'s line: {line}")
                break
    for run in runs:
        data = json.loads(run.read_text())
        for name in ("rows", "tables", "machine", "date"):
            if name not in data:
                out.append(f"{run.name}: no {name!r}")
        for line in data.get("tables", "").splitlines():
            if line.strip() and line not in text:
                out.append(f"{page.name} does not quote {run.name}'s line: {line}")
                break
        for row in data.get("rows", []):
            if row.get("rc", 0) != 0 and f"exit {row['rc']}" not in text:
                out.append(f"{run.name}: {row['case']} / {row['tool']} exited {row['rc']}, which {page.name} does not say")
    return out


def main() -> int:
    found = problems()
    for line in found:
        print(f"check_recorded: {line}", file=sys.stderr)
    if not found:
        print(f"check_recorded: {len(list(RECORDED.glob('*.json')))} recorded run(s) agree with {PAGE.relative_to(HERE.parent)}")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
