#!/usr/bin/env python3
"""Alarm onsets by time into the drive, from `spoofwatch evaluate --rows` of attack-free drives.

A false-alarm budget met on short drives need not hold on a vehicle in service: the detector's
per-vehicle levels and calibration settle over the first half hour. This prints, per bin of
`--bin-s` seconds from each vehicle's first row, the onsets, the vehicle-hours and the rate.

    python3 scripts/onsets_by_time.py rows.csv [--bin-s 600]
"""
import argparse
import csv
from collections import defaultdict


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rows")
    parser.add_argument("--bin-s", type=float, default=600.0)
    args = parser.parse_args()
    onsets = defaultdict(int)
    seconds = defaultdict(float)
    start = {}
    previous = {}
    with open(args.rows, newline="") as f:
        for r in csv.DictReader(f):
            vehicle, time_s = r["vehicle_id"], float(r["time_s"])
            start.setdefault(vehicle, time_s)
            index = int((time_s - start[vehicle]) // args.bin_s)
            if vehicle in previous:
                # Time between consecutive rows up to 5 s counts as driving (longer: an outage).
                seconds[index] += min(time_s - previous[vehicle], 5.0)
            previous[vehicle] = time_s
            if r["alarm_onset"] == "1":
                onsets[index] += 1
    print("from (s) | to (s) | vehicle-hours | onsets | per hour")
    for index in sorted(seconds):
        hours = seconds[index] / 3600.0
        if hours <= 0:
            continue
        rate = onsets[index] / hours
        print(
            f"{index * args.bin_s:.0f} | {(index + 1) * args.bin_s:.0f} | {hours:.1f} | "
            f"{onsets[index]} | {rate:.2f}"
        )
    total_hours = sum(seconds.values()) / 3600.0
    total = sum(onsets.values())
    print(f"all | | {total_hours:.1f} | {total} | {total / total_hours:.2f}")


if __name__ == "__main__":
    main()
