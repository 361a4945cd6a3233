"""`trimeter bench http`: request latency of `GET /api/status` under many concurrent clients.

A twin and a real `trimeter serve --http 127.0.0.1:0` (its own process, polling the twin's button as
in the field) are started with the host directories in a temporary place; N aiohttp clients then ask
for the status back to back for a bounded time and count. Prints p50/p95/p99/max latency, requests
per second and errors. Loopback only: the figure is the server's, not a network's.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from trimeter.errors import InputError


async def _load(url: str, token: str, clients: int, seconds: float, max_requests: int
                ) -> tuple[list[float], int, float]:
    """(latencies of the answered requests in s, failed requests, wall seconds of the whole load)"""
    from aiohttp import ClientSession, ClientTimeout, TCPConnector

    latencies: list[float] = []
    errors = 0
    started = time.perf_counter()
    deadline = started + seconds
    headers = {"Authorization": f"Bearer {token}"}

    async def client(session: ClientSession) -> None:
        nonlocal errors
        while time.perf_counter() < deadline and len(latencies) + errors < max_requests:
            start = time.perf_counter()
            try:
                async with session.get(f"{url}/api/status", headers=headers) as response:
                    await response.read()
                    ok = response.status == 200
            except Exception:
                ok = False
            if ok:
                latencies.append(time.perf_counter() - start)
            else:
                errors += 1

    async with ClientSession(connector=TCPConnector(limit=clients), timeout=ClientTimeout(total=30)) as session:
        await asyncio.gather(*(client(session) for _ in range(clients)))
    return latencies, errors, time.perf_counter() - started


def run_bench(clients: int, seconds: float, max_requests: int, time_scale: float = 50.0) -> dict:
    from trimeter.twin import Twin

    if not 1 <= clients <= 1000:
        raise InputError(f"--clients must be within 1..1000, got {clients}")
    if not 0 < seconds <= 600:
        raise InputError(f"--seconds must be within (0, 600], got {seconds:g}")
    with tempfile.TemporaryDirectory(prefix="trimeter-bench-http-") as tmp:
        root = Path(tmp)
        env = {**os.environ, "TRIMETER_DATA_DIR": str(root / "data"), "TRIMETER_CONFIG_DIR": str(root / "config")}
        with Twin(sample=None, time_scale=time_scale, state_dir=root / "twin", seed=0) as twin:
            assert twin.modbus_port is not None  # set by start()
            serve = subprocess.Popen(
                [sys.executable, "-m", "trimeter", "serve", "--port", twin.modbus_port, "--spectrometer",
                 twin.spectrometer_url, "--http", "127.0.0.1:0"], env=env, stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT, text=True)
            try:
                url = _wait_for_url(serve)
                # its log must not fill the pipe and stall it
                assert serve.stdout is not None  # stdout=PIPE
                threading.Thread(target=serve.stdout.read, daemon=True).start()
                token = (root / "config" / "web-token").read_text().strip()
                status = _get_status(url, token)
                deadline = time.monotonic() + 30
                while status["state"] == "connecting" and time.monotonic() < deadline:
                    time.sleep(0.2)
                    status = _get_status(url, token)
                latencies, errors, wall = asyncio.run(_load(url, token, clients, seconds, max_requests))
            finally:
                serve.terminate()
                try:
                    serve.wait(15)
                except subprocess.TimeoutExpired:
                    serve.kill()
                    serve.wait()
    ms = np.asarray(latencies) * 1e3
    return {"clients": clients, "seconds": seconds, "requests": int(len(ms)), "errors": errors,
            "requests_per_s": round(len(ms) / max(wall, 1e-9), 1),
            "p50_ms": _pct(ms, 50), "p95_ms": _pct(ms, 95), "p99_ms": _pct(ms, 99),
            "max_ms": round(float(ms.max()), 2) if len(ms) else None, "server_state": status["state"]}


def _pct(ms: np.ndarray, q: float) -> float | None:
    return round(float(np.percentile(ms, q)), 2) if len(ms) else None


def _wait_for_url(serve: subprocess.Popen, timeout_s: float = 60.0) -> str:
    deadline = time.monotonic() + timeout_s
    assert serve.stdout is not None  # stdout=PIPE
    lines = []
    while time.monotonic() < deadline:
        line = serve.stdout.readline()
        if not line:
            break
        lines.append(line.rstrip())
        if match := re.search(r"web page on (http://\S+?)/ ", line):
            return match[1]
    raise InputError("trimeter serve --http did not start: " + " | ".join(lines[-5:]))


def _get_status(url: str, token: str) -> dict:
    import urllib.request

    request = urllib.request.Request(f"{url}/api/status", headers={"Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(request, timeout=10) as response:
        return json.loads(response.read())


def run(args: argparse.Namespace) -> int:
    report = run_bench(args.clients, args.seconds, args.max_requests, args.time_scale)
    print(f"GET /api/status, {report['clients']} concurrent clients, {report['seconds']:g} s on 127.0.0.1 "
          f"(server: trimeter serve --http on the twin, state {report['server_state']})")
    print(f"requests {report['requests']}  errors {report['errors']}  {report['requests_per_s']} requests/s")
    print(f"latency p50 {report['p50_ms']} ms  p95 {report['p95_ms']} ms  p99 {report['p99_ms']} ms  "
          f"max {report['max_ms']} ms")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    return 0 if report["requests"] and not report["errors"] else 1


def register(bench_subparsers: argparse._SubParsersAction) -> None:
    p = bench_subparsers.add_parser("http", help="GET /api/status latency under concurrent clients (loopback)",
                                    description=__doc__)
    p.add_argument("--clients", type=int, default=50, help="concurrent clients (default: %(default)s)")
    p.add_argument("--seconds", type=float, default=30.0, help="how long they ask (default: %(default)s)")
    p.add_argument("--max-requests", type=int, default=1_000_000, help="stop after this many (default: %(default)s)")
    p.add_argument("--time-scale", type=float, default=50.0, help="twin time scale (default: %(default)s)")
    p.add_argument("--json", help="also write the figures as JSON here")
    p.set_defaults(func=run)
