"""Twin benchmark: start/stop time, the Modbus proxy's cost against the bare firmware pty, and the
spectrometer's overhead against the exposure itself — all measured in the same run.

    trimeter bench twin [--map PATH] [--transactions 200] [--time-scale 20]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import select
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from trimeter.twin._rtu import RtuMaster
from trimeter.twin.twin import Twin, ensure_firmware

VENDOR_ID_REGISTER = 0  # input register 0: vendor_id (hardware/registers.toml)


def _rtt_ms(port: str, n: int) -> list[float]:
    rtu = RtuMaster(port, timeout_s=1.0, gap_s=0.0)  # back-to-back: the proxy must still see new requests
    try:
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            if rtu.read_input(VENDOR_ID_REGISTER, 5) is None:
                raise RuntimeError(f"no valid reply on {port}")
            times.append((time.perf_counter() - t0) * 1e3)
        return times
    finally:
        rtu.close()


def _bare_firmware_rtt(n: int, time_scale: float) -> list[float]:
    """Baseline: the firmware's own pty, no proxy."""
    with tempfile.TemporaryDirectory(prefix="trimeter-bench-") as tmp:
        link, plant = Path(tmp) / "modbus", Path(tmp) / "plant.sock"
        proc = subprocess.Popen([str(ensure_firmware()), "--storage", f"{tmp}/storage.bin", "--modbus-link", str(link),
                                 "--plant-link", str(plant), "--time-scale", repr(time_scale)],
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        stdout = proc.stdout
        assert stdout is not None  # stdout=PIPE
        try:
            if not select.select([stdout], [], [], 20)[0] or b"ready" not in os.read(stdout.fileno(), 64):
                raise RuntimeError("firmware sim not ready")
            return _rtt_ms(os.path.realpath(link), n)
        finally:
            proc.terminate()
            proc.wait(timeout=5)
            stdout.close()


def run(args: argparse.Namespace) -> int:
    from trimeter.spectrometer import open_spectrometer

    ensure_firmware()
    appearance_map = args.map
    starts, stops = [], []
    for _ in range(args.restarts):
        t0 = time.perf_counter()
        twin = Twin(time_scale=args.time_scale, appearance_map=appearance_map).start()
        starts.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        twin.close()
        stops.append(time.perf_counter() - t0)
    print(f"twin start {statistics.median(starts) * 1e3:7.1f} ms   stop {statistics.median(stops) * 1e3:6.1f} ms"
          f"   (median of {args.restarts}, firmware already built)")

    bare = _bare_firmware_rtt(args.transactions, args.time_scale)
    with Twin(time_scale=args.time_scale, appearance_map=appearance_map) as twin:
        assert twin.modbus_port is not None  # started
        proxied = _rtt_ms(twin.modbus_port, args.transactions)
        with contextlib.closing(open_spectrometer(twin.spectrometer_url)) as spec:
            rows = []
            for it_us in (1_000, 100_000, 1_000_000):
                spec.integration_time_us = it_us
                spec.intensities()  # warm
                walls = []
                for _ in range(args.exposures):
                    t0 = time.perf_counter()
                    spec.intensities()
                    walls.append(time.perf_counter() - t0)
                rows.append((it_us, it_us * 1e-6 / args.time_scale, statistics.median(walls)))
    b, p = statistics.median(bare), statistics.median(proxied)
    print(f"Modbus read of 5 registers: bare firmware pty {b:6.2f} ms, through the fault proxy {p:6.2f} ms "
          f"(ratio {p / b:4.2f}, +{p - b:5.2f} ms; median of {args.transactions})")
    for it_us, ideal, wall in rows:
        print(f"spectrometer ACQ at {it_us / 1e3:7.1f} ms exposure: wall {wall * 1e3:7.2f} ms vs exposure/K "
              f"{ideal * 1e3:7.2f} ms → overhead {(wall - ideal) * 1e3:5.2f} ms")
    return 0


def _parser(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    parser.add_argument("--map", default=None, help="appearance map (only loaded if a sample is inserted)")
    parser.add_argument("--transactions", type=int, default=200)
    parser.add_argument("--restarts", type=int, default=5)
    parser.add_argument("--exposures", type=int, default=10)
    parser.add_argument("--time-scale", type=float, default=20.0)
    parser.set_defaults(func=run)
    return parser


def register(bench_subparsers: argparse._SubParsersAction) -> None:
    _parser(bench_subparsers.add_parser("twin", help="twin start/stop, Modbus proxy and spectrometer overhead",
                                        description=__doc__))


if __name__ == "__main__":
    args = _parser(argparse.ArgumentParser(description=__doc__)).parse_args()
    raise SystemExit(run(args))
