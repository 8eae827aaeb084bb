#!/usr/bin/env python3
"""Breaks an offsets run's drifts down by the vehicle's speed (the table in docs/experiments.md).

A drift is a disagreement in metres per second between GNSS and the vehicle's own motion. Before the
onboard calibration is warm (a session's first minutes), a vehicle's own heading bias and speed-scale
error also drift its dead reckoning, by the bias times its speed: 2.5° at 10 m/s is 0.44 m/s. So how
early a drift can be told from the vehicle's own errors depends on the speed it is driven at.

    python3 scripts/offsets_by_speed.py out/offsets [--detector NAME]

Reads DIR/drives.csv (one row per detector and attacked test drive) and prints, for the detector
(default: the HO-LLN model of the run's first training seed; NAME picks another, e.g. "CUSUM", every
seed of it pooled), each drift kind's share detected within its deadline per band of the mean onboard speed from the onset to the deadline, for onsets
15 s into a session and minutes into it, pooled over the sample rates.
"""

import csv
import json
import sys
from pathlib import Path

BANDS = [(0.0, 3.0), (3.0, 10.0), (10.0, float("inf"))]
DRIFTS = ("ramp_drift", "accelerating_drift", "toggling_drift")


def band_label(low, high):
    return f"≥ {low:g} m/s" if high == float("inf") else f"{low:g}–{high:g} m/s"


def main(argv):
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0 if argv else 2
    out = Path(argv[0])
    detector, seed = None, ""
    if "--detector" in argv:
        detector = argv[argv.index("--detector") + 1]
    if detector is None:
        report = json.loads((out / "report.json").read_text())
        seed = str(report["training_seeds"][0])
        detector = next(
            d["name"]
            for d in report["detectors"]
            if d["name"].startswith("HO-LLN") and str(d["seed"]) == seed
        )
    rows = [
        r
        for r in csv.DictReader((out / "drives.csv").open())
        if r["detector"] == detector and seed in ("", r["seed"]) and r["attack"] in DRIFTS
    ]
    if not rows:
        print(f"no drift rows for {detector!r} in {out / 'drives.csv'}", file=sys.stderr)
        return 1
    kinds = sorted({(r["attack"], float(r["magnitude"])) for r in rows})
    header = "| attack | onset | " + " | ".join(band_label(*b) for b in BANDS) + " |"
    label = f"{detector} (seed {seed})" if seed else detector
    print(f"{label}: share detected within the deadline (drives)\n")
    print(header)
    print("|---|---|" + "---|" * len(BANDS))
    for attack, magnitude in kinds:
        for early in ("true", "false"):
            cells = []
            for low, high in BANDS:
                band = [
                    r
                    for r in rows
                    if r["attack"] == attack
                    and float(r["magnitude"]) == magnitude
                    and r["early_onset"] == early
                    and low <= float(r["mean_speed_mps"]) < high
                ]
                hits = sum(r["in_time"] == "true" for r in band)
                cells.append(f"{hits / len(band):.2f} ({len(band)})" if band else "–")
            onset = "15 s" if early == "true" else "300–600 s"
            unit = "m/s²" if attack == "accelerating_drift" else "m/s"
            print(f"| {attack} {magnitude:g} {unit} | {onset} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
