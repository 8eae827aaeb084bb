#!/usr/bin/env python3
"""Storage-fault probe of a release build, with real faults (needs root for mount/chattr).

For each fault (a full disk: a small tmpfs filled with a ballast file; an unwritable database:
`chattr +i` on the database and its WAL; a database file deleted while the server runs) this:
starts `spoofwatch-server` on a fresh database, injects the fault, replays recorded drives with
`spoofwatch detect --out` (alarm onsets as the clients saw them), tries an upload, clears the fault
where it can, waits, tries another upload, stops the server and compares the stored alarm events
with the onsets the clients were shown.

    sudo python3 scripts/storage_fault_probe.py BIN_DIR DRIVE.csv [DRIVE.csv ...]

BIN_DIR holds `spoofwatch-server` and `spoofwatch`. Prints one JSON line per fault.
"""

import csv
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time

PORT = 50461
SERVER = f"http://127.0.0.1:{PORT}"


def run(*args, **kwargs):
    return subprocess.run(args, capture_output=True, text=True, **kwargs)


def wait_serving(client, bound_s=30):
    deadline = time.time() + bound_s
    while time.time() < deadline:
        if run(client, "health", "--server", SERVER).returncode == 0:
            return
        time.sleep(0.2)
    raise RuntimeError("server never became SERVING")


def upload(client, small_csv, name):
    """The outcome of one upload: 'ok' or the client's error line."""
    result = run(client, "datasets", "upload", "--server", SERVER, "--file", small_csv,
                 "--name", name)
    if result.returncode == 0:
        return "ok"
    return (result.stderr.strip().splitlines() or ["?"])[0][:160]


def shown_onsets(out_csv):
    with open(out_csv, newline="") as f:
        return sum(1 for row in csv.DictReader(f) if row["alarm_onset"] in ("true", "1"))


def stored_events(database):
    if not os.path.exists(database):
        return None
    con = sqlite3.connect(database)
    try:
        rows = con.execute("SELECT id, vehicle_id, ended_at, samples FROM alarm_events").fetchall()
    except sqlite3.OperationalError as error:
        return {"error": f"{error} (an empty file took the database's place)"}
    finally:
        con.close()
    ids = [r[0] for r in rows]
    return {"rows": len(rows), "unique_ids": len(set(ids)) == len(ids),
            "open": sum(1 for r in rows if r[2] is None)}


def probe(fault, bin_dir, drives, work):
    server_bin = os.path.join(bin_dir, "spoofwatch-server")
    client = os.path.join(bin_dir, "spoofwatch")
    fs = os.path.join(work, f"fs-{fault}")
    os.makedirs(fs)
    if fault == "full":
        subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", fs], check=True)
    database = os.path.join(fs, "spoofwatch.db")
    log = open(os.path.join(work, f"{fault}.log"), "w")
    server = subprocess.Popen([server_bin, "--listen", f"127.0.0.1:{PORT}", "--database", database],
                              stdout=log, stderr=subprocess.STDOUT)
    result = {"fault": fault, "bin": bin_dir}
    try:
        wait_serving(client)
        small = drives[0]
        files = [database, database + "-wal"]
        if fault == "full":
            run("dd", "if=/dev/zero", f"of={fs}/ballast", "bs=64k")
        elif fault == "unwritable":
            subprocess.run(["chattr", "+i", *files], check=True)
        elif fault == "deleted":
            for suffix in ("", "-wal", "-shm"):
                if os.path.exists(database + suffix):
                    os.remove(database + suffix)
            time.sleep(2)
            result["health_after_delete"] = run(client, "health", "--server", SERVER).returncode
        out = os.path.join(work, f"{fault}-detections.csv")
        replay = run(client, "detect", "--server", SERVER, "--quiet", "--out", out, "--data", *drives)
        result["replay_exit"] = replay.returncode
        result["onsets_shown"] = shown_onsets(out) if os.path.exists(out) else None
        result["upload_during"] = upload(client, small, "during the fault")
        if fault == "full":
            os.remove(f"{fs}/ballast")
        elif fault == "unwritable":
            subprocess.run(["chattr", "-i", *files], check=True)
        time.sleep(8)  # the alarm writer's backoff is at most 5 s
        result["upload_after"] = upload(client, small, "after the fault")
    finally:
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=60)
        log.close()
    result["stored"] = stored_events(database)
    with open(os.path.join(work, f"{fault}.log")) as f:
        result["log_errors"] = sorted({line.split("ERROR", 1)[1].strip()[:120]
                                       for line in f if "ERROR" in line})[:6]
    if fault == "full":
        subprocess.run(["umount", fs], check=True)
    return result


def main():
    bin_dir, drives = sys.argv[1], sys.argv[2:]
    work = tempfile.mkdtemp(prefix="fault-probe-")
    try:
        for fault in ("full", "unwritable", "deleted"):
            print(json.dumps(probe(fault, bin_dir, drives, work)), flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
