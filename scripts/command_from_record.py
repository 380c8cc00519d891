"""A bench's recorded test command as a command config: the record's command column as a breakpoint profile.

Usage:
    python scripts/command_from_record.py --record healthy_run.csv --out $HOME/phm_conf/command/my_test.yaml \
        [--tolerance 1e-3]

Reads a measurement CSV (phm_torch/io/measurement_csv.py: its units converted, any uniform rate), keeps as few of
its command samples as hold every sample within ``--tolerance`` of the profile (relative to the command's largest
|value|; phm_torch.command.profile_from_samples) and writes a ``phm_torch.command.Profile`` YAML that
``command=my_test`` then selects from the user's config folder (hydra.searchpath). Prints the breakpoints kept and
the largest deviation. The profile starts at the record's first sample (t = 0) and lasts as long as the record.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from phm_torch.command import Profile, profile_from_samples
from phm_torch.io.atomic import atomic_open
from phm_torch.io.measurement_csv import read_measurement


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--record", type=Path, required=True, help="measurement CSV with a command column")
    parser.add_argument("--out", type=Path, required=True, help="the command YAML to write")
    parser.add_argument("--tolerance", type=float, default=1e-3, help="largest deviation / largest |command|")
    args = parser.parse_args(argv)
    try:
        record = read_measurement(args.record, optional=("position",))
        t, x = np.asarray(record.time, dtype=np.float64), np.asarray(record.command, dtype=np.float64)
        if not np.isfinite(x).all():
            raise ValueError(f"{args.record}: the command column has missing samples; a test command has none")
        peak = float(np.abs(x).max())
        if peak == 0.0:
            raise ValueError(f"{args.record}: the command column is 0 throughout")
        if not 0.0 < args.tolerance < 1.0:
            raise ValueError(f"--tolerance must be in (0, 1) (relative to the largest |command|), got {args.tolerance}")
        found = profile_from_samples(t, x, args.tolerance * peak)
        # the values as the YAML writes them (9 digits), so that the deviation printed is the file's
        profile = Profile(
            tuple(round(v, 9) for v in found.times),
            tuple(float(f"{v:.9g}") for v in found.positions),
            round(found.duration, 9),
        )
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    off = float(np.abs(profile(torch.as_tensor(t - t[0])).numpy() - x).max())
    lines = [
        f"# the command column of {args.record.name} ({t.size} samples at {(t.size - 1) / (t[-1] - t[0]):g} Hz) as a",
        f"# profile: {len(profile.times)} breakpoints, every sample within {off:.3g} rad (scripts/command_from_record.py)",
        "_target_: phm_torch.command.Profile",
        f"times: {json.dumps(list(profile.times))}",
        f"positions: {json.dumps(list(profile.positions))}",
        f"duration: {profile.duration!r}",
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(args.out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print(f"{args.out}: {len(profile.times)} breakpoints of {t.size} samples, largest deviation {off:.3g} rad")
    return 0


if __name__ == "__main__":
    sys.exit(main())
