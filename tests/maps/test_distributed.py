"""Map builds on Dask: the same bits whatever the worker count, order or retries (seeds from each column's
identity), a killed worker's column runs again, a column that keeps failing stops the build naming it with
its checkpoint intact (and --resume finishes it), an unreachable scheduler is one clear error.
One local cluster per worker count for the whole module (start-up costs seconds)."""

import os
import socket
import sys
import time

import cloudpickle
import numpy as np
import pytest

from trimeter.cli import main
from trimeter.errors import BuildError, InputError
from trimeter.maps.builder import MapJob, build_map, build_maps, default_checkpoint_dir
from trimeter.maps.distributed import check_dask_scheduler, local_client, remote_client
from trimeter.maps.recipe import parse_recipe
from trimeter.forward.transport import trace_column

FIELDS = ("A", "B", "C", "std_b", "std_w")
# The test tracers below run on the workers: shipped by value, since the workers cannot import this file.
cloudpickle.register_pickle_by_value(sys.modules[__name__])


def library(tiny_data):
    """Two small maps: six and four columns."""
    first = tiny_data()
    first["grid"]["sigma_t"] = [0.3, 3.0, 30.0]
    second = {**tiny_data(), "name": "tiny-b", "n": 1.4, "seed": 8}
    return [parse_recipe(first), parse_recipe(second)]


@pytest.fixture(scope="module")
def references(tmp_path_factory, tiny_data):
    """Each map of the library built in this process, one column after another."""
    d = tmp_path_factory.mktemp("ref")
    return [build_map(r, d / f"{r.name}.tmap", progress=False) for r in library(tiny_data)]


@pytest.fixture(scope="module")
def one_worker():
    with local_client(1, retries=1) as client:
        yield client


@pytest.fixture(scope="module")
def two_workers():
    with local_client(2, retries=1) as client:
        yield client


def assert_same_bits(maps, references):
    for amap, ref in zip(maps, references, strict=True):
        for f in FIELDS:
            np.testing.assert_array_equal(getattr(amap, f), getattr(ref, f), err_msg=f"{amap.name}.{f}")


def jobs(directory, tiny_data):
    return [MapJob(r, directory / f"{r.name}.tmap") for r in library(tiny_data)]


def kill_once(marker, column):
    """A tracer that kills its own worker process the first time it traces `column` (σt, g)."""
    def tracer(stack, sigma_t, g, n_paths, seed, k_max):
        if (sigma_t, g) == column and not os.path.exists(marker):
            open(marker, "w").close()
            os._exit(1)
        return trace_column(stack, sigma_t, g, n_paths, seed, k_max)
    return tracer


def always_kill(column):
    def tracer(stack, sigma_t, g, n_paths, seed, k_max):
        if (sigma_t, g) == column:
            os._exit(1)
        return trace_column(stack, sigma_t, g, n_paths, seed, k_max)
    return tracer


def always_raise(stack, sigma_t, g, n_paths, seed, k_max):
    raise RuntimeError("tracer broke")


def test_one_and_two_workers_build_the_library_bit_for_bit(tmp_path, tiny_data, references, one_worker,
                                                           two_workers):
    """A library build (both maps' columns on one cluster) on 1 and on 2 workers gives the arrays the
    in-process build gives; the provenance says what ran it."""
    for client, n in ((one_worker, 1), (two_workers, 2)):
        maps = build_maps(jobs(tmp_path / f"w{n}", tiny_data), client=client, progress=False)
        assert_same_bits(maps, references)
        assert maps[0].provenance["executor"] == f"dask ({n} workers, {n} threads)"
        assert maps[0].provenance["columns_traced_last_run"] == 6


def test_a_killed_worker_is_replaced_and_its_column_traced_again(tmp_path, tiny_data, references, two_workers):
    marker = tmp_path / "killed"
    maps = build_maps(jobs(tmp_path, tiny_data), client=two_workers, progress=False, retries=1,
                      tracer=kill_once(str(marker), (3.0, 0.6)))
    assert marker.exists()                      # the worker did die mid-build
    assert_same_bits(maps, references)


def test_a_column_that_keeps_killing_its_worker_stops_the_build_and_resume_finishes(tmp_path, tiny_data,
                                                                                    references, two_workers):
    job = jobs(tmp_path, tiny_data)[0]
    with pytest.raises(BuildError) as err:
        build_maps([job], client=two_workers, progress=False, retries=1, tracer=always_kill((30.0, 0.0)))
    message = str(err.value)
    assert "σt[2] = 30 /mm, g[0] = 0" in message and "worker died 2 times" in message and "--resume" in message
    ckpt = default_checkpoint_dir(job.out)
    assert str(ckpt) in message and not job.out.exists()
    kept = sorted(p.name for p in ckpt.glob("col_*.npz"))
    assert "col_002_000.npz" not in kept
    calls = []

    def counting(stack, sigma_t, g, n_paths, seed, k_max):
        calls.append((sigma_t, g))
        return trace_column(stack, sigma_t, g, n_paths, seed, k_max)

    resumed = build_map(job.recipe, job.out, progress=False, resume=True, tracer=counting)
    # (a column still running when the build stopped may land in the checkpoint after the listing)
    assert len(calls) <= 6 - len(kept) and (30.0, 0.0) in calls
    assert_same_bits([resumed], references[:1])


def test_a_column_that_keeps_raising_is_named(tmp_path, tiny_data, one_worker):
    job = jobs(tmp_path, tiny_data)[1]
    with pytest.raises(BuildError, match=r"failed 2 times, last with RuntimeError: tracer broke"):
        build_maps([job], client=one_worker, progress=False, retries=1, tracer=always_raise)


def test_an_unreachable_scheduler_is_one_clear_error(tmp_path, capsys):
    t0 = time.perf_counter()
    with pytest.raises(InputError, match="no Dask scheduler answered within 1 s"):
        with remote_client("tcp://127.0.0.1:9", connect_timeout=1):
            pass
    assert time.perf_counter() - t0 < 15
    recipe = tmp_path / "r.toml"
    recipe.write_text('geometry = "ideal"\nn = 1.5\nthickness_mm = 0.5\n[grid]\nalpha = [0, 0.5]\n'
                      'sigma_t = [1, 2]\ng = [0, 0.5]\n')
    for address, says in (("tcp://127.0.0.1:9", "no Dask scheduler"), ("no-such-scheme://x", "not an address")):
        assert main(["map", "build", str(recipe), "--out", str(tmp_path / "m.tmap"), "--scheduler", address,
                     "--connect-timeout", "1", "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"trimeter: error: --scheduler {address}: {says}") and err.count("\n") == 1
    assert not (tmp_path / "m.tmap").exists()


def test_a_failed_connect_leaves_no_half_built_client_for_a_later_gc():
    """A Client whose construction failed sits in a reference cycle; finalised by the cyclic GC inside a later
    LocalCluster's loop start, its close() deadlocks on the lock that start holds. So: an
    unknown scheme builds no Client, and a failed one is finalised at once, even with the GC off."""
    import gc

    import distributed

    def live_clients() -> int:
        return sum(isinstance(o, distributed.Client) for o in gc.get_objects())

    gc.collect()
    gc.disable()
    try:
        before = live_clients()
        for address in ("no-such-scheme://x", "inproc://nope"):
            with pytest.raises(InputError, match=f"--scheduler {address}"):
                with remote_client(address, connect_timeout=1):
                    pass
            assert live_clients() == before
    finally:
        gc.enable()


def test_a_scheduler_address_where_something_else_listens_is_refused_before_anything_is_read(tmp_path):
    import http.server
    import threading

    web = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    threading.Thread(target=web.serve_forever, daemon=True).start()
    talker = socket.create_server(("127.0.0.1", 0))   # answers at once, with text, as an HTTP error page would

    def talk() -> None:
        conn, _ = talker.accept()
        with conn:
            conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")
            time.sleep(1)

    threading.Thread(target=talk, daemon=True).start()
    try:
        for port, message in ((web.server_address[1], "no Dask scheduler answered"),
                              (talker.getsockname()[1], "not a Dask scheduler")):
            t0 = time.perf_counter()
            with pytest.raises(InputError, match=message):
                with remote_client(f"tcp://127.0.0.1:{port}", connect_timeout=1):
                    pass
            assert time.perf_counter() - t0 < 5
    finally:
        web.shutdown()
        web.server_close()
        talker.close()


def test_a_real_scheduler_passes_the_check():
    from distributed import LocalCluster

    with LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster:
        check_dask_scheduler(cluster.scheduler_address, connect_timeout=5)
