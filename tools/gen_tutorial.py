"""Generate the tutorial notebook docs/tutorial.ipynb from its source, tools/tutorial.py.

    python -m tools.gen_tutorial           # (re)write docs/tutorial.ipynb
    python -m tools.gen_tutorial --check   # exit 1 if the notebook is stale; write nothing

The source is a plain Python script in the "percent" format (as jupytext reads it): `# %%` starts a code cell,
`# %% [markdown]` a Markdown cell whose lines are comments. So the tutorial is linted and type-checked with the
rest of tools/, runs as a script too, and the notebook carries no outputs (tests/docs/test_tutorial.py
executes it). Cell ids are numbered, so the same source always makes the same file.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import nbformat

ROOT = Path(__file__).resolve().parent.parent
SOURCE = ROOT / "tools" / "tutorial.py"
NOTEBOOK = ROOT / "docs" / "tutorial.ipynb"
CODE, MARKDOWN = "# %%", "# %% [markdown]"


def cells(source: str) -> list[tuple[str, str]]:
    """(kind, text) per cell of a percent-format script: kind "code" or "markdown"."""
    out: list[tuple[str, list[str]]] = []
    for line in source.splitlines():
        if line.strip() == MARKDOWN:
            out.append(("markdown", []))
        elif line.strip() == CODE:
            out.append(("code", []))
        elif out:
            kind, lines = out[-1]
            if kind == "markdown":
                if line and not line.startswith("#"):
                    raise ValueError(f"a Markdown cell holds a line that is not a comment: {line!r}")
                line = line[2:] if line.startswith("# ") else line[1:]
            lines.append(line)
        elif line.strip():
            raise ValueError(f"text before the first cell marker: {line!r}")
    return [(kind, "\n".join(lines).strip("\n")) for kind, lines in out]


def notebook(source: str) -> str:
    nb = nbformat.v4.new_notebook()
    nb.metadata = {"kernelspec": {"display_name": "Python 3", "language": "python", "name": "python3"},
                   "language_info": {"name": "python"}}
    for i, (kind, text) in enumerate(cells(source)):
        cell = nbformat.v4.new_markdown_cell(text) if kind == "markdown" else nbformat.v4.new_code_cell(text)
        cell.id = f"cell-{i:02d}"
        nb.cells.append(cell)
    nbformat.validate(nb)
    return nbformat.writes(nb) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if docs/tutorial.ipynb is stale; write nothing")
    args = ap.parse_args(argv)
    made = notebook(SOURCE.read_text())
    if args.check:
        if not NOTEBOOK.is_file() or NOTEBOOK.read_text() != made:
            print(f"{NOTEBOOK.relative_to(ROOT)} is stale: run python -m tools.gen_tutorial", file=sys.stderr)
            return 1
        return 0
    NOTEBOOK.write_text(made)
    print(f"wrote {NOTEBOOK.relative_to(ROOT)} ({len(made)} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
