#!/usr/bin/env python3
"""Poisoned-input probe of a release build: model artifacts with extreme values and samples with
extreme reported uncertainty, against a running server on a fresh database.

    python3 scripts/poison_probe.py BIN_DIR CLEAN_DRIVE.csv

BIN_DIR holds `spoofwatch-server` and `spoofwatch`; CLEAN_DRIVE.csv is an attack-free telemetry CSV
(e.g. `spoofwatch scenario simulate --out clean.csv --vehicles 5 --duration 600`). Prints one JSON
line per case: whether an artifact import was accepted (and the refusal's first line), and for
samples the replay's exit status and the number of alarm onsets the clients were shown.
"""

import csv
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

PORT = 50462
SERVER = f"http://127.0.0.1:{PORT}"
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run(*args):
    return subprocess.run(args, capture_output=True, text=True)


def error_text(result):
    """The client's error output on one line (code, message and field violations)."""
    return " | ".join(line.strip() for line in result.stderr.strip().splitlines())[:300]


def poisoned_artifacts(work):
    with open(os.path.join(REPO, "models", "default.json")) as f:
        base = json.load(f)

    def first_tensor(artifact):
        params = artifact["model"]["params"]
        return params[sorted(params)[0]]

    def weights(a):
        first_tensor(a)["data"][0] = 1e308

    def mu_e(a):
        a["evidence"]["mu_e"] = 1e308

    def scale(a):
        a["scaler"]["scale"][0] = -0.5

    def n_p(a):
        a["operating_point"]["n_p"] = 2**32 - 1

    def notes(a):
        a["provenance"]["notes"] = "x" * 50_000_000

    cases = {"weights 1e308": weights, "mu_e 1e308": mu_e, "negative scaler scale": scale,
             "n_p 2^32-1": n_p, "50 MB notes": notes}
    for name, poison in cases.items():
        artifact = json.loads(json.dumps(base))
        poison(artifact)
        path = os.path.join(work, name.replace(" ", "_") + ".json")
        with open(path, "w") as f:
            json.dump(artifact, f)
        yield name, path


def with_std(clean_csv, work, value):
    path = os.path.join(work, f"std-{value}.csv")
    with open(clean_csv, newline="") as src, open(path, "w", newline="") as dst:
        reader = csv.DictReader(src)
        fields = reader.fieldnames + ["position_std_m", "speed_std_mps", "heading_std_deg"]
        writer = csv.DictWriter(dst, fieldnames=fields)
        writer.writeheader()
        for row in reader:
            row.update(position_std_m=value, speed_std_mps=value, heading_std_deg=value)
            writer.writerow(row)
    return path


def onsets(out_csv):
    if not os.path.exists(out_csv):
        return None
    with open(out_csv, newline="") as f:
        return sum(1 for row in csv.DictReader(f) if row["alarm_onset"] in ("true", "1"))


def main():
    bin_dir, clean = sys.argv[1], sys.argv[2]
    client = os.path.join(bin_dir, "spoofwatch")
    work = tempfile.mkdtemp(prefix="poison-probe-")
    server = subprocess.Popen([os.path.join(bin_dir, "spoofwatch-server"), "--listen",
                               f"127.0.0.1:{PORT}", "--database", os.path.join(work, "db")],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(150):
            if run(client, "health", "--server", SERVER).returncode == 0:
                break
            time.sleep(0.2)
        for name, path in poisoned_artifacts(work):
            result = run(client, "models", "import", "--server", SERVER, "--file", path,
                         "--name", name[:40])
            print(json.dumps({"case": f"artifact: {name}", "accepted": result.returncode == 0,
                              "refusal": None if result.returncode == 0
                              else error_text(result)}), flush=True)
        # The paper-schema model (energy-driven) beside the default one.
        paper = run(client, "models", "import", "--server", SERVER, "--name", "paper",
                    "--file", os.path.join(REPO, "models", "paper.json"))
        paper_name = next(word for word in paper.stdout.split() if word.startswith("models/"))
        for model in ("", paper_name):
            for value in ("none", "0", "1e-300", "1e200"):
                data = clean if value == "none" else with_std(clean, work, value)
                out = os.path.join(work, f"out-{value}.csv")
                model_args = ["--model", model] if model else []
                result = run(client, "detect", "--server", SERVER, "--quiet", "--out", out,
                             *model_args, "--data", data)
                print(json.dumps({"case": f"samples: std = {value}, model {model or 'default'}",
                                  "exit": result.returncode, "onsets_shown": onsets(out),
                                  "error": error_text(result) or None}), flush=True)
    finally:
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=60)


if __name__ == "__main__":
    main()
