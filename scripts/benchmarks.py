#!/usr/bin/env python3
"""Spoofwatch's benchmark rows: run them, keep their results as JSON, render the benchmark page.

    scripts/benchmarks.py list                     # every row, its command and whether it was measured
    scripts/benchmarks.py run [--only ID,..] [--group G,..] [--runs 3] [--bin target/release]
    scripts/benchmarks.py compare --only ID,.. --before DIR --before-label COMMIT [--runs 3]
    scripts/benchmarks.py render                   # docs/benchmarks.md from docs/benchmarks/results.json
    scripts/benchmarks.py check                    # fails when the page is not the JSON's rendering

`run` measures each selected row `--runs` times (3 by default), each time on a new server and a new
database: the server pinned to core 0 (`taskset -c 0`), the load generator to core 1. Before every run
it notes the load average (as `uptime` shows it). It stores each run's values, their median and range,
the machine, the git commit and the date in docs/benchmarks/results.json, row by row as they finish,
and renders the page. `compare` runs rows against two server builds, alternating run by run (before,
after, before, ...) so that both see the same machine, with one load generator (`--bin`'s), and
keeps the pairs in docs/benchmarks/compare.json. Rows it did not run keep their earlier result, with that result's own date and
commit; a row never measured is listed as such. Numbers are never typed in by hand.

Needs release binaries (`cargo build --release -p spoofwatch-server -p spoofwatch-client
-p spoofwatch-lab`), taskset, and for the PostgreSQL rows Debian's postgresql (scripts/postgres-ephemeral.sh).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "benchmarks" / "results.json"
COMPARISON = ROOT / "docs" / "benchmarks" / "compare.json"
PAGE = ROOT / "docs" / "benchmarks.md"
PORT, SECOND_PORT, METRICS_PORT, PG_PORT = 50093, 50094, 9493, 55493
SCHEMA = 1

# ---------------------------------------------------------------------------------------------------
# The rows. `bench` rows run `spoofwatch bench` against one server; `memory` rows its memory phase;
# `handoff` rows move vehicles between two servers on one PostgreSQL database; `criterion` rows run a
# criterion bench of spoofwatch-core; `command` rows time a whole command.

GROUPS = [
    ("model", "Detector, one core",
     "The detector's own cost, without gRPC: criterion benches of `spoofwatch-core` on one core. "
     "A vehicle's step is the model step plus the evidence builder's per-sample cost."),
    ("grpc", "gRPC detection, one server",
     "One server on SQLite (`spoofwatch-server` on core 0) and `spoofwatch bench` as the load "
     "generator (core 1). With a rate, every stream sends on its own schedule and *delivered* is the "
     "share of the messages due within the phase that were answered (late answers count: the "
     "percentiles show how late). Without a rate every stream sends its next message as soon as its "
     "reply is back (saturation): the p99 there is queueing, not service time. *CPU* is the server "
     "process's CPU time per sample."),
    ("fleet", "Vehicle fleets at 1 Hz",
     "Every vehicle sends one sample per second, the phases of the vehicles spread over the second. "
     "A *fleet* row gives each vehicle its own StreamDetect stream, 50 streams per connection; a "
     "*gateway* row carries 100 vehicles per StreamDetectFleet message. *A connection's vehicles "
     "together* (`--spread connections`): the vehicles of one connection send at the same moment "
     "of the second, as a gateway forwarding its vehicles' fixes of one GNSS second does, and the "
     "connections are spread over the second. *Unpinned*: server and load generator share both "
     "cores. Goal for a fleet: p99 ≤ 10 ms with every sample answered (≤ 50 ms at 50,000)."),
    ("modes", "Metrics and TLS",
     "The same rows with `--metrics-listen` (scraped after the run) or with TLS "
     "(`--tls-cert/--tls-key`, the client trusting the CA with `--ca-cert`)."),
    ("storage", "SQLite and PostgreSQL",
     "One server on a new SQLite file or on a new database of a local PostgreSQL "
     "(`scripts/postgres-ephemeral.sh`, `fsync=off`), with the default snapshot policy."),
    ("handoff", "Session hand-off",
     "1,000 vehicles stream 6 batches of 10 to one server and end their streams; then each starts on "
     "a second server on the same PostgreSQL database, which never held them, resumes from its "
     "snapshot and sends its next batch. Beside them, as many vehicles never seen start there. Timed "
     "from the start request to the first detection. Noticing the failure and reconnecting (the "
     "balancer's health check, the client's back-off) come before and are not included."),
    ("memory", "Memory",
     "Idle sessions: the server's resident memory grows by this much per session opened "
     "(one stream start and one batch each, then the stream ends)."),
    ("admin", "Detection beside administrative work",
     "A fleet streams while an administrator works on the same server (`--admin-load`, on "
     "connections of its own): two clients upload datasets of 100,000 structured records, every "
     "record its own vehicle, back to back; one imports a model of about 300,000 parameters, back "
     "to back; four score 1,000-sample Detect calls on such a model without pause; and a health "
     "check goes every 50 ms. *health* is the health checks' round trip; *done* counts the pieces "
     "of admin work finished during the phase. Goal: health p99 ≤ 50 ms, and the fleet at 100 % "
     "delivered with p99 ≤ 20 ms."),
    ("uploads", "Dataset uploads",
     "One server on SQLite receives a telemetry CSV of 128 MiB (2.1 million rows, 1,000 vehicles) "
     "through `spoofwatch datasets upload`, in 1 MiB chunks. *Peak RSS* is the server process's "
     "high-water mark (`VmHWM` in `/proc/PID/status`) after the upload, its whole memory and not "
     "only the upload's; *idle* is its resident memory before the upload. Goal: the peak stays "
     "within twice the upload's size."),
    ("experiments", "Experiments",
     "Wall time of whole research commands (`spoofwatch-lab`, AV-GPS data in `$D`)."),
]

THROUGHPUT = ["samples_per_s", "p50_ms", "p99_ms", "p999_ms", "max_ms", "delivered_pct",
              "cpu_us_per_sample", "rss_mib"]


def bench_row(id, group, title, args, goal="", server=(), backend="sqlite", mode="plain", heavy=False,
              pinned=True):
    return dict(id=id, group=group, title=title, kind="bench", client_args=list(args),
                server_args=list(server), backend=backend, mode=mode, goal=goal, heavy=heavy,
                pinned=pinned)


STREAM_60K = ["--streams", "100", "--rate", "60000", "--seconds", "10"]
FLEET_10K = ["--streams", "10000", "--batch", "1", "--rate", "10000", "--seconds", "30"]
FLEET_20K = ["--streams", "20000", "--batch", "1", "--rate", "20000", "--seconds", "30", "--warmup", "2"]
FLEET_50K = ["--streams", "50000", "--batch", "1", "--rate", "50000", "--seconds", "30", "--warmup", "2"]
GATEWAY_SAT = ["--streams", "1000", "--batch", "1", "--vehicles-per-message", "100", "--seconds", "10"]

ROWS = [
    dict(id="evidence-builder", group="model", kind="criterion", bench="evidence",
         title="evidence builder, one vehicle", goal="", heavy=False),
    dict(id="model-step", group="model", kind="criterion", bench="model",
         title="model step, one vehicle; 1,000 vehicles one step; one training epoch",
         goal="step + evidence ≤ 5 µs", heavy=False),
    dict(id="incident-areas", group="model", kind="criterion", bench="incident_areas",
         title="a vehicle's step with the area prior's lookup, 0, 10 and 10,000 open incidents",
         goal="10,000 open incidents cost within 10 % of none", heavy=False),
    dict(id="vehicle-step", group="model", kind="criterion", bench="vehicle_step",
         title="a vehicle's whole step with the bundled model (evidence, model, alarm and severity), "
               "1 and 10 Hz", goal="step + evidence ≤ 5 µs", heavy=False),
    bench_row("stream-100-rate-60k", "grpc", "100 streams, 60,000 samples/s offered, batches of 10",
              STREAM_60K, goal="≥ 50,000 samples/s, p99 ≤ 5 ms"),
    bench_row("saturation-100-batch-1", "grpc", "saturation, 100 streams, batches of 1",
              ["--streams", "100", "--batch", "1", "--seconds", "10"]),
    bench_row("saturation-1000-batch-1", "grpc", "saturation, 1,000 streams, batches of 1",
              ["--streams", "1000", "--batch", "1", "--seconds", "10"]),
    bench_row("saturation-100-batch-10", "grpc", "saturation, 100 streams, batches of 10",
              ["--streams", "100", "--batch", "10", "--seconds", "10"]),
    bench_row("saturation-1000-batch-10", "grpc", "saturation, 1,000 streams, batches of 10",
              ["--streams", "1000", "--batch", "10", "--seconds", "10"]),
    bench_row("fleet-10000", "fleet", "fleet, 10,000 vehicles, one sample per message", FLEET_10K,
              goal="p99 ≤ 10 ms, 100 % delivered"),
    bench_row("fleet-10000-shadow", "fleet",
              "fleet, 10,000 vehicles, one sample per message, a shadow model on every vehicle",
              [*FLEET_10K, "--shadow", "models/default"], goal="p99 ≤ 10 ms, 100 % delivered"),
    bench_row("fleet-20000", "fleet", "fleet, 20,000 vehicles, one sample per message", FLEET_20K,
              goal="p99 ≤ 10 ms, 100 % delivered", heavy=True),
    bench_row("fleet-20000-500-per-connection", "fleet",
              "fleet, 20,000 vehicles, one sample per message, 500 streams per connection",
              [*FLEET_20K, "--streams-per-connection", "500"], heavy=True),
    bench_row("fleet-50000", "fleet", "fleet, 50,000 vehicles, one sample per message", FLEET_50K,
              server=["--max-sessions", "300000"], heavy=True),
    bench_row("fleet-20000-by-connection", "fleet",
              "fleet, 20,000 vehicles, one sample per message, a connection's vehicles together",
              [*FLEET_20K, "--spread", "connections"], goal="p99 ≤ 10 ms, 100 % delivered", heavy=True),
    bench_row("fleet-50000-by-connection", "fleet",
              "fleet, 50,000 vehicles, one sample per message, a connection's vehicles together",
              [*FLEET_50K, "--spread", "connections"], server=["--max-sessions", "300000"],
              goal="p99 ≤ 50 ms, 100 % delivered", heavy=True),
    bench_row("fleet-50000-by-connection-unpinned", "fleet",
              "fleet, 50,000 vehicles, one sample per message, a connection's vehicles together, "
              "unpinned",
              [*FLEET_50K, "--spread", "connections"], server=["--max-sessions", "300000"],
              goal="p99 ≤ 50 ms, 100 % delivered", heavy=True, pinned=False),
    bench_row("gateway-100000", "fleet", "gateway, 100,000 vehicles, 100 per message",
              ["--streams", "100000", "--batch", "1", "--rate", "100000", "--vehicles-per-message",
               "100", "--seconds", "30"], server=["--max-sessions", "300000"], heavy=True),
    bench_row("gateway-saturation-1000", "fleet", "gateway saturation, 1,000 vehicles, 100 per message",
              GATEWAY_SAT),
    bench_row("gateway-saturation-10000", "fleet",
              "gateway saturation, 10,000 vehicles, 100 per message",
              ["--streams", "10000", "--batch", "1", "--vehicles-per-message", "100", "--seconds", "10"]),
    bench_row("fleet-1000-admin-load", "admin",
              "fleet, 1,000 vehicles at 1 Hz, one sample per message, beside admin work",
              ["--streams", "1000", "--batch", "1", "--rate", "1000", "--seconds", "30",
               "--admin-load"], goal="health p99 ≤ 50 ms; fleet p99 ≤ 20 ms, 100 % delivered"),
    bench_row("stream-100-rate-60k-metrics", "modes", "100 streams, 60,000/s offered: metrics on",
              STREAM_60K, mode="metrics"),
    bench_row("stream-100-rate-60k-tls", "modes", "100 streams, 60,000/s offered: TLS on",
              STREAM_60K, mode="tls"),
    bench_row("fleet-10000-metrics", "modes", "fleet, 10,000 vehicles: metrics on", FLEET_10K,
              mode="metrics"),
    bench_row("fleet-10000-tls", "modes", "fleet, 10,000 vehicles: TLS on", FLEET_10K, mode="tls"),
    bench_row("gateway-saturation-1000-metrics", "modes", "gateway saturation, 1,000 vehicles: metrics on",
              GATEWAY_SAT, mode="metrics"),
    bench_row("gateway-saturation-1000-tls", "modes", "gateway saturation, 1,000 vehicles: TLS on",
              GATEWAY_SAT, mode="tls"),
    bench_row("saturation-100-batch-10-postgres", "storage",
              "saturation, 100 streams, batches of 10, PostgreSQL",
              ["--streams", "100", "--batch", "10", "--seconds", "10"], backend="postgres"),
    bench_row("gateway-saturation-1000-postgres", "storage",
              "gateway saturation, 1,000 vehicles, PostgreSQL", GATEWAY_SAT, backend="postgres"),
    bench_row("fleet-10000-postgres", "storage", "fleet, 10,000 vehicles, PostgreSQL", FLEET_10K,
              backend="postgres"),
    dict(id="handoff-one-at-a-time", group="handoff", kind="handoff", concurrency=1,
         title="1,000 vehicles, one at a time", goal="", heavy=False),
    dict(id="handoff-all-at-once", group="handoff", kind="handoff", concurrency=1000,
         title="1,000 vehicles at once (a whole server failing over)", goal="", heavy=False),
    dict(id="idle-sessions-10000", group="memory", kind="memory", sessions=10000,
         title="10,000 idle sessions", goal="≤ 4 KiB per session", heavy=False),
    dict(id="idle-sessions-100000", group="memory", kind="memory", sessions=100000,
         title="100,000 idle sessions", goal="≤ 4 KiB per session", heavy=True),
    dict(id="upload-csv-128mib", group="uploads", kind="upload-memory", mib=128,
         title="CSV upload of 128 MiB", goal="peak RSS ≤ 2 × the upload (256 MiB)", heavy=False),
    dict(id="experiment-av-gps", group="experiments", kind="command",
         title="av-gps experiment (23 models)",
         argv=["spoofwatch-lab", "experiment", "av-gps", "--data-dir", "$D", "--out", "$OUT"],
         goal="", heavy=True),
    dict(id="experiment-av-gps-5-seeds", group="experiments", kind="command",
         title="av-gps comparison over five seeds",
         argv=["spoofwatch-lab", "experiment", "av-gps", "--data-dir", "$D", "--out", "$OUT",
               "--seeds", "5"], goal="≤ 5 min", heavy=True),
    # The fit's own time is the report's `fit_wall_time_s`; the wall time adds simulating the fleet.
    dict(id="fleet-fit-100-vehicle-hours", group="experiments", kind="command",
         title="a fleet fit of 100 vehicle-hours (50 simulated vehicles × 4 drives of 30 min at 5 Hz, "
               "10 epochs)",
         argv=["spoofwatch-lab", "experiment", "fleet-fit", "--fleet", "wide-sensors", "--out", "$OUT",
               "--seed", "42", "--vehicles", "50", "--drives-per-vehicle", "4", "--clean-hours", "0"],
         report_values={"fit_wall_time_s": "fit_s"}, goal="the fit ≤ 5 min", heavy=True),
]


def display_command(row: dict) -> str:
    """The command a reader runs to reproduce the row (against their own server)."""
    kind = row["kind"]
    if kind == "criterion":
        return f"cargo bench -p spoofwatch-core --bench {row['bench']}"
    if kind == "command":
        return " ".join(row["argv"])
    if kind == "upload-memory":
        return (f"spoofwatch-server · spoofwatch datasets upload --server URL --file "
                f"telemetry-{row['mib']}mib.csv")
    if kind == "handoff":
        return ("spoofwatch bench --server URL_A --handoff-to URL_B --handoff 1000 "
                f"--handoff-concurrency {row['concurrency']}")
    server = ["spoofwatch-server"] + row.get("server_args", [])
    client = ["spoofwatch", "bench", "--server", "URL", "--server-pid", "PID"]
    if kind == "memory":
        server += ["--session-idle-secs", "600"]
        client += ["--streams", "1", "--seconds", "1", "--sessions", str(row["sessions"])]
    else:
        mode = row.get("mode", "plain")
        if mode == "metrics":
            server += ["--metrics-listen", "ADDR"]
        elif mode == "tls":
            server += ["--tls-cert", "server.pem", "--tls-key", "server-key.pem"]
            client[3] = "https://HOST:PORT"
            client += ["--ca-cert", "ca.pem"]
        if row.get("backend") == "postgres":
            server += ["--database", "postgres://…"]
        client += ["--sessions", "0"] + row["client_args"]
    return " ".join(server) + " · " + " ".join(client)


# ---------------------------------------------------------------------------------------------------
# Measuring.

def sh(*argv: str, **kw) -> str:
    return subprocess.run(argv, check=True, capture_output=True, text=True, **kw).stdout.strip()


def loadavg() -> list[float]:
    return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]


def machine() -> dict:
    cpu = "unknown"
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            cpu = line.split(":", 1)[1].strip()
            break
    mem_kib = int(re.search(r"MemTotal:\s+(\d+)", Path("/proc/meminfo").read_text()).group(1))
    os_name = "unknown"
    if Path("/etc/os-release").exists():
        m = re.search(r'PRETTY_NAME="([^"]*)"', Path("/etc/os-release").read_text())
        os_name = m.group(1) if m else os_name
    try:
        rustc = sh("rustc", "--version")
    except (OSError, subprocess.CalledProcessError):
        rustc = "unknown"
    return dict(cpu=cpu, cores=os.cpu_count(), memory_gib=round(mem_kib / 2**20, 1),
                kernel=platform.release(), os=os_name, rustc=rustc)


def provenance() -> dict:
    commit = sh("git", "rev-parse", "--short=8", "HEAD", cwd=ROOT)
    source = ["core", "server", "client", "proto", "lab", "baselines", "migrations", "models",
              "Cargo.lock"]
    dirty = bool(sh("git", "status", "--porcelain", "--", *source, cwd=ROOT))
    return dict(commit=commit, source_modified=dirty,
                date=datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"))


def wait_for_port(port: int, proc: subprocess.Popen, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the server exited with {proc.returncode}")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                time.sleep(0.5)  # the default model loads on the first stream; let startup settle
                return
        time.sleep(0.1)
    raise RuntimeError(f"no server on port {port} after {timeout} s")


def stop(proc: subprocess.Popen | None) -> None:
    """Stops a server this script started (by its process id) and waits for its drain."""
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class Env:
    """What the runs share: binaries, a work directory, certificates, PostgreSQL when needed."""

    def __init__(self, bin_dir: Path):
        self.bin = bin_dir
        # The server's build when it is not --bin's (`compare`).
        self.server_bin: Path | None = None
        # The source checkout a criterion row is built from when it is not this one (`compare`).
        self.source: Path | None = None
        self.work = Path(tempfile.mkdtemp(prefix="spoofwatch-bench."))
        os.chmod(self.work, 0o755)
        self.pg_url: str | None = None
        self.databases = 0
        self.certs = False

    def tool(self, name: str) -> str:
        path = self.bin / name
        if not path.exists():
            sys.exit(f"{path} is missing: cargo build --release -p spoofwatch-server "
                     "-p spoofwatch-client -p spoofwatch-lab")
        return str(path)

    def make_certs(self) -> None:
        if self.certs:
            return
        w = self.work
        quiet = dict(stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt",
                        "ec_paramgen_curve:P-256", "-nodes", "-days", "2", "-subj", "/CN=bench CA",
                        "-keyout", w / "ca-key.pem", "-out", w / "ca.pem"], **quiet)
        subprocess.run(["openssl", "req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256",
                        "-nodes", "-subj", "/CN=bench", "-keyout", w / "server-key.pem", "-out",
                        w / "server.csr"], **quiet)
        (w / "san.ext").write_text("subjectAltName=IP:127.0.0.1\n")
        subprocess.run(["openssl", "x509", "-req", "-in", w / "server.csr", "-CA", w / "ca.pem",
                        "-CAkey", w / "ca-key.pem", "-CAcreateserial", "-days", "2", "-out",
                        w / "server.pem", "-extfile", w / "san.ext"], **quiet)
        self.certs = True

    def database(self, backend: str) -> str:
        self.databases += 1
        if backend == "sqlite":
            return str(self.work / f"bench{self.databases}.db")
        if self.pg_url is None:
            self.pg_url = sh(str(ROOT / "scripts/postgres-ephemeral.sh"), "start",
                             str(self.work / "pg"), str(PG_PORT))
        name = f"bench{self.databases}"
        psql = shutil.which("psql") or sorted(Path("/usr/lib/postgresql").glob("*/bin/psql"))[-1]
        sh(str(psql), self.pg_url, "-qc", f"CREATE DATABASE {name}")
        return self.pg_url.rsplit("/", 1)[0] + "/" + name

    def server(self, port: int, database: str, flags: list[str], core: int | None) -> subprocess.Popen:
        log = open(self.work / f"server-{port}.log", "w")
        server = str(self.server_bin / "spoofwatch-server") if self.server_bin else self.tool("spoofwatch-server")
        proc = subprocess.Popen([*pinned_to(core), server,
                                 "--listen", f"127.0.0.1:{port}", "--database", database, *flags],
                                stdout=log, stderr=subprocess.STDOUT)
        wait_for_port(port, proc)
        return proc

    def close(self) -> None:
        if self.pg_url is not None:
            subprocess.run([str(ROOT / "scripts/postgres-ephemeral.sh"), "stop", str(self.work / "pg")],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        shutil.rmtree(self.work, ignore_errors=True)


def number(cell: str) -> float | None:
    cell = cell.strip().rstrip("%").strip()
    return None if cell in ("-", "") else float(cell)


def parse_table(text: str, first: str) -> list[list[str]]:
    """The cells of the markdown table rows of `text` whose first cell matches `first`."""
    rows = []
    for line in text.splitlines():
        if line.startswith("|") and not line.startswith("|-") and not line.startswith("|:"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if re.fullmatch(first, cells[0]):
                rows.append(cells)
    return rows


def pinned_to(core: int | None) -> list[str]:
    """The prefix that runs a command on `core` alone (`None`: on every core)."""
    return [] if core is None else ["taskset", "-c", str(core)]


def client(env: Env, argv: list[str], timeout: float, core: int | None = 1) -> str:
    out = subprocess.run([*pinned_to(core), env.tool("spoofwatch"), *argv], capture_output=True,
                         text=True, timeout=timeout)
    if out.returncode != 0:
        raise RuntimeError(f"spoofwatch {' '.join(argv)} failed:\n{out.stdout}\n{out.stderr}")
    return out.stdout


def run_bench(env: Env, row: dict) -> dict:
    flags = list(row.get("server_args", []))
    url = f"http://127.0.0.1:{PORT}"
    extra_client: list[str] = []
    mode = row.get("mode", "plain")
    if mode == "metrics":
        flags += ["--metrics-listen", f"127.0.0.1:{METRICS_PORT}"]
    elif mode == "tls":
        env.make_certs()
        flags += ["--tls-cert", str(env.work / "server.pem"), "--tls-key", str(env.work / "server-key.pem")]
        url = f"https://127.0.0.1:{PORT}"
        extra_client = ["--ca-cert", str(env.work / "ca.pem")]
    if row["kind"] == "memory":
        flags += ["--session-idle-secs", "600"]
        args = ["--streams", "1", "--seconds", "1", "--sessions", str(row["sessions"])]
    else:
        args = ["--sessions", "0", *row["client_args"]]
    pinned = row.get("pinned", True)
    server = env.server(PORT, env.database(row.get("backend", "sqlite")), flags,
                        core=0 if pinned else None)
    try:
        out = client(env, ["bench", "--server", url, *extra_client, "--server-pid", str(server.pid),
                           *args], timeout=900, core=1 if pinned else None)
        if mode == "metrics":
            subprocess.run(["curl", "-sf", f"127.0.0.1:{METRICS_PORT}/metrics"],
                           stdout=subprocess.DEVNULL, check=True)
    finally:
        stop(server)
    if row["kind"] == "memory":
        m = re.search(r"= ([0-9.]+) KiB per session", out)
        if not m:
            raise RuntimeError(f"no memory line in:\n{out}")
        return {"kib_per_session": float(m.group(1))}
    cells = parse_table(out, r"[0-9]+")
    if len(cells) != 1:
        raise RuntimeError(f"expected one result row in:\n{out}")
    c = cells[0]
    values = dict(zip(THROUGHPUT, [number(c[3]), number(c[5]), number(c[6]), number(c[7]),
                                   number(c[8]), number(c[9]), number(c[10]), number(c[11])]))
    values["errors"] = float(c[12])
    if "--admin-load" in args:
        values.update(admin_values(out))
    if "--shadow" in args:
        values.update(shadow_values(out))
    return values


def shadow_values(out: str) -> dict:
    """The shadow table's samples scored and shed and the candidate's scoring time per sample."""
    cells = parse_table(out, r"shadow")
    cells = [c for c in cells if c[1] != "scored"]
    if len(cells) != 1:
        raise RuntimeError(f"no shadow table in:\n{out}")
    c = cells[0]
    return {"shadow_scored": number(c[1]), "shadow_shed": number(c[2]),
            "shadow_shed_pct": number(c[3]), "shadow_us_per_sample": number(c[4])}


ADMIN_WORK = {"health check": "health", "dataset upload": "uploads", "model import": "imports",
              "Detect, 1,000 samples": "heavy_detects"}


def admin_values(out: str) -> dict:
    """The admin-load table's health percentiles and the count of each kind of work done."""
    values = {}
    for cells in parse_table(out, r"health check|dataset upload.*|model import.*|Detect, 1,000.*"):
        key = next(v for k, v in ADMIN_WORK.items() if cells[0].startswith(k))
        if key == "health":
            values.update(health_p50_ms=number(cells[2]), health_p99_ms=number(cells[3]),
                          health_max_ms=number(cells[4]))
        else:
            values[f"{key}_done"] = number(cells[1])
    if len(values) != 6:
        raise RuntimeError(f"no complete admin-load table in:\n{out}")
    return values


def run_handoff(env: Env, row: dict) -> dict:
    database = env.database("postgres")
    target = env.server(PORT, database, [], core=0)
    source = env.server(SECOND_PORT, database, [], core=1)
    try:
        out = client(env, ["bench", "--server", f"http://127.0.0.1:{SECOND_PORT}", "--handoff-to",
                           f"http://127.0.0.1:{PORT}", "--handoff", "1000", "--handoff-concurrency",
                           str(row["concurrency"])], timeout=900)
    finally:
        stop(source)
        stop(target)
    values = {}
    for cells in parse_table(out, r"from the snapshot|fresh \(never seen\)"):
        key = "snapshot" if cells[0].startswith("from") else "fresh"
        values[f"{key}_accepted_p50_ms"] = number(cells[2])
        values[f"{key}_first_detection_p50_ms"] = number(cells[4])
        values[f"{key}_first_detection_p99_ms"] = number(cells[5])
        values[f"{key}_first_detection_max_ms"] = number(cells[6])
    if len(values) != 8:
        raise RuntimeError(f"no hand-off table in:\n{out}")
    return values


# Criterion bench ids and what a reader calls them; per element where the bench sets a throughput.
CRITERION_NAMES = {
    "evidence_builder/wgs84_local": "evidence, paper ξ_t, µs per sample",
    "evidence_builder/equirectangular": "evidence, equirectangular projection, µs per sample",
    "evidence_builder/per_step_sigma": "evidence with per-sample uncertainties, µs per sample",
    "evidence_builder/v2_drift_channels": "evidence v2 (drift and integrity channels), µs per sample",
    "evidence_builder/v3_offset_channels": "evidence v3 (offset channels), µs per sample",
    "step_one_vehicle": "model step, one vehicle, µs",
    "step/1000_vehicles": "1,000 vehicles one step each, µs per vehicle",
    "train/epoch_5000_rows": "training epoch, µs per row",
    "incident_areas_step/0": "step and lookup, no open incident, µs per sample",
    "incident_areas_step/10": "step and lookup, 10 open incidents, µs per sample",
    "incident_areas_step/10000": "step and lookup, 10,000 open incidents, µs per sample",
    "incident_areas_lookup/10": "lookup alone, 10 open incidents, µs",
    "incident_areas_lookup/10000": "lookup alone, 10,000 open incidents, µs",
    "incident_areas_lookup/10000_linear": "lookup alone testing every area (no index), 10,000 open incidents, µs",
    "vehicle_step/1hz": "a vehicle's step at 1 Hz, µs per sample",
    "vehicle_step/10hz": "a vehicle's step at 10 Hz, µs per sample",
}
# Ratios of two criterion values a row reports besides them: (name, numerator, denominator).
CRITERION_RATIOS = {
    "incident_areas": [("10,000 open incidents over none, per sample",
                        "incident_areas_step/10000", "incident_areas_step/0")],
}


def run_criterion(env: Env, row: dict) -> dict:
    # `compare` measures an earlier commit's checkout (`env.source`); every other run this one.
    source = env.source or ROOT
    target = (Path(os.environ["CARGO_TARGET_DIR"]) if "CARGO_TARGET_DIR" in os.environ and source == ROOT
              else source / "target") / "criterion"
    subprocess.run(["cargo", "bench", "--locked", "-p", "spoofwatch-core", "--bench", row["bench"], "--",
                    "--measurement-time", "3"], cwd=source, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    values = {}
    for bench, name in CRITERION_NAMES.items():
        new = target / bench / "new"
        prefixes = {"evidence": ("evidence_builder/",), "model": ("step", "train/"),
                    "incident_areas": ("incident_areas_",), "vehicle_step": ("vehicle_step/",)}[row["bench"]]
        if not (new / "estimates.json").exists() or not bench.startswith(prefixes):
            continue
        ns = json.loads((new / "estimates.json").read_text())["median"]["point_estimate"]
        throughput = json.loads((new / "benchmark.json").read_text()).get("throughput") or {}
        elements = throughput.get("Elements", 1)
        values[name] = round(ns / elements / 1000, 4)
    if not values:
        raise RuntimeError(f"no criterion estimates under {target}")
    for name, numerator, denominator in CRITERION_RATIOS.get(row["bench"], []):
        ratio = values[CRITERION_NAMES[numerator]] / values[CRITERION_NAMES[denominator]]
        values[name] = round(ratio, 3)
    return values


def run_command(env: Env, row: dict) -> dict:
    data = os.environ.get("SPOOFWATCH_AVGPS_DIR", str(ROOT.parent / "shared/data/av-gps"))
    out = env.work / f"out-{time.monotonic_ns()}"
    argv = [a.replace("$D", data).replace("$OUT", str(out)) for a in row["argv"]]
    argv[0] = env.tool(argv[0])
    started = time.monotonic()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    # wait4: this command's own CPU time and peak memory, not those of earlier children.
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.monotonic() - started
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed with {proc.returncode}")
    values = {"wall_s": round(wall, 1), "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
              "peak_rss_mib": round(usage.ru_maxrss / 1024)}
    # Times the command measured of its own parts, from its report.
    if row.get("report_values"):
        report = json.loads((out / "report.json").read_text())
        for field, name in row["report_values"].items():
            values[name] = round(report[field], 1)
    shutil.rmtree(out, ignore_errors=True)
    return values


def telemetry_csv(path: Path, size: int) -> None:
    """A telemetry CSV of exactly `size` bytes or just under: 1,000 vehicles at 1 Hz, labelled,
    the same file on every run (a fixed seed)."""
    if path.exists() and path.stat().st_size > size - 200:
        return
    import random
    rnd = random.Random(1)
    with open(path, "w") as f:
        written = f.write("vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,label\n")
        n = 0
        while True:
            vehicle, t = n % 1000, n // 1000
            line = (f"vehicle-{vehicle:04d},{1_700_000_000 + t},{32.2 + vehicle * 1e-3 + t * 1e-5:.7f},"
                    f"{-110.9 + t * 1e-5:.7f},{10 + rnd.random():.3f},{rnd.random() * 360:.2f},"
                    f"{int(t > 1500)}\n")
            if written + len(line) > size:
                return
            written += f.write(line)
            n += 1


def memory_kib(pid: int, field: str) -> int:
    m = re.search(rf"{field}:\s+(\d+) kB", Path(f"/proc/{pid}/status").read_text())
    if not m:
        raise RuntimeError(f"no {field} for process {pid}")
    return int(m.group(1))


def run_upload_memory(env: Env, row: dict) -> dict:
    size = row["mib"] << 20
    csv = env.work / f"telemetry-{row['mib']}mib.csv"
    telemetry_csv(csv, size)
    server = env.server(PORT, env.database("sqlite"), [], core=0)
    try:
        idle = memory_kib(server.pid, "VmRSS")
        out = client(env, ["datasets", "upload", "--server", f"http://127.0.0.1:{PORT}", "--file",
                           str(csv)], timeout=600)
        if "rows" not in out:
            raise RuntimeError(f"the upload did not report its dataset:\n{out}")
        peak = memory_kib(server.pid, "VmHWM")
    finally:
        stop(server)
    upload_mib = csv.stat().st_size / 2**20
    return {"upload_mib": round(upload_mib, 1), "idle_rss_mib": round(idle / 1024, 1),
            "peak_rss_mib": round(peak / 1024, 1),
            "peak_over_upload": round(peak / 1024 / upload_mib, 2)}


RUNNERS = {"bench": run_bench, "memory": run_bench, "handoff": run_handoff,
           "criterion": run_criterion, "command": run_command, "upload-memory": run_upload_memory}


def summarise(runs: list[dict]) -> dict:
    keys = [k for k in runs[0]["values"]]
    out = {}
    for key in keys:
        xs = [r["values"][key] for r in runs if r["values"].get(key) is not None]
        if xs:
            out[key] = dict(median=statistics.median(xs), min=min(xs), max=max(xs))
    return out


# ---------------------------------------------------------------------------------------------------
# The JSON and the page.

def load_results() -> dict:
    if RESULTS.exists():
        return json.loads(RESULTS.read_text())
    return dict(schema=SCHEMA, rows={})


def catalogue(results: dict) -> dict:
    """The JSON with every row of the script (definition refreshed, measurements kept)."""
    rows = {}
    for row in ROWS:
        old = results["rows"].get(row["id"], {})
        rows[row["id"]] = dict(group=row["group"], title=row["title"], command=display_command(row),
                               goal=row.get("goal", ""), heavy=row.get("heavy", False),
                               measured=old.get("measured"))
    return dict(schema=SCHEMA, generated_by="scripts/benchmarks.py run", rows=rows)


def save(results: dict) -> None:
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=1, ensure_ascii=False) + "\n")
    PAGE.write_text(render(results))


def fmt(x: float) -> str:
    if x >= 1000:
        return f"{x:,.0f}"
    if x >= 100:
        return f"{x:.0f}"
    if x >= 10:
        return f"{x:.1f}"
    if x >= 1:
        return f"{x:.2f}"
    return f"{x:.3g}"


def stat(summary: dict, key: str, unit: str = "") -> str | None:
    s = summary.get(key)
    if s is None:
        return None
    text = fmt(s["median"]) + unit
    if s["min"] != s["max"]:
        text += f" ({fmt(s['min'])}–{fmt(s['max'])})"
    return text


LABELS = [("samples_per_s", "", "/s"), ("p50_ms", "p50 ", " ms"), ("p99_ms", "**p99** ", " ms"),
          ("p999_ms", "p99.9 ", " ms"), ("max_ms", "max ", " ms"), ("delivered_pct", "delivered ", " %"),
          ("cpu_us_per_sample", "CPU ", " µs/sample"), ("rss_mib", "RSS ", " MiB"),
          ("kib_per_session", "**", " KiB per session**"), ("fit_s", "**the fit** ", " s"),
          ("wall_s", "wall ", " s"),
          ("cpu_s", "CPU ", " s"), ("peak_rss_mib", "peak RSS ", " MiB"),
          ("idle_rss_mib", "idle ", " MiB"), ("upload_mib", "upload ", " MiB"),
          ("peak_over_upload", "**peak ", " × the upload**"),
          ("health_p50_ms", "health p50 ", " ms"), ("health_p99_ms", "**health p99** ", " ms"),
          ("health_max_ms", "health max ", " ms"), ("uploads_done", "uploads done ", ""),
          ("imports_done", "imports done ", ""), ("heavy_detects_done", "heavy Detect calls done ", ""),
          ("shadow_scored", "shadow scored ", " samples"), ("shadow_shed", "**shed** ", " samples"),
          ("shadow_shed_pct", "", " % shed"),
          ("shadow_us_per_sample", "candidate's scoring ", " µs/sample")]


def handoff_text(summary: dict) -> str:
    parts = []
    for key, label in (("snapshot", "from the snapshot"), ("fresh", "fresh (never seen)")):
        accepted = stat(summary, f"{key}_accepted_p50_ms", " ms")
        p50 = stat(summary, f"{key}_first_detection_p50_ms", " ms")
        p99 = stat(summary, f"{key}_first_detection_p99_ms", " ms")
        top = stat(summary, f"{key}_first_detection_max_ms", " ms")
        parts.append(f"{label}: accepted p50 {accepted}, first detection **p50 {p50}**, p99 {p99}, max {top}")
    return "; ".join(parts)


def result_text(measured: dict) -> str:
    summary = measured["summary"]
    if "snapshot_accepted_p50_ms" in summary:
        return handoff_text(summary)
    parts = []
    known = {k for k, _, _ in LABELS}
    for key, prefix, unit in LABELS:
        text = stat(summary, key, unit)
        if text is not None:
            parts.append(prefix + text)
    for key in summary:
        if key not in known and key != "errors":
            parts.append(f"{key}: {stat(summary, key)}")
    errors = summary.get("errors")
    if errors and errors["max"] > 0:
        parts.append(f"errors {fmt(errors['median'])}")
    return "; ".join(parts)


def load_text(measured: dict) -> str:
    loads = [r["load_before"][0] for r in measured["runs"]]
    return f"{min(loads):.2f}–{max(loads):.2f}" if min(loads) != max(loads) else f"{loads[0]:.2f}"


def render(results: dict) -> str:
    rows = results["rows"]
    out = [
        "# Benchmarks",
        "",
        "<!-- GENERATED by `scripts/benchmarks.py render` from docs/benchmarks/results.json: do not edit. -->",
        "",
        "Every number on this page was measured by `scripts/benchmarks.py run` and is rendered from "
        "`docs/benchmarks/results.json`. Each row ran three times (each time on a new server and a new "
        "database); a result is the median with the range of the runs in parentheses. *Load* is the "
        "1-minute load average before the runs (what `uptime` shows): other work on the machine "
        "lowers throughput and lengthens the tail. Each row names the date and commit it was "
        "measured on, and the CPU (rows measured on different machines compare only within a machine: "
        "see the end of the page); a row not measured yet says so. To measure rows again:",
        "",
        "```sh",
        "cargo build --release -p spoofwatch-server -p spoofwatch-client -p spoofwatch-lab",
        "python3 scripts/benchmarks.py list                          # the rows",
        "python3 scripts/benchmarks.py run --only fleet-10000,stream-100-rate-60k",
        "python3 scripts/benchmarks.py run --group grpc              # or every row of a group",
        "```",
        "",
        "A row's command is the server's, then, after `·`, the load generator's. `URL` is the "
        "server's address and `PID` its process id (for its CPU time and memory); the script pins "
        "the server to core 0 and the load generator to core 1 (`taskset`), except in *unpinned* rows.",
        "",
    ]
    for group, heading, intro in GROUPS:
        members = [(rid, r) for rid, r in rows.items() if r["group"] == group]
        if not members:
            continue
        out += [f"## {heading}", "", intro, ""]
        out += ["| row | result | goal | load | measured |", "|---|---|---|---|---|"]
        for rid, r in members:
            m = r["measured"]
            name = f"{r['title']}<br>`{r['command']}`"
            if m is None:
                out.append(f"| {name} | not measured | {r['goal'] or '—'} | — | — |")
            else:
                when = (f"{m['date'][:10]}, `{m['commit']}`" + (" (modified)" if m["source_modified"] else "")
                        + f", {m['machine']['cpu']}")
                out.append(f"| {name} | {result_text(m)} | {r['goal'] or '—'} | {load_text(m)} | {when} |")
        out.append("")
    comparison = load_comparison()
    if comparison:
        out += comparison_section(comparison)
    machines = []
    measured = [r["measured"] for r in rows.values() if r["measured"]]
    measured += [pair[side] for pair in comparison.get("rows", {}).values() for side in ("before", "after")]
    for m in measured:
        if m["machine"] not in machines:
            machines.append(m["machine"])
    if machines:
        out += ["## Machines", ""]
        for m in machines:
            out.append(f"- {m['cpu']}, {m['cores']} cores, {m['memory_gib']} GiB, {m['os']}, "
                       f"Linux {m['kernel']}, {m['rustc']}")
        out.append("")
    return "\n".join(out)


def load_comparison() -> dict:
    if not COMPARISON.exists():
        return {}
    comparison = json.loads(COMPARISON.read_text())
    # Files written before each pair carried its own builds named them once for all pairs.
    for pair in comparison.get("rows", {}).values():
        pair.setdefault("before_label", comparison.get("before"))
        pair.setdefault("after_label", comparison.get("after"))
    comparison.pop("before", None)
    comparison.pop("after", None)
    return comparison


def comparison_ratio(pair: dict) -> str:
    """After over before: CPU per sample for a server row, each value for a criterion row."""
    before, after = pair["before"]["summary"], pair["after"]["summary"]
    cpu = [m.get("cpu_us_per_sample", {}).get("median") for m in (before, after)]
    if all(cpu):
        return f"CPU per sample {cpu[1] / cpu[0]:.2f}"
    ratios = [f"{name.split(',')[0]} {after[name]['median'] / before[name]['median']:.3f}"
              for name in after if name in before and before[name].get("median")]
    return "; ".join(ratios) or "—"


def comparison_section(comparison: dict) -> list[str]:
    """The before-and-after table: each row's runs alternated between the two builds."""
    out = ["## Before and after", "",
           "One build against another on the same machine, run by run alternately "
           "(`scripts/benchmarks.py compare`): a server row runs both server builds with one load "
           "generator (the *after* build's); a criterion row builds its bench in a checkout of each "
           "commit. The ratio is the after median over the before median.", "",
           "| row | before | after | after / before | load | measured |",
           "|---|---|---|---|---|---|"]
    for rid, pair in comparison["rows"].items():
        before, after = pair["before"], pair["after"]
        loads = [r["load_before"][0] for m in (before, after) for r in m["runs"]]
        out.append(f"| {pair['title']}<br>`{pair['command']}` | `{pair['before_label']}`: "
                   f"{result_text(before)} | `{pair['after_label']}`: {result_text(after)} | "
                   f"{comparison_ratio(pair)} | {min(loads):.2f}–{max(loads):.2f} | "
                   f"{after['date'][:10]}, {after['machine']['cpu']} |")
    out.append("")
    return out


def compare(rows: list[dict], env: Env, before: Path, label: str, runs: int) -> None:
    after = env.bin
    after_label = provenance()["commit"] + (" (modified)" if provenance()["source_modified"] else "")
    comparison = load_comparison() or dict(generated_by="scripts/benchmarks.py compare", rows={})
    for row in rows:
        sides: dict[str, list] = {"before": [], "after": []}
        for i in range(runs):
            for side, build in (("before", before), ("after", after)):
                if row["kind"] == "criterion":
                    # A criterion row builds its bench from source: --before names a checkout.
                    env.source = build if side == "before" else None
                else:
                    env.server_bin = build
                load = loadavg()
                print(f"{row['id']} {side} run {i + 1}/{runs}, load {load[0]:.2f}", file=sys.stderr, flush=True)
                sides[side].append(dict(load_before=load, values=RUNNERS[row["kind"]](env, row)))
        pair = dict(title=row["title"], command=display_command(row), before_label=label,
                    after_label=after_label)
        for side, side_runs in sides.items():
            pair[side] = dict(provenance(), machine=machine(), runs=side_runs, summary=summarise(side_runs))
            print(f"{row['id']} {side}: {result_text(pair[side])}", file=sys.stderr, flush=True)
        comparison["rows"][row["id"]] = pair
        COMPARISON.write_text(json.dumps(comparison, indent=1, ensure_ascii=False) + "\n")
        # The after build is this checkout's: its runs are the row's current result too.
        results = catalogue(load_results())
        results["rows"][row["id"]]["measured"] = pair["after"]
        save(results)


# ---------------------------------------------------------------------------------------------------

def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("list")
    run = sub.add_parser("run")
    run.add_argument("--only", default="", help="row ids, comma-separated")
    run.add_argument("--group", default="", help="groups, comma-separated")
    run.add_argument("--heavy", action="store_true", help="include the long rows of the groups")
    run.add_argument("--runs", type=int, default=3)
    run.add_argument("--bin", type=Path, default=ROOT / "target/release")
    cmp = sub.add_parser("compare")
    cmp.add_argument("--only", required=True, help="row ids, comma-separated")
    cmp.add_argument("--before", type=Path, required=True, help="directory of the earlier server build; for a criterion row, a checkout of the earlier commit")
    cmp.add_argument("--before-label", required=True, help="what the earlier build is (its commit)")
    cmp.add_argument("--runs", type=int, default=3)
    cmp.add_argument("--bin", type=Path, default=ROOT / "target/release")
    sub.add_parser("render")
    sub.add_parser("check")
    args = parser.parse_args()

    if args.command == "list":
        results = catalogue(load_results())
        for rid, r in results["rows"].items():
            m = r["measured"]
            state = f"{m['date']} {m['commit']}" if m else "not measured"
            print(f"{rid:36} {r['group']:12} {'heavy ' if r['heavy'] else ''}{state}\n    {r['command']}")
        return
    if args.command == "render":
        save(catalogue(load_results()))
        return
    if args.command == "check":
        results = load_results()
        if catalogue(results) != results:
            sys.exit(f"{RESULTS} is not in the script's row catalogue: run `scripts/benchmarks.py render`")
        if not PAGE.exists() or PAGE.read_text() != render(results):
            sys.exit(f"{PAGE} is not the rendering of {RESULTS}: run `scripts/benchmarks.py render` "
                     "(the page is generated; edit the script or measure again)")
        print(f"{PAGE.relative_to(ROOT)} matches {RESULTS.relative_to(ROOT)}")
        return

    only = {x for x in args.only.split(",") if x}
    groups = {x for x in getattr(args, "group", "").split(",") if x}
    unknown = only - {r["id"] for r in ROWS}
    if unknown:
        sys.exit(f"unknown rows: {', '.join(sorted(unknown))} (see `list`)")
    selected = [r for r in ROWS if r["id"] in only
                or (r["group"] in groups and (args.heavy or not r.get("heavy")))]
    if not selected:
        sys.exit("no row selected: --only ID,.. or --group G,.. (see `list`)")
    if args.command == "compare":
        env = Env(args.bin.resolve())
        try:
            compare(selected, env, args.before.resolve(), args.before_label, args.runs)
        finally:
            env.close()
        return
    results = catalogue(load_results())
    env = Env(args.bin.resolve())
    try:
        for row in selected:
            runs = []
            for i in range(args.runs):
                load = loadavg()
                print(f"{row['id']} run {i + 1}/{args.runs}, load {load[0]:.2f}", file=sys.stderr, flush=True)
                values = RUNNERS[row["kind"]](env, row)
                runs.append(dict(load_before=load, values=values))
            measured = dict(provenance(), machine=machine(), runs=runs, summary=summarise(runs))
            results["rows"][row["id"]]["measured"] = measured
            save(results)
            print(f"{row['id']}: {result_text(measured)}", file=sys.stderr, flush=True)
    finally:
        env.close()


if __name__ == "__main__":
    main()
