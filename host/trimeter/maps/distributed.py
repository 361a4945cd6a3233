"""Map builds on Dask (`dask.distributed`): every unfinished (map, σt, g) column is one task.

- Embedded default: `local_client(workers)` starts a LocalCluster of `workers` spawned worker
  processes with one thread each, and each task runs Dr.Jit on one thread
  (trimeter.forward.transport.backend.set_drjit_threads), so N workers use N cores and never
  oversubscribe them.
- An existing cluster: `remote_client(address)` (`dask scheduler` / `dask worker` by hand, or
  dask-jobqueue on SLURM: maps/README.md). An address nobody answers at is one clear error after
  `connect_timeout` seconds, never a hang.
- Tasks are `trimeter.maps.builder.column_task` (passed in by the builder): pure functions of (recipe,
  j, k) that write their column into the map's checkpoint. A task whose worker dies (killed, out of
  memory: the nanny restarts it) or that raises is run again, up to `retries` more times; after that the
  build stops with the column named, and the finished columns stay in the checkpoint for `--resume`.
"""

from __future__ import annotations

import gc
import logging
import os
import socket
import struct
from contextlib import contextmanager
from typing import Callable, Iterator

from trimeter.errors import BuildError, InputError

CONNECT_TIMEOUT_S = 10.0
# Workers start with Dr.Jit's LLVM backend pointed at Debian's libLLVM 19 (the default LLVM aborts at
# JIT time, docs/platform-notes.md), whatever the environment of the process that starts the cluster.
_LIBLLVM = "/usr/lib/x86_64-linux-gnu/libLLVM-19.so"


def _dask():
    try:
        import dask
        import distributed
    except ImportError:
        raise InputError("distributed map builds need Dask: pip install 'trimeter[maps]'") from None
    return dask, distributed


@contextmanager
def local_client(workers: int | None = None, retries: int = 2) -> Iterator:
    """A Client on a fresh LocalCluster of `workers` processes (default: this machine's cores)."""
    dask, distributed = _dask()
    workers = workers or os.cpu_count() or 1
    if not 1 <= workers <= 1024:
        raise InputError(f"--workers must be 1…1024, got {workers}")
    env = {"DRJIT_LIBLLVM_PATH": os.environ.get("DRJIT_LIBLLVM_PATH", _LIBLLVM)} if os.path.exists(_LIBLLVM) else {}
    # allowed-failures: how many worker deaths one task may be part of before it is given up on;
    # dashboard ":0": the scheduler's HTTP server on a free port (it always starts one; 8787 may be taken).
    # The nanny's default MALLOC_TRIM_THRESHOLD_=65536 makes the tracer segfault on dense device columns
    # (σt = 50, g = 0.9: also in a plain process with that variable set), so workers keep glibc's default.
    environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ").items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    # A Client whose construction failed (a bad --scheduler) is left half-built in a reference cycle; if the
    # cyclic GC finalises it inside LocalCluster's loop start, its close() waits for the lock that start
    # holds: a hang. Finalise any such garbage now, outside it.
    gc.collect()
    with dask.config.set({"distributed.worker.multiprocessing-method": "spawn",
                          "distributed.nanny.pre-spawn-environ": environ,
                          "distributed.scheduler.allowed-failures": retries,
                          "distributed.worker.daemon": False}):
        cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                           dashboard_address=":0", silence_logs=logging.CRITICAL, env=env)
        try:
            with distributed.Client(cluster) as client:
                yield client
        finally:
            cluster.close()


# The first message a Dask scheduler sends on a new connection (its handshake) is a few hundred bytes; its
# first 8 bytes are that size. Whatever else listens there (a web server answering the client's handshake
# with text) would have the client allocate what those bytes read as.
MAX_HANDSHAKE_BYTES = 1 << 20


def check_dask_scheduler(address: str, connect_timeout: float = CONNECT_TIMEOUT_S) -> None:
    """InputError unless what listens at a tcp:// `address` speaks first as a Dask scheduler does: its
    handshake's size within MAX_HANDSHAKE_BYTES, sent unasked within `connect_timeout`. Other schemes
    (tls://, ucx://, inproc://) are left to Dask."""
    from distributed.comm import registry
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        registry.get_backend(scheme)  # a scheme Dask has no transport for: refused before any Client is built
        if scheme != "tcp":
            return
        host, port = parse_host_port(location)
    except (ValueError, TypeError) as exc:
        raise InputError(f"--scheduler {address}: not an address ({exc})") from None
    try:
        with socket.create_connection((host, port), timeout=connect_timeout) as sock:
            sock.settimeout(connect_timeout)
            first = b""
            while len(first) < 8 and (chunk := sock.recv(8 - len(first))):
                first += chunk
    except (OSError, ValueError) as exc:  # refused, unreachable, silent (a timeout is an OSError)
        raise InputError(f"--scheduler {address}: no Dask scheduler answered within {connect_timeout:g} s "
                         f"({exc.strerror if isinstance(exc, OSError) and exc.strerror else exc or 'timed out'})"
                         ) from None
    size = struct.unpack("<Q", first)[0] if len(first) == 8 else 0
    if not 0 < size <= MAX_HANDSHAKE_BYTES:
        raise InputError(f"--scheduler {address}: what answers there is not a Dask scheduler "
                         f"(its first bytes {first!r} are no Dask handshake)")


@contextmanager
def remote_client(address: str, connect_timeout: float = CONNECT_TIMEOUT_S) -> Iterator:
    """A Client on the running Dask cluster whose scheduler listens at `address` (tcp://host:8786), checked to
    be one before the client reads anything from it."""
    _, distributed = _dask()
    check_dask_scheduler(address, connect_timeout)
    failure = None
    try:
        client = distributed.Client(address, timeout=connect_timeout)
    except (OSError, TimeoutError, ValueError, TypeError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        failure = InputError(f"--scheduler {address}: no Dask scheduler answered within {connect_timeout:g} s "
                             f"({reason})")
    if failure is not None:
        gc.collect()  # the half-built Client, finalised here rather than inside a later loop start (local_client)
        raise failure
    try:
        yield client
    finally:
        client.close()


def describe_cluster(client) -> str:
    """What ran the tasks, for the map's provenance: 'dask (N workers, T threads)'."""
    workers = client.scheduler_info().get("workers", {})
    threads = sum(int(w.get("nthreads", 1)) for w in workers.values())
    return f"dask ({len(workers)} workers, {threads} threads)"


def run_on_cluster(client, pending, column_task: Callable, tracer: Callable, retries: int):
    """Submit every pending (map state, j, k) column at once (a library build fills the cluster with
    every column of every map) as `column_task` (the builder's) and yield (state, j, k, column) as they
    finish, in any order."""
    from distributed import as_completed

    futures = {}
    for state, j, k in pending:
        future = client.submit(column_task, state.recipe, str(state.ckpt.dir), j, k, tracer, 1, retries=retries,
                               pure=False, key=f"{state.recipe.name}-col_{j:03d}_{k:03d}-{os.urandom(4).hex()}")
        futures[future] = (state, j, k)
    try:
        for future in as_completed(futures):
            state, j, k = futures.pop(future)
            # A result held by a worker that died since is lost (Dask would recompute it); its column
            # file is not, and it is the truth.
            col = state.ckpt.load(j, k) if future.status == "lost" else None
            if col is None:
                try:
                    col, written = future.result()
                except Exception as exc:  # noqa: BLE001 - the task's own error or KilledWorker, named below
                    raise _column_failed(state, j, k, exc, retries) from None
                if not written:     # the worker did not see the checkpoint directory: keep the column here
                    state.ckpt.save(j, k, col)
            future.release()
            yield state, j, k, col
    finally:
        if futures:
            client.cancel(list(futures))


def _column_failed(state, j: int, k: int, exc: BaseException | None, retries: int) -> BuildError:
    from distributed import KilledWorker

    r = state.recipe
    if isinstance(exc, KilledWorker):
        what = f"its worker died {retries + 1} times (killed or out of memory)"
    else:
        what = f"it failed {retries + 1} times, last with {type(exc).__name__}: {(str(exc) or '-').splitlines()[0]}"
    return BuildError(f"map {r.name}: column σt[{j}] = {r.sigma_t[j]:g} /mm, g[{k}] = {r.g[k]:g} stopped the build: "
                      f"{what}. The finished columns are kept in {state.ckpt.dir}; run the same command again "
                      f"with --resume once the cause is fixed")
