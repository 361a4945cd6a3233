"""The Dr.Jit backends the tracer runs on, imported lazily (maps load and query without Dr.Jit), and the
process's memory settings for its large per-path arrays."""

from __future__ import annotations

import importlib
import os

from trimeter.errors import InputError

BACKENDS = ("llvm", "cuda", "auto")


def resolve_backend(name: str = "auto") -> str:
    """The Dr.Jit backend a trace runs on: `llvm` (CPU, all cores), `cuda` (a GPU), or `auto` (CUDA
    when Dr.Jit finds a CUDA device, else LLVM). Asking for `cuda` without one is an InputError."""
    if name not in BACKENDS:
        raise InputError(f"--backend must be one of {', '.join(BACKENDS)}, got {name!r}")
    if name == "llvm":
        return name
    dr = _import_drjit()
    has_cuda = bool(dr.has_backend(dr.JitBackend.CUDA))
    if name == "cuda" and not has_cuda:
        raise InputError("--backend cuda: Dr.Jit finds no CUDA device (driver and GPU) on this machine; "
                         "use --backend llvm or auto")
    return "cuda" if has_cuda else "llvm"


def _import_drjit():
    llvm = "/usr/lib/x86_64-linux-gnu/libLLVM-19.so"
    if os.path.exists(llvm):  # the machine's default LLVM aborts at JIT time (docs/platform-notes.md)
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", llvm)
    _keep_freed_memory()
    import drjit as dr
    return dr


def _keep_freed_memory() -> None:
    """Make glibc keep the memory this process frees instead of handing it back to the OS, once per
    process. Why, twice over:
    - Speed: glibc maps every buffer over 32 MB afresh and unmaps it when freed, so each trace's
      per-path arrays (tens of MB) land on fresh pages, and on a virtual machine touching a fresh page
      can cost more than the copy into it (the git history of maps/README.md has the measurement).
    - A segfault inside Dr.Jit's compiled kernels (on its worker thread, in the background-path
      trace that follows a dense column's detector trace: σt = 50/mm, g = 0.9, 8M paths) in processes
      started with MALLOC_TRIM_THRESHOLD_ set, as Dask's nanny does (65536): every large buffer freed
      went back to the OS at once and a later read of it faulted. Our side was ruled out as far as
      tried (one Dr.Jit thread, each wave's gathers evaluated and synchronised before the next, every
      numpy↔Dr.Jit conversion an explicit copy); memory that is never unmapped cannot fault.
    The process keeps its peak footprint (a 16M-path chunk: ~2.5 GB) until it exits."""
    global _MEMORY_KEPT
    if _MEMORY_KEPT:
        return
    _MEMORY_KEPT = True
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
    except OSError:  # not glibc
        return
    m_trim_threshold, m_mmap_max = -1, -4           # glibc's mallopt parameters
    libc.mallopt(m_mmap_max, 0)                      # no mmap'ed chunks: large buffers come from the heap
    libc.mallopt(m_trim_threshold, 1 << 62)          # … and the heap's top is never trimmed


_MEMORY_KEPT = False


def load_drjit(backend: str = "llvm"):
    """Dr.Jit and the array module of one backend (drjit.llvm or drjit.cuda), imported lazily: maps
    load and query without Dr.Jit. The only place the array types are chosen."""
    dr = _import_drjit()
    if backend not in ("llvm", "cuda"):
        raise InputError(f"backend must be 'llvm' or 'cuda' (resolve 'auto' first), got {backend!r}")
    return dr, importlib.import_module(f"drjit.{backend}")


def set_drjit_threads(count: int) -> None:
    """Dr.Jit's thread pool size in this process (a worker runs one task at a time on one core)."""
    dr, _ = load_drjit()
    if dr.thread_count() != count:
        dr.set_thread_count(count)
