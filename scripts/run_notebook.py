"""Execute a notebook (nbclient, a fresh Python kernel) and save the picture of its cell tagged ``figure``.

    python scripts/run_notebook.py docs/quickstart.ipynb --figure docs/images/quickstart.png

Used by ``make figures`` (the README picture) and by tests/project/test_notebook.py.
A failing cell (an ``assert`` on the report, say) stops the run with exit
status 1 and names the cell.  The notebook file itself is not changed: it is
committed without outputs.
"""

from __future__ import annotations

import argparse
import base64
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def execute(path: str | os.PathLike, timeout: int = 120):
    """Run every cell of the notebook at ``path`` in a new kernel, with this repository first on the import path.

    Parameters
    ----------
    path : str or Path
    timeout : int
        Seconds allowed per cell.

    Returns
    -------
    nbformat.NotebookNode
        The executed notebook (outputs filled in).

    Raises
    ------
    nbclient.exceptions.CellExecutionError
        A cell raised; the message names the cell and the error.
    """
    import nbformat
    from nbclient import NotebookClient

    path = Path(path)
    nb = nbformat.read(path, as_version=4)
    saved = {k: os.environ.get(k) for k in ("PYTHONPATH", "O3DRBF_NO_PROGRESS")}
    # the kernel inherits this process's environment: the repository first, no tqdm widgets in the outputs;
    # restored afterwards, so nothing later in this process (e.g. a pip subprocess) sees the repository on its path
    os.environ["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])
    os.environ.setdefault("O3DRBF_NO_PROGRESS", "1")
    try:
        client = NotebookClient(nb, timeout=timeout, kernel_name="python3", resources={"metadata": {"path": str(path.parent)}},
                                extra_arguments=["--IPKernelApp.log_level=ERROR"])  # no warning about its local TCP sockets
        client.execute()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return nb


def figure(nb, tag: str = "figure") -> bytes:
    """The PNG shown by the first cell tagged ``tag``.

    Raises
    ------
    ValueError
        No such cell, or it showed no PNG.
    """
    for cell in nb.cells:
        if tag in cell.get("metadata", {}).get("tags", []):
            for output in cell.get("outputs", []):
                png = output.get("data", {}).get("image/png")
                if png:
                    return base64.b64decode(png)
            raise ValueError(f"the cell tagged {tag!r} showed no PNG; it should call result.plot()")
    raise ValueError(f"no cell is tagged {tag!r}; tag the cell whose picture is the figure")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("notebook", type=Path)
    parser.add_argument("--figure", type=Path, help="write the PNG of the cell tagged 'figure' here")
    parser.add_argument("--timeout", type=int, default=120, help="seconds per cell (default %(default)s)")
    args = parser.parse_args(argv)
    from nbclient.exceptions import CellExecutionError

    try:
        nb = execute(args.notebook, timeout=args.timeout)
    except CellExecutionError as exc:
        print(f"run_notebook: {args.notebook}: a cell failed:\n{exc}", file=sys.stderr)
        return 1
    if args.figure:
        args.figure.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.figure.with_name(args.figure.name + ".tmp")
        tmp.write_bytes(figure(nb))
        tmp.replace(args.figure)
        print(f"run_notebook: {args.notebook} ran; wrote {args.figure}")
    else:
        print(f"run_notebook: {args.notebook} ran")
    return 0


if __name__ == "__main__":
    sys.exit(main())
