#!/usr/bin/env python3
"""Summarises `spoofwatch-lab experiment offsets` reports side by side (the ablation table of
docs/experiments.md).

Each argument is LABEL=DIR, DIR holding a run's report.json. For every run the HO-LLN detector of
the run's first training seed is summarised by attack group, pooled over the three sample rates and
the group's magnitudes: the share detected within the deadline for an onset early in a session and
minutes into it, the late attack's coverage, and the false alarms per attack-free hour at each rate.
The shares are the means of the report's cells (every cell has the same number of drives).

    python3 scripts/offsets_summary.py "full=out/offsets" "no offset evidence (v2)=out/v2" ...
"""

import json
import sys
from pathlib import Path

GROUPS = [
    ("jumps ≥ 20 m", lambda c: c["family"] == "jump" and c["magnitude"] >= 20),
    ("frozen fix", lambda c: c["family"].startswith("frozen_position")),
    ("hops", lambda c: c["family"] == "hopping"),
    ("ramps and accelerating", lambda c: c["family"] in ("ramp_drift", "accelerating_drift")),
    ("toggling drift", lambda c: c["family"] == "toggling_drift"),
]


def mean(values):
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def cell(value):
    return "–" if value is None else f"{value:.2f}"


def learned(report):
    seed = report["training_seeds"][0]
    for detector in report["detectors"]:
        if detector["name"].startswith("HO-LLN") and detector["seed"] == seed:
            return detector
    raise SystemExit(f"no HO-LLN detector of seed {seed} in the report")


def row(label, report):
    detector = learned(report)
    if detector["operating_point"] is None:
        return f"| {label} | no operating point within the budget |" + " |" * (len(GROUPS) + 1)
    point = detector["operating_point"]
    op = point["operating_point"]
    lifecycle = point.get("lifecycle")
    if lifecycle:
        described = (
            f"θ {op['theta']}, T_on {lifecycle['on_s']:g} s, T_off {lifecycle['off_s']:g} s, "
            f"decisive {lifecycle['decisive_s']:g} s"
        )
    else:
        described = f"θ {op['theta']}, N_p {op['n_p']} rows"
    cells = []
    for _, member in GROUPS:
        attacks = [c for c in detector["attacks"] if member(c)]
        early = mean(c["detected_in_time"] for c in attacks if c["early_onset"])
        late = [c for c in attacks if not c["early_onset"]]
        cells.append(
            f"{cell(early)} / {cell(mean(c['detected_in_time'] for c in late))}, "
            f"cov {cell(mean(c['coverage'] for c in late))}"
        )
    false_alarms = " / ".join(f"{c['per_hour']:.2f}" for c in detector["clean"])
    after = sum(c["after_start_or_outage"] for c in detector["clean"])
    return f"| {label} | {described} | " + " | ".join(cells) + f" | {false_alarms} ({after}) |"


def main(arguments):
    if not arguments or any("=" not in a for a in arguments):
        raise SystemExit(__doc__)
    runs = []
    for argument in arguments:
        label, directory = argument.split("=", 1)
        path = Path(directory) / "report.json"
        try:
            runs.append((label, json.loads(path.read_text())))
        except (OSError, ValueError) as error:
            raise SystemExit(f"{path}: {error}")
    rates = " / ".join(f"{r:g}" for r in runs[0][1]["rates_hz"])
    print(
        "| variant | operating point | "
        + " | ".join(name for name, _ in GROUPS)
        + f" | false alarms per hour at {rates} Hz (within 30 s of a start or outage) |"
    )
    print("|---|---|" + "---|" * (len(GROUPS) + 1))
    for label, report in runs:
        print(row(label, report))


if __name__ == "__main__":
    main(sys.argv[1:])
