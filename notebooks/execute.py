"""Execute the notebooks at full size and save them with their outputs (plots, tables, printed
results), so that a reader sees them without running anything.

    python notebooks/execute.py                 # every notebook
    python notebooks/execute.py plush_pile      # the ones named

Each notebook runs with notebooks/ as its working directory, in a fresh kernel, and is written
back only when every cell ran (atomically: a temporary file, then a rename), without outputs over
1 MiB (an embedded 3-D viewer page). The tests run the
same notebooks again at small size (tests/test_notebooks.py).
"""

from __future__ import annotations

import os
import pathlib
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
#: Outputs larger than this (characters) are left out of the saved notebook (a 3-D viewer page
#: embedded as HTML is megabytes; the saved file keeps its text).
MAX_OUTPUT = 1 << 20


def execute(path, timeout=3600):
    import nbclient
    import nbformat
    nb = nbformat.read(path, as_version=4)
    env = {k: v for k, v in os.environ.items() if k not in ("JAXPLUSH_SMALL", "MPLBACKEND")}
    old = dict(os.environ)
    os.environ.clear()
    os.environ.update(env)              # the kernel inherits this: full size, inline plots
    try:
        client = nbclient.NotebookClient(nb, timeout=timeout, kernel_name="python3",
                                         resources={"metadata": {"path": str(path.parent)}})
        client.execute()
    finally:
        os.environ.clear()
        os.environ.update(old)
    for cell in nb.cells:               # no wall-clock stamps in the committed file
        cell.get("metadata", {}).pop("execution", None)
        for out in cell.get("outputs", []):
            data = out.get("data", {})
            for mime in [m for m, v in data.items() if m != "text/plain" and len(str(v)) > MAX_OUTPUT]:
                # (an embedded 3-D viewer page: the notebook says where its HTML file is written)
                del data[mime]
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".ipynb.tmp")
    os.close(fd)
    try:
        nbformat.write(nb, tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def main(argv):
    names = set(argv)
    paths = [p for p in sorted(HERE.glob("*.ipynb")) if not names or p.stem in names]
    if names - {p.stem for p in paths}:
        print(f"no notebook named {', '.join(sorted(names - {p.stem for p in paths}))}", file=sys.stderr)
        return 2
    for p in paths:
        t0 = time.perf_counter()
        print(f"{p.name}: running", flush=True)
        execute(p)
        print(f"{p.name}: saved with its outputs ({time.perf_counter() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
