#!/usr/bin/env python3
"""The soak test's monitor, checks and report (scripts/soak-test.sh runs it; docs/reliability.md).

  sample   --work DIR --every S --replica NAME=HOST:PORT ...   CPU and RSS of each replica's process
           (from /proc, by the pid in DIR/NAME.pid, so a restarted replica is followed) and its
           /metrics gauges, every S seconds, appended to DIR/samples.csv until killed.
  drained  --replica HOST:PORT ...   waits until every replica's alarm outbox and snapshot queue are
           empty (the stored alarms are complete), at most 180 s.
  report   --work DIR --seconds N --vehicles N --rollout-model NAME [--out FILE]   the checks; prints
           the report (markdown) and writes it to FILE; exits 1 when a check fails.

Times are seconds from the client's start (the `replaying` line of DIR/run-detect.log).
"""

import argparse
import csv
import json
import os
import platform
import subprocess
import sys
import time
import urllib.request
from collections import Counter, defaultdict

GAUGES = {
    "spoofwatch_alarm_outbox_backlog": "alarm_backlog",
    "spoofwatch_session_snapshots_backlog": "snapshot_backlog",
    "spoofwatch_session_snapshots_lag_seconds": "snapshot_lag_s",
    "spoofwatch_sessions_open": "sessions_open",
    "spoofwatch_sessions_connected": "sessions_connected",
}
SAMPLE_COLUMNS = ["unix_s", "replica", "pid", "cpu_s", "rss_mb"] + list(GAUGES.values())
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
# Memory is flat when a replica's RSS grows by at most this much while its sessions stay the same...
RSS_GROWTH_LIMIT = 0.05
# ...or by at most this many MB: room for the roll-out's second model and the allocator's arenas, which
# outweigh 5 % of a replica holding a few hundred sessions (5 % of one holding 10,000 is more).
RSS_GROWTH_FLOOR_MB = 16


def scrape(address):
    """The gauges of GAUGES from http://address/metrics, or {} when it does not answer."""
    try:
        with urllib.request.urlopen(f"http://{address}/metrics", timeout=2) as reply:
            text = reply.read().decode()
    except OSError:
        return {}
    values = {}
    for line in text.splitlines():
        name, _, value = line.partition(" ")
        if name in GAUGES:
            values[GAUGES[name]] = float(value)
    return values


def process_usage(pid):
    """(CPU seconds, RSS in MB) of a live process, or None."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            # Fields after the command (which may hold spaces): utime and stime are the 12th and 13th.
            fields = stat.read().rsplit(")", 1)[1].split()
        with open(f"/proc/{pid}/status") as status:
            rss_kb = next(int(l.split()[1]) for l in status if l.startswith("VmRSS:"))
    except (OSError, StopIteration, IndexError, ValueError):
        return None
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS, rss_kb / 1024


def sample(args):
    path = os.path.join(args.work, "samples.csv")
    new = not os.path.exists(path)
    with open(path, "a", newline="") as out:
        writer = csv.writer(out)
        if new:
            writer.writerow(SAMPLE_COLUMNS)
        while True:
            for replica in args.replica:
                name, address = replica.split("=", 1)
                try:
                    pid = int(open(os.path.join(args.work, f"{name}.pid")).read())
                except (OSError, ValueError):
                    continue
                usage = process_usage(pid)
                if usage is None:
                    continue
                gauges = scrape(address)
                writer.writerow([f"{time.time():.3f}", name, pid, f"{usage[0]:.2f}", f"{usage[1]:.1f}"]
                                + [gauges.get(column, "") for column in GAUGES.values()])
            out.flush()
            time.sleep(args.every)


def drained(args):
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        gauges = [scrape(address) for address in args.replica]
        if all(g and g["alarm_backlog"] == 0 and g["snapshot_backlog"] == 0 for g in gauges):
            return
        time.sleep(0.5)
    sys.exit("the replicas did not store their queued alarms and snapshots within 180 s")


def client_start(work):
    """Unix time of the client's `replaying` line (written by soak-test.sh next to it)."""
    with open(os.path.join(work, "client-started.txt")) as f:
        return float(f.read())


def read_alarms(path):
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def alarm_key(alarm):
    return (alarm["vehicle_id"], alarm["onset_timestamp_s"])


def alarm_row(alarm):
    return (alarm["vehicle_id"], alarm["onset_timestamp_s"], alarm.get("end_timestamp_s"),
            alarm["peak_probability"], alarm["samples"], alarm.get("open", False))


class Checks:
    def __init__(self):
        self.results = []

    def check(self, name, ok, detail):
        self.results.append((name, bool(ok), detail))

    def failed(self):
        return [r for r in self.results if not r[1]]


def csv_rows(path):
    """(header, rows): the rows as ((vehicle, line), fields), in the file's order (vehicles sorted,
    each vehicle's rows in recorded order, as `detect --out` writes them)."""
    f = open(path, newline="")
    reader = csv.reader(f)
    header = next(reader)
    return header, (((row[0], int(row[1])), row) for row in reader)


def compare_detections(work, reference_model, rollout_model, replies_lost, checks):
    """Merges the run's rows with the reference's by vehicle and line. Returns the per-vehicle
    switch times (the first timestamp under the roll-out model), the onsets shown, the vehicles
    whose last detection still alarms, and the (vehicle, timestamp) of the rows without a
    detection."""
    switched_at, shown_onsets, alarming, lost = {}, [], {}, set()
    compared = after_rollout = differing = extra = back_to_old = 0
    first_difference = None
    header, reference = csv_rows(os.path.join(work, "reference.csv"))
    run_header, run = csv_rows(os.path.join(work, "run.csv"))
    if run_header != header:
        checks.check("same columns", False, "the run's CSV has other columns than the reference's")
        return switched_at, shown_onsets, set(), lost
    model, onset, alarm = header.index("model"), header.index("alarm_onset"), header.index("alarm")
    ref, got = next(reference, None), next(run, None)
    while ref or got:
        if got is None or (ref and ref[0] < got[0]):
            lost.add((ref[0][0], float(ref[1][2])))
            ref = next(reference, None)
            continue
        if ref is None or got[0] < ref[0]:
            extra += 1
            got = next(run, None)
            continue
        (vehicle, line), run_row, ref_row = got[0], got[1], ref[1]
        timestamp = float(run_row[2])
        alarming[vehicle] = run_row[alarm] == "1"
        if run_row[onset] == "1":
            shown_onsets.append((vehicle, timestamp))
        if run_row[model] == rollout_model:
            after_rollout += 1
            switched_at.setdefault(vehicle, timestamp)
        else:
            back_to_old += vehicle in switched_at
            compared += 1
            if run_row[model] != reference_model or run_row != ref_row:
                differing += 1
                first_difference = first_difference or f"{vehicle} line {line}: {run_row} vs {ref_row}"
        ref, got = next(reference, None), next(run, None)
    checks.check("every recorded row has its detection, but for replies lost with a failed stream",
                 extra == 0 and len(lost) == replies_lost,
                 f"{compared + after_rollout} rows with a detection; {len(lost)} without, where the client "
                 f"counted {replies_lost} replies lost (the server applied the sample, the stream failed "
                 f"before its reply arrived); {extra} rows the reference does not have")
    checks.check("detections equal the uninterrupted run's, bit for bit, under its model",
                 differing == 0 and compared > 0,
                 f"{compared} rows compared, {differing} differ"
                 + (f" (first: {first_difference})" if first_difference else "")
                 + f"; {after_rollout} rows under the roll-out model")
    checks.check("each vehicle changes model once, at the roll-out", back_to_old == 0,
                 f"{len(switched_at)} vehicles moved to {rollout_model}; {back_to_old} rows back under the old model")
    return switched_at, shown_onsets, {v for v, on in alarming.items() if on}, lost


def compare_alarms(work, switched_at, shown_onsets, alarming_at_end, lost, checks):
    stored = read_alarms(os.path.join(work, "run-alarms.json"))
    reference = read_alarms(os.path.join(work, "reference-alarms.json"))
    counts = Counter(alarm_key(a) for a in stored)
    duplicated = [k for k, n in counts.items() if n > 1]
    shown = Counter(shown_onsets)
    missing = [k for k in shown if k not in counts]
    # An onset whose reply was lost is stored without having been shown.
    unshown = [k for k in counts if k not in shown and k not in lost]
    # Open: only a vehicle's latest alarm, when its last detection still alarmed (its session,
    # held for its return, holds the alarm open).
    latest = {}
    for a in stored:
        if a["onset_timestamp_s"] >= latest.get(a["vehicle_id"], float("-inf")):
            latest[a["vehicle_id"]] = a["onset_timestamp_s"]
    is_open = [a for a in stored if a.get("open") or a.get("end_timestamp_s") is None]
    wrongly_open = [alarm_key(a) for a in is_open
                    if a["vehicle_id"] not in alarming_at_end or a["onset_timestamp_s"] != latest[a["vehicle_id"]]]
    wrongly_ended = [v for v in alarming_at_end if not any(a["vehicle_id"] == v for a in is_open)]
    checks.check("every onset shown is stored exactly once, with its end",
                 not (missing or duplicated or unshown or wrongly_open or wrongly_ended) and shown,
                 f"{len(shown)} onsets shown, {len(stored)} alarms stored; {len(missing)} missing, "
                 f"{len(duplicated)} duplicated, {len(unshown)} stored but never shown (nor lost in transit); "
                 f"{len(is_open)} open, those of the {len(alarming_at_end)} vehicles still alarming at their "
                 f"last sample: {len(wrongly_open)} other alarms without an end, {len(wrongly_ended)} ended early")
    # Alarms the old model ended before the vehicle's switch are the reference's exactly.
    before_switch = [a for a in reference
                     if a.get("end_timestamp_s") is not None
                     and a["end_timestamp_s"] < switched_at.get(a["vehicle_id"], float("inf"))]
    stored_rows = {alarm_row(a) for a in stored}
    differ = [alarm_row(a) for a in before_switch if alarm_row(a) not in stored_rows]
    checks.check("alarms ended before the roll-out equal the uninterrupted run's",
                 not differ and before_switch,
                 f"{len(before_switch)} of the reference's {len(reference)} alarms ended before their "
                 f"vehicle's switch; {len(differ)} differ" + (f" (first: {differ[0]})" if differ else ""))
    return len(stored)


def replica_log_lines(work, text):
    """Lines of the replicas' logs that contain `text`."""
    found = []
    for name in sorted(os.listdir(work)):
        if name.startswith("replica-") and name.endswith(".log"):
            with open(os.path.join(work, name), errors="replace") as f:
                found += [line for line in f if text in line]
    return found


def check_failovers(work, checks):
    with open(os.path.join(work, "run-summary.json")) as f:
        summary = json.load(f)
    failovers = summary["failovers"]
    resumed = summary["resumed_reconnects"]
    rolled = summary["failovers_onto_another_model"]
    lost = failovers - resumed - rolled
    # A replica that started a session afresh although its stored snapshot was not refused for its
    # model (the roll-out) lost it, even when the client saw the fresh session only on a retry.
    afresh = [line for line in replica_log_lines(work, "the session starts afresh") if "ran model" not in line]
    waited = len(replica_log_lines(work, "the stream is refused, to be retried"))
    checks.check("every failover resumed its session or went on under the new model",
                 failovers > 0 and lost == 0 and not afresh,
                 f"{failovers} failovers: {resumed} resumed, {rolled} onto the roll-out model, {lost} started afresh; "
                 f"the replicas started {len(afresh)} sessions afresh without their snapshot and refused "
                 f"{waited} streams to be retried while it could not be read")
    return summary


def per_interval(work, start, seconds, interval):
    """{(replica, interval index): stats} from samples.csv."""
    rows = defaultdict(list)
    with open(os.path.join(work, "samples.csv")) as f:
        for row in csv.DictReader(f):
            t = float(row["unix_s"]) - start
            if 0 <= t < seconds + interval:
                rows[row["replica"]].append((t, row))
    table = {}
    for replica, samples in rows.items():
        previous = {}
        for t, row in samples:
            index = min(int(t // interval), seconds // interval - 1)
            cell = table.setdefault((replica, index), {"cpu_s": 0.0, "rss_mb": 0.0, "alarm_backlog": 0.0,
                                                       "snapshot_lag_s": 0.0, "sessions_open": None})
            pid, cpu = row["pid"], float(row["cpu_s"])
            if pid in previous:
                cell["cpu_s"] += cpu - previous[pid]
            previous = {pid: cpu}
            cell["rss_mb"] = float(row["rss_mb"])  # the last in the interval
            for gauge in ("alarm_backlog", "snapshot_lag_s"):
                if row[gauge]:
                    cell[gauge] = max(cell[gauge], float(row[gauge]))
            if row["sessions_open"]:
                cell["sessions_open"] = float(row["sessions_open"])
    return table


def check_memory(table, replicas, intervals, checks):
    """Per replica, from the end of the third interval (minute 3 of 10) or, when its held sessions
    still changed after that, from the first interval after which they stay within 5 % of their
    final number, to the end: RSS growth within the limit."""
    details, ok = [], True
    for replica in replicas:
        cells = [table.get((replica, i)) for i in range(intervals)]
        final = cells[-1]
        if not final or not final["sessions_open"]:
            ok = False
            details.append(f"{replica}: no sessions at the end")
            continue
        steady = None
        for i in range(intervals - 1, 1, -1):
            cell = cells[i]
            if not cell or cell["sessions_open"] is None or abs(cell["sessions_open"] / final["sessions_open"] - 1) > 0.05:
                break
            steady = i
        if steady is None or steady == intervals - 1:
            details.append(f"{replica}: sessions not steady for two intervals; not checked")
            continue
        # From the end of the first steady interval to the end of the last.
        start_mb = cells[steady]["rss_mb"]
        growth = final["rss_mb"] / start_mb - 1
        ok &= final["rss_mb"] - start_mb <= max(RSS_GROWTH_LIMIT * start_mb, RSS_GROWTH_FLOOR_MB)
        details.append(f"{replica}: {cells[steady]['rss_mb']:.0f} MB at the end of interval {steady + 1}, "
                       f"{final['rss_mb']:.0f} MB at the end ({growth:+.1%}) with "
                       f"{final['sessions_open']:.0f} sessions held")
    checks.check(f"memory flat: RSS growth at most {RSS_GROWTH_LIMIT:.0%} (or {RSS_GROWTH_FLOOR_MB} MB) while "
                 "the sessions held stay the same",
                 ok, "; ".join(details))


def machine():
    cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "?")
    memory = next(int(l.split()[1]) for l in open("/proc/meminfo") if l.startswith("MemTotal")) / 2**20
    return f"{os.cpu_count()} cores ({cpu}), {memory:.0f} GiB, {platform.system()} {platform.release()}"


def commit():
    def git(*a):
        return subprocess.run(["git", *a], capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "--short=8", "HEAD") or "unknown"
    return head + (" with uncommitted changes" if git("status", "--porcelain", "--untracked-files=no") else "")


def report(args):
    work, seconds = args.work, args.seconds
    interval = seconds // 10
    start = client_start(work)
    checks = Checks()
    with open(os.path.join(work, "run-summary.json")) as f:
        replies_lost = json.load(f)["replies_lost"]
    switched_at, shown_onsets, alarming_at_end, lost = compare_detections(
        work, "models/default", args.rollout_model, replies_lost, checks)
    compare_alarms(work, switched_at, shown_onsets, alarming_at_end, lost, checks)
    summary = check_failovers(work, checks)
    with open(os.path.join(work, "timeline.csv")) as f:
        timeline = list(csv.DictReader(f))
    table = per_interval(work, start, seconds, interval)
    replicas = sorted({replica for replica, _ in table})
    check_memory(table, replicas, 10, checks)
    with open(os.path.join(work, "faults.txt")) as f:
        faults = [line.strip().split(" ", 1) for line in f if line.strip()]

    lines = [
        f"# Soak test: {args.vehicles:,} vehicles for {seconds} s, with faults",
        "",
        "Generated by `scripts/soak-test.sh"
        + (f" --seconds {seconds} --vehicles {args.vehicles}" if (seconds, args.vehicles) != (600, 20000) else "")
        + "` (release build); see [Reliability](reliability.md#soak-test) for what it runs and checks.",
        "",
        f"- machine: {machine()}",
        f"- load average (1, 5, 15 min): {args.load_before} before, {args.load_after} after",
        f"- commit: {commit()}",
        f"- date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
        f"- client: {summary['vehicles']:,} vehicles, {summary['samples']:,} samples, "
        f"{summary['streams']:,} streams ({summary['failovers']:,} failovers)",
        "",
        "## Faults",
        "",
        "| at (s) | fault |",
        "|---:|---|",
    ]
    lines += [f"| {t} | {what} |" for t, what in faults]
    lines += ["", "## Checks", "", "| check | result | measured |", "|---|---|---|"]
    lines += [f"| {name} | {'pass' if ok else '**FAIL**'} | {detail} |" for name, ok, detail in checks.results]
    lines += [
        "",
        "## Interval by interval",
        "",
        "Samples count in the interval they were due in; latency runs from when a sample was due to its "
        "detection (a failover's wait and resends included). CPU is the replica's share of one core; RSS "
        "at the end of the interval; outbox backlog and snapshot lag the largest sampled.",
        "",
        "| interval (s) | delivered | on time | p50 ms | p99 ms | max ms | "
        + " | ".join(f"{r} CPU | {r} RSS MB | {r} sessions | {r} outbox | {r} snapshot lag s" for r in replicas)
        + " |",
        "|---|---:|---:|---:|---:|---:|" + "---:|" * (5 * len(replicas)),
    ]
    for i, row in enumerate(timeline[:10]):
        cells = [f"{float(row['start_s']):.0f}–{float(row['end_s']):.0f}", f"{float(row['delivered_pct']):.2f} %",
                 f"{float(row['on_time_pct']):.2f} %", row["p50_ms"] or "-", row["p99_ms"] or "-",
                 row["max_ms"] or "-"]
        for replica in replicas:
            cell = table.get((replica, i))
            if cell is None:
                cells += ["down"] + ["-"] * 4
                continue
            sessions = "-" if cell["sessions_open"] is None else f"{cell['sessions_open']:.0f}"
            cells += [f"{100 * cell['cpu_s'] / interval:.0f} %", f"{cell['rss_mb']:.0f}", sessions,
                      f"{cell['alarm_backlog']:.0f}", f"{cell['snapshot_lag_s']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)
    failed = checks.failed()
    if failed:
        sys.exit("soak checks failed: " + "; ".join(name for name, _, _ in failed))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser("sample")
    p.add_argument("--work", required=True)
    p.add_argument("--every", type=float, required=True)
    p.add_argument("--replica", action="append", required=True)
    p = commands.add_parser("drained")
    p.add_argument("--replica", action="append", required=True)
    p = commands.add_parser("report")
    p.add_argument("--work", required=True)
    p.add_argument("--seconds", type=int, required=True)
    p.add_argument("--vehicles", type=int, required=True)
    p.add_argument("--rollout-model", required=True)
    p.add_argument("--load-before", default="?")
    p.add_argument("--load-after", default="?")
    p.add_argument("--out")
    args = parser.parse_args()
    {"sample": sample, "drained": drained, "report": report}[args.command](args)


if __name__ == "__main__":
    main()
