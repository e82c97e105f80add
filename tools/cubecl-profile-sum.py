#!/usr/bin/env python3
"""Sums a CubeCL kernel-profile log per kernel name (BENCHMARKS.md, "On a GPU (NVIDIA H100 ...)").

The log comes from running a benchmark with a `cubecl.toml` in its working directory:

    [profiling.logger]
    level = "basic"
    file = "/tmp/profile.log"

Each line is `| <duration> | <kernel name>_<hash>`. Each kernel's first launch is left out (it
includes the kernel's compilation); names are summed without their hashes.

    python3 tools/cubecl-profile-sum.py /tmp/profile.log STEPS
"""
import collections
import re
import sys

UNIT_MS = {"ns": 1e-6, "µs": 1e-3, "us": 1e-3, "ms": 1.0, "s": 1e3}


def main(path: str, steps: float) -> None:
    seen, total_ms, launches = set(), collections.Counter(), collections.Counter()
    for line in open(path, errors="replace"):
        m = re.match(r"\|\s*([0-9.]+)(ns|µs|us|ms|s)\s*\|\s*(.*)$", line)
        if not m:
            continue
        name = m.group(3).strip()
        if name not in seen:
            seen.add(name)
            continue
        key = re.sub(r"_[0-9a-f]{8}", "", name)
        total_ms[key] += float(m.group(1)) * UNIT_MS[m.group(2)]
        launches[key] += 1
    print(
        f"all kernels: {sum(total_ms.values()) / steps:.1f} ms per step, "
        f"{sum(launches.values()) / steps:.0f} launches per step"
    )
    for key, ms in total_ms.most_common(40):
        print(f"{ms / steps:9.2f} ms/step {launches[key] / steps:7.0f} launches  {key}")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], float(sys.argv[2]))
