#!/usr/bin/env python3
"""Where a one-sample StreamDetect message's server CPU time goes.

    scripts/message_profile.py [--vehicles 20000] [--seconds 30] [--bin target/release]

Starts a server on a new SQLite database (pinned to core 0) and `spoofwatch bench` as a fleet of
`--vehicles` vehicles at 1 Hz, one sample per message (core 1), samples the server with `perf record`
for 10 s in the middle of the phase, and prints its CPU time grouped by what spends it (the detector,
the kernel, the async runtime, HTTP/2, ...), as shares and as µs per message (the share times the
bench's server CPU µs/sample). Needs `perf` (Debian's linux-perf) and release binaries.
"""

from __future__ import annotations

import argparse
import collections
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PORT = 50097

# Symbol prefix → what it is, first match wins.
GROUPS = [
    (r"(^|<)spoofwatch_core::", "detector (model step, evidence, alarm)"),
    (r"(^|<)(h2|hyper|hyper_util|http_body_util|http_body|tonic|tonic_prost|tower|axum)::", "HTTP/2 and gRPC framing"),
    (r"(^|<)(prost|spoofwatch_proto)::|encode_varint|decode_varint", "protobuf encoding"),
    (r"(^|<)(tokio|tokio_util|tokio_stream|futures_util|futures_core|mio)::", "async runtime, timers, channels"),
    (r"(^|<)spoofwatch_server::", "service code (sessions, validation, metrics)"),
    (r"^_?mi_|^mi_", "allocator"),
    (r"memmove|memcpy|memset|(^|<)bytes::", "copying buffers"),
]


def group_of(symbol: str, kernel: bool) -> str:
    if kernel:
        return "kernel (TCP on loopback, epoll, scheduler)"
    for pattern, name in GROUPS:
        if re.search(pattern, symbol):
            return name
    return "other (libm, libc, std, ...)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vehicles", type=int, default=20000)
    parser.add_argument("--seconds", type=int, default=30)
    parser.add_argument("--bin", type=Path, default=ROOT / "target/release")
    args = parser.parse_args()
    if args.seconds < 20:
        sys.exit("--seconds must be at least 20 (the profile takes 10 s from the middle of the phase)")
    work = Path(tempfile.mkdtemp(prefix="spoofwatch-profile."))
    server = subprocess.Popen(
        ["taskset", "-c", "0", str(args.bin / "spoofwatch-server"), "--listen", f"127.0.0.1:{PORT}",
         "--database", str(work / "db.sqlite"), "--max-sessions", "300000"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(2)
        bench = subprocess.Popen(
            ["taskset", "-c", "1", str(args.bin / "spoofwatch"), "bench", "--server", f"http://127.0.0.1:{PORT}",
             "--server-pid", str(server.pid), "--sessions", "0", "--streams", str(args.vehicles), "--batch", "1",
             "--rate", str(args.vehicles), "--seconds", str(args.seconds), "--warmup", "2"],
            stdout=subprocess.PIPE, text=True)
        # Opening the streams takes a while; the profile starts once they send.
        time.sleep(10 + args.seconds / 2 - 5)
        data = work / "perf.data"
        subprocess.run(["perf", "record", "-F", "1999", "-p", str(server.pid), "-o", str(data), "--", "sleep", "10"],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        out, _ = bench.communicate()
    finally:
        server.terminate()
        server.wait()
    row = [line for line in out.splitlines() if line.startswith(f"| {args.vehicles} |")]
    if not row:
        sys.exit(f"no result row from the bench:\n{out}")
    cells = [c.strip() for c in row[0].strip("|").split("|")]
    cpu_us = float(cells[10])
    report = subprocess.run(["perf", "report", "-i", str(data), "--no-children", "--sort", "symbol",
                             "--stdio", "-g", "none"], capture_output=True, text=True, check=True).stdout
    shares: collections.Counter[str] = collections.Counter()
    for line in report.splitlines():
        m = re.match(r"\s+([0-9.]+)%\s+\[(.)\]\s+(.*)", line)
        if m:
            shares[group_of(m.group(3).strip(), m.group(2) == "k")] += float(m.group(1))
    print(f"fleet of {args.vehicles:,} vehicles at 1 Hz, one sample per message: {out.splitlines()[-1]}")
    print(f"server CPU {cpu_us} µs per message\n")
    print("| spent in | share | µs per message |")
    print("|---|---:|---:|")
    for name, share in shares.most_common():
        print(f"| {name} | {share:.1f} % | {share / 100 * cpu_us:.1f} |")


if __name__ == "__main__":
    main()
