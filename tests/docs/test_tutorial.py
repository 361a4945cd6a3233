"""docs/tutorial.ipynb: generated from tools/tutorial.py (never stale, never committed with outputs), and executed
end to end on the twin (nbclient, every cell within a bounded time), so the tutorial cannot rot."""

from __future__ import annotations

import importlib.util
import sys
import time
from pathlib import Path

import nbformat
import pytest

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("gen_tutorial", ROOT / "tools" / "gen_tutorial.py")
gen = importlib.util.module_from_spec(_spec)
sys.modules["gen_tutorial"] = gen
_spec.loader.exec_module(gen)

CELL_TIMEOUT_S = 240  # the slowest cell (calibration, two measurements) takes seconds here; minutes means a hang


def test_the_notebook_is_generated_from_its_source_without_outputs():
    assert gen.main(["--check"]) == 0, "run: python -m tools.gen_tutorial"
    nb = nbformat.read(gen.NOTEBOOK, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(not c.outputs and c.execution_count is None for c in code)


def test_the_percent_format_becomes_cells():
    source = "# %% [markdown]\n# # Title\n#\n# text\n\n# %%\nx = 1\n\nprint(x)\n\n# %%\ny = 2\n"
    assert gen.cells(source) == [("markdown", "# Title\n\ntext"), ("code", "x = 1\n\nprint(x)"), ("code", "y = 2")]
    with pytest.raises(ValueError, match="not a comment"):
        gen.cells("# %% [markdown]\n# fine\nnot a comment\n")
    with pytest.raises(ValueError, match="before the first cell"):
        gen.cells("import os\n# %%\n")


@pytest.mark.slow
def test_the_tutorial_runs_on_the_twin(tmp_path, monkeypatch):
    from jupyter_client.manager import AsyncKernelManager
    from jupyter_core.utils import run_sync
    from nbclient import NotebookClient

    monkeypatch.setenv("TMPDIR", str(tmp_path))  # the notebook's working directory lands here
    nb = nbformat.read(gen.NOTEBOOK, as_version=4)
    # the kernel talks over Unix sockets in tmp_path, not over TCP ports any local user could reach.
    # Async, as NotebookClient's own: a blocking KernelManager driven from its event loop starts a
    # "MainThread - runner" loop thread that lives as long as this process.
    kernel = AsyncKernelManager(kernel_name="python3", transport="ipc", ip=str(tmp_path / "kernel"))
    t0 = time.monotonic()
    try:
        # cleanup_kc: also for a kernel manager handed in, stop the client's channels and the kernel when done;
        # left open, the heartbeat thread outlives the test and keeps re-opening its socket to the dead kernel
        NotebookClient(nb, km=kernel, timeout=CELL_TIMEOUT_S, shutdown_kernel="immediate",
                       resources={"metadata": {"path": str(tmp_path)}}).execute(cleanup_kc=True)
    finally:  # a kernel manager handed in is the caller's to stop (if the client could not)
        if kernel.has_kernel:
            run_sync(kernel.shutdown_kernel)(now=True)
    print(f"\nthe tutorial ran in {time.monotonic() - t0:.0f} s")

    def text(i):
        return "".join(o.get("text", "") for o in nb.cells[i].outputs if o.output_type == "stream")

    def images(i):
        return [o for o in nb.cells[i].outputs if o.output_type == "display_data" and "image/png" in o.data]

    code = [i for i, c in enumerate(nb.cells) if c.cell_type == "code"]
    outputs = "".join(text(i) for i in code)
    assert "calibrated:" in outputs and "usable" in outputs
    assert outputs.count("→ ") == 2  # two results directories
    assert "<trimeter.Measurement" in outputs and "α = " in outputs
    assert "written: medium.xml, medium.json" in outputs and "rendered in" in outputs
    assert "50/50 mixture" in outputs and "on white #" in outputs
    # the plot, the render and the prediction each show a figure
    assert sum(1 for i in code if images(i)) == 3
    results = sorted((tmp_path).glob("trimeter-tutorial-*/results/*"))
    assert len(results) == 2 and all((r / "measurement.json").is_file() for r in results)
