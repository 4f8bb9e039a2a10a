"""Run the course's notebooks (notebooks/*.py) top to bottom at one budget and record, per notebook,
its wall time and the text it printed: what the notebooks' first cells and docs/course.md cite.

    python benchmarks/notebooks.py --budget full --out benchmarks/results/notebooks_full.json
    python benchmarks/notebooks.py --budget quick --only 01 03      # some notebooks (name prefixes)

Each notebook runs in a fresh Jupyter kernel (as tests/test_notebooks.py does) in its own folder
under --work (runs, videos and plots stay there); the executed notebook, outputs included, is
saved there as NAME.ipynb. A notebook that fails is recorded with its error, and the next runs.
With --only and an existing --out, the other notebooks' entries in that file are kept: each entry
records the commit it ran at.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import jupytext
import nbformat
from nbclient import NotebookClient
from nbclient.exceptions import CellExecutionError

from provenance import REPO, provenance


def printed_text(notebook: nbformat.NotebookNode) -> list[str]:
    """The stdout of each code cell that printed, in order (progress bars and warnings on stderr left out)."""
    texts = []
    for cell in notebook.cells:
        if cell.cell_type != "code":
            continue
        text = "".join(out.get("text", "") for out in cell.get("outputs", [])
                       if out.get("output_type") == "stream" and out.get("name") == "stdout")
        if text.strip():
            texts.append(text.strip())
    return texts


def run_notebook(path: Path, budget: str, work: Path) -> dict:
    """Execute one notebook at ``budget`` in ``work/<name>``; its seconds, printed text and error (None when it ran)."""
    folder = work / path.stem
    shutil.rmtree(folder, ignore_errors=True)   # a notebook starts from an empty folder, as on a fresh clone
    folder.mkdir(parents=True)
    notebook = jupytext.read(path)
    os.environ["DRIVELAB_NOTEBOOK_BUDGET"] = budget  # the kernel inherits the environment
    os.environ["MPLBACKEND"] = "Agg"
    started = time.perf_counter()
    error = None
    try:
        NotebookClient(notebook, timeout=None, kernel_name="python3", resources={"metadata": {"path": str(folder)}}).execute()
    except CellExecutionError as exc:
        error = str(exc).strip().splitlines()[-1]
    seconds = time.perf_counter() - started
    nbformat.write(notebook, folder / f"{path.stem}.ipynb")
    return {"notebook": str(path.relative_to(REPO)), "seconds": round(seconds, 1), "error": error,
            "commit": provenance()["commit"], "printed": printed_text(notebook)}


def kept_entries(out: Path | None, budget: str, rerun: list[Path]) -> list[dict]:
    """The entries of an earlier results file at the same budget for notebooks not run now (each
    with the commit it ran at: its own, else the file's)."""
    if out is None or not out.is_file():
        return []
    earlier = json.loads(out.read_text())
    if earlier.get("budget") != budget:
        return []
    names = {str(p.relative_to(REPO)) for p in rerun}
    return [{**entry, "commit": entry.get("commit", earlier["provenance"]["commit"])}
            for entry in earlier["notebooks"] if entry["notebook"] not in names]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--budget", choices=("quick", "full"), default="full")
    parser.add_argument("--only", nargs="*", default=(), help="notebook name prefixes, e.g. 01 04")
    parser.add_argument("--work", type=Path, default=Path("runs/notebooks"), help="where the notebooks run")
    parser.add_argument("--out", type=Path, help="results JSON (default: print only)")
    args = parser.parse_args()
    started = time.time()
    paths = sorted((REPO / "notebooks").glob("*.py"))
    paths = [p for p in paths if not args.only or p.stem.startswith(tuple(args.only))]
    if not paths:
        sys.exit(f"--only: no notebook in notebooks/ starts with {' or '.join(args.only)}")
    kept = kept_entries(args.out, args.budget, paths)
    results = []
    for path in paths:
        print(f"== {path.stem} at the {args.budget} budget", flush=True)
        results.append(run_notebook(path, args.budget, args.work.resolve()))
        print(f"   {results[-1]['seconds']:.0f} s" + (f", failed: {results[-1]['error']}" if results[-1]["error"] else ""),
              flush=True)
        if args.out:  # after each notebook, so that a killed run keeps what it measured
            args.out.parent.mkdir(parents=True, exist_ok=True)
            entries = sorted(kept + results, key=lambda entry: entry["notebook"])
            args.out.write_text(json.dumps({"budget": args.budget, "notebooks": entries,
                                            "provenance": provenance(started)}, indent=1) + "\n")
    for r in results:
        print(f"\n## {r['notebook']}: {r['seconds']:.0f} s{', ERROR ' + r['error'] if r['error'] else ''}")
        print("\n".join(r["printed"][-3:]))


if __name__ == "__main__":
    main()
